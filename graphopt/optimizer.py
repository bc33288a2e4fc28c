"""``SparseOptimizer``: g2o's optimizer API, and the iteration loop.

Data flow (see ``docs/architecture.md``): ``add_vertex``/``add_edge`` (or their bulk forms) go to
the :class:`~graphopt.graph.Graph`, which checks them and stores them as arrays;
``initialize_optimization`` resolves ids to slots and builds the numeric
:class:`~graphopt.problem.Problem` once (linearizer, linear system with its block pattern and
Schur plan, the solver's symbolic analysis); ``optimize`` runs the algorithm's iterations on it,
which only compute numbers.
"""

from __future__ import annotations

import math
import sys
import time
import weakref
from collections.abc import Callable, Iterable, Sequence
from typing import Any, TextIO

import numpy as np

from graphopt.algorithms import Algorithm, AlgorithmConfig, make_algorithm
from graphopt.edge import BaseEdge
from graphopt.edge_output import first_non_finite
from graphopt.edge_set import EdgeSet
from graphopt.editing import GraphEditing
from graphopt.errors import GraphError
from graphopt.graph import Graph
from graphopt.linear import LinearSystem, SchurConfig
from graphopt.linearizer import Evaluation
from graphopt.problem import Problem
from graphopt.result import IterationInfo, OptimizationResult, StopReason
from graphopt.robust_kernel import RobustKernel
from graphopt.run_memo import keep, replay, run_key
from graphopt.single_vertex import make_problem
from graphopt.solvers import LinearSolver, make_solver
from graphopt.stopping import StoppingConfig
from graphopt.storage import EdgeGroup
from graphopt.vertex import BaseVertex

Callback = Callable[["SparseOptimizer", IterationInfo], Any]
_DEFAULT_STOPPING = StoppingConfig()  # the default tests, shared (frozen)


