"""The reverse pass of the batched tape (:mod:`graphopt.autodiff.tape`): adjoints of the
error's rows, propagated from the result to the leaves, contracted per edge with the leaves'
derivatives."""

from __future__ import annotations

from typing import Any

import numpy as np

import graphopt.autodiff.structure as structure
from graphopt.autodiff.jet import Jet
from graphopt.autodiff.tape import _Node, _unbroadcast, recorded

__all__ = ["backward"]


def backward(out: Jet, n: int, buffer: np.ndarray | None = None) -> np.ndarray | None:
    """Jacobian rows of a recorded ``(m, r)`` result: ``J (r, n, m)``, or ``None`` when a leaf's
    rows are not known edges (the caller forms the tangent forward instead).

    Args:
        out: The result.
        n: Total directions.
        buffer: Optional ``(≥ r·n·m,)`` float64 scratch for ``J`` (reused between blocks).
    """
    if out.value.ndim != 2 or out._tape.root is not None:
        return None
    _SOURCES.clear()
    structure.clear()
    m, r = out.value.shape
    nodes = recorded(out)
    leaves = {id(p): p for a in nodes for p in _inputs(a)
              if p._tape is None or p._tape.source is not None}
    if any(p.rows is None or p.value.ndim == 0 for p in leaves.values()):
        return None
    # Each output column's adjoint rows contiguous over the edges (an error made by
    # stacking columns hands g0[:, :, c] to each; strided rows slow every product after).
    g0 = np.zeros((r, r, m)).transpose(1, 2, 0)
    for i in range(r):
        g0[i, :, i] = 1.0
    adj: dict[int, list[Any]] = {id(out): [out, g0, True]}
    with np.errstate(all="ignore"):
        _propagate(nodes, adj, r)
    if buffer is not None and buffer.size >= r * n * m:
        J = buffer[: r * n * m].reshape(r, n, m)
    else:
        J = np.empty((r, n, m))
    rows = Rows(J)
    for ent in adj.values():
        _contract(rows, ent[0], ent[1])
    for p in leaves.values():  # products of structured blocks (graphopt.autodiff.structure)
        node = p._tape
        if node is not None and node.direct:
            for plan, g, y in node.direct:
                structure.contract_product(rows, node.struct.lo, plan, g, y, *p.rows)
    structure.contract_deferred(rows)
    rows.finish()
    return J


class Rows:
    """A block's Jacobian rows ``J (r, n, m)``, zeroed lazily: a direction's rows are
    assigned by their first write that covers the whole block, zeroed only before a partial
    one or at the end (no fill of all ``r·n·m`` values first, then a read-modify-write of
    each).

    Args:
        J: The rows (any contents).
    """

    def __init__(self, J: np.ndarray) -> None:
        self.J = J
        self.m = J.shape[2]
        self.fresh = [True] * J.shape[1]

    def add(self, lo: int, hi: int, a: int, b: int, value: Any, sign: float = 1.0) -> None:
        """``J[:, lo:hi, a:b] += sign · value`` (``value`` broadcast to that shape)."""
        target = self.J[:, lo:hi, a:b]
        if a == 0 and b == self.m and all(self.fresh[lo:hi]):
            for d in range(lo, hi):
                self.fresh[d] = False
            if sign == 1.0:
                target[...] = value
            elif sign == -1.0:
                np.negative(value, out=target)
            else:
                np.multiply(value, sign, out=target)
            return
        self.zero(lo, hi)
        if sign == 1.0:
            target += value
        elif sign == -1.0:
            target -= value
        else:
            target += sign * value

    def add_product(self, d: int, a: int, b: int, g: np.ndarray, s: np.ndarray,
                    c: float) -> None:
        """``J[:, d, a:b] += c · g ⊙ s`` (``g`` ``(r, m)``, ``s`` ``(m,)``), into the rows
        themselves when they are not written yet (no temporary ``g ⊙ s``)."""
        target = self.J[:, d, a:b]
        if a == 0 and b == self.m and self.fresh[d]:
            self.fresh[d] = False
            np.multiply(g, s if c == 1.0 else c * s, out=target)
            return
        self.zero(d, d + 1)
        target += g * (s if c == 1.0 else c * s)

    def zero(self, lo: int, hi: int) -> None:
        """Zero the rows of directions ``lo…hi−1`` not written yet."""
        for d in range(lo, hi):
            if self.fresh[d]:
                self.J[:, d] = 0.0
                self.fresh[d] = False

    def view(self, lo: int, hi: int, a: int, b: int) -> np.ndarray:
        """``J[:, lo:hi, a:b]`` to accumulate into (its rows zeroed if not written yet)."""
        self.zero(lo, hi)
        return self.J[:, lo:hi, a:b]

    def finish(self) -> None:
        """Zero the rows no leaf wrote."""
        self.zero(0, len(self.fresh))


def _propagate(nodes: list[Jet], adj: dict[int, list[Any]], r: int) -> None:
    for a in reversed(nodes):
        node = a._tape
        if node.source is not None:  # gathered rows: a leaf (contracted from its source)
            continue
        ent = adj.pop(id(a), None)
        if ent is None:
            continue
        if node.writes is not None:
            contrib = _container_back(node, ent[1] if ent[2] else ent[1].copy())
        else:
            contrib = node.back(ent[1])
        for p, c, key in contrib:
            _accumulate(adj, p, c, key, r)


def _inputs(a: Jet) -> list[Jet]:
    node = a._tape
    ps = list(node.parents)
    if node.writes is not None:
        ps += [w[1] for w in node.writes if type(w[1]) is Jet]
    return ps


