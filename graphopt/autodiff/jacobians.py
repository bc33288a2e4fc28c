"""Jacobians of a whole edge group from one evaluation of its ``error`` on jets.

The derivative is taken w.r.t. each vertex's tangent increment ``δ`` at ``δ = 0`` — the
Jacobian of ``e(x ⊞ δ)`` the optimizer needs — by running the vertex type's own ``oplus`` on a
jet ``δ`` (value 0, derivative the identity over that position's directions). Nothing else is
asked of a vertex type: exponential maps, angle-axis updates and their small-angle series are
differentiated as written (a series exact to first order at 0 gives the exact derivative).
"""

from __future__ import annotations

import gc
import threading
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

import graphopt.autodiff.programs as programs
import graphopt.autodiff.tape as tape
from graphopt.autodiff.blocks import Block, first_blocks, inputs_of
from graphopt.autodiff.jet import Jet, JetError
from graphopt.autodiff.structure import Structure, detect
from graphopt.errors import GraphError
from graphopt.vertex import VertexVector

__all__ = ["BLOCK_EDGES", "autodiff_linearize", "check_independent_edges", "distinct_vertices",
           "seeded"]

#: Edges per jet evaluation: one block's values and adjoints stay in the CPU caches, and the
#: Python cost per operation (~0.3 ms a block for the BAL error) is paid once per block.
#: Measured on 100,000 BAL edges: 10,000–14,000 alike, 8,192 ~7 % slower (docs/autodiff.md).
BLOCK_EDGES = 12_000


class _VertexType(Protocol):
    dimension: int
    __name__: str

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray: ...


class _EdgeType(Protocol):
    dimension: int
    vertex_types: Sequence[type[_VertexType]]
    __name__: str

    @classmethod
    def evaluate(cls, x: Sequence[Any], measurement: np.ndarray, ctx: Any) -> Any: ...


def seeded(vtype: type[_VertexType], x: np.ndarray, lo: int, n: int) -> Jet:
    """``x ⊞ δ`` as a jet at ``δ = 0``, its derivative w.r.t. directions ``lo…lo+d−1``.

    Args:
        vtype: The vertex type (its ``oplus`` runs on the jet).
        x: ``(m, *estimate_shape)`` estimates.
        lo: The position's first tangent direction.
        n: Total directions.

    Raises:
        GraphError: an ``oplus`` that drops the derivative or returns another shape.
    """
    m, d = len(x), vtype.dimension
    if vtype.oplus is VertexVector.oplus and x.shape == (m, d):
        return Jet.seeded(x, lo, n)  # x + δ: the derivative is the identity
    # ∂δ/∂δ = I, broadcast over the edges (a read-only view, no m·d² array).
    delta = Jet.seeded(np.zeros((m, d)), lo, n)
    out = vtype.oplus(x.copy(), delta)  # type: ignore[arg-type]
    name = getattr(vtype, "__name__", str(vtype))
    if type(out) is not Jet:
        raise GraphError(f"{name}.oplus returned a {type(out).__name__} without derivatives for "
                         "a jet increment (automatic differentiation needs it to compute with "
                         "NumPy operations on the increment)")
    if out.shape != x.shape:
        raise GraphError(f"{name}.oplus returned shape {out.shape}, expected {x.shape}")
    # The value at δ = 0 is x itself (oplus(x, 0) may differ from it in the last bit).
    out.value = x
    return out


def _columns(j: Jet) -> None:
    """Record each column's support of a 2-D jet (its non-zero derivative directions)."""
    if j.value.ndim != 2 or j.seed:
        return
    nz = np.any(j.tangent != 0.0, axis=1)  # (k, d)
    cols: list[Any] = []
    for c in range(j.value.shape[1]):
        rows = np.flatnonzero(nz[:, c])
        if not len(rows):
            cols.append((j.lo, j.lo + 1))
            continue
        lo, hi = int(rows[0]), int(rows[-1]) + 1
        # A column with one direction of derivative 1 everywhere (t of x + δ): "unit".
        unit = hi - lo == 1 and bool(np.all(j.tangent[lo, :, c] == 1.0))
        cols.append((j.lo + lo, j.lo + hi, unit))
    j.columns = cols


