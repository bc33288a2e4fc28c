"""Recorded ufuncs, products, joins and reductions of the batched tape
(:mod:`graphopt.autodiff.tape`): elementwise ufuncs, ``matmul`` of stacked matrices,
``stack``/``concatenate`` and ``sum``/``mean`` over non-edge axes, each computing its value
now and its adjoints in the reverse pass."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from graphopt.autodiff.jet import Jet
from graphopt.autodiff.tape import _Node, _operand, _record, _unbroadcast, binary

__all__ = ["concatenate", "matmul", "reduce", "ufunc", "where"]


def matmul(a: Any, b: Any, mm: Callable[..., np.ndarray], replay: Callable[[], Any]) -> Any:
    """A recorded ``a @ b`` of stacks of matrices (``mm``: the product), or ``None``."""
    a, b = _operand(a), _operand(b)
    # A plain operand as it is now (np.copy keeps a traced array traced: replay.py).
    va = a.value if type(a) is Jet else np.copy(a)
    vb = b.value if type(b) is Jet else np.copy(b)
    if not (isinstance(va, np.ndarray) and isinstance(vb, np.ndarray)) or min(
            va.ndim, vb.ndim) < 2 or va.dtype.kind != "f" or vb.dtype.kind != "f":
        return None
    y = mm(va, vb)
    direct = _product_plan(a, va, vb)
    leaf = a._tape if direct is not None else None

    def back(g: np.ndarray) -> list[Any]:
        out = []
        # A structured A adds its contribution from g and y directly — unless its derivatives
        # were formed since (read by a forward rule): then it is an ordinary leaf.
        if direct is not None and a._tape is leaf:
            leaf.direct = (leaf.direct or []) + [(direct, g, y)]
        elif type(a) is Jet:
            out.append((a, _unbroadcast(mm(g, np.swapaxes(vb, -1, -2)), va.shape), None))
        if type(b) is Jet:
            out.append((b, _unbroadcast(mm(np.swapaxes(va, -1, -2), g), vb.shape), None))
        return out

    parents = tuple(x for x in (a, b) if type(x) is Jet)
    return _record(y, parents[0].n, _Node(parents, back, replay))


def _product_plan(a: Any, va: np.ndarray, vb: np.ndarray) -> Any:
    """The :meth:`~graphopt.autodiff.structure.Structure.product_plan` of ``a @ b`` when ``a``
    is a block of gathered rows of a structured matrix (``(m, r, c) @ (m, c, q)``)."""
    if type(a) is not Jet or a._tape is None or a._tape.struct is None:
        return None
    if va.ndim != 3 or vb.ndim != 3 or len(va) != len(vb):
        return None
    node = a._tape
    entries = node.entries
    if entries is None:
        entries = np.arange(va.shape[1] * va.shape[2]).reshape(va.shape[1:])
    return node.struct.product_plan(entries)


def concatenate(arrays: list[Any], axis: int, stack: bool, replay: Callable[[], Any]) -> Any:
    """A recorded ``np.concatenate`` (``stack``: ``np.stack``) of jets and arrays."""
    arrays = [_operand(a) for a in arrays]
    values = [a.value if type(a) is Jet else np.asarray(a) for a in arrays]
    y = np.stack(values, axis=axis) if stack else np.concatenate(values, axis=axis)
    ax = axis % y.ndim + 1
    spans, start = [], 0
    for v in values:
        w = 1 if stack else v.shape[ax - 1]
        spans.append(start if stack else slice(start, start + w))
        start += w

    def back(g: np.ndarray) -> list[Any]:
        pre = (slice(None),) * ax
        return [(a, g[pre + (s,)], None) for a, s in zip(arrays, spans, strict=True)
                if type(a) is Jet]

    jets = tuple(a for a in arrays if type(a) is Jet)
    return _record(y, max(j.n for j in jets), _Node(jets, back, replay))


def reduce(fn: Any, a: Jet, axis: Any, keepdims: bool, replay: Callable[[], Any]) -> Any:
    """A recorded ``np.sum``/``np.mean`` over axes other than the edges' (axis 0)."""
    a = _operand(a)
    nd = a.value.ndim
    axes = tuple(x % nd for x in (axis if isinstance(axis, tuple) else (axis,)))
    if 0 in axes or a.value.dtype.kind != "f":
        return None
    y = fn(a.value, axis=axes, keepdims=keepdims)
    scale = 1.0 if fn is np.sum else 1.0 / np.prod([a.value.shape[x] for x in axes])

    def back(g: np.ndarray) -> list[Any]:
        gk = g if keepdims else np.expand_dims(g, tuple(x + 1 for x in axes))
        c = np.broadcast_to(gk if scale == 1.0 else gk * scale, (g.shape[0],) + a.value.shape)
        return [(a, c, None)]

    return _record(np.asarray(y), a.n, _Node((a,), back, replay))


def ufunc(uf: np.ufunc, inputs: tuple[Any, ...], rules: dict[Any, Any],
          replay: Callable[[], Any]) -> Jet | None:
    """A recorded elementwise ufunc (``rules``: the unary derivative rules), or ``None``."""
    if len(inputs) == 2:
        return binary(uf, inputs[0], inputs[1], replay)
    if len(inputs) != 1:
        return None
    a = _operand(inputs[0])
    v = a.value
    if v.dtype.kind != "f":
        return None
    if uf is np.negative:
        return _record(uf(v), a.n, _Node((a,), lambda g: [(a, -g, None)], replay))
    rule = rules.get(uf)
    if rule is None or (uf is np.sqrt and not np.all(v)):
        return None
    y = uf(v)
    return _record(y, a.n, _Node((a,), lambda g: [(a, g * rule(v, y), None)], replay))


def where(cond: Any, x: Any, y: Any, replay: Callable[[], Any]) -> Jet | None:
    """A recorded ``np.where(cond, x, y)`` (a plain condition: comparisons of jets are values
    only): each element's adjoint goes to the operand it was taken from."""
    if type(cond) is Jet or not isinstance(cond, np.ndarray | bool | np.bool_):
        return None
    x, y = _operand(x), _operand(y)
    vx = x.value if type(x) is Jet else x
    vy = y.value if type(y) is Jet else y
    val = np.where(cond, vx, vy)
    if val.dtype.kind != "f" or any(type(a) is Jet and a.value.dtype.kind != "f"
                                    for a in (x, y)):
        return None
    c = np.copy(cond)  # (read again in the reverse pass: as it is now)

    def back(g: np.ndarray) -> list[Any]:
        out = []
        if type(x) is Jet:
            out.append((x, _unbroadcast(np.where(c, g, 0.0), vx.shape), None))
        if type(y) is Jet:
            out.append((y, _unbroadcast(np.where(c, 0.0, g), vy.shape), None))
        return out

    jets = tuple(a for a in (x, y) if type(a) is Jet)
    return _record(val, jets[0].n, _Node(jets, back, replay))
