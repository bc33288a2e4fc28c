"""``IncrementalOptimizer``: keep the estimate current while vertices and edges keep coming.

Usage (the online loop of a SLAM front end)::

    opt = SparseOptimizer()
    opt.add_vertices(VertexSE2, [0], [[0, 0, 0]], fixed=True)
    inc = IncrementalOptimizer(opt)
    for each new pose:
        opt.add_vertices(...); opt.add_edges(...)     # the pose, its odometry, loop closures
        report = inc.update()                         # the estimates are now current

Design (numbers in ``docs/online.md``). The optimizer keeps the Gauss–Newton system
``H Δ = −g`` of all edges linearised at points ``θ`` (the estimate is ``θ ⊞ Δ``) as a CHOLMOD
factor that grows (:class:`~graphopt.incremental.factor.GrowingFactor`): new edges enter by a
rank update with their whitened Jacobians, new vertices take reserved trailing unknowns.

* An update whose new edges are already satisfied by the current estimate (chi2 below
  ``solve_threshold``: a pose placed by its odometry, a landmark by its first observation)
  changes no estimate: the edges wait, and enter the factor with the next update that
  solves.
* Any other update flushes the waiting edges into the factor and solves with it (one solve,
  every vertex's estimate updated).
* A batch step — relinearise every edge at the current estimate, reorder (nested dissection
  on the vertex graph; the newest vertices last while loop closures stay among them),
  refactorise — runs when the reserve runs out, when the linear model no longer predicts the
  chi2 after a vertex's step from its linearisation point exceeded ``relinearize_threshold``,
  or when the factor loses positive definiteness. Its result is checked: if chi2 went up,
  damped steps (Levenberg–Marquardt, ``λ·diag(H)``) take over until it goes down.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from graphopt.errors import GraphError, NotPositiveDefiniteError
from graphopt.incremental.factor import GrowingFactor
from graphopt.incremental.ordering import Ordering
from graphopt.incremental.state import Batch, State, by_group
from graphopt.incremental.whitened import (
    determine,
    gradient_into,
    hessian,
    largest_diagonal,
    negated,
    robust_cost,
    update_columns,
)
from graphopt.optimizer import SparseOptimizer

__all__ = ["IncrementalConfig", "IncrementalOptimizer", "UpdateReport"]


@dataclass(frozen=True)
class IncrementalConfig:
    """How the incremental optimizer trades work for accuracy.

    Args:
        reserve: Vertices' worth of unknowns reserved beyond those in use at every batch step
            (at least; see ``reserve_fraction``): a batch step (reordering) runs when they
            are used up.
        reserve_fraction: The reserve as a share of the vertices in use, when larger.
        recent: The newest vertices of each type that a batch step orders last (new edges
            mostly reach them; none when the loop closures since the last batch step mostly
            reach further back).
        relinearize_threshold: Once a vertex's step from its linearisation point exceeds this
            (largest tangent component), the linear model is checked against the true chi2
            (a full evaluation); a batch step relinearises everything if they differ by more
            than ``model_tolerance`` (relative).
        model_tolerance: See ``relinearize_threshold``.
        check_every: While a vertex stays past the threshold, the model is checked again
            after this many solves (or once the largest step grew by half).
        partial_fraction: A relinearisation whose vertices' edges hold at most this share
            of the rows relinearises only them (a downdate and an update of the factor, as
            iSAM2 does); a larger one is a batch step.
        solve_threshold: New edges whose chi2 at the current estimate is at most this are
            taken in without a solve.
        check_chi2: Also check the chi2 of every incremental solve (a full evaluation), not
            only of batch steps; a rise falls back to a damped batch step.
        max_batch_iterations: Gauss–Newton iterations of a batch step at most: it stops once
            no vertex moves by more than ``relinearize_threshold`` and the chi2 fell by at most
            ``batch_tolerance`` (relative).
        batch_tolerance: See ``max_batch_iterations``.
        max_damped_iterations: Damped iterations of a fallback.
    """

    reserve: int = 100
    recent: int = 64
    reserve_fraction: float = 0.0
    relinearize_threshold: float = 0.1
    model_tolerance: float = 1e-4
    check_every: int = 40
    partial_fraction: float = 0.02
    solve_threshold: float = 1e-9
    check_chi2: bool = False
    max_batch_iterations: int = 5
    batch_tolerance: float = 1e-4
    max_damped_iterations: int = 10


@dataclass
class UpdateReport:
    """What one :meth:`IncrementalOptimizer.update` did.

    Args:
        vertices: Vertices taken in.
        edges: Edges taken in.
        solved: Whether the estimates were solved for (else they were already current).
        factor: ``"unchanged"``, ``"pending"`` (edges wait for the next solve), ``"updated"``
            (rank updates) or ``"rebuilt"`` (a batch step).
        reason: Why a batch step ran (``""`` if none): ``"first"``, ``"reserve"``,
            ``"relinearize"``, ``"not positive definite"``, ``"flags"``, ``"chi2"``; with
            ``factor="updated"``, ``"relinearize"`` is a partial relinearisation.
        relinearized: Vertices relinearised.
        fallback: Whether damped steps were needed (chi2 went up, or the system was not
            positive definite).
        seconds: Wall time of the update.
    """

    vertices: int = 0
    edges: int = 0
    solved: bool = False
    factor: str = "unchanged"
    reason: str = ""
    relinearized: int = 0
    fallback: bool = False
    seconds: float = 0.0


class IncrementalOptimizer:
    """Incremental Gauss–Newton over a :class:`~graphopt.optimizer.SparseOptimizer`'s graph.

    Vertices and edges are added to the optimizer as usual; :meth:`update` takes in what was
    added since the last call and leaves the optimizer's estimates current. Robust kernels
    weight the edges at their linearisation; marginalised flags are ignored (every free vertex
    is an unknown).

    Args:
        optimizer: The optimizer holding the graph (its estimates are updated in place).
        config: An :class:`IncrementalConfig`.
    """

    def __init__(self, optimizer: SparseOptimizer, config: IncrementalConfig | None = None
                 ) -> None:
        self.optimizer = optimizer
        self.config = config if config is not None else IncrementalConfig()
        self._state = State(optimizer.graph)
        self._factor: GrowingFactor | None = None
        self._pending: list[Batch] = []
        self._pending_unknowns = 0
        self._g = np.zeros(0)
        self._delta = np.zeros(0)
        self._removals = 0
        self._weights: dict[int, tuple[int, int]] = {}
        self._ordering = Ordering(self.config.recent)
        self._checked = 0.0
        self._since_check = 0
        self.reports: list[UpdateReport] = []

    # --- public ------------------------------------------------------------------------------

    def update(self) -> UpdateReport:
        """Take in the vertices and edges added since the last update and bring the estimates
        up to date.

        Returns:
            An :class:`UpdateReport`.

        Raises:
            GraphError: a new free vertex that no edge constrains (naming it); nothing is
                taken in.
        """
        t0 = time.perf_counter()
        if self._factor is not None and self._state.removals() != self._removals:
            self._state, self._factor = State(self.optimizer.graph), None  # start afresh
            self._ordering = Ordering(self.config.recent)
        st = self._state
        new = st.new_vertices()
        batches = st.new_batches()
        lone = st.unconstrained(new, batches)
        if lone is not None:
            raise GraphError(f"vertex {lone[1]} ({lone[0].vtype.__name__}) has no edge: add "
                             "an edge that constrains it before updating")
        report = UpdateReport(vertices=sum(hi - lo for _, lo, hi in new),
                              edges=sum(len(b.vids) for b in batches))
        need = sum(st.stores[si].vtype.dimension * int((~st.stores[si].fixed[lo:hi]).sum())
                   for si, lo, hi in new)
        reason = ("first" if self._factor is None else "flags" if st.flags_changed()
                  else "weights" if self._weights_changed()
                  else "reserve" if need > self._factor.free - self._pending_unknowns else "")
        if reason:
            self._take_in(new, batches, 0)
            self._rebuild(report, reason)
            self._removals = st.removals()
        elif new or batches:
            self._take_in(new, batches, self._factor.used + self._pending_unknowns)
            self._pending_unknowns += need
            self._pending += batches
            report.factor = "pending"
            # More new edges than new vertices (a loop closure, a landmark seen again) almost
            # never leave the estimate optimal: solve without evaluating them first (a solve
            # that was not needed costs time, never accuracy).
            if report.edges > report.vertices or sum(
                    float(st.chi2(b).sum()) for b in batches) > self.config.solve_threshold:
                self._solve(report)
        report.seconds = time.perf_counter() - t0
        self.reports.append(report)
        return report

    def _weights_key(self) -> dict[int, tuple[int, int]]:
        """What weighs the factor's rows besides the estimates: every group's kernels and
        levels (``activity_version``)."""
        return {id(g): g.activity_version for g in self.optimizer.graph.groups.values()}

    def _weights_changed(self) -> bool:
        """Whether a group the last batch step weighed has had its kernels or levels edited
        since (a group that appeared since enters by rank updates, at its own weights). The
        next update is then a batch step: the factor's rows carry the old weights, which the
        model check cannot be relied on to notice (a kernel removed left the chi2 5.7e-5
        relative above the optimum, within its tolerance)."""
        for g in self.optimizer.graph.groups.values():
            v = g.activity_version
            if self._weights.get(id(g), v) != v:
                return True
        return False

    def chi2(self, robust: bool = True) -> float:
        """``Σ ρ(e'Ωe)`` over every edge taken in, at the current estimates (what the
        optimizer minimises; ``Σ e'Ωe`` with ``robust=False``, equal without kernels).

        Args:
            robust: Apply the edges' robust kernels.
        """
        return float(sum(self._state.chi2(b, robust).sum() for b in self._state.all_edges()))

    @property
    def factor(self) -> GrowingFactor | None:
        """The current factor (``None`` before the first update)."""
        return self._factor

    def system(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """``(H, g)`` of every edge taken in, at the linearisation points, freshly assembled
        in the factor's unknowns (tests compare the incremental factor with it).

        Returns:
            ``H`` ``(n, n)`` and ``g`` ``(n,)`` over the unknowns in use.
        """
        self._flush()
        assert self._factor is not None
        wb = [self._state.whiten(b) for b in self._state.all_edges()]
        n = self._factor.used
        H = hessian(wb, self._factor.size)[:n, :n]
        g = np.zeros(self._factor.size)
        gradient_into(g, wb)
        return H.tocsc(), g[:n]

    # --- steps -------------------------------------------------------------------------------

    def _take_in(self, new: list[tuple[int, int, int]], batches: list[Batch], first: int) -> None:
        for si, lo, hi in new:
            first += self._state.extend(si, lo, hi, first)
        self._state.take_edges(batches)

    def _flush(self) -> None:
        """Rank-update the waiting edges into the factor and release their new unknowns."""
        if not self._pending and not self._pending_unknowns:
            return
        assert self._factor is not None
        pending = by_group(self._pending)
        wb = [self._state.whiten(b) for b in pending]
        self._state.keep_linear(pending, wb, fresh=False)
        gradient_into(self._g, wb)
        self._factor.update(update_columns(wb, self._factor.size))
        first, count = self._factor.used, self._pending_unknowns
        self._factor.take(count, check=not determine(wb, first, count))
        self._pending, self._pending_unknowns = [], 0

    def _solve(self, report: UpdateReport) -> None:
        cfg = self.config
        before = self.chi2() if cfg.check_chi2 else None
        try:
            self._flush()
            delta = -self._factor.solve(self._g)
        except NotPositiveDefiniteError:
            self._rebuild(report, "not positive definite")
            return
        old = self._delta
        self._delta = delta
        worst = self._state.apply(delta, old)
        report.solved, report.factor = True, "updated"
        robust = any(g.kernels for g in self.optimizer.graph.groups.values())
        self._since_check += 1
        if robust or (worst > cfg.relinearize_threshold and (
                worst > self._checked * 1.5 or self._since_check >= cfg.check_every)):
            # A vertex left its linearisation point: relinearise if the linear model no
            # longer predicts the chi2 (checked again once the steps grew by half or after
            # check_every solves; with robust kernels at every solve, as their weights go
            # stale with any step).
            true, model = self._state.model_check(delta, self._g)
            self._checked, self._since_check = worst, 0
            if abs(true - model) > cfg.model_tolerance * max(true, 1.0) and (
                    robust or not self._relinearize_partly(report)):
                self._rebuild(report, "relinearize")
        elif before is not None and self.chi2() > before:
            self._delta = old
            self._state.apply(old)
            self._rebuild(report, "chi2")

    def _relinearize_partly(self, report: UpdateReport) -> bool:
        """iSAM2's partial relinearisation: the vertices whose step exceeds the threshold
        move their linearisation point to their estimate, the rows of their edges leave the
        factor (a downdate) and enter it relinearised (an update), and the system is solved
        again. Only when those edges hold at most ``partial_fraction`` of the rows (else a
        batch step costs less); returns whether it ran and the linear model then predicts
        the chi2 (else the caller's batch step starts afresh)."""
        st, cfg = self._state, self.config
        masks, count = st.moved(self._delta, cfg.relinearize_threshold)
        if not count:
            return False
        edges = st.touching(masks)
        rows = sum(int(hit.sum()) * b.info.shape[1] for b, hit in edges)
        total = sum(len(b.vids) * b.info.shape[1] for b in st.all_edges())
        if rows > cfg.partial_fraction * total:
            return False
        out = st.relinearize_partly(masks, edges)
        if out is None:
            return False
        old, new = out
        try:
            self._factor.update(update_columns(new, self._factor.size))
            self._factor.downdate(update_columns(old, self._factor.size))
            gradient_into(self._g, new)
            gradient_into(self._g, [negated(w) for w in old])
            self._delta = -self._factor.solve(self._g)
        except NotPositiveDefiniteError:
            return False  # the caller's batch step starts afresh
        self._checked = st.apply(self._delta)
        # As a batch step, done once the linear model predicts the chi2 (the vertices left
        # below the threshold may still be off: then the batch step relinearises all).
        true, model = st.model_check(self._delta, self._g)
        if abs(true - model) > cfg.model_tolerance * max(true, 1.0):
            return False
        report.relinearized = count
        report.reason = "relinearize"
        return True

    def _rebuild(self, report: UpdateReport, reason: str) -> None:
        """A batch step: relinearise everything at the current estimate, reorder,
        refactorise, solve, check the chi2 (damped steps if it went up); again while the step
        exceeds the relinearisation threshold (at most ``max_batch_iterations`` times)."""
        st = self._state
        report.factor, report.reason, report.solved = "rebuilt", reason, True
        self._pending, self._pending_unknowns = [], 0
        self._weights = self._weights_key()  # the kernels and levels this factor weighs by
        # A reserve step only makes room: one iteration (the model check relinearises later
        # if it must); the others iterate until converged or the linear model predicts the
        # chi2 of the step.
        cfg = self.config
        iterations = 1 if reason == "reserve" else cfg.max_batch_iterations
        for it in range(iterations):
            st.relinearize_all()
            batches = st.all_edges()
            self._ordering.renumber(st, batches)
            st.flags = [s.flags_version for s in st.stores]
            report.relinearized = sum(int((o >= 0).sum()) for o in st.offsets)
            dims = [s.vtype.dimension for s in st.stores]
            n = sum(int((o >= 0).sum()) * d for d, o in zip(dims, st.offsets, strict=True))
            reserve = max(dims, default=1) * max(
                cfg.reserve, int(cfg.reserve_fraction * report.relinearized))
            wb = [st.whiten(b) for b in batches]
            st.keep_linear(batches, wb, fresh=True)
            self._checked, self._since_check = 0.0, 0
            before = float(sum(robust_cost(w.chi2, b.kernel_index, b.group.kernels).sum()
                               for w, b in zip(wb, batches, strict=True)))
            self._g = np.zeros(n + reserve)
            gradient_into(self._g, wb)
            # The model check below needs the chi2 at the new estimate anyway: without
            # kernels it is the chi2 (one evaluation of every edge instead of two); after the
            # last iteration it is not needed.
            check = it + 1 < iterations
            robust = any(b.group.kernels for b in batches)
            try:
                self._factor = (GrowingFactor(hessian(wb, n), reserve, True) if self._large()
                                else GrowingFactor.of_columns(update_columns(wb, n + reserve),
                                                              n, reserve,
                                                              largest_diagonal(wb, n)))
                self._delta = -self._factor.solve(self._g)
                worst = st.apply(self._delta)
                true, model = (st.model_check(self._delta, self._g) if check
                               else (0.0, 0.0))
                after = true if check and not robust else self.chi2()
                if after > before:
                    raise NotPositiveDefiniteError("chi2 went up")
            except NotPositiveDefiniteError:
                report.fallback = True
                self._damped(hessian(wb, n), self._g, before, reserve)
                return
            if not check or (worst <= cfg.relinearize_threshold
                             and before - after <= cfg.batch_tolerance * after):
                return
            # The step is as good as the model says: the next iteration would barely move
            # (the sphere: 1.55 factorisations per relinearising step without this, 1.1 with
            # it, ending at the same chi2); later solves check the model again.
            self._checked = worst
            if abs(true - model) <= cfg.model_tolerance * max(true, 1.0):
                return

    def _damped(self, H: sp.csc_matrix, g: np.ndarray, chi2: float, reserve: int) -> None:
        """Levenberg–Marquardt from the linearisation points until chi2 goes down; the factor
        is then the undamped system at the final estimate (its gradient set aside when the
        undamped step still does not pay, so that the estimate is the system's solution)."""
        st = self._state
        n = H.shape[0]
        diag = np.maximum(H.diagonal(), 1e-12)
        lam = 1e-4
        zero = np.zeros(n + reserve)
        for _ in range(self.config.max_damped_iterations):
            ok = False
            while lam < 1e12:
                damped = (H + sp.diags(lam * diag)).tocsc()
                try:
                    step = -GrowingFactor(damped, 0).solve(g[:n])
                except NotPositiveDefiniteError:
                    lam *= 10.0
                    continue
                self._delta = np.concatenate([step, np.zeros(reserve)])
                st.apply(self._delta)
                new = self.chi2()
                if new < chi2:
                    ok, chi2, lam = True, new, lam / 10.0
                    break
                lam *= 10.0
            if not ok:
                st.apply(zero)
                break
            st.relinearize_all()
            wb = [st.whiten(b) for b in st.all_edges()]
            H = hessian(wb, n)
            diag = np.maximum(H.diagonal(), 1e-12)
            g = np.zeros(n + reserve)
            gradient_into(g, wb)
        st.relinearize_all()
        self._delta = zero.copy()
        self._g = zero.copy()  # the estimate is taken as the old edges' optimum
        scale = float(diag.max()) if n else 1.0
        for damping in (0.0, 1e-9, 1e-6, 1e-3):  # a singular system keeps a small prior
            try:
                self._factor = GrowingFactor(
                    (H + sp.identity(n, format="csc") * (damping * scale)).tocsc(), reserve,
                    self._large())
                break
            except NotPositiveDefiniteError:
                continue

    def _large(self) -> bool:
        """Whether a vertex type has more than 3 unknowns (a supernodal factorisation pays
        off)."""
        return max((s.vtype.dimension for s in self._state.stores), default=1) > 3
