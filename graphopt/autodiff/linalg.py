"""Bilinear NumPy functions and linear algebra on jets (``einsum``, ``dot``, ``tensordot``,
``cross``, ``linalg.norm``/``inv``/``det``/``solve``), registered in
:data:`graphopt.autodiff.functions.HANDLED`.

A bilinear function's tangent is one call per jet operand with its tangent in place of its
value (the tangent axis carried as an extra leading index).
"""

from __future__ import annotations

import string
from collections.abc import Sequence
from typing import Any

import numpy as np

from graphopt.autodiff.functions import _implements, _n, _pos
from graphopt.autodiff.jet import Jet, JetError, combine, expand, make, parts
from graphopt.autodiff.ufuncs import write_out

__all__: list[str] = []


# --- products ---------------------------------------------------------------------------------

def _bilinear(y: np.ndarray, n: int, terms: list[tuple[int, np.ndarray]]) -> Any:
    return make(y, combine(y.shape, n, [(lo, t, True) for lo, t in terms]), n)


@_implements(np.einsum)
def _einsum(subscripts: Any, *operands: Any, out: Any = None, **kw: Any) -> Any:
    if not isinstance(subscripts, str):
        raise JetError("np.einsum in its sublist form", "use a subscripts string")
    sub = subscripts.replace(" ", "")
    ins, _, outs = sub.partition("->")
    inputs = ins.split(",")
    if "->" not in sub:  # NumPy's implicit output: indices seen once, in order
        letters = [c for c in ins if c.isalpha()]
        outs = ("..." if "..." in ins else "") + "".join(
            sorted(c for c in set(letters) if letters.count(c) == 1))
    free = next(c for c in string.ascii_letters if c not in sub)
    ps = [parts(o) for o in operands]
    y = np.einsum(f"{ins}->{outs}", *(p[0] for p in ps), **kw)
    terms = []
    for i, (_, t, lo) in enumerate(ps):
        if t is None:
            continue
        spec = ",".join(free + s if j == i else s for j, s in enumerate(inputs))
        ops = [t if j == i else p[0] for j, p in enumerate(ps)]
        terms.append((lo, np.einsum(f"{spec}->{free}{outs}", *ops, **kw)))
    r = _bilinear(np.asarray(y), _n(*operands) if terms else 0, terms)
    return r if out is None else write_out(r, out, "np.einsum")


def _axes_lists(axes: Any, na: int, nb: int) -> tuple[list[int], list[int]]:
    if isinstance(axes, int):
        return list(range(na - axes, na)), list(range(axes))
    xa, xb = axes
    xa = [xa] if isinstance(xa, int) else list(xa)
    xb = [xb] if isinstance(xb, int) else list(xb)
    return [_pos(i, na) for i in xa], [_pos(i, nb) for i in xb]


@_implements(np.tensordot)
def _tensordot(a: Any, b: Any, axes: Any = 2) -> Any:
    (va, ta, la), (vb, tb, lb) = parts(a), parts(b)
    xa, xb = _axes_lists(axes, va.ndim, vb.ndim)
    y = np.tensordot(va, vb, (xa, xb))
    terms = []
    if ta is not None:
        terms.append((la, np.tensordot(ta, vb, ([i + 1 for i in xa], xb))))
    if tb is not None:
        r = np.tensordot(va, tb, (xa, [i + 1 for i in xb]))
        terms.append((lb, np.moveaxis(r, va.ndim - len(xa), 0)))
    return _bilinear(np.asarray(y), _n(a, b) if terms else 0, terms)


@_implements(np.dot)
def _dot(a: Any, b: Any, out: Any = None) -> Any:
    na, nb = np.ndim(a), np.ndim(b)
    if na == 0 or nb == 0:
        r = np.multiply(a, b)
    else:
        r = _tensordot(a, b, ([na - 1], [nb - 2 if nb >= 2 else 0]))
    return r if out is None else write_out(r, out, "np.dot")


@_implements(np.inner)
def _inner(a: Any, b: Any) -> Any:
    return _tensordot(a, b, ([np.ndim(a) - 1], [np.ndim(b) - 1]))


@_implements(np.outer)
def _outer(a: Any, b: Any, out: Any = None) -> Any:
    return np.multiply(np.reshape(a, (-1, 1)), np.reshape(b, (1, -1)))


