"""g2o's ``SparseOptimizer`` in front of graphopt's.

``add_vertex``/``add_edge`` file records (a dict insertion each). ``initialize_optimization``
turns them into arrays — one *bank* per graphopt vertex type, one *batch* per g2o edge class and
parameters — and builds a graphopt :class:`~graphopt.SparseOptimizer` with the edges of the
requested level (one ``add_vertices`` per bank, one ``add_edges`` per batch; graphopt validates
there, in bulk, naming the offending ids). A later ``initialize_optimization`` after level
changes rebuilds the graphopt optimizer from the arrays without touching the records; records
added or edited after it are filed again.

g2o's semantics: ``optimize(n)`` runs ``n`` iterations unless no step is found or a trial
leaves chi2 unchanged to rounding (``StoppingConfig.g2o``) and returns the count; LM is g2o's
(τ = 1e-5, Nielsen's λ rule, ``set_user_lambda_init``); ``set_verbose`` prints g2o's iteration
lines; the force-stop flag is read after every iteration.
"""

from __future__ import annotations

import gc
import os
import sys
import weakref
from functools import lru_cache
from typing import Any

import numpy as np

from graphopt.errors import GraphError
from graphopt.optimizer import SparseOptimizer as CoreOptimizer
from graphopt.stopping import ROUNDING_CHANGE, StoppingConfig

from .batch import Batch
from .edges import BaseEdge
from .filing import bucket_edges, file_edges, file_vertices
from .params import Parameter
from .solvers import OptimizationAlgorithm, OptimizationAlgorithmLevenberg, iteration_line
from .vertices import Bank, BaseVertex, core_type

__all__ = ["SparseOptimizer"]


@lru_cache(maxsize=64)
def _g2o_stopping(iterations: int, change: float) -> StoppingConfig:
    """``StoppingConfig.g2o`` (frozen: one per count and change, not one per ``optimize``)."""
    return StoppingConfig.g2o(iterations, change)


