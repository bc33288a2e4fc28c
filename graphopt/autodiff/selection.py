"""Selection on jets (``where``, ``clip``, ``take``, ``take_along_axis``), registered in
:data:`graphopt.autodiff.functions.HANDLED`: the tangent follows the selected element."""

from __future__ import annotations

from typing import Any

import numpy as np

import graphopt.autodiff.tape_ops as tape_ops
from graphopt.autodiff.functions import _implements, _n, _pos
from graphopt.autodiff.jet import Jet, JetError, Tape, combine, expand, make, parts
from graphopt.autodiff.ufuncs import write_out

__all__: list[str] = []


# --- selection --------------------------------------------------------------------------------

@_implements(np.where)
def _where(condition: Any, x: Any = None, y: Any = None) -> Any:
    if x is None and y is None:
        return np.where(parts(condition)[0])
    if Tape.active and (type(x) is Jet or type(y) is Jet):
        rec = tape_ops.where(condition, x, y, lambda: _where(condition, x, y))
        if rec is not None:
            return rec
    cond = parts(condition)[0]
    (va, ta, la), (vb, tb, lb) = parts(x), parts(y)
    val = np.where(cond, va, vb)
    nd = val.ndim
    terms = []
    if ta is not None and tb is not None and la == lb and len(ta) == len(tb):
        terms.append((la, np.where(cond, expand(ta, nd), expand(tb, nd)), True))
    else:
        if ta is not None:
            terms.append((la, np.where(cond, expand(ta, nd), 0.0), True))
        if tb is not None:
            terms.append((lb, np.where(cond, 0.0, expand(tb, nd)), True))
    n = _n(x, y) if terms else 0
    return make(val, combine(val.shape, n, terms), n)


@_implements(np.clip)
def _clip(a: Any, a_min: Any = None, a_max: Any = None, out: Any = None, **kw: Any) -> Any:
    r = a
    if a_min is not None:
        r = np.maximum(r, a_min)
    if a_max is not None:
        r = np.minimum(r, a_max)
    return r if out is None else write_out(r, out, "np.clip")


@_implements(np.take)
def _take(a: Any, indices: Any, axis: Any = None, out: Any = None, mode: str = "raise") -> Any:
    if out is not None:
        raise JetError("np.take(..., out=...)")
    if axis is None:
        a, axis = np.ravel(a), 0
    v, t, lo = parts(a)
    ind = parts(indices)[0]
    y = np.take(v, ind, axis=axis, mode=mode)
    if t is None:
        return y
    return Jet(y, np.take(t, ind, axis=_pos(axis, v.ndim) + 1, mode=mode), lo, a.n)


@_implements(np.take_along_axis)
def _take_along_axis(arr: Any, indices: Any, axis: Any = -1) -> Any:
    if axis is None:
        arr, axis = np.ravel(arr), 0
    v, t, lo = parts(arr)
    ind = parts(indices)[0]
    y = np.take_along_axis(v, ind, axis=axis)
    if t is None:
        return y
    return Jet(y, np.take_along_axis(t, ind[None], axis=_pos(axis, v.ndim) + 1), lo, arr.n)
