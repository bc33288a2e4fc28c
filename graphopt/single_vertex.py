"""A problem with one free vertex and nothing to eliminate, linearised and solved in a few calls.

ORB-SLAM's most frequent optimisation — a motion-only BA of about 100 matches, every frame —
takes 13 iterations of a 6-unknown system: it is bound by Python calls, not flops. The general
:class:`~graphopt.problem.Problem` builds a block index, a pattern, a Schur plan and the
solver's analysis for it, and every iteration goes through the linearizer's per-state caches,
the assembler, the Schur reduction and the solver interface. Here the structure is the one
vertex's slot and, per edge group, which positions hold it; an iteration is the edge type's
call, its weights, two products for ``H`` and ``b``, and LAPACK's ``dpotrf``/``dpotrs`` on
``H + λD``. The numbers are formed as on the general path (the row weights of
:func:`~graphopt.row_weights.weighted_rows`, with inactive edges weighted zero where the general
path zeroes their rows; the products of
:class:`~graphopt.linear.single_block.SingleBlockAssembler`; the dense solver's rank rule), so
both paths give the same iterations; the tests compare them. With numba, a group whose type
offers a compiled loop (:mod:`graphopt.compiled`) is evaluated by it, the same numbers to
rounding.

The general path's objects that only a few callers need — the :class:`~graphopt.linear.
LinearSystem` (marginal covariances, :attr:`SparseOptimizer.linear_system`) and the solver's
symbolic analysis — are built on first use.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from graphopt.allocator import tune as tune_allocator
from graphopt.edge import EdgeContext, Linearization
from graphopt.edge_output import checked_output, raise_non_finite_edge
from graphopt.errors import GraphError
from graphopt.evaluation_memo import EvaluationMemo
from graphopt.linear import Assembly, LinearSystem, SchurConfig
from graphopt.linear.single_block import SingleBlockAssembler, group_terms
from graphopt.linearizer import (
    TRIAL_LINEARIZE_EDGES,
    Evaluation,
    Linearizer,
    Positions,
    broadcast_row,
)
from graphopt.problem import Problem, Timing
from graphopt.row_weights import weighted_rows
from graphopt.single_vertex_ops import OneVertexOps
from graphopt.solvers import LinearSolver, LinearSolverAuto, LinearSolverDense
from graphopt.storage import EdgeGroup, VertexStore
from graphopt.unary_terms import (
    CompiledGroup,
    Weighing,
    compiled_group,
    compiled_terms,
    unary_terms,
    weighing,
)

#: Most unknowns of the one vertex (a dense ``d × d`` system; poses, Sim(3), cameras).
MAX_DIMENSION = 64


class SingleVertexProblem(OneVertexOps, Problem):
    """:class:`~graphopt.problem.Problem` for graphs with exactly one free vertex, not
    marginalised, and small edge groups. Use :meth:`of`, which returns ``None`` otherwise.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
        solver: The dense (or automatic) solver, analysed only if :attr:`system` is used.
        schur: Passed on to the :class:`LinearSystem` built on first use.
        free: ``(store index, slot)`` of the free vertex.
    """

    replayable = True

    def __init__(self, stores: list[VertexStore], groups: list[EdgeGroup],
                 positions: Positions, solver: LinearSolver, schur: SchurConfig | None,
                 free: tuple[int, int]) -> None:
        tune_allocator()  # no page faults for the arrays every iteration allocates again
        self.stores = stores
        self.groups = groups
        self.positions = positions
        self.solver = solver
        self._schur_config = schur
        self._system: LinearSystem | None = None
        self.linearizer = Linearizer(stores, groups, positions)
        self.trial_linearization = True
        self.timing = Timing()
        self._pushed: np.ndarray | None = None  # the free store's estimates before a trial
        si, slot = free
        self._store, self._slot = si, slot
        self._free = [si]
        self.runs: dict[tuple[Any, ...], Any] = {}  # kept runs (graphopt.run_memo)
        self.d = d = stores[si].vtype.dimension
        self._diag = np.arange(d) * (d + 1)  # diagonal positions in H's column-major data
        self._ones = np.ones(d)
        self._ones.flags.writeable = False
        # Per group: whether the free vertex is at each position, per edge.
        on = [[(s == si) & (slots == slot) for s, slots in pos] for pos in positions]
        self._on_any = [o[0] if len(o) == 1 else np.logical_or.reduce(o) if o
                        else np.zeros(0, dtype=bool) for o in on]
        #: Groups whose Jacobians reach ``H`` (the others are evaluated for their chi2 only).
        self._touch = [bool(a.any()) for a in self._on_any]
        self._assembler = SingleBlockAssembler(d, [group_terms(o) for o in on])
        # Per group, its context once its output has been checked (None: not yet, or it uses
        # derived values, which change with the estimates).
        self._ctx: list[EdgeContext | None] = [None] * len(groups)
        # Per group: one position, the free vertex at every edge (a pose's unary edges; more
        # than one edge, as the linearizer's broadcast gather).
        self._unary = [len(o) == 1 and len(o[0]) > 1 and bool(o[0].all()) for o in on]
        # Per unary group: the type's outputs by the free vertex's estimate.
        self._memo = [EvaluationMemo() for _ in groups]
        # Per unary group: its weighing at an activity version (None: the general weighting).
        self._weighing: list[tuple[tuple[int, int], Weighing | None] | None] = [None] * len(groups)
        # Per unary group: (measurements, activity version, compiled evaluation, the type's
        # loop).
        self._compiled: list[tuple[Any, ...] | None] = [None] * len(groups)
        # The last evaluation's (state key, Hᵀ, Jᵀρ'Ωe, Jacobians per group), for the
        # linearisation at that state.
        self._terms: tuple[object, np.ndarray | None, np.ndarray | None,
                           list[tuple[np.ndarray, ...] | None]] | None = None
        self._idle_key: tuple[tuple[int, int], ...] | None = None
        self._idle = False

    @classmethod
    def of(cls, stores: list[VertexStore], groups: list[EdgeGroup], positions: Positions,
           solver: LinearSolver, schur: SchurConfig | None = None
           ) -> SingleVertexProblem | None:
        """The single-vertex problem of a resolved graph, or ``None`` if it has another number
        of free vertices, a marginalised one, a group larger than
        :data:`~graphopt.linearizer.TRIAL_LINEARIZE_EDGES`, a reduced linearisation, or a solver
        of another class than the dense or automatic one (a user's own solver is called as
        given).

        Args:
            stores: The vertex stores.
            groups: The finalised edge groups.
            positions: Per group, per vertex position: ``(store index, slots (m,))``.
            solver: The solver made for the problem.
            schur: The Schur configuration.
        """
        if type(solver) not in (LinearSolverDense, LinearSolverAuto):
            return None
        free = [(si, np.flatnonzero(~st.fixed)) for si, st in enumerate(stores)]
        if sum(len(f) for _, f in free) != 1:
            return None
        si, slots = next((si, f) for si, f in free if len(f))
        slot = int(slots[0])
        st = stores[si]
        if st.marginalized[slot] or st.vtype.dimension > MAX_DIMENSION:
            return None
        if any(g.size > TRIAL_LINEARIZE_EDGES or g.etype.linearization_rows is not None
               for g in groups):
            return None
        return cls(stores, groups, positions, solver, schur, (si, slot))

    @property
    def system(self) -> LinearSystem:  # type: ignore[override]
        """The general linear system (built, and the solver analysed, on first use)."""
        if self._system is None:
            self._system = LinearSystem(self.stores, self.groups, self.positions,
                                        self._schur_config)
            self.solver.analyze(self._system.pattern, self._system.udims)
        return self._system

    # --- evaluation --------------------------------------------------------------------------

    def _evaluate(self, linearize: bool, every: bool = False, safe: bool = False,
                  memo: bool = True) -> Evaluation:
        """Every group's errors and, with ``linearize``, the normal equations' terms of the
        groups that reach ``H`` and linearise on trial steps (``every``: of all that reach
        ``H``), kept for :meth:`linearize` at this state; the totals.

        Inactive edges (other levels, or deactivated by their type) weigh zero. Unless
        ``safe``, their rows are not zeroed first, as :func:`~graphopt.activity.only_active`
        does, but their weights: the same numbers, two array passes fewer — unless one of their
        Jacobians is not finite, which :meth:`linearize` finds in ``H`` and then evaluates
        again with ``safe``. ``memo``: look the unary groups' outputs up in (and add them to)
        their :class:`~graphopt.evaluation_memo.EvaluationMemo`."""
        lz = self.linearizer
        totals = [0.0, 0.0, 0.0]
        state, versions = key = lz.state_key()
        ht = bu = None
        jac: list[tuple[np.ndarray, ...] | None] = []
        complete = True
        for gi, g in enumerate(self.groups):
            touch = self._touch[gi]
            lin = linearize and touch and (every or lz.on_trial[gi])
            cg = self._compiled_of(gi, g, versions[gi]) if self._unary[gi] and not safe else None
            fused = None
            if cg is not None:  # the type's compiled loop (graphopt.compiled)
                e, s_all, s, hg, bg, chi, rchi = compiled_terms(
                    cg, self.stores[self._store].estimates[self._slot], lin)
                fused, J = cg.count, None  # J: the type's, if wanted
            else:
                out = self._call(gi, g, "linearize" if lin else "evaluate", memo)
                wg = (self._weighing_of(gi, g, versions[gi])
                      if self._unary[gi] and not safe and out.active is None else None)
                if wg is not None:  # one vertex, one kernel or none, a diagonal Ω: fused
                    e, J = out.error, (out.jacobians[0],) if lin else ()
                    s_all, s, chi, rchi, hg, bg = unary_terms(wg, e, J[0] if J else None)
                    fused = wg.count
            if fused is not None:
                self._keep(gi, g, state, e, s, fused, s_all)
                totals[0] += chi
                totals[1] += rchi
                totals[2] += fused
                if lin:
                    ht = hg if ht is None else ht + hg
                    bu = bg if bu is None else bu + bg
            else:
                if safe:
                    out, oe, s = lz._weigh(gi, g, out, state)
                    rho, w = lz._robustify(g, s, weights=lin)
                    lz._record(g, s, rho, out.active, totals)
                    if lin:
                        assert w is not None
                        J, wj, we = weighted_rows(g, out.jacobians, oe, w, lz._live[gi])
                else:
                    J, wj, we = self._lean_terms(gi, g, out, state, lin, totals)
                if lin:
                    ht, bu = self._assembler.add_group(gi, J, wj, we, ht, bu)
            if lin:
                jac.append(J)
            else:
                complete = complete and not touch
                jac.append(())
        ev = lz._finish(totals, state, key)
        self._terms = (key, ht, bu, jac) if linearize and complete else None
        return ev

    def _weighing_of(self, gi: int, g: EdgeGroup, version: tuple[int, int]
                     ) -> Weighing | None:
        """Group ``gi``'s :class:`~graphopt.unary_terms.Weighing` at its activity ``version``."""
        kept = self._weighing[gi]
        if kept is None or kept[0] != version:
            kept = self._weighing[gi] = (version, weighing(g))
        return kept[1]

    def _compiled_of(self, gi: int, g: EdgeGroup, version: tuple[int, int]
                     ) -> CompiledGroup | None:
        """Group ``gi``'s compiled evaluation at its activity ``version``, or ``None``."""
        kept = self._compiled[gi]
        if kept is not None and kept[1] == version and kept[0] is g.measurements:
            return kept[2]
        same = kept is not None and kept[0] is g.measurements
        loop = (kept[3] if same else None if g.etype.uses_derived  # type: ignore[index]
                else g.etype.compiled_unary(g.measurements, g.context()))
        cg = None if loop is None else compiled_group(loop, weighing(g, active_info=False))
        self._compiled[gi] = (g.measurements, version, cg, loop)
        return cg

    def _keep(self, gi: int, g: EdgeGroup, state: tuple[int, ...], e: np.ndarray,
              s: np.ndarray, count: int, every: np.ndarray | None = None) -> None:
        """Keep a group's errors (and ``every`` edge's ``e'Ωe``) for the edge sets' queries at
        this state (``raw_eval``), its chi2 per edge and active count (``Linearizer._record``)."""
        self.linearizer.keep_errors(gi, state, e, every)
        g.last_chi2 = s
        g.active_count = count

    def _call(self, gi: int, g: EdgeGroup, method: str, use_memo: bool) -> Linearization:
        """:meth:`Linearizer._run` without its per-call bookkeeping once a group's output was
        checked: the context kept (no derived values), the type's method called directly; with
        ``use_memo``, a unary group's outputs kept by the estimate
        (:mod:`~graphopt.evaluation_memo`)."""
        lz = self.linearizer
        memo = None
        unary = self._unary[gi] and lz._one[gi] is not None
        if unary:
            est = self.stores[self._store].estimates
            if use_memo:
                memo = self._memo[gi]
                at = est[self._slot].tobytes()
                out = memo.get(method, at)
                if out is not None:
                    return out
            self._memo[gi].release()  # the type is called again
        ctx = self._ctx[gi]
        if ctx is None:
            if g.etype.uses_derived:  # derived values change with the estimates
                return lz._run(gi, method)
            ctx = self._ctx[gi] = lz.context(gi)  # with the vertex grouping autodiff uses
        if unary:  # the free vertex's row, broadcast
            x: tuple[np.ndarray, ...] = (broadcast_row(est, self._slot, g.size, False),)
        else:
            x = lz.gather(gi)
        try:
            out = getattr(g.etype, method)(x, g.measurements, ctx)
        except (GraphError, ValueError):  # named, or a broadcast input written: the full path
            out = lz._run(gi, method)
        else:
            key = (id(g), method, g.size)
            if type(out) is not Linearization or key not in lz._trusted:
                checked = checked_output(g, out, method, g.size)
                if checked is out:
                    lz._trusted.add(key)
                out = checked
        if unary and lz._one[gi] is not None:
            if memo is not None:
                memo.put(method, at, out)
            else:
                self._memo[gi].hold(method, est[self._slot].tobytes(), out)
        return out

    def keep_last_outputs(self) -> None:
        """Put each unary group's latest output that the memo did not take — a run's last
        trial's, at its end state, which a replay of the run evaluates again — into the memo."""
        for memo in self._memo:
            memo.settle()

    def _lean_terms(self, gi: int, g: EdgeGroup, out: Linearization, state: tuple[int, ...],
                    lin: bool, totals: list[float]
                    ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], np.ndarray]:
        """What :meth:`Linearizer._weigh`, ``_robustify``, ``_record`` and
        :func:`~graphopt.row_weights.weighted_rows` do for one group, inactive edges weighed
        zero instead of zeroed: ``(J, ρ'ΩJ, ρ'Ωe)`` if ``lin``, else empty."""
        lz = self.linearizer
        e = out.error
        act = g.active_edges
        if out.active is not None:
            own = np.asarray(out.active, dtype=bool)
            act = own if act is None else act & own
        oe, s = lz._sq(g, e)
        if act is not None:  # an inactive edge's non-finite error reaches b: linearize sees it
            s = np.where(act, s, 0.0)
        rho, w = lz._robustify(g, s, weights=lin) if g.kernels else (s, None)
        self._keep(gi, g, state, e, s, g.size if act is None else int(np.count_nonzero(act)))
        chi2 = float(s.sum())
        totals[0] += chi2
        totals[1] += chi2 if rho is s else float(rho.sum())
        totals[2] += g.active_count
        if not lin:
            return (), (), oe
        return weighted_rows(g, out.jacobians, oe, w, lz._live[gi], act)

    def evaluate(self, linearize: bool = True) -> Evaluation:
        """See :meth:`Problem.evaluate`.

        Args:
            linearize: Keep the Jacobians for the next :meth:`linearize` at this state.
        """
        return self._evaluate(linearize)

    def robust_chi2(self, linearize: bool = True) -> float:
        """See :meth:`Problem.robust_chi2`.

        Args:
            linearize: Linearise the trial (its Jacobians serve the next iteration).
        """
        # A trial's state is a step away from every earlier one: no memo (in ORB-SLAM's
        # procedure only the runs' starts, where a round restarts from the same pose, hit it).
        chi = self._evaluate(linearize, memo=False).robust_chi2
        if not math.isfinite(chi):
            self._check_finite_estimates()
        return chi

    def _idle_vertex(self, key: tuple[tuple[int, int], ...]) -> bool:
        """Whether no active edge reaches the free vertex (levels only, as :class:`~graphopt.
        activity.IdleAnchors`): ``H`` then gets the identity and the step is zero.

        Args:
            key: Every group's ``activity_version`` now.
        """
        if key != self._idle_key:
            self._idle_key = key
            self._idle = True
            for g, on in zip(self.groups, self._on_any, strict=True):
                act = g.active_edges
                if on.any() and (act is None or bool((act & on).any())):
                    self._idle = False
                    break
        return self._idle

    def linearize(self, safe: bool = False) -> tuple[Assembly, float]:
        """See :meth:`Problem.linearize`.

        Args:
            safe: Inactive rows zeroed (after a non-finite Jacobian of an inactive edge).

        Raises:
            FloatingPointError: a non-finite error or Jacobian (naming the edge).
        """
        t0 = time.perf_counter()
        lz = self.linearizer
        terms = self._terms
        key = lz.state_key()
        if terms is None or terms[0] != key:
            self._evaluate(True, every=True, safe=safe)
            terms = self._terms
        assert terms is not None and lz.last is not None
        self._terms = None
        ev = lz.last
        _, ht, bu, jac = terms
        if not math.isfinite(ev.chi2):  # one sum: no pass over the errors when finite
            self._name_non_finite(jac)
        asm = self._assembler.finish(ht, bu)
        if self._idle_vertex(key[1]):
            asm.h_data[self._diag] += 1.0
        h, b = asm.h_data, asm.bu
        if not math.isfinite(h @ h + b @ b) and not (np.isfinite(h).all()  # two dots, not
                                                     and np.isfinite(b).all()):  # four passes
            if not safe and any(g.active_count < g.size for g in self.groups):
                # An inactive edge's non-finite Jacobian: zero the rows, as the general path.
                self._evaluate(True, every=True, safe=True)
                return self.linearize(safe=True)
            self._name_non_finite(jac)
            raise FloatingPointError("the normal equations are not finite (overflow)")
        self.timing.linearize += time.perf_counter() - t0
        return asm, ev.robust_chi2

    def _name_non_finite(self, jac: list[tuple[np.ndarray, ...] | None]) -> None:
        """Raise naming the first edge with a non-finite error or Jacobian among the groups
        that reach ``H`` (their Jacobians ``jac``; ``None``: a compiled loop's, which keeps
        none — the type's own), if there is one."""
        for gi, (g, J) in enumerate(zip(self.groups, jac, strict=True)):
            if J is None:
                J = self._call(gi, g, "linearize", False).jacobians
            if J:
                raise_non_finite_edge(g, g.raw_eval[1], J)  # type: ignore[index]


def make_problem(stores: list[VertexStore], groups: list[EdgeGroup], positions: Positions,
                 solver: LinearSolver, schur: SchurConfig | None = None) -> Problem:
    """The :class:`SingleVertexProblem` where it applies, else the general :class:`Problem`.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
        solver: The linear solver.
        schur: How to form the Schur complement.
    """
    return (SingleVertexProblem.of(stores, groups, positions, solver, schur)
            or Problem(stores, groups, positions, solver, schur))