@_implements(np.cross)
def _cross(a: Any, b: Any, axisa: int = -1, axisb: int = -1, axisc: int = -1,
           axis: Any = None) -> Any:
    if axis is not None:
        axisa = axisb = axisc = axis
    (va, ta, la), (vb, tb, lb) = parts(a), parts(b)
    if va.shape[axisa] != 3 or vb.shape[axisb] != 3:
        raise JetError("np.cross of 2-vectors")
    # Negative axes mean the same axis of the value and of the tangent.
    neg_a, neg_b = _pos(axisa, va.ndim) - va.ndim, _pos(axisb, vb.ndim) - vb.ndim
    y = np.cross(va, vb, axisa, axisb, axisc)
    neg_c = _pos(axisc, y.ndim) - y.ndim
    terms = []
    if ta is not None:
        terms.append((la, np.cross(ta, vb, neg_a, neg_b, neg_c)))
    if tb is not None:
        terms.append((lb, np.cross(va, tb, neg_a, neg_b, neg_c)))
    return _bilinear(y, _n(a, b), terms)


# --- linear algebra ---------------------------------------------------------------------------

@_implements(np.linalg.norm)
def _norm(x: Any, ord: Any = None, axis: Any = None, keepdims: bool = False) -> Any:
    v, t, lo = parts(x)
    nd = v.ndim
    if axis is None:
        axes: tuple[int, ...] = tuple(range(nd))
        if ord not in (None, "fro") and not (ord == 2 and nd == 1):
            raise JetError(f"np.linalg.norm(..., ord={ord!r})")
    else:
        axes = tuple(_pos(i, nd) for i in (axis if isinstance(axis, Sequence) else (axis,)))
        if (len(axes) == 1 and ord not in (None, 2)) or (len(axes) == 2
                                                         and ord not in (None, "fro")):
            raise JetError(f"np.linalg.norm(..., ord={ord!r})")
    y = np.sqrt(np.sum(v * v, axis=axes, keepdims=True))
    out = y if keepdims else np.squeeze(y, axis=axes)
    if t is None:
        return out
    # Where the norm is 0, the derivative is taken as 0 (a subgradient), not NaN.
    with np.errstate(all="ignore"):
        c = np.where(y > 0.0, v / np.where(y > 0.0, y, 1.0), 0.0)
    tan = np.sum(t * c, axis=tuple(i + 1 for i in axes), keepdims=keepdims)
    return Jet(out, tan, lo, x.n)


@_implements(np.linalg.inv)
def _inv(a: Any) -> Any:
    v, t, lo = parts(a)
    y = np.linalg.inv(v)
    return y if t is None else Jet(y, -(y @ t @ y), lo, a.n)


@_implements(np.linalg.det)
def _det(a: Any) -> Any:
    v, t, lo = parts(a)
    y = np.linalg.det(v)
    if t is None:
        return y
    inv = np.linalg.inv(v)
    return Jet(y, y * np.einsum("...ij,k...ji->k...", inv, t), lo, a.n)


@_implements(np.linalg.cholesky)
def _cholesky(a: Any, upper: bool = False) -> Any:
    if upper:
        raise JetError("np.linalg.cholesky(..., upper=True)")
    v, t, lo = parts(a)
    L = np.linalg.cholesky(v)
    if t is None:
        return L
    # dL = L Φ(L⁻¹ dA L⁻ᵀ), Φ: the lower triangle with the diagonal halved.
    Li = np.linalg.inv(L)
    S = Li @ t @ np.swapaxes(Li, -1, -2)
    phi = np.tril(S, -1) + 0.5 * (S * np.eye(v.shape[-1]))
    return Jet(L, L @ phi, lo, a.n)


@_implements(np.linalg.solve)
def _solve(a: Any, b: Any) -> Any:
    (va, ta, la), (vb, tb, lb) = parts(a), parts(b)
    vec = vb.ndim == 1
    B = vb[:, None] if vec else vb
    x = np.linalg.solve(va, B)
    terms = []
    if ta is not None:
        terms.append((la, -np.linalg.solve(va, ta @ x)))
    if tb is not None:
        terms.append((lb, np.linalg.solve(va, expand(tb[..., None] if vec else tb, x.ndim))))
    r = _bilinear(x, _n(a, b), terms)
    return r[..., 0] if vec else r

