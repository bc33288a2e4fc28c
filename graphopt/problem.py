"""The numeric problem the algorithms talk to: linearise, solve, step, evaluate.

:class:`Problem` ties together what :meth:`SparseOptimizer.initialize_optimization
<graphopt.optimizer.SparseOptimizer.initialize_optimization>` builds once — the
:class:`~graphopt.linearizer.Linearizer` (edges), the :class:`~graphopt.linear.LinearSystem`
(normal equations and Schur complement) and the linear solver with its symbolic analysis — with
the state stack and the step layout. A step is ``(u part, [v part per V class])``: the unknowns
of the reduced system and, per class of marginalised vertices, their ``(n, d)`` increments.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from graphopt.activity import IdleAnchors
from graphopt.allocator import tune as tune_allocator
from graphopt.errors import GraphError, NotPositiveDefiniteError
from graphopt.linear import Assembly, LinearSystem, SchurConfig
from graphopt.linearizer import Evaluation, Linearizer, Positions
from graphopt.numeric import checked_oplus
from graphopt.solvers import LinearSolver
from graphopt.solvers.auto import available_memory
from graphopt.storage import EdgeGroup, VertexStore

#: ``(u part (n,), [v part (n_c, d_c) per V class])``.
Step = tuple[np.ndarray, list[np.ndarray]]


@dataclass
class Timing:
    """Seconds spent since the last :meth:`Problem.reset_timing`.

    Args:
        linearize: Errors, Jacobians and assembly.
        schur: Damping, Schur complement and back-substitution.
        solve: The linear solver.
    """

    linearize: float = 0.0
    schur: float = 0.0
    solve: float = 0.0


@dataclass
class _StoreUpdate:
    """Where a store's increments are in a step: U slots and their columns, V slots."""

    uslots: np.ndarray  # (k,) store slots with a U block
    upos: np.ndarray  # (k, d) their columns in the u part
    vclass: int  # V class of the store's marginalised vertices, or -1
    vslots: np.ndarray  # (n_c,) store slots of the V class, by V block
    # Every slot a U block whose columns are one contiguous run: the step's part is a
    # reshaped slice, the update needs no gather or scatter (a motion-only BA's one pose).
    whole: slice | None = None


#: A trial linearises only while one set of its Jacobians takes at most this share of the
#: memory available when the problem is built (matrix-free solvers only; see below).
TRIAL_JACOBIAN_SHARE = 1 / 8


def trial_linearization_allowed(groups: list[EdgeGroup], matrix_free: bool,
                                available: float) -> bool:
    """Whether trial steps may linearise (``linearize_on_trial`` types) rather than evaluate
    errors only.

    A matrix-free (implicit-Schur) solver keeps the assembly's Jacobians for its products until
    the step is accepted, so a trial that linearises holds a second set beside them: that pair
    is the peak of a large run (at 29M BAL observations 2 × 5.6 GB). When one set exceeds
    :data:`TRIAL_JACOBIAN_SHARE` of the available memory, trials evaluate errors only; an
    accepted step is then linearised again (about 7 % of a BAL iteration) instead.

    Args:
        groups: The edge groups.
        matrix_free: Whether the solver works on products with ``S`` alone.
        available: Bytes of memory available.
    """
    if not matrix_free:
        return True
    jac = sum(8 * g.size * g.etype.jacobian_rows() * sum(vt.dimension for vt in
                                                        g.etype.vertex_types)
              for g in groups if g.etype.linearize_on_trial)
    return jac <= TRIAL_JACOBIAN_SHARE * available


