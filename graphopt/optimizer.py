"""``SparseOptimizer``: g2o's optimizer API over batched edge groups.

Data flow (see ``docs/architecture.md``): ``add_vertex``/``add_edge`` (or their bulk forms) fill
struct-of-arrays stores; ``initialize_optimization`` resolves ids to slots and builds the
:class:`~graphopt.linear.LinearSystem` (block pattern, scatter maps, Schur strategies) and the
linear solver's symbolic analysis once; ``optimize`` then runs the chosen algorithm, whose
iterations only compute numbers.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from graphopt.algorithms import (
    Algorithm,
    AlgorithmConfig,
    IterationInfo,
    LevenbergMarquardt,
    make_algorithm,
)
from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError, NotPositiveDefiniteError
from graphopt.graph import EdgeGroup, VertexStore
from graphopt.linear import Assembly, LinearSystem, SchurConfig
from graphopt.robust_kernel import RobustKernel
from graphopt.solvers import LinearSolver, make_solver
from graphopt.vertex import BaseVertex

Callback = Callable[["SparseOptimizer", IterationInfo], Any]


@dataclass
class OptimizationResult:
    """What :meth:`SparseOptimizer.optimize` did.

    Args:
        initial_chi2: Robust chi2 before the first iteration.
        final_chi2: Robust chi2 at the end.
        chi2_history: Robust chi2 after each iteration.
        iterations: Iterations performed.
        seconds: Wall time of the whole call.
        stop_reason: ``"iterations"`` (the count was reached), ``"gain"`` (relative decrease
            below the threshold), ``"stopped"`` (:meth:`SparseOptimizer.force_stop`),
            ``"converged"`` (zero chi2, or no trial step reduced chi2) or ``"failed"`` (every
            solve met a system that is not positive definite).
        lambda_history: λ of each iteration (LM/Dogleg).
        linearize_seconds: Per iteration: errors, Jacobians, assembly.
        schur_seconds: Per iteration: damping and Schur complement (all trials).
        solve_seconds: Per iteration: linear solver (all trials).
        trials: Per iteration: damped solves (g2o's ``levenbergIter``).
        not_positive_definite: Solves that met a non-positive-definite system.
        info: The :class:`~graphopt.algorithms.IterationInfo` of every iteration.
    """

    initial_chi2: float
    final_chi2: float = float("nan")
    chi2_history: list[float] = field(default_factory=list)
    iterations: int = 0
    seconds: float = 0.0
    stop_reason: str = "iterations"
    lambda_history: list[float] = field(default_factory=list)
    linearize_seconds: list[float] = field(default_factory=list)
    schur_seconds: list[float] = field(default_factory=list)
    solve_seconds: list[float] = field(default_factory=list)
    trials: list[int] = field(default_factory=list)
    not_positive_definite: int = 0
    info: list[IterationInfo] = field(default_factory=list)

    @property
    def seconds_per_iteration(self) -> float:
        """Mean wall time of one iteration."""
        return self.seconds / self.iterations if self.iterations else 0.0


@dataclass
class _Evaluation:
    chi2: float
    robust_chi2: float
    active: int


class SparseOptimizer:
    """A graph of vertices and edges, optimised by GN, LM or Dogleg with a Schur complement.

    Args:
        algorithm: ``"lm"``, ``"gn"``, ``"dogleg"`` or a config dataclass
            (:class:`~graphopt.algorithms.LevenbergConfig`, ...).
        solver: ``"cholmod"``, ``"dense"``, ``"pcg"``, ``"scipy"`` or a
            :class:`~graphopt.solvers.LinearSolver`.
        verbose: Print g2o's iteration line after every iteration.
        gain_threshold: Stop when the relative chi2 decrease of an iteration falls below this
            (g2o's ``-gain``); ``0`` disables it.
        stream: Where verbose lines go (stderr by default).
        schur: How ``W V⁻¹ Wᵀ`` is formed (:class:`~graphopt.linear.SchurConfig`; default:
            the cheapest way per W class by the cost model).
    """

    def __init__(
        self,
        algorithm: str | AlgorithmConfig = "lm",
        solver: str | LinearSolver = "cholmod",
        verbose: bool = False,
        gain_threshold: float = 0.0,
        stream: TextIO | None = None,
        schur: SchurConfig | None = None,
    ) -> None:
        self._stores: dict[type[BaseVertex], VertexStore] = {}
        self._groups: dict[tuple[type[BaseEdge], int], EdgeGroup] = {}
        self._ids: dict[int, tuple[VertexStore, int]] = {}
        self._objects: dict[int, BaseVertex] = {}
        self._edge_objects: list[BaseEdge] = []
        self.algorithm: Algorithm = make_algorithm(algorithm)
        self._solver_spec = solver
        self.solver: LinearSolver | None = None
        self.verbose = verbose
        self.gain_threshold = gain_threshold
        self.stream = stream
        self._callbacks: dict[str, list[Callback]] = {"pre_iteration": [], "post_iteration": []}
        self._system: LinearSystem | None = None
        self._schur_config = schur
        self._structure_key: tuple[Any, ...] | None = None
        self._stop = False
        self._saved: list[np.ndarray] = []
        self._last_eval: _Evaluation | None = None
        self._timing = {"schur": 0.0, "solve": 0.0}
        self._positions: list[list[tuple[int, np.ndarray]]] = []
        self._lin_cache: dict[int, tuple[tuple[int, ...], tuple[Any, ...], Any]] = {}
        # Per (store, "estimates" | "derived"): (estimate version, array to gather edges from,
        # whether it is stored transposed).
        self._state_cache: dict[tuple[int, str], tuple[int, np.ndarray | None, bool]] = {}

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
        self._system = None

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

    # --- vertices ----------------------------------------------------------------------------

    def _store(self, vtype: type[BaseVertex]) -> VertexStore:
        if not (isinstance(vtype, type) and issubclass(vtype, BaseVertex)):
            raise GraphError(f"not a vertex type: {vtype!r}")
        if vtype.dimension <= 0:
            raise GraphError(f"{vtype.__name__}: dimension must be a positive integer")
        if vtype not in self._stores:
            self._stores[vtype] = VertexStore(vtype)
        return self._stores[vtype]

    def add_vertex(self, vertex: BaseVertex) -> bool:
        """Add one vertex (g2o's ``addVertex``).

        Args:
            vertex: The vertex, with id and estimate set.

        Returns:
            True.

        Raises:
            GraphError: duplicate id, missing or malformed estimate.
        """
        if vertex._store is not None:
            raise GraphError(f"vertex {vertex._id} ({type(vertex).__name__}) is already added")
        vid = vertex.id
        est = vertex._estimate
        if est is None:
            raise GraphError(f"vertex {vid} ({type(vertex).__name__}) has no estimate")
        self._add(type(vertex), np.array([vid]), est[None], vertex._fixed, vertex._marginalized)
        store, slot = self._ids[vid]
        vertex._store, vertex._slot, vertex._estimate = store, slot, None
        self._objects[vid] = vertex
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
        ids_arr = np.asarray(ids)
        if ids_arr.ndim != 1 or not np.issubdtype(ids_arr.dtype, np.integer):
            raise GraphError(f"{vtype.__name__}: ids must be a 1-D integer array")
        self._add(vtype, ids_arr.astype(np.int64), estimates, fixed, marginalized)

    def _add(self, vtype: type[BaseVertex], ids: np.ndarray, estimates: Any, fixed: Any,
             marg: Any) -> None:
        store = self._store(vtype)
        n = len(ids)
        shape = tuple(vtype.estimate_shape)
        try:
            est = np.array(estimates, dtype=float)
        except (TypeError, ValueError) as exc:
            raise GraphError(f"{vtype.__name__}: estimates are not numeric: {exc}") from None
        if est.shape != (n, *shape):
            raise GraphError(
                f"{vtype.__name__}: estimates have shape {est.shape}, expected {(n, *shape)} "
                f"(first vertex id {int(ids[0]) if n else '-'})"
            )
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            raise GraphError(f"duplicate vertex id {int(uniq[counts > 1][0])} ({vtype.__name__})")
        dup = next((v for v in ids.tolist() if v in self._ids), None)
        if dup is not None:
            raise GraphError(f"duplicate vertex id {dup} ({vtype.__name__})")
        store.check_estimates(est, ids)
        fixed_arr = np.broadcast_to(np.asarray(fixed, dtype=bool), (n,)).copy()
        marg_arr = np.broadcast_to(np.asarray(marg, dtype=bool), (n,)).copy()
        start = store.append(ids, est, fixed_arr, marg_arr)
        self._ids.update(zip(ids.tolist(), ((store, s) for s in range(start, start + n)),
                             strict=True))
        self._system = None

    def vertex(self, vid: int) -> BaseVertex | None:
        """The vertex with this id, or ``None`` (g2o's ``vertex(id)``).

        Args:
            vid: The id.
        """
        vid = int(vid)
        if vid in self._objects:
            return self._objects[vid]
        if vid not in self._ids:
            return None
        store, slot = self._ids[vid]
        v = store.vtype._bound(store, slot, vid)
        self._objects[vid] = v
        return v

    def vertex_ids(self) -> list[int]:
        """All vertex ids."""
        return list(self._ids)

    def estimates_of(self, vtype: type[BaseVertex]) -> np.ndarray:
        """A copy of the estimates of all vertices of a type, in the order they were added.

        Args:
            vtype: The vertex class.
        """
        return self._stores[vtype].estimates.copy() if vtype in self._stores else np.zeros(
            (0, *vtype.estimate_shape))

    def ids_of(self, vtype: type[BaseVertex]) -> np.ndarray:
        """Ids of all vertices of a type, in the order they were added.

        Args:
            vtype: The vertex class.
        """
        return self._stores[vtype].ids.copy() if vtype in self._stores else np.zeros(0, int)

    def set_estimates_of(self, vtype: type[BaseVertex], estimates: np.ndarray) -> None:
        """Replace the estimates of all vertices of a type (same order as :meth:`ids_of`).

        Args:
            vtype: The vertex class.
            estimates: ``(n, *estimate_shape)``.
        """
        st = self._stores[vtype]
        est = np.array(estimates, dtype=float)
        if est.shape != st.estimates.shape:
            raise GraphError(f"{vtype.__name__}: estimates have shape {est.shape}, expected "
                             f"{st.estimates.shape}")
        st.check_estimates(est, st.ids)
        st.estimates = est

    # --- edges -------------------------------------------------------------------------------

    def _group(self, etype: type[BaseEdge], params: Any) -> EdgeGroup:
        if not (isinstance(etype, type) and issubclass(etype, BaseEdge)):
            raise GraphError(f"not an edge type: {etype!r}")
        if etype.dimension <= 0 or not etype.vertex_types:
            raise GraphError(f"{etype.__name__}: set dimension and vertex_types")
        key = (etype, id(params))
        if key not in self._groups:
            self._groups[key] = EdgeGroup(etype, params)
        return self._groups[key]

    def add_edge(self, edge: BaseEdge) -> bool:
        """Add one edge (g2o's ``addEdge``).

        Args:
            edge: The edge with its vertices, measurement and (optionally) information/kernel.

        Returns:
            True.

        Raises:
            GraphError: a missing vertex, wrong shapes of measurement or information.
        """
        et = type(edge)
        if edge._group is not None:
            raise GraphError(f"{edge!r} is already added")
        ids = []
        for i, v in enumerate(edge._vertices):
            if v is None:
                raise GraphError(f"{et.__name__}: vertex {i} is not set")
            ids.append(v.id if isinstance(v, BaseVertex) else int(v))
        if edge._measurement is None:
            raise GraphError(f"{et.__name__} on vertices {ids}: no measurement set")
        info = edge._information if edge._information is not None else np.eye(et.dimension)
        data = {k: np.asarray(v)[None] for k, v in edge.data.items()}
        group = self._group(et, edge.params)
        idx = self._add_edges(group, np.array([ids]), edge._measurement[None], info[None],
                              edge._robust_kernel, data, single=True)
        edge._group, edge._index, edge._optimizer = group, idx, self
        self._edge_objects.append(edge)
        return True

    def add_edges(
        self,
        etype: type[BaseEdge],
        vertex_ids: Any,
        measurements: Any,
        information: Any = None,
        robust_kernel: RobustKernel | None = None,
        params: Any = None,
        data: dict[str, Any] | None = None,
    ) -> None:
        """Add many edges of one type at once (the fast path).

        Args:
            etype: The edge class.
            vertex_ids: ``(m, k)`` vertex ids, one column per entry of ``vertex_types``.
            measurements: ``(m, *measurement_shape)``.
            information: ``None`` (identity), one ``(e, e)`` matrix for all, or ``(m, e, e)``.
            robust_kernel: One kernel for all these edges, or ``None``.
            params: Shared parameters (edges with the same type and params form one group).
            data: Per-edge auxiliary arrays, each with first dimension ``m``.

        Raises:
            GraphError: missing vertices, wrong shapes, non-finite values.
        """
        group = self._group(etype, params)
        vids = np.asarray(vertex_ids)
        k = len(etype.vertex_types)
        if vids.ndim != 2 or vids.shape[1] != k or not np.issubdtype(vids.dtype, np.integer):
            raise GraphError(
                f"{etype.__name__}: vertex_ids must be an integer array of shape (m, {k}), "
                f"got {vids.shape}"
            )
        m = len(vids)
        e = etype.dimension
        if information is None:
            info = np.eye(e)
        else:
            info = np.asarray(information, dtype=float)
            if info.shape not in ((e, e), (m, e, e)):
                raise GraphError(
                    f"{etype.__name__}: information has shape {info.shape}, expected {(e, e)} "
                    f"or {(m, e, e)}"
                )
        try:
            meas = np.asarray(measurements, dtype=float)
        except (TypeError, ValueError) as exc:
            raise GraphError(f"{etype.__name__}: measurements are not numeric: {exc}") from None
        arrays = {}
        for key, val in (data or {}).items():
            arr = np.asarray(val)
            if arr.shape[:1] != (m,):
                raise GraphError(f"{etype.__name__}: data[{key!r}] must have first dimension {m}")
            arrays[key] = arr
        self._add_edges(group, vids.astype(np.int64), meas, info, robust_kernel, arrays)

    def _add_edges(self, group: EdgeGroup, vids: np.ndarray, meas: np.ndarray, info: np.ndarray,
                   kernel: RobustKernel | None, data: dict[str, np.ndarray],
                   single: bool = False) -> int:
        et = group.etype
        m, e = len(vids), et.dimension
        mshape = group.mshape
        if meas.shape != (m, *mshape):
            what = f"on vertices {vids[0].tolist()}" if single else ""
            got = meas.shape[1:] if single else meas.shape
            want = mshape if single else (m, *mshape)
            raise GraphError(f"{et.__name__} {what}: measurement has shape {got}, expected {want}"
                             .replace("  ", " "))
        bad = ~np.isfinite(meas.reshape(m, -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise GraphError(f"{et.__name__} on vertices {vids[i].tolist()}: non-finite "
                             "measurement")
        if single:
            info = info[0]
            if info.shape != (e, e):
                raise GraphError(f"{et.__name__} on vertices {vids[0].tolist()}: information "
                                 f"has shape {info.shape}, expected {(e, e)}")
        infos = info.reshape(-1, e, e)
        if not np.all(np.isfinite(infos)):
            raise GraphError(f"{et.__name__}: non-finite information matrix")
        if not np.allclose(infos, np.swapaxes(infos, 1, 2), rtol=1e-9, atol=1e-12):
            raise GraphError(f"{et.__name__}: information matrix is not symmetric")
        uniq_info = infos if len(infos) <= 1 else np.unique(infos, axis=0)
        low = np.linalg.eigvalsh(uniq_info)
        if np.any(low[:, 0] < -1e-9 * np.maximum(np.abs(low[:, -1]), 1.0)):
            raise GraphError(f"{et.__name__}: information matrix is not positive semi-definite")
        for pos, vt in enumerate(et.vertex_types):
            # Check each distinct id once; report the first edge that names a bad one.
            col = vids[:, pos]
            distinct = np.unique(col).tolist()
            bad = [v for v in distinct
                   if v not in self._ids or not issubclass(self._ids[v][0].vtype, vt)]
            if bad:
                i = int(np.flatnonzero(np.isin(col, bad))[0])
                self._check_vertex(et, vids[i], pos, int(col[i]), vt)
        kslot = group.kernel_slot(kernel)
        self._system = None
        return group.append(vids, meas, info, kslot, data)

    def _check_vertex(self, et: type[BaseEdge], ids: np.ndarray, pos: int, vid: int,
                      vt: type[BaseVertex]) -> None:
        if vid not in self._ids:
            raise GraphError(f"{et.__name__} on vertices {ids.tolist()}: vertex {vid} "
                             f"(position {pos}) does not exist")
        st = self._ids[vid][0]
        if not issubclass(st.vtype, vt):
            raise GraphError(f"{et.__name__} on vertices {ids.tolist()}: vertex {vid} is a "
                             f"{st.vtype.__name__}, position {pos} needs a {vt.__name__}")

    def edges(self) -> list[BaseEdge]:
        """The edges added one at a time (bulk edges live only as arrays)."""
        return list(self._edge_objects)

    def edge_groups(self) -> list[EdgeGroup]:
        """The edge groups (one per edge type and parameter object)."""
        return list(self._groups.values())

    def num_edges(self) -> int:
        """Number of edges."""
        return sum(g.size for g in self._groups.values())

    # --- initialisation ----------------------------------------------------------------------

    def _key(self) -> tuple[Any, ...]:
        return (tuple((id(s), len(s), s.flags_version) for s in self._stores.values()),
                tuple((id(g), g.size) for g in self._groups.values()))

    def initialize_optimization(self) -> bool:
        """Build the structure: slots, block pattern, scatter maps, Schur pairs, symbolic
        factorisation. Called by :meth:`optimize` when the graph changed.

        Returns:
            True.
        """
        stores = list(self._stores.values())
        index = {id(s): i for i, s in enumerate(stores)}
        lookup: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for i, s in enumerate(stores):
            order = np.argsort(s.ids)
            lookup[i] = (s.ids[order], order)
        self._positions = []
        groups = list(self._groups.values())
        for g in groups:
            g.finalize()
            pos = []
            for a in range(g.k):
                col = g.vertex_ids[:, a]
                first = self._ids[int(col[0])][0]
                si = index[id(first)]
                sids, order = lookup[si]
                loc = np.searchsorted(sids, col).clip(0, max(len(sids) - 1, 0))
                ok = sids[loc] == col
                if not ok.all():
                    bad = int(col[np.flatnonzero(~ok)[0]])
                    other = self._ids[bad][0].vtype.__name__
                    raise GraphError(
                        f"{g.etype.__name__}: position {a} mixes vertex types "
                        f"({first.vtype.__name__} and {other}, vertex {bad}); use one type per "
                        "position within an edge type"
                    )
                pos.append((si, order[loc]))
            self._positions.append(pos)
        self._store_list = stores
        self._group_list = groups
        self._system = LinearSystem(stores, groups, self._positions, self._schur_config)
        self.solver = make_solver(self._solver_spec)
        self.solver.analyze(self._system.pattern, self._system.udims)
        self._build_update_maps()
        self._lin_cache = {}
        self._state_cache = {}
        self._structure_key = self._key()
        self.algorithm.reset()
        return True

    def _build_update_maps(self) -> None:
        assert self._system is not None
        sysm = self._system.index
        self._update: list[tuple[np.ndarray, np.ndarray, list[tuple[int, np.ndarray,
                                                                    np.ndarray]]]] = []
        for si, st in enumerate(self._store_list):
            ub = sysm.ublock[si]
            uslots = np.flatnonzero(ub >= 0)
            d = st.vtype.dimension
            upos = sysm.uoffset[ub[uslots]][:, None] + np.arange(d)
            vparts = []
            vc = sysm.vclass_of_store[si]
            if vc >= 0:
                vslots = sysm.vclasses[vc].slots
                vparts.append((vc, vslots, np.arange(len(vslots))))
            self._update.append((uslots, upos, vparts))

    def _ensure_initialized(self) -> None:
        if self._system is None or self._structure_key != self._key():
            self.initialize_optimization()

    # --- evaluation --------------------------------------------------------------------------

    def _gather(self, gi: int) -> tuple[np.ndarray, ...]:
        out = tuple(self._gather_rows(si, "estimates", slots) for si, slots in self._positions[gi])
        return out  # type: ignore[return-value]  # estimates are never None

    def _gather_rows(self, si: int, what: str, slots: np.ndarray) -> np.ndarray | None:
        """Rows ``slots`` of a store's estimates or derived values, cached per state.

        2-D arrays ``(n, d)`` are gathered coordinate by coordinate from a transposed copy: the
        result ``(m, d)`` is in Fortran order, so each coordinate over the edges is one
        contiguous array — what batched edge code reads, and a cheaper gather.
        """
        st = self._store_list[si]
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
        return np.take(a, slots, axis=1).T if transposed else a[slots]

    def _context(self, gi: int, g: EdgeGroup) -> EdgeContext:
        """The group's context, with the vertices' derived values if its type uses them."""
        ctx = g.context()
        if g.etype.uses_derived:
            ctx.derived = tuple(self._gather_rows(si, "derived", slots)
                                for si, slots in self._positions[gi])
        return ctx

    def _robustify(self, g: EdgeGroup, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-edge ρ(s) and the weight ρ'(s) (clipped at 0)."""
        if not g.kernels:
            return s, np.ones_like(s)
        rho = s.copy()
        w = np.ones_like(s)
        if len(g.kernels) == 1 and np.all(g.kernel_index == 0):
            r0, r1, _ = g.kernels[0].robustify(s)
            return r0, np.maximum(r1, 0.0)
        for ki, kern in enumerate(g.kernels):
            sel = g.kernel_index == ki
            if sel.any():
                r0, r1, _ = kern.robustify(s[sel])
                rho[sel], w[sel] = r0, np.maximum(r1, 0.0)
        return rho, w

    def _sq(self, g: EdgeGroup, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Ω e`` and ``e'Ω e`` per edge."""
        if g.info_is_identity:
            return e, np.einsum("me,me->m", e, e)
        assert g.information is not None
        oe = e @ g.information if g.information.ndim == 2 else np.einsum("mij,mj->mi",
                                                                          g.information, e)
        return oe, np.einsum("me,me->m", e, oe)

    @staticmethod
    def _reduced(g: EdgeGroup, out: Linearization, J: tuple[np.ndarray, ...]) -> np.ndarray:
        """Check and return ``e_lin`` of a reduced linearisation."""
        r = g.etype.linearization_rows
        name = g.etype.__name__
        if out.reduced_error is None:
            raise GraphError(f"{name}: linearization_rows is set, so linearize must return a "
                             "Linearization with reduced_error (e_lin)")
        e_lin = out.reduced_error
        if e_lin.shape != (g.size, r) or any(j.shape[:2] != (g.size, r) for j in J):
            raise GraphError(f"{name}: a reduced linearisation needs e_lin ({g.size}, {r}) and "
                             f"Jacobians ({g.size}, {r}, d)")
        if not g.info_is_identity:
            raise GraphError(f"{name}: a reduced linearisation needs an identity information "
                             "matrix")
        if not np.isfinite(e_lin.sum()):
            raise FloatingPointError(f"{name}: non-finite reduced error at linearisation")
        return e_lin

    def _state(self) -> tuple[int, ...]:
        """Versions of every store's estimates: the key of cached linearisations."""
        return tuple(st.version for st in self._store_list)

    def _group_linearization(self, gi: int, g: EdgeGroup) -> Linearization:
        """The group's linearisation, reusing a trial's if still valid."""
        key = self._state()
        hit = self._lin_cache.get(gi)
        if hit is not None and hit[0] == key:
            return hit[1]
        ctx = self._context(gi, g)
        out = g.etype.linearize(self._gather(gi), g.measurements, ctx)
        if not isinstance(out, Linearization):
            out = Linearization(*out)
        if g.etype.linearize_on_trial:
            self._lin_cache[gi] = (key, out)
        return out

    def _evaluate(self) -> _Evaluation:
        chi2 = rchi2 = 0.0
        active = 0
        for gi, g in enumerate(self._group_list):
            if g.etype.linearize_on_trial:
                out = self._group_linearization(gi, g)
            else:
                out = g.etype.evaluate(self._gather(gi), g.measurements, self._context(gi, g))
            e = out.error
            _, s = self._sq(g, e)
            rho, _ = self._robustify(g, s)
            g.last_chi2 = s
            g.active_count = g.size if out.active is None else int(np.count_nonzero(out.active))
            active += g.active_count
            chi2 += float(s.sum())
            rchi2 += float(rho.sum())
        if not np.isfinite(rchi2):
            rchi2 = float("inf")
        self._last_eval = _Evaluation(chi2, rchi2, active)
        return self._last_eval

    # The Problem protocol used by the algorithms.

    def linearize(self) -> tuple[Assembly, float]:
        """Errors, Jacobians and the assembled normal equations at the current state.

        Returns:
            The assembly and the robust chi2.
        """
        t0 = time.perf_counter()
        assert self._system is not None
        jac, wjac, wes = [], [], []
        chi2 = rchi2 = 0.0
        active = 0
        for gi, g in enumerate(self._group_list):
            out = self._group_linearization(gi, g)
            e, J, active_mask = out.error, out.jacobians, out.active
            oe, s = self._sq(g, e)
            if g.etype.linearization_rows is not None:
                oe = self._reduced(g, out, J)
            rho, w = self._robustify(g, s)
            if not np.isfinite(s.sum()):  # one sum is cheaper than isfinite().all()
                self._raise_non_finite(g, e, J)
            g.last_chi2 = s
            g.active_count = (g.size if active_mask is None
                              else int(np.count_nonzero(active_mask)))
            active += g.active_count
            chi2 += float(s.sum())
            rchi2 += float(rho.sum())
            J = tuple(np.ascontiguousarray(j) for j in J)
            weighted = bool(g.kernels)
            if g.info_is_identity:
                wj = tuple(j * w[:, None, None] for j in J) if weighted else J
            else:
                assert g.information is not None
                wj = tuple(np.matmul(g.information, j) for j in J)
                if weighted:
                    wj = tuple(j * w[:, None, None] for j in wj)
            jac.append(J)
            wjac.append(wj)
            wes.append(oe * w[:, None] if weighted else oe)
        asm = self._system.assemble(jac, wjac, wes)
        # A non-finite Jacobian of a free vertex reaches its U or V block (every block holds
        # Σ J'ΩJ): checking the small assembled arrays spares a pass over the Jacobians.
        if not self._system.is_finite(asm):
            for g, J, e in zip(self._group_list, jac, wes, strict=True):
                self._raise_non_finite(g, e, J)
            raise FloatingPointError("the normal equations are not finite (overflow)")
        self._last_eval = _Evaluation(chi2, rchi2, active)
        self._timing["linearize"] = time.perf_counter() - t0
        return asm, rchi2

    @staticmethod
    def _raise_non_finite(g: EdgeGroup, e: np.ndarray, J: tuple[np.ndarray, ...]) -> None:
        """Raise naming the first edge of ``g`` with a non-finite error or Jacobian, if any."""
        ok = np.isfinite(e.reshape(len(e), -1)).all(axis=1)
        for j in J:
            ok &= np.isfinite(j.reshape(len(j), -1)).all(axis=1)
        if ok.all():
            return
        ids = g.vertex_ids[int(np.flatnonzero(~ok)[0])].tolist()
        raise FloatingPointError(
            f"{g.etype.__name__} on vertices {ids}: non-finite error or Jacobian at linearisation"
        )

    def solve(self, asm: Assembly, lam: float, diagonal: bool = False
              ) -> tuple[np.ndarray, list[np.ndarray]]:
        """Solve the damped normal equations through the Schur complement.

        Args:
            asm: The assembly.
            lam: Damping λ.
            diagonal: Damp with ``λ·diag(H)`` instead of ``λ I``.

        Raises:
            NotPositiveDefiniteError: if the system is not positive definite.
        """
        assert self._system is not None and self.solver is not None
        t0 = time.perf_counter()
        try:
            s, rhs, vinv = self._system.reduce(asm, lam, diagonal)
        finally:
            t1 = time.perf_counter()
            self._timing["schur"] += t1 - t0
        try:
            du = self.solver.solve(s, rhs)
        finally:
            t2 = time.perf_counter()
            self._timing["solve"] += t2 - t1
        dv = self._system.back_substitute(asm, du, vinv)
        self._timing["schur"] += time.perf_counter() - t2
        if not (np.all(np.isfinite(du)) and all(np.all(np.isfinite(x)) for x in dv)):
            raise NotPositiveDefiniteError("the step is not finite")
        return du, dv

    def hessian_product(self, asm: Assembly, step: tuple[np.ndarray, list[np.ndarray]]
                        ) -> tuple[np.ndarray, list[np.ndarray]]:
        """Undamped ``H · step``.

        Args:
            asm: The assembly.
            step: ``(u part, [v parts])``.
        """
        assert self._system is not None
        return self._system.hessian_product(asm, step[0], step[1])

    def damping(self, asm: Assembly, diagonal: bool) -> tuple[np.ndarray, list[np.ndarray]]:
        """The damping diagonal ``D`` (identity or clipped ``diag(H)``).

        Args:
            asm: The assembly.
            diagonal: Marquardt scaling.
        """
        assert self._system is not None
        return self._system.damping(asm, diagonal)

    def max_diagonal(self, asm: Assembly) -> float:
        """Largest diagonal entry of the undamped Hessian.

        Args:
            asm: The assembly.
        """
        assert self._system is not None
        return self._system.max_diagonal(asm)

    def push(self) -> None:
        """Save the estimates of all non-fixed vertices (g2o's ``push``)."""
        self._saved = [st.estimates.copy() for st in self._store_list]

    def pop(self) -> None:
        """Restore the estimates saved by :meth:`push` (g2o's ``pop``)."""
        for st, est in zip(self._store_list, self._saved, strict=True):
            st.estimates = est
        self._saved = []

    def apply(self, step: tuple[np.ndarray, list[np.ndarray]]) -> None:
        """``x ← x ⊞ Δ`` with every type's vectorised ``oplus``.

        Args:
            step: ``(u part, [v parts])`` as returned by :meth:`solve`.
        """
        du, dv = step
        for st, (uslots, upos, vparts) in zip(self._store_list, self._update, strict=True):
            est = st.estimates.copy()
            if len(uslots):
                est[uslots] = st.vtype.oplus(est[uslots], du[upos])
            for vc, vslots, vidx in vparts:
                est[vslots] = st.vtype.oplus(est[vslots], dv[vc][vidx])
            st.estimates = est

    def robust_chi2(self) -> float:
        """Robust chi2 at the current estimates (``inf`` if any error is not finite)."""
        return self._evaluate().robust_chi2

    # --- g2o's evaluation API ----------------------------------------------------------------

    def compute_active_errors(self) -> None:
        """Evaluate every edge's error at the current estimates (g2o's
        ``computeActiveErrors``)."""
        self._ensure_initialized()
        self._evaluate()

    def chi2(self) -> float:
        """Σ e'Ωe over the edges, without robust kernels, at the last evaluation."""
        if self._last_eval is None:
            self.compute_active_errors()
        assert self._last_eval is not None
        return self._last_eval.chi2

    def active_robust_chi2(self) -> float:
        """Σ ρ(e'Ωe) at the last evaluation (what g2o prints)."""
        if self._last_eval is None:
            self.compute_active_errors()
        assert self._last_eval is not None
        return self._last_eval.robust_chi2

    def active_edge_count(self) -> int:
        """Edges active at the last evaluation (edges may deactivate themselves)."""
        if self._last_eval is None:
            self.compute_active_errors()
        assert self._last_eval is not None
        return self._last_eval.active

    # --- optimisation ------------------------------------------------------------------------

    def optimize(self, iterations: int) -> OptimizationResult:
        """Run up to ``iterations`` iterations of the selected algorithm.

        Args:
            iterations: Maximum number of iterations (non-negative).

        Returns:
            An :class:`OptimizationResult`.
        """
        if int(iterations) != iterations or iterations < 0:
            raise ValueError(f"iterations must be a non-negative integer, got {iterations!r}")
        t_start = time.perf_counter()
        self._ensure_initialized()
        self._stop = False
        initial = self._evaluate().robust_chi2
        res = OptimizationResult(initial_chi2=initial, final_chi2=initial)
        if not np.isfinite(initial):
            raise FloatingPointError("the initial chi2 is not finite: check the estimates")
        cum = 0.0
        last = initial
        for it in range(int(iterations)):
            pre = IterationInfo(it, last)
            for cb in self._callbacks["pre_iteration"]:
                cb(self, pre)
            self._timing = {"schur": 0.0, "solve": 0.0, "linearize": 0.0}
            t0 = time.perf_counter()
            info = self.algorithm.iterate(self, it)
            dt = time.perf_counter() - t0
            cum += dt
            info.linearize_seconds = self._timing["linearize"]
            info.schur_seconds = self._timing["schur"]
            info.solve_seconds = self._timing["solve"]
            if info.failed:
                # State was restored; keep the evaluation consistent with it.
                self._evaluate()
            res.info.append(info)
            res.not_positive_definite += info.not_pd
            if self.verbose:
                self._print_line(info, dt, cum)
            for cb in self._callbacks["post_iteration"]:
                cb(self, info)
            if info.failed:
                # No trial reduced chi2: converged if the solves worked, failed otherwise.
                res.stop_reason = "failed" if info.not_pd >= info.trials else "converged"
                if info.not_pd and self.verbose:
                    print(f"# {self.algorithm.config.name}: the system was not positive "
                          f"definite {info.not_pd} time(s); no acceptable step", file=self._out)
                break
            res.iterations += 1
            res.chi2_history.append(info.chi2)
            res.lambda_history.append(info.lam)
            res.linearize_seconds.append(info.linearize_seconds)
            res.schur_seconds.append(info.schur_seconds)
            res.solve_seconds.append(info.solve_seconds)
            res.trials.append(info.trials)
            gain = (last - info.chi2) / info.chi2 if info.chi2 > 0 else 0.0
            last = info.chi2
            if self._stop:
                res.stop_reason = "stopped"
                break
            if info.chi2 == 0.0:
                res.stop_reason = "converged"
                break
            if self.gain_threshold > 0 and 0 <= gain < self.gain_threshold:
                res.stop_reason = "gain"
                break
        res.final_chi2 = last
        res.seconds = time.perf_counter() - t_start
        return res

    @property
    def linear_system(self) -> LinearSystem | None:
        """The normal equations' structure after :meth:`initialize_optimization`, else None."""
        return self._system

    @property
    def _out(self) -> TextIO:
        return self.stream if self.stream is not None else sys.stderr

    def _print_line(self, info: IterationInfo, dt: float, cum: float) -> None:
        schur = 1 if self._system is not None and self._system.schur else 0
        line = (f"iteration= {info.iteration}\t chi2= {info.chi2:.6f}\t time= {dt:.6g}\t "
                f"cumTime= {cum:.6g}\t edges= {self.active_edge_count()}\t schur= {schur}")
        if isinstance(self.algorithm, LevenbergMarquardt):
            line += f"\t lambda= {info.lam:.6g}\t levenbergIter= {info.trials}"
        elif self.algorithm.config.name == "dogleg":
            line += f"\t delta= {info.radius:.6f}\t lambda= {info.lam:.6g}"
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
        from graphopt.marginals import marginal_covariances

        self._ensure_initialized()
        ids = [v.id if isinstance(v, BaseVertex) else int(v) for v in vertices]
        return marginal_covariances(self, ids)