class SparseOptimizer(GraphEditing):
    """A graph of vertices and edges, optimised by GN, LM or Dogleg with a Schur complement.

    Args:
        algorithm: ``"lm"``, ``"gn"``, ``"dogleg"`` or a config dataclass
            (:class:`~graphopt.algorithms.LevenbergConfig`, ...).
        solver: ``"auto"`` (dense Cholesky for small dense reduced systems, else CHOLMOD),
            ``"cholmod"``, ``"dense"``, ``"pcg"``, ``"scipy"`` or a
            :class:`~graphopt.solvers.LinearSolver`.
        verbose: Print g2o's iteration line after every iteration.
        stopping: When a run has converged (:class:`~graphopt.stopping.StoppingConfig`; by
            default Ceres' tolerances; ``StoppingConfig.iterations_only()`` for g2o's
            behaviour).
        stream: Where verbose lines go (stderr by default).
        schur: How to form the Schur complement (:class:`~graphopt.linear.SchurConfig`);
            ``None``: the cost model chooses per class of W blocks.
    """

    def __init__(
        self,
        algorithm: str | AlgorithmConfig = "lm",
        solver: str | LinearSolver = "auto",
        verbose: bool = False,
        stopping: StoppingConfig | None = None,
        stream: TextIO | None = None,
        schur: SchurConfig | None = None,
    ) -> None:
        self.graph = Graph()
        self.algorithm: Algorithm = make_algorithm(algorithm)
        self._solver_spec = solver
        self._schur = schur
        self.verbose = verbose
        self.stopping = stopping if stopping is not None else _DEFAULT_STOPPING
        self.stream = stream
        self._callbacks: dict[str, list[Callback]] = {"pre_iteration": [], "post_iteration": []}
        self._problem: Problem | None = None
        self._structure_key: tuple[Any, ...] | None = None
        self._stop = False
        self._interrupt = False
        # The algorithm's interrupt poll, made once. A weak reference: a bound method would
        # make a cycle that keeps the whole problem (w10000: 72 MB, CHOLMOD's 15 MB factor)
        # alive until the garbage collector runs.
        self._interrupt_poll = _weak_call(weakref.WeakMethod(self._interrupted))

    # --- configuration -----------------------------------------------------------------------

    def set_verbose(self, verbose: bool = True) -> None:
        """Print g2o's iteration lines.

        Args:
            verbose: On or off.
        """
        self.verbose = verbose

    def set_algorithm(self, algorithm: str | AlgorithmConfig) -> None:
        """Select the algorithm.

        Args:
            algorithm: Name or config dataclass.
        """
        self.algorithm = make_algorithm(algorithm)

    def set_solver(self, solver: str | LinearSolver) -> None:
        """Select the linear solver (takes effect at the next initialisation).

        Args:
            solver: Name or instance.
        """
        self._solver_spec = solver
        self._problem = None

    def add_callback(self, when: str, fn: Callback) -> None:
        """Call ``fn(optimizer, info)`` before or after every iteration.

        Args:
            when: ``"pre_iteration"`` or ``"post_iteration"``.
            fn: The callback. Call :meth:`force_stop` from it to stop after this iteration.
        """
        if when not in self._callbacks:
            raise ValueError(f"unknown callback kind {when!r}; use pre_iteration/post_iteration")
        self._callbacks[when].append(fn)

    def force_stop(self) -> None:
        """Ask ``optimize`` to stop after the current iteration (g2o's force-stop flag)."""
        self._stop = True

    def stop(self) -> None:
        """Ask a running ``optimize`` to end at the next safe point — the end of the current
        iteration, whose estimate is kept only if it was accepted, or after a rejected trial of
        LM or Dogleg (the estimate restored) — with the stop reason ``interrupted``.

        Safe to call from a signal handler or another thread: it only sets a flag.
        """
        self._interrupt = True

    def _interrupted(self) -> bool:
        return self._interrupt

    @property
    def solver(self) -> LinearSolver | None:
        """The linear solver in use (after initialisation), else ``None``."""
        return self._problem.solver if self._problem is not None else None

    @property
    def problem(self) -> Problem | None:
        """The numeric problem built by :meth:`initialize_optimization`, else ``None``."""
        return self._problem

    @property
    def linear_system(self) -> LinearSystem | None:
        """The normal equations' structure (after initialisation), else ``None``."""
        return self._problem.system if self._problem is not None else None

    # --- the graph (see graphopt.graph.Graph) ------------------------------------------------

    def add_vertex(self, vertex: BaseVertex) -> bool:
        """Add one vertex (g2o's ``addVertex``).

        Args:
            vertex: The vertex, with id and estimate set.

        Returns:
            True.

        Raises:
            GraphError: duplicate id, missing or malformed estimate.
        """
        self.graph.add_vertex(vertex)
        return True

    def add_vertices(
        self,
        vtype: type[BaseVertex],
        ids: Sequence[int] | np.ndarray,
        estimates: Any,
        fixed: bool | Sequence[bool] | np.ndarray = False,
        marginalized: bool | Sequence[bool] | np.ndarray = False,
    ) -> None:
        """Add many vertices of one type at once (the fast path).

        Args:
            vtype: The vertex class.
            ids: ``(n,)`` unique integer ids.
            estimates: ``(n, *estimate_shape)``.
            fixed: One flag for all or ``(n,)`` flags.
            marginalized: One flag for all or ``(n,)`` flags.

        Raises:
            GraphError: duplicate ids, wrong shapes, invalid estimates.
        """
        self.graph.add_vertices(vtype, ids, estimates, fixed, marginalized)

    def vertex(self, vid: int) -> BaseVertex | None:
        """The vertex with this id, or ``None`` (g2o's ``vertex(id)``).

        Args:
            vid: The id.
        """
        return self.graph.vertex(vid)

    def vertex_ids(self) -> list[int]:
        """All vertex ids."""
        return list(self.graph.ids)

    def estimates_of(self, vtype: type[BaseVertex]) -> np.ndarray:
        """A copy of the estimates of all vertices of a type, in the order they were added.

        Args:
            vtype: The vertex class.
        """
        st = self.graph.stores.get(vtype)
        return st.estimates.copy() if st is not None else np.zeros((0, *vtype.estimate_shape))

    def ids_of(self, vtype: type[BaseVertex]) -> np.ndarray:
        """Ids of all vertices of a type, in the order they were added.

        Args:
            vtype: The vertex class.
        """
        st = self.graph.stores.get(vtype)
        return st.ids.copy() if st is not None else np.zeros(0, int)

    def set_estimates_of(self, vtype: type[BaseVertex], estimates: np.ndarray) -> None:
        """Replace the estimates of all vertices of a type (same order as :meth:`ids_of`).

        Args:
            vtype: The vertex class.
            estimates: ``(n, *estimate_shape)``.
        """
        st = self.graph.stores[vtype]
        est = np.array(estimates, dtype=float)
        if est.shape != st.estimates.shape:
            raise GraphError(f"{vtype.__name__}: estimates have shape {est.shape}, expected "
                             f"{st.estimates.shape}")
        st.check_estimates(est, st.ids)
        st.estimates = est

    def add_edge(self, edge: BaseEdge) -> bool:
        """Add one edge (g2o's ``addEdge``).

        Args:
            edge: The edge with its vertices, measurement and (optionally) information/kernel.

        Returns:
            True.

        Raises:
            GraphError: a missing vertex, wrong shapes of measurement or information.
        """
        self.graph.add_edge(edge)
        return True

    def add_edges(self, etype: type[BaseEdge], vertex_ids: Any, measurements: Any,
                  information: Any = None, robust_kernel: RobustKernel | None = None,
                  params: Any = None, data: dict[str, Any] | None = None) -> EdgeSet:
        """Add many edges of one type at once (the fast path).

        Args:
            etype: The edge class.
            vertex_ids: ``(m, k)`` vertex ids, one column per entry of ``vertex_types``.
            measurements: ``(m, *measurement_shape)``.
            information: ``None`` (identity), one ``(e, e)`` matrix for all, or ``(m, e, e)``.
            robust_kernel: One kernel for all these edges, or ``None``.
            params: Shared parameters (edges with the same type and params form one group).
            data: Per-edge auxiliary arrays, each with first dimension ``m``.

        Returns:
            An :class:`~graphopt.edge_set.EdgeSet` of these edges (per-edge chi2, levels,
            kernels, removal).

        Raises:
            GraphError: missing vertices, wrong shapes, non-finite values.
        """
        group, start, m = self.graph.add_edges(etype, vertex_ids, measurements, information,
                                               robust_kernel, params, data)
        return EdgeSet(self.graph, group, np.arange(start, start + m), ascending=True)

    def edges(self) -> list[BaseEdge]:
        """The edges added one at a time (bulk edges live only as arrays)."""
        return self.graph.edges()

    def edge_groups(self) -> list[EdgeGroup]:
        """The edge groups (one per edge type and parameter object)."""
        return list(self.graph.groups.values())

    def num_edges(self) -> int:
        """Number of edges."""
        return sum(g.size for g in self.graph.groups.values())

    # --- initialisation ----------------------------------------------------------------------

    def initialize_optimization(self, level: int = 0) -> bool:
        """Select the edges of ``level`` (g2o's ``initializeOptimization(level)``) and build the
        structure — slots, block pattern, scatter maps, Schur plan, symbolic factorisation —
        unless the graph's structure is unchanged: a change of levels, kernels or estimates
        reuses it (inactive edges weigh nothing). Called by :meth:`optimize` when the graph
        changed.

        Args:
            level: The level whose edges are optimised (g2o: 0 unless set otherwise).

        Returns:
            True.

        Raises:
            GraphError: a level that is not a non-negative integer, or invalid objects.
        """
        self.graph.set_level(level)  # checked there
        self.graph.flush()
        if self._problem is None or self._structure_key != self.graph.structure_key():
            stores, groups, positions = self.graph.resolve()
            self._problem = None  # the old structure's memory goes before the new is built
            self._problem = make_problem(stores, groups, positions,
                                         make_solver(self._solver_spec), self._schur)
            self._structure_key = self.graph.structure_key()
        return True

    def _ensure_problem(self) -> Problem:
        self.graph.flush()
        if self._problem is None or self._structure_key != self.graph.structure_key():
            self.initialize_optimization(self.graph.level)
        assert self._problem is not None
        return self._problem

    # --- g2o's evaluation API ----------------------------------------------------------------

    def compute_active_errors(self) -> None:
        """Evaluate every edge's error at the current estimates (g2o's
        ``computeActiveErrors``): errors only, and none if the last evaluation was at the same
        estimates, levels and kernels."""
        self._last()

    def _last(self) -> Evaluation:
        """The evaluation at the current estimates, levels and kernels (made if stale)."""
        p = self._ensure_problem()
        lin = p.linearizer
        if lin.last is None or lin.last_state != lin.state_key():
            return p.evaluate(linearize=False)
        return lin.last

    def chi2(self) -> float:
        """Σ e'Ωe over the active edges, without robust kernels, at the current estimates."""
        return self._last().chi2

    def active_robust_chi2(self) -> float:
        """Σ ρ(e'Ωe) over the active edges at the current estimates (what g2o prints)."""
        return self._last().robust_chi2

    def active_edge_count(self) -> int:
        """Edges active at the current estimates: those of the initialised level (and not
        deactivated by their type, as a projection outside the image)."""
        return self._last().active

    # --- optimisation ------------------------------------------------------------------------

    def optimize(self, iterations: int | None = None) -> OptimizationResult:
        """Run the algorithm until a stopping test fires or ``iterations`` iterations are done;
        every call starts LM's λ (Dogleg's radius) from its rule, as g2o and Ceres do.

        Args:
            iterations: Most iterations (non-negative); ``None``: the stopping config's
                ``max_iterations``.

        Returns:
            An :class:`~graphopt.result.OptimizationResult`.
        """
        if iterations is None:
            iterations = self.stopping.max_iterations
        if int(iterations) != iterations or iterations < 0:
            raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
        t_start = time.perf_counter()
        p = self._ensure_problem()
        plain = not (self.verbose or any(self._callbacks.values()))
        key = run_key(p, self.algorithm, self.stopping, int(iterations), plain)
        if key is not None and (replayed := replay(p, key, t_start)) is not None:
            return replayed  # the inputs of a kept run (graphopt.run_memo)
        self.algorithm.reset()  # λ (Dogleg: the radius) from its rule again, as g2o and Ceres
        self._stop = self._interrupt = False
        self.algorithm.interrupted = self._interrupt_poll
        initial = p.evaluate().robust_chi2
        res = OptimizationResult(initial_chi2=initial, final_chi2=initial)
        if not math.isfinite(initial):
            raise FloatingPointError("the initial chi2 is not finite: "
                                     + first_non_finite(self.graph.groups.values()))
        res.final_chi2 = self._iterations(p, int(iterations), res, initial)
        res.seconds = time.perf_counter() - t_start
        if key is not None:
            keep(p, key, res, self.algorithm, self.stopping)
        return res

    def _iterations(self, p: Problem, iterations: int, res: OptimizationResult,
                    initial: float) -> float:
        """A run's iterations (every algorithm and problem, callbacks, iteration lines): records
        in ``res.info``, ``res.stop_reason`` set; returns the last accepted chi2."""
        cum = 0.0
        last = initial
        for it in range(iterations):
            if self._interrupt:
                res.stop_reason = StopReason.INTERRUPTED
                break
            for cb in self._callbacks["pre_iteration"]:
                cb(self, IterationInfo(it, last))
            p.reset_timing()
            t0 = time.perf_counter()
            self.algorithm.final_iteration = it == iterations - 1
            info = self.algorithm.iterate(p, it, self.stopping)
            info.seconds = time.perf_counter() - t0
            if info.trials == 0:  # converged at the linearisation: not an iteration
                res.stop_reason = info.stop or StopReason.CONVERGED
                break
            cum += info.seconds
            info.linearize_seconds = p.timing.linearize
            info.schur_seconds = p.timing.schur
            info.solve_seconds = p.timing.solve
            if info.failed:  # the state was restored: keep the evaluation consistent with it
                p.evaluate(linearize=False)
            res.info.append(info)
            if self.verbose:
                self._print_line(info, cum)
            for cb in self._callbacks["post_iteration"]:
                cb(self, info)
            stop = self._stop_reason(info, last)
            if not info.failed:
                last = info.chi2
            if stop is not None:
                res.stop_reason = stop
                break
        return last

    def _stop_reason(self, info: IterationInfo, last: float) -> StopReason | None:
        """Why to stop after this iteration, or ``None`` to go on."""
        if info.not_pd and info.failed and self.verbose:
            what = (f"singular (rank deficient) {info.singular} time(s)" if info.singular
                    == info.not_pd else f"not positive definite {info.not_pd} time(s)"
                    + (f", {info.singular} of them singular" if info.singular else ""))
            print(f"# {self.algorithm.config.name}: the system was {what}; no acceptable step",
                  file=self._out)
        if info.stop is not None:
            return info.stop
        if info.failed:
            # No trial reduced chi2: converged if the solves worked, failed otherwise.
            if info.not_pd < info.trials:
                return StopReason.CONVERGED
            return StopReason.SINGULAR if info.singular >= info.trials else StopReason.FAILED
        if self._interrupt:
            return StopReason.INTERRUPTED
        if self._stop:
            return StopReason.STOPPED
        if info.chi2 == 0.0:
            return StopReason.CONVERGED
        if self.stopping.gain_reached(last, info.chi2):
            return StopReason.GAIN
        return None

    @property
    def _out(self) -> TextIO:
        return self.stream if self.stream is not None else sys.stderr

    def _print_line(self, info: IterationInfo, cum: float) -> None:
        schur = 1 if self._problem is not None and self._problem.system.schur else 0
        line = (f"iteration= {info.iteration}\t chi2= {info.chi2:.6f}\t time= {info.seconds:.6g}"
                f"\t cumTime= {cum:.6g}\t edges= {self.active_edge_count()}\t schur= {schur}"
                + self.algorithm.line_fields(info))
        print(line, file=self._out)

    # --- marginals ---------------------------------------------------------------------------

    def compute_marginals(self, vertices: Iterable[BaseVertex | int]) -> dict[int, np.ndarray]:
        """Marginal covariances (blocks of ``H⁻¹`` at the current estimates, undamped).

        Args:
            vertices: Vertices or ids (not fixed).

        Returns:
            ``{id: (d, d) covariance}``.

        Raises:
            GraphError: unknown or fixed vertex.
            NotPositiveDefiniteError: if ``H`` is singular (e.g. no gauge fixed).
        """
        from graphopt.marginals import marginals_of

        return marginals_of(self.graph, self._ensure_problem(), vertices)


def _weak_call(method: weakref.WeakMethod) -> Callable[[], bool]:
    """A callable that calls ``method`` while its object lives (``False`` after)."""

    def call() -> bool:
        bound = method()
        return bool(bound is not None and bound())

    return call