class Problem:
    """Linearisation, damped solves and state updates of one initialised graph.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
        solver: The linear solver (analysed here, once).
        schur: How to form the Schur complement (``None``: the cost model chooses).
    """

    #: Whether runs are kept and replayed by their inputs (:mod:`~graphopt.run_memo`, which
    #: reads :attr:`runs`): for small states only.
    replayable: ClassVar[bool] = False

    def __init__(self, stores: list[VertexStore], groups: list[EdgeGroup],
                 positions: Positions, solver: LinearSolver,
                 schur: SchurConfig | None = None) -> None:
        tune_allocator()  # no page faults for the arrays every iteration allocates again
        self.stores = stores
        self.linearizer = Linearizer(stores, groups, positions)
        self.system = LinearSystem(stores, groups, positions, schur,
                                   matrix_free=solver.choose_matrix_free
                                   if solver.decides_matrix_free else solver.matrix_free,
                                   u_order=solver.block_order)
        self.solver = solver
        solver.analyze(self.system.pattern, self.system.udims)
        self.anchors = IdleAnchors(self.system.index)  # vertices whose edges are all inactive
        # /proc/meminfo only matters to a matrix-free solver (13 us: a motion-only BA's build).
        self.trial_linearization = not self.system.matrix_free or trial_linearization_allowed(
            groups, True, available_memory())
        self.timing = Timing()
        self._saved: list[np.ndarray] = []
        index = self.system.index
        self._updates = []
        for si, st in enumerate(stores):
            ub = index.ublock[si]
            uslots = np.flatnonzero(ub >= 0)
            upos = index.uoffset[ub[uslots]][:, None] + np.arange(st.vtype.dimension)
            vc = index.vclass_of_store[si]
            vslots = index.vclasses[vc].slots if vc >= 0 else np.zeros(0, dtype=np.int64)
            whole = None
            if (vc < 0 and len(uslots) == len(st.ids) and len(uslots)
                    and np.array_equal(upos.ravel(), np.arange(upos[0, 0], upos[-1, -1] + 1))):
                whole = slice(int(upos[0, 0]), int(upos[-1, -1]) + 1)
            self._updates.append(_StoreUpdate(uslots, upos, vc, vslots, whole))
        # The stores a step changes: push, pop and apply leave the others (fixed points) alone,
        # so that their gathered copies stay valid from one state to the next.
        self._free = [i for i, up in enumerate(self._updates)
                      if len(up.uslots) or up.vclass >= 0]

    def reset_timing(self) -> None:
        """Start a new :class:`Timing` (one per iteration; the same object, zeroed)."""
        t = self.timing
        t.linearize = t.schur = t.solve = 0.0

    # --- linearisation -----------------------------------------------------------------------

    def linearize(self) -> tuple[Assembly, float]:
        """Errors, Jacobians and the assembled normal equations at the current state.

        Returns:
            The assembly and the robust chi2.

        Raises:
            FloatingPointError: a non-finite error or Jacobian (naming the edge).
        """
        t0 = time.perf_counter()
        lin, ev = self.linearizer.linearize()
        asm = self.system.assemble(lin.jacobians, lin.weighted, lin.weighted_errors)
        self.anchors.apply(asm)
        # A non-finite Jacobian of a free vertex reaches its U or V block (every block holds
        # Σ J'ΩJ): checking the small assembled arrays spares a pass over the Jacobians.
        if not self.system.is_finite(asm):
            self.linearizer.raise_non_finite(lin)
        self.timing.linearize += time.perf_counter() - t0
        return asm, ev.robust_chi2

    def evaluate(self, linearize: bool = True) -> Evaluation:
        """Chi2 totals at the current state.

        Args:
            linearize: Let edge types that linearise on trial do so (their Jacobians are then
                reused by the next :meth:`linearize` at this state).
        """
        return self.linearizer.evaluate(linearize and self.trial_linearization)

    def robust_chi2(self, linearize: bool = True) -> float:
        """Robust chi2 at the current state (``inf`` if any error is not finite).

        Args:
            linearize: Let edge types that linearise on trial do so (see
                :meth:`Linearizer.evaluate <graphopt.linearizer.Linearizer.evaluate>`).

        Raises:
            GraphError: the chi2 is not finite because a vertex type's ``oplus`` returned
                non-finite estimates (naming the type and ids); the estimates saved by
                :meth:`push` are restored first.
        """
        chi = self.linearizer.evaluate(linearize and self.trial_linearization).robust_chi2
        if not math.isfinite(chi):  # only then look for the cause in the estimates
            self._check_finite_estimates()
        return chi

    def _check_finite_estimates(self) -> None:
        """Raise naming the first store with non-finite estimates (after a finite step)."""
        for st in self.stores:
            est = st.estimates
            ok = np.isfinite(est.reshape(len(est), -1)).all(axis=1)
            if not ok.all():
                ids = st.ids[~ok][:5].tolist()
                if self._saved:
                    self.pop()
                raise GraphError(f"{st.vtype.__name__}.oplus returned non-finite estimates for "
                                 f"a finite step (vertices {ids})")

    # --- the linear algebra ------------------------------------------------------------------

    @staticmethod
    def gradient(asm: Assembly) -> Step:
        """The right-hand side ``b = −Jᵀρ'Ωe`` (minus half the chi2 gradient), in the step layout.

        Args:
            asm: The assembly.
        """
        return asm.bu, asm.bv

    def damping(self, asm: Assembly, diagonal: bool) -> Step:
        """The damping diagonal ``D``: the identity, or ``diag(H)`` clipped (Marquardt).

        Args:
            asm: The assembly.
            diagonal: Marquardt's scaling instead of the identity.
        """
        return self.system.damping(asm, diagonal)

    def solve(self, asm: Assembly, lam: float, damping: Step | None = None) -> Step:
        """Solve ``(H + λD) Δ = b`` through the Schur complement.

        Args:
            asm: The assembly.
            lam: Damping λ (0 for none).
            damping: ``D`` from :meth:`damping`; ``None`` for the identity.

        Raises:
            NotPositiveDefiniteError: if the damped system is not positive definite.
        """
        t0 = time.perf_counter()
        try:
            s, rhs, vinv = self.system.reduce(asm, lam, damping)
        finally:
            t1 = time.perf_counter()
            self.timing.schur += t1 - t0
        try:
            du = self.solver.solve(s, rhs)
        finally:
            t2 = time.perf_counter()
            self.timing.solve += t2 - t1
        dv = self.system.back_substitute(asm, du, vinv)
        self.timing.schur += time.perf_counter() - t2
        if not (np.isfinite(du).all() and all(np.isfinite(x).all() for x in dv)):
            raise NotPositiveDefiniteError("the step is not finite")
        return du, dv

    def hessian_product(self, asm: Assembly, step: Step) -> Step:
        """Undamped ``H · step``.

        Args:
            asm: The assembly.
            step: A vector in the step layout.
        """
        return self.system.hessian_product(asm, step[0], step[1])

    def max_diagonal(self, asm: Assembly) -> float:
        """Largest diagonal entry of the undamped Hessian.

        Args:
            asm: The assembly.
        """
        return self.system.max_diagonal(asm)

    # --- the state ---------------------------------------------------------------------------

    def state_norm(self) -> float:
        """``‖x‖`` over the estimates of the free vertices (the parameter tolerance's scale)."""
        total = 0.0
        for st, up in zip(self.stores, self._updates, strict=True):
            est = st.estimates
            if up.whole is not None:  # every slot: no gather
                total += float(np.vdot(est, est))
                continue
            for slots in (up.uslots, up.vslots):
                if len(slots):
                    x = est[slots]
                    total += float(np.vdot(x, x))
        return math.sqrt(total)

    @staticmethod
    def max_abs(step: Step) -> float:
        """``max |Δ|`` of a step (0 for an empty one).

        Args:
            step: A vector in the step layout.
        """
        du, dv = step
        parts = [float(np.abs(a).max()) for a in (du, *dv) if a.size]
        return max(parts, default=0.0)

    @property
    def free_stores(self) -> list[int]:
        """The indices of the stores with free vertices: those a step changes."""
        return self._free

    def keep_last_outputs(self) -> None:
        """Keep what a finished run's replay evaluates again (:mod:`~graphopt.run_memo`; the
        single-vertex problem keeps its last trial's outputs); nothing here."""

    def push(self) -> None:
        """Save the estimates of every store with free vertices (g2o's ``push``): the arrays
        themselves, since :meth:`apply` replaces them instead of writing into them."""
        self._saved = [self.stores[i].estimates for i in self._free]

    def pop(self) -> None:
        """Restore the estimates saved by :meth:`push` (g2o's ``pop``)."""
        for i, est in zip(self._free, self._saved, strict=True):
            self.stores[i].estimates = est
        self._saved = []

    def apply(self, step: Step) -> None:
        """``x ← x ⊞ Δ`` with every vertex type's vectorised ``oplus``.

        ``oplus`` receives the estimates gathered by slot (a copy), so one that updates its input
        in place cannot change the state; what it returns must have the input's shape. No store
        changes unless every ``oplus`` succeeds.

        Args:
            step: ``(u part, [v parts])`` as returned by :meth:`solve`.

        Raises:
            GraphError: an ``oplus`` returned the wrong shape (naming the vertex type).
        """
        du, dv = step
        new = []
        for i in self._free:
            st, up = self.stores[i], self._updates[i]
            if up.whole is not None:
                est = st.estimates
                new.append(checked_oplus(st.vtype, est.copy(),
                                         du[up.whole].reshape(len(est), -1)))
                continue
            est = st.estimates.copy()
            if len(up.uslots):
                est[up.uslots] = checked_oplus(st.vtype, est[up.uslots], du[up.upos])
            if up.vclass >= 0:
                est[up.vslots] = checked_oplus(st.vtype, est[up.vslots], dv[up.vclass])
            new.append(est)
        for i, est in zip(self._free, new, strict=True):
            self.stores[i].estimates = est