def _container_back(node: _Node, g: np.ndarray) -> list[Any]:
    out = []
    for chain, src in reversed(node.writes):  # type: ignore[arg-type]
        view = g
        for k in chain:
            view = view[(slice(None),) + k]
        if type(src) is Jet:
            out.append((src, _unbroadcast(view, src.value.shape).copy(), None))
        view[...] = 0.0  # overwritten: earlier contents do not reach the result
    return out


def _accumulate(adj: dict[int, list[Any]], p: Jet, c: np.ndarray, key: Any, r: int) -> None:
    ent = adj.get(id(p))
    if key is None:
        if ent is None:
            adj[id(p)] = [p, c, False]
        elif ent[2]:
            ent[1] += c
        else:
            ent[1], ent[2] = ent[1] + c, True
        return
    if ent is None:
        # (zeros_like: a traced c makes traced zeros, whose writes a trace sees: replay.py)
        z = np.zeros_like(c, shape=(r,) + p.value.shape)
        z[key] = c
        adj[id(p)] = [p, z, True]
        return
    if not ent[2]:
        ent[1], ent[2] = ent[1].copy(), True
    ent[1][key] += c


def _contract(rows: Rows, leaf: Jet, g: np.ndarray) -> None:
    """``J[:, dirs, rows] += Σ_entries g · t`` for one leaf (per edge: its rows)."""
    if leaf._tape is not None:
        _contract_gathered(rows, leaf, g)
        return
    t, lo = leaf._tangent, leaf._lo
    a, b = leaf.rows  # type: ignore[misc]
    r, m = g.shape[:2]
    if leaf.columns is not None and leaf.value.ndim == 2:
        for c, col in enumerate(leaf.columns):
            clo, chi = col[:2]
            gc = g[:, :, c]
            if leaf.seed or (len(col) > 2 and col[2]):  # derivative 1 on one direction
                rows.add(clo, clo + 1, a, b, gc[:, None, :])
            elif chi - clo == 1:
                rows.add(clo, clo + 1, a, b, (gc * t[clo - lo, :, c])[:, None, :])
            else:
                tc = t[clo - lo: chi - lo, :, c]
                view = rows.view(clo, chi, a, b)
                for i in range(r):
                    view[i] += tc * gc[i]
        return
    k = len(t)
    if leaf.value.ndim == 1:
        if k == 1 and t.strides == (0, 0) and t[0, 0] == 1.0:
            rows.add(lo, lo + 1, a, b, g[:, None, :])
        else:
            rows.add(lo, lo + k, a, b, g[:, None, :] * t)
        return
    view = rows.view(lo, lo + k, a, b)
    if t.strides[1] == 0:  # the same derivative for every edge (a seed): one product
        t0 = t[:, 0].reshape(k, -1)
        for i in range(r):
            view[i] += t0 @ g[i].reshape(m, -1).T
        return
    gf, tf = g.reshape(r, m, -1), t.reshape(k, m, -1)
    for i in range(r):  # (r·s passes over k × m: twice as fast as einsum's)
        acc = view[i]
        for e in range(tf.shape[2]):
            acc += tf[:, :, e] * gf[i, :, e]


#: Per-vertex tangents with the edge axis moved last, by the memory they view (cleared by each
#: :func:`backward`; the per-vertex jets live as long as one linearisation).
_SOURCES: dict[tuple[Any, ...], tuple[np.ndarray, np.ndarray, int]] = {}


def _source_rows(src: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``(t (k', s', vertices), entries (s',), first)``: a per-vertex tangent
    ``(k, vertices, *s)`` restricted to its entries that have a derivative (a transform's
    constant last row has none) and to the directions ``first…first+k'−1`` they depend on,
    the vertex axis last (contiguous gathers per entry)."""
    key = (src.__array_interface__["data"][0], src.shape, src.strides)
    hit = _SOURCES.get(key)
    if hit is not None:
        return hit
    k, nv = src.shape[:2]
    flat = src.reshape(k, nv, -1)
    nz = np.any(flat != 0.0, axis=1)  # (k, s)
    ent = np.flatnonzero(np.any(nz, axis=0))
    dirs = np.flatnonzero(np.any(nz, axis=1))
    first, last = (int(dirs[0]), int(dirs[-1]) + 1) if len(dirs) else (0, 1)
    t = np.ascontiguousarray(flat[first:last][:, :, ent].transpose(0, 2, 1))
    _SOURCES[key] = hit = (t, ent, first)
    return hit


def _contract_gathered(rows: Rows, leaf: Jet, g: np.ndarray) -> None:
    """:func:`_contract` for gathered rows of a per-vertex jet: its tangent's entries are
    gathered per edge from the vertices' (``(k, s, m)``, the edge axis contiguous) and
    contracted with the adjoint in one ``einsum``; nothing is gathered for entries without
    derivatives."""
    node = leaf._tape
    a, b = leaf.rows  # type: ignore[misc]
    if node.struct is not None:
        entries = node.entries if node.entries is not None else np.arange(
            int(np.prod(leaf.value.shape[1:])))
        plan = node.struct.plan(entries, len(node.source))
        if plan is not None:
            structure.contract(rows, node.struct.lo, plan, node.full, g, a, b, node.struct.one)
            return
    t, ent, first = _source_rows(node.source)
    r, m = g.shape[:2]
    if not len(ent):
        return
    tg = np.take(t, node.index, axis=2)  # (k', s', m)
    gs = np.moveaxis(g.reshape(r, m, -1)[:, :, ent], 1, 2)  # (r, s', m)
    lo = leaf._lo + first
    rows.add(lo, lo + len(t), a, b, np.einsum("ksm,ism->ikm", tg, gs))