class SparseOptimizer:
    """g2o's ``SparseOptimizer`` (both bindings' method names).

    Attributes:
        rounding_change: The relative chi2 change of a trial that ``optimize`` reads as none and
            ends the run on (g2o's ``rho == 0``; ``StoppingConfig.g2o``); 0 runs every
            iteration that finds a step, as ``StoppingConfig.iterations_only``.
    """

    rounding_change: float = ROUNDING_CHANGE

    def __init__(self) -> None:
        # Records point back weakly (this weak reference, shared by all of them), and batches
        # and banks do not point at records: a finished program's graph is freed by reference
        # counting, not left to the cyclic collector.
        self._ref = weakref.ref(self)
        self._vertices: dict[int, BaseVertex] = {}
        self._edges: dict[BaseEdge, None] = {}
        self._parameters: dict[int, Parameter] = {}
        self._algorithm: OptimizationAlgorithm = OptimizationAlgorithmLevenberg()
        self._verbose = False
        self._flag: Any = None
        self._core: CoreOptimizer | None = None
        self._banks: dict[type, Bank] = {}
        #: The batches and, for each, its edge records in order (a batch does not hold them).
        self._batches: dict[Batch, list[BaseEdge]] = {}
        self._records_dirty = True
        self._level = 0
        self._core_params: dict[Any, Any] = {}
        self._changed: list[Batch] = []
        self._cum_time = 0.0

    # --- configuration -----------------------------------------------------------------------

    def set_algorithm(self, algorithm: OptimizationAlgorithm) -> None:
        """Select the algorithm (and through it the linear solver).

        Args:
            algorithm: ``OptimizationAlgorithmLevenberg(...)`` etc.
        """
        if not isinstance(algorithm, OptimizationAlgorithm):
            raise TypeError(f"set_algorithm: expected an OptimizationAlgorithm*, got "
                            f"{type(algorithm).__name__}")
        self._algorithm = algorithm
        if self._core is not None:
            self._core.set_algorithm(algorithm.config)
            self._core.set_solver(algorithm.solver)

    def algorithm(self) -> OptimizationAlgorithm:
        """The algorithm."""
        return self._algorithm

    def set_verbose(self, verbose: bool) -> None:
        """Print g2o's iteration lines (stderr).

        Args:
            verbose: On or off.
        """
        self._verbose = bool(verbose)
        if self._core is not None:
            self._core.verbose = self._verbose

    def verbose(self) -> bool:
        """Whether iteration lines are printed."""
        return self._verbose

    def set_force_stop_flag(self, flag: Any) -> None:
        """A flag (``g2o.Flag``, or anything with a truth value) read after every iteration.

        Args:
            flag: The flag, or ``None``.
        """
        self._flag = flag

    def force_stop_flag(self) -> Any:
        """The force-stop flag, or ``None``."""
        return self._flag

    def add_parameter(self, parameter: Parameter) -> bool:
        """Register a parameter under its id.

        Args:
            parameter: ``CameraParameters``, ``ParameterSE3Offset``...
        """
        pid = parameter.id()
        if pid in self._parameters:
            return False
        self._parameters[pid] = parameter
        self._structure_changed()
        return True

    def parameter(self, pid: int) -> Parameter | None:
        """The parameter with this id.

        Args:
            pid: The id.
        """
        return self._parameters.get(int(pid))

    # --- the graph ---------------------------------------------------------------------------

    def add_vertex(self, vertex: BaseVertex) -> bool:
        """File a vertex (False if its id is taken).

        Args:
            vertex: The vertex record.
        """
        try:
            vid = vertex._id
        except AttributeError:
            raise TypeError(f"add_vertex: expected a g2o vertex, got {type(vertex).__name__}"
                            ) from None
        if vid in self._vertices or (vertex._opt is not None and not self._orphan(vertex)):
            return False
        self._vertices[vid] = vertex
        vertex._opt = self._ref
        self._records_dirty = True
        return True

    def add_edge(self, edge: BaseEdge) -> bool:
        """File an edge (False, as g2o, if it is already in a graph, a vertex is missing or
        one vertex is named twice).

        Args:
            edge: The edge record.
        """
        try:
            v0, v1, vn = edge._v0, edge._v1, edge._vn
        except AttributeError:
            raise TypeError(f"add_edge: expected a g2o edge, got {type(edge).__name__}"
                            ) from None
        if edge._opt is not None and not self._orphan(edge):
            return False
        if vn is None:  # one or two vertices (v1 is None for one)
            if v0 is None or v1 is v0 or (v1 is None and edge._k != 1):
                return False
        else:
            vs = edge._v
            if None in vs or len(set(map(id, vs))) < len(vs):
                return False
        self._edges[edge] = None
        edge._opt = self._ref
        self._records_dirty = True
        return True

    @staticmethod
    def _orphan(record: BaseVertex | BaseEdge) -> bool:
        """Whether a record's optimizer is gone (then it is detached and may join another).

        Args:
            record: A vertex or edge record whose ``_opt`` is set.
        """
        if record._opt() is not None:
            return False
        record._detach()
        return True

    def vertex(self, vid: int) -> BaseVertex | None:
        """The vertex with this id, or ``None``.

        Args:
            vid: The id.
        """
        return self._vertices.get(vid)

    def vertices(self) -> dict[int, BaseVertex]:
        """``{id: vertex}``."""
        return dict(self._vertices)

    def edges(self) -> list[BaseEdge]:
        """All edges, in the order they were added."""
        return list(self._edges)

    def remove_edge(self, edge: BaseEdge) -> bool:
        """Remove an edge.

        Args:
            edge: The edge.
        """
        if edge._opt is not self._ref:
            return False
        del self._edges[edge]
        edge._detach()
        self._records_dirty = True
        return True

    def remove_vertex(self, vertex: BaseVertex) -> bool:
        """Remove a vertex and its edges (as g2o does).

        Args:
            vertex: The vertex.
        """
        if vertex._opt is not self._ref:
            return False
        for e in [e for e in self._edges if any(v is vertex for v in e._v)]:
            self.remove_edge(e)
        del self._vertices[vertex._id]
        vertex._detach()
        self._records_dirty = True
        return True

    def clear(self) -> None:
        """Remove everything."""
        for v in list(self._vertices.values()):
            self.remove_vertex(v)
        self._core = None

    # --- notifications from records ----------------------------------------------------------

    def _structure_changed(self) -> None:
        self._records_dirty = True

    # --- building ----------------------------------------------------------------------------

    def _core_param(self, cls: type, key: tuple[Any, ...]) -> Any:
        """graphopt's parameter object of an edge batch (one object per key: graphopt groups
        edges by parameter object)."""
        full = (cls._gname, key)
        if full not in self._core_params:
            if cls._nparams == 0 and cls._param_type:  # intrinsics on the edge (fx, fy, ...)
                value: Any = core_type(cls._param_type)(*key)
            elif cls._nparams == 0:
                value = None
            else:
                cores = []
                for pid in key:
                    p = self._parameters.get(pid)
                    if p is None:
                        raise GraphError(f"{cls.__name__}: parameter {pid} was never added "
                                         "(optimizer.add_parameter)")
                    cores.append(p._core())
                value = cores[0] if len(cores) == 1 else tuple(cores)
            self._core_params[full] = value
        return self._core_params[full]

    def _build_core(self) -> None:
        alg = self._algorithm
        core = CoreOptimizer(alg.config, alg.solver, verbose=self._verbose,
                             stopping=StoppingConfig.iterations_only())
        for gtype, bank in self._banks.items():  # (ids: the keys of a dict, in a new graph)
            core.graph.add_vertices(gtype, bank.ids, bank.estimates(), bank.user_fixed,
                                    bank.marg, new_ids=True)
        for gtype, bank in self._banks.items():
            bank.store = core.graph.stores[gtype]
        for b in self._batches:
            b.add_to(core)
        self._core = core
        self._changed = []

    def _batch_changed(self, batch: Batch) -> None:
        self._changed.append(batch)

    def _prepare(self, levels: bool = False) -> CoreOptimizer:
        if self._records_dirty or self._core is None:
            # Filing creates many small containers while the program holds many records: the
            # cyclic collector would rescan them all, several times (3x the filing time measured
            # on 25,000 edges); nothing made here forms cycles that outlive it.
            enabled = gc.isenabled()
            gc.disable()
            try:
                if self._records_dirty:
                    self._core_params = {}  # parameters may have changed since
                    buckets = bucket_edges(self._edges)
                    self._banks = file_vertices(list(self._vertices.values()), buckets)
                    self._batches = file_edges(self, buckets, self._vertices,
                                               self._core_param)
                    self._records_dirty = False
                self._build_core()
            finally:
                if enabled:
                    gc.enable()
        if self._changed:
            keep = []
            for b in self._changed:
                b.sync(levels)
                if b.levels_dirty:
                    keep.append(b)
            self._changed = keep
        assert self._core is not None
        return self._core

    def initialize_optimization(self, level: int = 0) -> bool:
        """Take the edges of ``level`` (and their vertices) for the next ``optimize`` calls;
        levels, kernels, estimates and flags changed since the last call are written into the
        optimizer's arrays, and its structure is reused unless vertices or edges were added or
        removed.

        Args:
            level: The edge level.

        Returns:
            True.
        """
        self._level = int(level)
        self._prepare(levels=True).initialize_optimization(self._level)
        return True

    # --- optimising --------------------------------------------------------------------------

    def optimize(self, iterations: int, online: bool = False) -> int:
        """Run ``iterations`` iterations (fewer only if no step is found or the force-stop flag
        is set).

        Args:
            iterations: The count.
            online: Ignored (g2o's incremental mode).

        Returns:
            The number of iterations run.
        """
        core = self._prepare()
        if self._flag is not None and bool(self._flag):
            return 0
        core.verbose = False  # g2o's lines come from _print_line (λ after its update)
        core.stopping = _g2o_stopping(max(int(iterations), 1), self.rounding_change)
        if self._verbose or self._flag is not None:  # else none: a run may be replayed
            core._callbacks["post_iteration"] = [self._after_iteration]
        self._cum_time = 0.0
        try:
            result = core.optimize(int(iterations))
        finally:  # the bound method would be a cycle (this optimizer -> core -> this one)
            core._callbacks["post_iteration"] = []
        return len(result.info)

    def _after_iteration(self, core: CoreOptimizer, info: Any) -> None:
        if self._verbose:
            self._print_line(core, info)
        if self._flag is not None and bool(self._flag):
            core.stop()

    def _print_line(self, core: CoreOptimizer, info: Any) -> None:
        self._cum_time += info.seconds
        print(iteration_line(core, info, self._cum_time), file=sys.stderr)

    def compute_active_errors(self) -> None:
        """Evaluate the active edges at the current estimates."""
        self._prepare().compute_active_errors()

    def active_chi2(self) -> float:
        """Σ eᵀΩe over the active edges (no kernel), at the last evaluation."""
        return self._prepare().chi2()

    def active_robust_chi2(self) -> float:
        """Σ ρ(eᵀΩe) over the active edges, at the last evaluation."""
        return self._prepare().active_robust_chi2()

    def chi2(self) -> float:
        """Σ eᵀΩe over the active edges (g2o's ``chi2``)."""
        return self.active_chi2()

    def active_edges(self) -> list[BaseEdge]:
        """The edges of the current level."""
        self._prepare()
        return [r for b, recs in self._batches.items()
                for r, lv in zip(recs, b.levels.tolist(), strict=True) if lv == self._level]

    def active_vertices(self) -> list[BaseVertex]:
        """The vertices of the active edges."""
        ids = {v._id for e in self.active_edges() for v in e._v}
        return [self._vertices[i] for i in ids]

    def set_estimates_of(self, vtype: type[BaseVertex], estimates: Any) -> None:
        """graphopt's bulk reset (not in g2o): all estimates of a vertex class at once.

        Args:
            vtype: The g2o vertex class.
            estimates: ``(n, *shape)`` in the bank's slot order (the order added).
        """
        self._prepare()
        bank = self._banks[core_type(vtype._gname)]
        assert bank.store is not None
        est = np.array(estimates, dtype=float)
        bank.store.check_estimates(est, bank.ids)
        bank.store.estimates = est

    # --- files -------------------------------------------------------------------------------

    def load(self, filename: str | os.PathLike[str], *args: Any) -> bool:
        """Read a g2o, TORO or GTSAM file (see :mod:`graphopt.io.g2o`) into this optimizer.

        Args:
            filename: The file.
            args: g2o's format argument (ignored: the format is detected).
        """
        from .files import load

        load(self, filename)
        return True

    def save(self, filename: str | os.PathLike[str], *args: Any) -> bool:
        """Write the graph with the current estimates as a g2o file (atomically).

        Args:
            filename: The file.
            args: g2o's format and level arguments (ignored).
        """
        from .files import save

        save(self, filename)
        return True

    @property
    def core(self) -> CoreOptimizer:
        """graphopt's optimizer behind this one (built on demand)."""
        return self._prepare()

