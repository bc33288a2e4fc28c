"""Errors, Jacobians and robust weights of every edge group at the current estimates.

:class:`Linearizer` is the per-linearisation tier on the edge side: it gathers each group's
vertex estimates by slot (cached per state), calls the edge type's batched ``evaluate`` or
``linearize``, applies the information matrix and the robust kernel, and hands the linear system
``J``, ``ρ'ΩJ`` and ``ρ'Ωe`` per group. Where those are scattered into the normal equations is
the linear system's business (:mod:`graphopt.linear`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from graphopt.activity import only_active
from graphopt.autodiff.jacobians import distinct_vertices
from graphopt.edge import EdgeContext, Linearization
from graphopt.edge_output import checked_output, raise_non_finite_edge, reduced_error, where
from graphopt.errors import GraphError
from graphopt.row_weights import row_dots, weighted_rows
from graphopt.storage import EdgeGroup, VertexStore

Positions = list[list[tuple[int, np.ndarray]]]

#: Edges per call of an edge type's ``evaluate``/``linearize`` in a larger group. Only one
#: chunk's gathered estimates and derived values are alive at a time (a few MB, against 168
#: bytes per BAL edge for the whole group: cameras, rotations and points); the results are
#: copied into the group's arrays.
CHUNK_EDGES = 65536

#: Groups of at most this many edges whose type has analytic Jacobians linearise on trial steps
#: as if the type set ``linearize_on_trial``: their Jacobians are small (a few MB), a trial's
#: linearisation costs about twice its errors, and an accepted trial — most of them — spares
#: the next linearisation's edge pass (measured: a 5,000-observation local BA 3.3 -> 2.3 ms an
#: iteration, a 100-match motion-only BA 140 -> 122 µs). A rejected trial evaluates errors
#: only (``Algorithm.trial_linearizes``).
TRIAL_LINEARIZE_EDGES = 32768


@dataclass
class Evaluation:
    """Totals of one evaluation of every edge.

    Args:
        chi2: ``Σ e'Ωe`` without robust kernels.
        robust_chi2: ``Σ ρ(e'Ωe)`` (g2o's chi2); ``inf`` if any error is not finite.
        active: Edges active in this evaluation.
    """

    chi2: float
    robust_chi2: float
    active: int


@dataclass
class WeightedLinearization:
    """Per edge group, what the normal equations are built from.

    Args:
        jacobians: Per group, per vertex position, ``J`` ``(m, rows, d)`` (C-contiguous).
        weighted: Per group, per position, ``ρ'ΩJ`` ``(m, rows, d)`` (C-contiguous); ``J``
            itself at a position whose vertices are all fixed (no block uses it).
        weighted_errors: Per group ``ρ'Ωe`` ``(m, rows)`` (``rows``: the error dimension, or
            ``linearization_rows`` for a reduced linearisation).
    """

    jacobians: list[tuple[np.ndarray, ...]]
    weighted: list[tuple[np.ndarray, ...]]
    weighted_errors: list[np.ndarray]


def broadcast_row(a: np.ndarray, one: int, m: int, transposed: bool) -> np.ndarray:
    """Row ``one`` of ``a`` (column ``one`` of a transposed store) repeated ``m`` times, as a
    read-only view with stride 0 (1 µs; ``np.broadcast_to`` takes 4)."""
    if not a.flags.c_contiguous:
        row = a[:, one] if transposed else a[one]
        return np.broadcast_to(row, (m, *row.shape))
    if transposed:
        shape, offset, strides = (m, a.shape[0]), one * a.strides[1], (0, a.strides[0])
    else:
        shape, offset, strides = (m, *a.shape[1:]), one * a.strides[0], (0, *a.strides[1:])
    view = np.ndarray(shape, a.dtype, a, offset, strides)
    view.flags.writeable = False
    return view


class Linearizer:
    """Evaluates and linearises every edge group.

    Args:
        stores: The vertex stores, in the order of ``positions``' store indices.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
    """

    def __init__(self, stores: list[VertexStore], groups: list[EdgeGroup],
                 positions: Positions) -> None:
        self.stores = stores
        self.groups = groups
        self.positions = positions
        # A trial's linearisation per group (linearize_on_trial types), keyed by the state.
        self._lin_cache: dict[int, tuple[tuple[int, ...], Linearization]] = {}
        #: Per group, whether it linearises on trial steps (see TRIAL_LINEARIZE_EDGES).
        self.on_trial = [g.etype.linearize_on_trial or (
            g.size <= TRIAL_LINEARIZE_EDGES and g.etype.has_analytic_jacobians())
            for g in groups]
        # Per (store, "estimates" | "derived"): (estimate version, array to gather edges from,
        # whether it is stored transposed).
        self._state_cache: dict[tuple[int, str], tuple[int, np.ndarray | None, bool]] = {}
        self.last: Evaluation | None = None
        # (group, first edge, end) -> (the slots, their EdgeContext.vertices): see _vertices.
        self._distinct: dict[tuple[int, int, int], tuple[Any, Any]] = {}
        # (group, method, edges) whose output passed _checked as it was (no conversion): a type
        # returns the same kinds and shapes at every call, so later calls are trusted.
        self._trusted: set[tuple[int, str, int]] = set()
        # Per group, per position: whether any of its vertices is free. A Jacobian of fixed
        # vertices only reaches no block, so it is not weighted (fixed flags are structure: a
        # change builds a new problem).
        self._live = [tuple(bool(len(slots)) and not stores[si].fixed[slots].all()
                            for si, slots in pos) for pos in positions]
        # Per group, per position: the one slot every edge has there (a pose's unary edges, the
        # Sim(3) of OptimizeSim3), or -1. Such a position is gathered as a read-only broadcast
        # of that vertex's estimate (stride 0), which batched code can treat as one transform
        # (graphopt.lie: one (m, 3) x (3, 3) product instead of m small ones). ``None``: the
        # type wrote into its inputs once, so the group gets copies.
        self._one: list[tuple[int, ...] | None] = [
            tuple(int(slots[0]) if len(slots) > 1 and not np.any(slots != slots[0]) else -1
                  for _, slots in pos) for pos in positions]
        self.last_state: tuple[tuple[int, ...], tuple[int, ...]] | None = None
        # Per group, the store index of each vertex position (``raw_eval``'s state, see
        # keep_errors); None where they are every store in order (the state itself).
        every = tuple(range(len(stores)))
        self._stores_of = [None if at == every else at
                           for at in (tuple(si for si, _ in pos) for pos in positions)]
        # The one store and the one group, if so (a motion-only BA's): see state_key.
        self._lone = (stores[0], groups[0]) if len(stores) == len(groups) == 1 else None
        # Per group, what a trial that linearised computed besides the linearisation — Ωe,
        # e'Ωe, ρ, ρ' — keyed by (state, activity version): the next linearize reuses it.
        self._weights: dict[int, tuple[object, Linearization, np.ndarray, np.ndarray,
                                       np.ndarray, np.ndarray | None]] = {}

    # --- gathering ---------------------------------------------------------------------------

    def gather(self, gi: int) -> tuple[np.ndarray, ...]:
        """Estimates of group ``gi``'s vertices, one ``(m, *estimate_shape)`` array per position
        (read-only where every edge has the same vertex there).

        Args:
            gi: Group index.
        """
        one = self._one[gi]
        if one is None:
            return tuple(self._gather_rows(si, "estimates", slots)  # type: ignore[misc]
                         for si, slots in self.positions[gi])
        return tuple(self._gather_rows(si, "estimates", slots, o)  # type: ignore[misc]
                     for (si, slots), o in zip(self.positions[gi], one, strict=True))

    def _gather_rows(self, si: int, what: str, slots: np.ndarray, one: int = -1
                     ) -> np.ndarray | None:
        """Rows ``slots`` of a store's estimates or derived values, cached per state.

        2-D arrays ``(n, d)`` are gathered coordinate by coordinate from a transposed copy: the
        result ``(m, d)`` is in Fortran order, so each coordinate over the edges is one
        contiguous array — what batched edge code reads, and a cheaper gather. With ``one``
        (every slot equal to it) the result is a read-only broadcast of that row.
        """
        st = self.stores[si]
        key = (si, what)
        hit = self._state_cache.get(key)
        if hit is None or hit[0] != st.version:
            a = st.estimates if what == "estimates" else st.vtype.derived(st.estimates)
            transposed = a is not None and a.ndim == 2
            hit = (st.version, np.ascontiguousarray(a.T) if transposed else a, transposed)
            self._state_cache[key] = hit
        _, a, transposed = hit
        if a is None:
            return None
        if one >= 0:
            return broadcast_row(a, one, len(slots), transposed)
        # take, not a[slots]: 4x faster on (n, 4, 4) poses (a 33 against 8 µs gather of
        # 4,807 edges' poses); the method, not np.take: 1 against 2.5 µs a call.
        return a.take(slots, axis=1).T if transposed else a.take(slots, axis=0)

    def context(self, gi: int) -> EdgeContext:
        """Group ``gi``'s context, with the vertices' derived values if its type uses them.

        Args:
            gi: Group index.
        """
        g = self.groups[gi]
        ctx = g.context()
        if g.etype.uses_derived:
            ctx.derived = tuple(self._gather_rows(si, "derived", slots)
                                for si, slots in self.positions[gi])
        ctx.vertices = self._vertices(gi, slice(0, g.size))
        return ctx

    def _vertices(self, gi: int, sl: slice) -> tuple[tuple[np.ndarray, np.ndarray], ...] | None:
        """:attr:`EdgeContext.vertices` of edges ``sl`` of group ``gi`` for a type that is
        differentiated automatically (else ``None``): structure, found once per chunk."""
        if self.groups[gi].etype.differentiation_method() != "autodiff":
            return None
        slots = tuple(s for _, s in self.positions[gi])
        hit = self._distinct.get((gi, sl.start, sl.stop))
        if hit is None or any(a is not b for a, b in zip(hit[0], slots, strict=True)):
            hit = (slots, tuple(distinct_vertices(s[sl]) for s in slots))
            self._distinct[gi, sl.start, sl.stop] = hit
        return hit[1]

    def _state(self) -> tuple[int, ...]:
        """Versions of every store's estimates: the key of cached linearisations."""
        return tuple(st.version for st in self.stores)

    def _linearization(self, gi: int, consume: bool = False,
                       key: tuple[int, ...] | None = None) -> Linearization:
        """Group ``gi``'s linearisation, reusing a trial's if the state is the same.

        Args:
            gi: Group index.
            consume: Drop the cached trial linearisation once used (the assembly's): its
                Jacobians would otherwise stay alive through the solves, next to the normal
                equations formed from them.
            key: The current state (:meth:`_state`), if known.
        """
        if not self._lin_cache and not self.on_trial[gi]:  # nothing to reuse or keep
            return self._run(gi, "linearize")
        key = self._state() if key is None else key
        hit = self._lin_cache.pop(gi, None) if consume else self._lin_cache.get(gi)
        if hit is not None and hit[0] == key:
            return hit[1]
        # A stale trial's (a rejected step's) Jacobians: not alive next to the new ones.
        self._lin_cache.pop(gi, None)
        del hit
        out = self._run(gi, "linearize")
        if self.on_trial[gi] and not consume:  # the assembly's is not kept
            self._lin_cache[gi] = (key, out)
        return out

    # --- checking what edge types return ------------------------------------------------------

    def _run(self, gi: int, method: str) -> Linearization:
        """Group ``gi``'s ``evaluate`` or ``linearize``, in chunks of :data:`CHUNK_EDGES`
        edges when it is larger (one call per chunk, not per edge; the results are the same
        as one call's for types that treat every edge on its own, as batched types do).

        Args:
            gi: Group index.
            method: ``"evaluate"`` or ``"linearize"``.
        """
        g = self.groups[gi]
        if g.size <= CHUNK_EDGES:
            try:
                return self._call(g, method, self.gather(gi), self.context(gi))
            except ValueError as exc:  # a type that writes into a broadcast input: copies
                if self._one[gi] is None or "read-only" not in str(exc):
                    raise
                self._one[gi] = None
                return self._call(g, method, self.gather(gi), self.context(gi))
        full: list[np.ndarray | None] = []
        for c0 in range(0, g.size, CHUNK_EDGES):
            sl = slice(c0, min(c0 + CHUNK_EDGES, g.size))
            x = tuple(self._gather_rows(si, "estimates", slots[sl])  # type: ignore[misc]
                      for si, slots in self.positions[gi])
            ctx = g.context().subset(sl)
            if g.etype.uses_derived:
                ctx.derived = tuple(self._gather_rows(si, "derived", slots[sl])
                                    for si, slots in self.positions[gi])
            ctx.vertices = self._vertices(gi, sl)
            out = self._call(g, method, x, ctx, sl)
            del x, ctx
            parts = [out.error, *out.jacobians, out.reduced_error, out.active]
            if not full:
                full = [None if a is None else np.empty((g.size, *np.shape(a)[1:]),
                                                        dtype=np.asarray(a).dtype)
                        for a in parts]
            for i, a in enumerate(parts):
                if a is None and full[i] is None:
                    continue
                if full[i] is None:  # an active mask from this chunk on: the others' are all
                    full[i] = np.ones(g.size, dtype=bool)
                target = full[i]
                assert target is not None
                target[sl] = True if a is None else a
        nj = len(full) - 3
        return Linearization(full[0], tuple(full[1:1 + nj]), full[-2],  # type: ignore[arg-type]
                             full[-1])

    def _call(self, g: EdgeGroup, method: str, x: tuple[np.ndarray, ...],
              ctx: EdgeContext, chunk: slice | None = None) -> Linearization:
        """Call the type's ``evaluate`` or ``linearize`` on group ``g`` (or a chunk of its
        edges) and check the result.

        Args:
            g: The group.
            method: ``"evaluate"`` or ``"linearize"``.
            x: The estimates of the call's edges, per position.
            ctx: Their context.
            chunk: The call's edges (``None``: all of the group's).

        Raises:
            GraphError: a result of the wrong kind or shape (naming the type and the group's
                first edge), also when raised inside the call (numeric differences check
                ``error`` and ``oplus``).
        """
        meas = g.measurements if chunk is None else g.measurements[chunk]
        try:
            out = getattr(g.etype, method)(x, meas, ctx)
        except GraphError as exc:
            raise GraphError(f"{exc} ({where(g)})") from exc
        key = (id(g), method, len(meas))
        if type(out) is Linearization and key in self._trusted:
            return out
        checked = checked_output(g, out, method, len(meas))
        if checked is out:
            self._trusted.add(key)
        return checked

    # --- weighting ---------------------------------------------------------------------------

    @staticmethod
    def _robustify(g: EdgeGroup, s: np.ndarray, weights: bool = True
                   ) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-edge ρ(s) and the weight ρ'(s) (clipped at 0; ``None`` unless ``weights``)."""
        if not g.kernels:
            return s, np.ones_like(s) if weights else None
        kern = g.sole_kernel
        if kern is not None:
            return kern.cost_and_clipped_weight(s) if weights else (kern.cost(s), None)
        rho = s.copy()
        w = np.ones_like(s)
        for ki, kern in enumerate(g.kernels):
            sel = g.kernel_index == ki
            if sel.any():
                rho[sel], w[sel] = kern.cost_and_clipped_weight(s[sel])
        return rho, w

    @staticmethod
    def _sq(g: EdgeGroup, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Ω e`` and ``e'Ω e`` per edge."""
        if g.info_is_identity:
            return e, row_dots(e, e)
        info, diag = g.information, g.info_diagonal  # diag: per-edge diagonal, a row scaling
        assert info is not None
        oe = (e @ info if info.ndim == 2 else e * diag if diag is not None
              else np.einsum("mij,mj->mi", info, e))
        return oe, row_dots(e, oe)

    def _weigh(self, gi: int, g: EdgeGroup, out: Linearization, state: tuple[int, ...]
               ) -> tuple[Linearization, np.ndarray, np.ndarray]:
        """``(out with inactive rows zeroed, Ωe, e'Ωe)`` of group ``gi``; every edge's errors
        are kept on the group (``raw_eval``) for the edge-set queries that usually follow an
        optimisation at the same estimates (ORB-SLAM's outlier checks)."""
        self.keep_errors(gi, state, out.error)
        act = g.active_edges
        if act is not None:  # edges of other levels: zero rows (also where not finite)
            out = only_active(out, act)
        oe, s = self._sq(g, out.error)
        return out, oe, s

    def keep_errors(self, gi: int, state: tuple[int, ...], e: np.ndarray,
                    s: np.ndarray | None = None) -> None:
        """Keep every edge's errors ``e`` of group ``gi`` at ``state`` (``raw_eval``), for the
        edge-set queries that usually follow an optimisation at the same estimates.

        Args:
            gi: Group index.
            state: Every store's estimate version (:meth:`_state`).
            e: ``(m, dimension)`` errors, whatever the edges' levels.
            s: ``(m,)`` every edge's ``e'Ωe``, if known (else the queries form it).
        """
        g = self.groups[gi]
        at = self._stores_of[gi]
        g.raw_eval = (state if at is None else tuple([state[si] for si in at]), g.next_uid,
                      g.removals), e, s

    def _record(self, g: EdgeGroup, s: np.ndarray, rho: np.ndarray,
                active: np.ndarray | None, totals: list[float], chi2: float | None = None
                ) -> None:
        """Keep a group's per-edge chi2 and active count; add its sums to ``totals``
        (``chi2``: ``s.sum()`` if already known)."""
        g.last_chi2 = s
        g.active_count = g.size if active is None else int(np.count_nonzero(active))
        chi2 = float(s.sum()) if chi2 is None else chi2
        totals[0] += chi2
        totals[1] += chi2 if rho is s else float(rho.sum())
        totals[2] += g.active_count

    def _finish(self, totals: list[float], state: tuple[int, ...],
                key: tuple[tuple[int, ...], tuple[Any, ...]] | None = None) -> Evaluation:
        """Keep the evaluation's totals as :attr:`last`, made at ``state`` (``key``: its
        :meth:`state_key`, if the caller has it)."""
        rchi2 = totals[1] if math.isfinite(totals[1]) else float("inf")
        self.last = Evaluation(totals[0], rchi2, int(totals[2]))
        self.last_state = key if key is not None else (
            state, tuple(g.activity_version for g in self.groups))
        return self.last

    def state_key(self) -> tuple[tuple[int, ...], tuple[Any, ...]]:
        """What an evaluation depends on besides the structure: estimates, levels, kernels
        (formed without comprehensions for one store and one group: a motion-only BA's key,
        taken twice an iteration)."""
        if self._lone is not None:
            st, g = self._lone
            return (st.version,), (g.activity_version,)
        return self._state(), tuple([g.activity_version for g in self.groups])

    # --- the two entry points ----------------------------------------------------------------

    def evaluate(self, linearize_trial: bool = True) -> Evaluation:
        """Errors only (a trial step): chi2, robust chi2 and active edges at the current state.

        Types with ``linearize_on_trial`` (and small groups of analytic types, see
        :data:`TRIAL_LINEARIZE_EDGES`) linearise instead when ``linearize_trial`` is set, and
        keep the result for the next :meth:`linearize` at the same state (the errors are then
        computed once for an accepted step).

        Args:
            linearize_trial: Let ``linearize_on_trial`` types linearise; pass ``False`` for a
                trial that is likely rejected, which then costs the errors alone.

        Raises:
            GraphError: an error (or Jacobian) of the wrong shape, naming the type.
        """
        totals = [0.0, 0.0, 0.0]
        self._weights.clear()
        state = self._state()
        for gi, g in enumerate(self.groups):
            on_trial = linearize_trial and self.on_trial[gi]
            out = (self._linearization(gi, key=state) if on_trial
                   else self._run(gi, "evaluate"))
            out, oe, s = self._weigh(gi, g, out, state)
            rho, w = self._robustify(g, s, weights=on_trial)
            if on_trial:  # the next linearize at this state takes all of it
                self._weights[gi] = ((state, g.activity_version), out, oe, s, rho, w)
            self._record(g, s, rho, out.active, totals)
        return self._finish(totals, state)

    def linearize(self) -> tuple[WeightedLinearization, Evaluation]:
        """Errors, Jacobians and robust weights of every group at the current state.

        Returns:
            ``J``, ``ρ'ΩJ`` and ``ρ'Ωe`` per group, and the evaluation totals.

        Raises:
            FloatingPointError: a non-finite error or Jacobian (naming the edge).
            GraphError: an error, Jacobian or reduced linearisation of the wrong shape.
        """
        jac, wjac, wes = [], [], []
        totals = [0.0, 0.0, 0.0]
        state = self._state()
        versions = tuple(g.activity_version for g in self.groups)
        hits = [self._weights.pop(gi, None) for gi in range(len(self.groups))]
        valid = [h is not None and h[0] == (state, v)
                 for h, v in zip(hits, versions, strict=True)]
        # Every group linearised by the last trial at this state: its evaluation's totals
        # (finite: the trial was accepted) and per-group records stand.
        reuse = self.last is not None and self.last_state == (state, versions) and all(valid)
        for gi, g in enumerate(self.groups):
            if valid[gi]:  # the trial's linearisation at this state, weighted already
                self._lin_cache.pop(gi, None)
                _, out, oe, s, rho, w = hits[gi]  # type: ignore[misc]
            else:
                out = self._linearization(gi, consume=True, key=state)
                out, oe, s = self._weigh(gi, g, out, state)
                rho, w = self._robustify(g, s)
            hits[gi] = None  # a stale trial's arrays are not kept alive through the assembly
            e, J = out.error, out.jacobians
            if g.etype.linearization_rows is not None:
                oe = reduced_error(g, out)
            assert w is not None
            if not reuse:
                chi2 = float(s.sum())
                if not math.isfinite(chi2):  # one sum is cheaper than isfinite().all()
                    raise_non_finite_edge(g, e, J)
                self._record(g, s, rho, out.active, totals, chi2)
            J, wj, we = weighted_rows(g, J, oe, w, self._live[gi])
            jac.append(J)
            wjac.append(wj)
            wes.append(we)
        ev = self.last if reuse and self.last is not None else self._finish(totals, state)
        return WeightedLinearization(jac, wjac, wes), ev

    def raise_non_finite(self, lin: WeightedLinearization) -> None:
        """Raise naming the first edge with a non-finite error or Jacobian.

        Args:
            lin: The linearisation whose assembly turned out not finite.

        Raises:
            FloatingPointError: always (naming the edge where one is found).
        """
        for g, J, e in zip(self.groups, lin.jacobians, lin.weighted_errors, strict=True):
            raise_non_finite_edge(g, e, J)
        raise FloatingPointError("the normal equations are not finite (overflow)")