def _gather(j: Any, index: np.ndarray | slice, value: np.ndarray | None = None,
            struct: Structure | None = None, support: np.ndarray | None = None) -> Any:
    """Rows ``index`` of a per-vertex jet, as a per-edge jet (``value``: the exact values;
    ``struct``: the jet's structure, if any)."""
    if type(j) is not Jet:
        return None if j is None else j[index]
    if not isinstance(index, slice):  # the tangent is gathered when (and as far as) used
        if value is None:
            v = j.value
            # (m, d) values column by column (Fortran order, as the optimizer gathers
            # estimates): every operation on a column x[:, c] then reads contiguous memory.
            value = (np.take(v.T, index, axis=1).T if v.ndim == 2 and v.flags.c_contiguous
                     else v[index])
        return tape.gathered(value, j, index, struct, support)
    t = j.tangent[:, index]
    out = Jet(j.value[index] if value is None else value, t, j.lo, j.n)
    out.columns = j.columns
    return out


_UNIQUE: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray]]] = {}


def distinct_vertices(slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` of edges' vertex indices (``slots`` ``(m,)``): ``first`` ``(k,)``
    one edge per distinct vertex, ``inverse`` ``(m,)`` each edge's entry in ``first``
    (``slots[first][inverse] == slots``), for :attr:`EdgeContext.vertices`."""
    _, first, inverse = np.unique(slots, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def _regathers(flat: np.ndarray, first: np.ndarray, inv: np.ndarray) -> bool:
    """``flat[first][inv] == flat`` exactly (``flat`` ``(m, s)``), gathered along its
    contiguous axis (the optimizer gathers 2-D estimates in Fortran order)."""
    if inv.shape != (len(flat),) or (len(first) and int(first.max()) >= len(flat)):
        return False
    # In chunks of edges: each chunk's gathered copy stays in the CPU cache (2x faster).
    if flat.flags.f_contiguous and not flat.flags.c_contiguous:
        u = np.ascontiguousarray(flat[first].T)  # (s, distinct)
        return all(np.array_equal(np.take(u, inv[s: s + BLOCK_EDGES], axis=1),
                                  flat[s: s + BLOCK_EDGES].T)
                   for s in range(0, len(flat), BLOCK_EDGES))
    u = flat[first]
    return all(np.array_equal(np.take(u, inv[s: s + BLOCK_EDGES], axis=0),
                              flat[s: s + BLOCK_EDGES])
               for s in range(0, len(flat), BLOCK_EDGES))


def _unique_rows(vtype: type, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` with ``x[first][inverse] == x`` exactly: the distinct vertices of
    the edges. The groupings of the last calls are tried first (the edges of a group keep
    their vertices between iterations); one is used only if the equality holds."""
    m = len(x)
    flat = x.reshape(m, -1)
    key = (id(vtype), m)
    for first, inv in _UNIQUE.get(key, []):
        if _regathers(flat, first, inv):
            return first, inv
    h = flat @ np.random.default_rng(0).normal(size=flat.shape[1])
    _, first, inv = np.unique(h, return_index=True, return_inverse=True)
    if not _regathers(flat, first, inv):  # a hash collision: no grouping
        first, inv = np.arange(m), np.arange(m)
    if len(_UNIQUE) > 64:  # many group sizes seen: start over (a cache, bounded)
        _UNIQUE.clear()
    entries = _UNIQUE.setdefault(key, [])
    entries.insert(0, (first, inv))
    del entries[4:]
    return first, inv


#: The last per-vertex jets by vertex type and position: ``(row bytes → row, jet, derived,
#: derived usable, their structures)``. A group linearised in chunks sees the same cameras
#: in each.
_VERTEX_JETS: dict[tuple[Any, ...], tuple[dict[bytes, int], Jet, Any, bool, Any, Any]] = {}


def _cached_rows(key: tuple[Any, ...], xu: np.ndarray) -> np.ndarray | None:
    """Rows of the cached per-vertex jets holding exactly the vertices ``xu`` (all of them
    cached: the jets are reused), else ``None``."""
    entry = _VERTEX_JETS.get(key)
    if entry is None or len(xu) > len(entry[0]):
        return None
    where = entry[0]
    rows = [where.get(r.tobytes(), -1) for r in xu.reshape(len(xu), -1)]
    return None if min(rows, default=-1) < 0 else np.asarray(rows)


class _Position:
    """One vertex position's ``x ⊞ δ`` (and derived values) as jets, per block of edges.

    ``oplus`` and ``derived`` run once per distinct vertex (a camera seen by thousands of
    edges is updated once) and the rows are gathered per edge; a Euclidean vertex is a seed.
    """

    def __init__(self, vtype: type[_VertexType], x: np.ndarray, lo: int, n: int,
                 derived: bool, distinct: tuple[np.ndarray, np.ndarray] | None = None,
                 given: np.ndarray | None = None) -> None:
        self.vtype, self.x, self.lo, self.n = vtype, x, lo, n
        # The derived values the optimizer gathered (ctx.derived): the per-edge values, as
        # the plain error reads them (no second gather).
        self.given = given
        self.vector = vtype.oplus is VertexVector.oplus and x.ndim == 2
        self.inverse: np.ndarray | None = None
        self.jet: Jet | None = None
        self.derived: Any = None
        self.derived_ok = True
        # Group structure of the per-vertex jets' derivatives (graphopt.autodiff.structure).
        self.struct: Structure | None = None
        self.dstruct: Structure | None = None
        if not self.vector:
            # The optimizer's grouping (edges that share a vertex), else found from x.
            first, inv = _unique_rows(vtype, x) if distinct is None else distinct
            if len(first) < len(x):
                self.inverse = inv
                key = (vtype, lo, n, derived)
                rows = _cached_rows(key, x[first])
                if rows is not None:  # vertices seen by another chunk of the group
                    self.inverse = rows[inv]
                    (self.jet, self.derived, self.derived_ok, self.struct,
                     self.dstruct) = _VERTEX_JETS[key][1:]
                    self._supports()
                    return
                self.jet = seeded(vtype, x[first], lo, n)
            else:
                self.jet = seeded(vtype, x, lo, n)
            _columns(self.jet)
            self.struct = detect(self.jet)
        if derived:
            self.derived = self._derived(self.jet if self.jet is not None
                                         else Jet.seeded(x, lo, n))
            if type(self.derived) is Jet and not self.vector:
                self.dstruct = detect(self.derived)
        if self.inverse is not None:  # only read afterwards (gathers copy), so reusable
            if len(_VERTEX_JETS) >= 4:
                _VERTEX_JETS.pop(next(iter(_VERTEX_JETS)))
            xs = x[first].reshape(len(first), -1)
            where = {r.tobytes(): i for i, r in enumerate(xs)} if len(xs) <= 4096 else {}
            _VERTEX_JETS[key] = (where, self.jet, self.derived, self.derived_ok, self.struct,
                                 self.dstruct)
        self._supports()

    def _supports(self) -> None:
        """Each gathered per-vertex jet's non-zero directions per entry, ``(k, *s)``: which
        directions a piece of it is gathered with (``tape._gathered_item``), decided here
        on all vertices rather than in a traced block (a program's signature has them)."""
        self.support = self.dsupport = None
        if self.inverse is not None:
            self.support = _support(self.jet)
            if type(self.derived) is Jet:
                self.dsupport = _support(self.derived)

    def _derived(self, j: Jet) -> Any:
        try:
            d = self.vtype.derived(j)  # type: ignore[attr-defined]
        except JetError:
            self.derived_ok = False  # derived values are a cache: go without
            return None
        if type(d) is Jet:
            _columns(d)
        return d

    def block(self, sl: slice) -> tuple[Jet, Any]:
        """The block's ``x ⊞ δ`` jet and derived values (axis 0: the block's edges)."""
        return self.build(sl, self.arrays(sl))

    def arrays(self, sl: slice) -> list[Any]:
        """What a block reads, in a fixed order: ``[x, index, given, jet value, jet tangent,
        derived value, derived tangent]`` (``None`` where absent). The per-vertex jets' arrays
        are listed too, as the block's rows of them when its edges are the vertices (no
        index), so that nothing a traced block (:mod:`graphopt.autodiff.replay`) reads
        depends on where the block starts."""
        d = self.derived
        whole = self.inverse is None  # (per-vertex rows are the edges': sliced here)
        rows: Any = sl if whole else slice(None)
        dj = [d.value[rows], d.tangent[:, rows]] if type(d) is Jet else [None, None]
        if self.vector:
            return [self.x[sl], None, None, None, None, *dj]
        g, dv = self.given, getattr(d, "value", None)
        if g is not None and not (dv is not None and g.shape[1:] == dv.shape[1:]
                                  and g.dtype == dv.dtype
                                  and (g.ndim != 2 or g.flags.f_contiguous)):
            g = self.given = None  # (2-D: Fortran order, as a gather here makes it)
        j = self.jet
        assert j is not None
        return [self.x[sl], None if whole else self.inverse[sl],  # type: ignore[index]
                None if g is None else g[sl], j.value[rows], j.tangent[:, rows], *dj]

    def build(self, sl: slice, a: list[Any]) -> tuple[Jet, Any]:
        """:meth:`block` from the block's :meth:`arrays` (or traced views of them)."""
        d = self.derived
        if type(d) is Jet:  # the block's (or all) rows of the derived values
            d = _like(d, a[5], a[6])
        index = slice(None) if a[1] is None else a[1]
        if self.vector:
            j, d = Jet.seeded(a[0], self.lo, self.n), _gather(d, index)
        else:
            assert self.jet is not None
            j = _gather(_like(self.jet, a[3], a[4]), index, a[0], self.struct, self.support)
            d = _gather(d, index, a[2], self.dstruct, self.dsupport)
        j.rows = (0, sl.stop - sl.start)
        if type(d) is Jet:
            d.rows = j.rows
        return j, d


def _support(j: Any) -> np.ndarray:
    t = j.tangent
    return np.any(t.reshape(t.shape[:2] + (-1,)) != 0.0, axis=1).reshape(
        (len(t),) + t.shape[2:])


def _like(j: Jet, value: np.ndarray, tangent: np.ndarray) -> Jet:
    """A copy of per-vertex jet ``j`` with other (traced) arrays: the shared one stays as is."""
    out = Jet(value, tangent, j.lo, j.n)
    out.columns, out.seed = j.columns, j.seed
    return out


_SCRATCH = threading.local()


def _scratch(size: int) -> np.ndarray:
    """A ``(≥ size,)`` float64 scratch array for a block's Jacobian rows, kept between calls
    (per thread): a fresh one of a few MB would take its pages from the system again at
    every linearisation (a page fault per 4 KB, ~10 % of a 100,000-edge BAL linearisation
    whose heap an earlier large computation returned)."""
    buf = getattr(_SCRATCH, "buffer", None)
    if buf is None or buf.size < size:
        buf = _SCRATCH.buffer = np.empty(size)
    return buf


def autodiff_linearize(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray | None]:
    """Errors and exact Jacobians of every edge of a group, from ``evaluate`` on jets.

    Python's cyclic garbage collector is paused for the call: the tape allocates thousands
    of small objects (jets, recorded operations), which would trigger collections that
    traverse them all, while none of them form cycles (freed by reference counting). The
    collector's state is restored afterwards.

    The edges are evaluated in blocks of :data:`BLOCK_EDGES`. The vertex types' ``derived``
    values (for types with ``uses_derived``) are recomputed from the jets of ``x ⊞ δ``, so
    that the error sees the same cache it would in the optimizer, with derivatives; a
    ``derived`` that does not run on jets is left out, as for numeric differences.

    Args:
        edge_type: The edge class (``evaluate``/``error``, ``vertex_types``, ``dimension``).
        x: Per position ``(m, *estimate_shape)`` estimates.
        measurement: ``(m, *measurement_shape)``.
        ctx: The :class:`~graphopt.edge.EdgeContext`.

    Returns:
        ``(e (m, dimension), (J_i (m, dimension, d_i), …), active (m,) or None)``; rows of
        inactive edges are zero.

    Raises:
        JetError: a NumPy function without a derivative rule (the caller names the type).
        GraphError: an ``oplus`` or ``error`` result of the wrong shape or without derivatives.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        return _linearize(edge_type, x, measurement, ctx)
    finally:
        tape.clear()  # (the last block's recorded jets, after an exception too)
        if enabled:
            gc.enable()


def _linearize(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray | None]:
    """:func:`autodiff_linearize` (the collector paused)."""
    dims = [vt.dimension for vt in edge_type.vertex_types]
    n = int(sum(dims))
    offsets = np.concatenate([[0], np.cumsum(dims)]).astype(int).tolist()
    m = len(measurement)
    want = bool(getattr(edge_type, "uses_derived", False)) and ctx is not None
    groups = getattr(ctx, "vertices", None) or (None,) * len(dims)
    given = (getattr(ctx, "derived", None) if want else None) or (None,) * len(dims)
    pos = [_Position(vt, np.asarray(xi), offsets[i], n, want, groups[i],
                     None if given[i] is None or len(given[i]) != len(xi) else given[i])
           for i, (vt, xi) in enumerate(zip(edge_type.vertex_types, x, strict=True))]
    want = want and all(p.derived_ok for p in pos)
    dim = edge_type.dimension
    e = np.empty((m, dim))
    # Written block by block (zeros where a block has no derivative): memory that malloc
    # reuses is not cleared first, as np.zeros would.
    jac = [np.empty((m, dim, d)) for d in dims]
    active: np.ndarray | None = None
    buffer: np.ndarray | None = None
    # Blocks of about BLOCK_EDGES, of equal size: no small last block that costs a whole
    # block's Python for a few edges (18,182 edges: 2 blocks of 9,091, not 8,192 + 8,192 + 1,798).
    size = -(-m // max(1, round(m / BLOCK_EDGES))) if m else 1
    buffer = _scratch(dim * n * min(m, size)) if m else None
    run = Block(edge_type, pos, measurement, ctx, want, size < m, dim, n)
    plan: programs.Plan | None = None
    traced: slice | None = None  # the block a program was traced on, in this call
    starts = list(range(0, max(m, 1), size))
    for s in starts:
        sl = slice(s, min(s + size, m))
        mb = sl.stop - sl.start
        arrays = [p.arrays(sl) for p in pos]
        if s == 0 and m and traced is None:  # (a program of blocks: graphopt.autodiff.programs)
            plan = programs.plan(edge_type, pos, arrays, measurement[sl], ctx, want, size,
                                 m // size)
        out = None
        if plan is not None and not plan.dead and mb == plan.length:
            assert buffer is not None
            inputs = inputs_of(arrays, measurement[sl], buffer[: dim * n * mb])
            if plan.checked:
                ev, ab = plan.run(inputs)
                out = (ev, ab, inputs[-1].reshape(dim, n, mb))
            elif plan.lock.acquire(blocking=False):  # (else another thread traces: the tape)
                try:
                    out, traced = first_blocks(plan, run, sl, arrays, inputs, traced)
                finally:
                    plan.lock.release()
                if plan.dead and traced is not None and traced != sl:  # the traced block
                    starts.append(traced.start)  # again, by the tape (the trace may have
                    plan = None  # behaved otherwise than the tape)
        if out is None:
            out = run(sl, arrays, None if buffer is None else buffer[: dim * n * mb])
        eb, ab, J = out
        if ab is not None:
            if active is None:
                active = np.ones(m, dtype=bool)
            active[sl] = ab
        if type(eb) is not Jet and J is None:  # the error does not depend on the estimates
            e[sl] = eb
            for Ji in jac:
                Ji[sl] = 0.0
            continue
        e[sl] = eb.value if type(eb) is Jet else eb
        if J is not None:  # reverse accumulation: J (rows, n, mb), one copy per position
            for i, d in enumerate(dims):
                jac[i][sl] = J[:, offsets[i]: offsets[i] + d].transpose(2, 0, 1)
            continue
        t, lo = eb.tangent, eb.lo
        for i, d in enumerate(dims):
            jac[i][sl] = 0.0
            a, b = max(offsets[i], lo), min(offsets[i] + d, lo + len(t))
            if a < b:
                jac[i][sl, :, a - offsets[i]: b - offsets[i]] = np.moveaxis(
                    t[a - lo: b - lo], 0, -1)
    if active is not None and not active.all():
        for J in jac:
            J[~active] = 0.0
    return e, tuple(jac), active






def check_independent_edges(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any,
    error: np.ndarray, jacobians: tuple[np.ndarray, ...],
) -> None:
    """Raise if the first edge's error or Jacobian changes when it is evaluated alone.

    A batched error must treat every edge on its own; one that mixes edges (a mean over the
    edge axis) would give each edge the derivative of the others' terms. Evaluating one edge
    again costs little and catches that (once per type, at its first linearisation).

    Args:
        edge_type: The edge class.
        x: As in :func:`autodiff_linearize`.
        measurement: As in :func:`autodiff_linearize`.
        ctx: As in :func:`autodiff_linearize`.
        error: The group's errors from the same estimates.
        jacobians: The group's Jacobians.

    Raises:
        GraphError: the edge's values differ (naming the type).
    """
    if len(measurement) < 2:
        return
    sub = ctx.subset(slice(0, 1)) if ctx is not None and hasattr(ctx, "subset") else ctx
    e1, j1, _ = autodiff_linearize(edge_type, [xi[:1] for xi in x], measurement[:1], sub)
    scale = max(float(np.max(np.abs(error[:1]), initial=0.0)), 1e-300)
    bad = not np.allclose(e1, error[:1], rtol=1e-9, atol=1e-12 * scale)
    for a, b in zip(j1, jacobians, strict=True):
        s = max(float(np.max(np.abs(b[:1]), initial=0.0)), 1e-300)
        bad = bad or not np.allclose(a, b[:1], rtol=1e-9, atol=1e-12 * s)
    if bad:
        raise GraphError(
            f"{edge_type.__name__}: the first edge's error or Jacobian changes when it is "
            "evaluated alone: the batched error mixes edges (a sum, mean or sort over the edge "
            "axis?), which neither automatic nor numeric differentiation supports; each edge's "
            "error must depend on its own vertices only")


def jet_error_message(edge_type: type, exc: JetError) -> str:
    """The message of a :class:`JetError` raised inside ``edge_type``'s error."""
    return (f"{edge_type.__name__}: {exc} (in its error or its vertices' oplus). Write that "
            "step with the supported NumPy operations (docs/autodiff.md), give the type analytic "
            "Jacobians, or set differentiation = 'numeric'")
