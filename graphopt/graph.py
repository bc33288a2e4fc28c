"""The graph: vertices and edges by id, checked on the way in, stored as arrays.

:class:`Graph` owns the stores (one per vertex type) and groups (one per edge type and parameter
object) of :mod:`graphopt.storage`, the id → (store, slot) map and the per-object fronts. Every
input is validated here, once, with messages that name the type and the ids;
:meth:`Graph.resolve` then turns the edges' vertex ids into store slots for the numeric layers.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.edge import BaseEdge, check_level
from graphopt.edge_set import group_errors
from graphopt.errors import GraphError
from graphopt.robust_kernel import RobustKernel
from graphopt.storage import EdgeGroup, VertexStore
from graphopt.vertex import BaseVertex

#: Per edge group, per vertex position: ``(store index, slots (m,))``.
Positions = list[list[tuple[int, np.ndarray]]]


class Graph:
    """Vertices and edges of one optimisation problem.

    The g2o-style facade (:class:`~graphopt.optimizer.SparseOptimizer`) forwards its
    ``add_*`` calls here.
    """

    def __init__(self) -> None:
        self.stores: dict[type[BaseVertex], VertexStore] = {}
        self.groups: dict[tuple[type[BaseEdge], int], EdgeGroup] = {}
        self.ids: dict[int, tuple[VertexStore, int]] = {}
        self._objects: dict[int, BaseVertex] = {}
        self._edge_objects: list[BaseEdge] = []
        #: The initialised level: the edges of this level are active.
        self.level = 0
        self._lookups: dict[int, tuple[Any, ...]] = {}
        self._evals: dict[int, tuple[Any, ...]] = {}  # per group: errors at a state

    # --- vertices ----------------------------------------------------------------------------

    def _store(self, vtype: type[BaseVertex]) -> VertexStore:
        if not (isinstance(vtype, type) and issubclass(vtype, BaseVertex)):
            raise GraphError(f"not a vertex type: {vtype!r}")
        if vtype.dimension <= 0:
            raise GraphError(f"{vtype.__name__}: dimension must be a positive integer")
        if vtype not in self.stores:
            self.stores[vtype] = VertexStore(vtype)
        return self.stores[vtype]

    def add_vertex(self, vertex: BaseVertex) -> None:
        """Add one vertex object (g2o's ``addVertex``).

        Args:
            vertex: The vertex, with id and estimate set.

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
        store, slot = self.ids[vid]
        vertex._store, vertex._slot, vertex._estimate = store, slot, None
        self._objects[vid] = vertex

    def add_vertices(self, vtype: type[BaseVertex], ids: Any, estimates: Any, fixed: Any = False,
                     marginalized: Any = False) -> None:
        """Add many vertices of one type (see :meth:`SparseOptimizer.add_vertices`).

        Args:
            vtype: The vertex class.
            ids: ``(n,)`` unique integer ids.
            estimates: ``(n, *estimate_shape)``.
            fixed: One flag for all or ``(n,)`` flags.
            marginalized: One flag for all or ``(n,)`` flags.
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
        dup = next((v for v in ids.tolist() if v in self.ids), None)
        if dup is not None:
            raise GraphError(f"duplicate vertex id {dup} ({vtype.__name__})")
        store.check_estimates(est, ids)
        fixed_arr = np.broadcast_to(np.asarray(fixed, dtype=bool), (n,)).copy()
        marg_arr = np.broadcast_to(np.asarray(marg, dtype=bool), (n,)).copy()
        start = store.append(ids, est, fixed_arr, marg_arr)
        self.ids.update(zip(ids.tolist(), ((store, s) for s in range(start, start + n)),
                            strict=True))

    def vertex(self, vid: int) -> BaseVertex | None:
        """The vertex object with this id (created on demand for bulk vertices), or ``None``.

        Args:
            vid: The id.
        """
        vid = int(vid)
        if vid in self._objects:
            return self._objects[vid]
        if vid not in self.ids:
            return None
        store, slot = self.ids[vid]
        v = store.vtype._bound(store, slot, vid)
        self._objects[vid] = v
        return v

    # --- edges -------------------------------------------------------------------------------

    def _group(self, etype: type[BaseEdge], params: Any) -> EdgeGroup:
        """The group of ``(etype, params)``, new (not yet registered) if there is none."""
        if not (isinstance(etype, type) and issubclass(etype, BaseEdge)):
            raise GraphError(f"not an edge type: {etype!r}")
        if etype.dimension <= 0 or not etype.vertex_types:
            raise GraphError(f"{etype.__name__}: set dimension and vertex_types")
        group = self.groups.get((etype, id(params)))
        return group if group is not None else EdgeGroup(etype, params)

    def add_edge(self, edge: BaseEdge) -> None:
        """Add one edge object (g2o's ``addEdge``).

        Args:
            edge: The edge with its vertices, measurement and (optionally) information/kernel.
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
        uid = self._add_edges(group, np.array([ids]), edge._measurement[None], info[None],
                              edge._robust_kernel, data, single=True, levels=edge._level)
        edge._group, edge._uid, edge._graph = group, uid, self
        self._edge_objects.append(edge)

    def add_edges(self, etype: type[BaseEdge], vertex_ids: Any, measurements: Any,
                  information: Any = None, robust_kernel: RobustKernel | None = None,
                  params: Any = None, data: dict[str, Any] | None = None
                  ) -> tuple[EdgeGroup, int, int]:
        """Add many edges of one type (see :meth:`SparseOptimizer.add_edges`).

        Args:
            etype: The edge class.
            vertex_ids: ``(m, k)`` vertex ids.
            measurements: ``(m, *measurement_shape)``.
            information: ``None``, ``(e, e)`` or ``(m, e, e)``.
            robust_kernel: One kernel for these edges, or ``None``.
            params: Shared parameters.
            data: Per-edge auxiliary arrays.

        Returns:
            ``(group, uid of the first edge, number of edges)``.
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
        start = self._add_edges(group, vids.astype(np.int64), meas, info, robust_kernel, arrays)
        return group, start, m

    def _add_edges(self, group: EdgeGroup, vids: np.ndarray, meas: np.ndarray, info: np.ndarray,
                   kernel: RobustKernel | None, data: dict[str, np.ndarray],
                   single: bool = False, levels: int = 0) -> int:
        """Validate and append; the group is registered only once something was added.

        Returns:
            The uid of the first edge appended.
        """
        et = group.etype
        m, e = len(vids), et.dimension
        mshape = group.mshape
        if meas.shape != (m, *mshape):
            what = f"on vertices {vids[0].tolist()}" if single else ""
            got = meas.shape[1:] if single else meas.shape
            want = mshape if single else (m, *mshape)
            raise GraphError(f"{et.__name__} {what}: measurement has shape {got}, expected {want}"
                             .replace("  ", " "))
        if m == 0:
            return group.next_uid  # nothing to add (and no empty group to register)
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

        def bad_info(ok: np.ndarray, what: str) -> GraphError:
            # Name the first edge whose own matrix fails (or say the one matrix is shared).
            who = (f"on vertices {vids[int(np.flatnonzero(~ok)[0])].tolist()}"
                   if len(infos) == m and m else f"(one matrix for all {m} edges)")
            return GraphError(f"{et.__name__} {who}: {what}")

        finite = np.isfinite(infos).all(axis=(1, 2))
        if not finite.all():
            raise bad_info(finite, "non-finite information matrix")
        sym = np.isclose(infos, np.swapaxes(infos, 1, 2), rtol=1e-9, atol=1e-12).all(axis=(1, 2))
        if not sym.all():
            raise bad_info(sym, "information matrix is not symmetric")
        def psd(mats: np.ndarray) -> np.ndarray:
            low = np.linalg.eigvalsh(mats)
            return low[:, 0] >= -1e-9 * np.maximum(np.abs(low[:, -1]), 1.0)

        # Distinct matrices only (most files share a few, often one: a comparison is 30x
        # cheaper than np.unique over rows); per edge only to name a failure. One matrix
        # repeated for every edge (every edge of w10000 and Victoria Park) is stored once: the
        # weighting is then a broadcast, not m products.
        if len(infos) > 1 and bool((infos == infos[0]).all()):
            distinct = infos[:1]
            info = infos[0].copy()
        else:
            distinct = infos if len(infos) <= 1 else np.unique(infos, axis=0)
        if not psd(distinct).all():
            raise bad_info(psd(infos), "information matrix is not positive semi-definite")
        for pos, vt in enumerate(et.vertex_types):
            # Check each distinct id once; report the first edge that names a bad one.
            col = vids[:, pos]
            distinct = np.unique(col).tolist()
            bad_ids = [v for v in distinct
                       if v not in self.ids or not issubclass(self.ids[v][0].vtype, vt)]
            if bad_ids:
                i = int(np.flatnonzero(np.isin(col, bad_ids))[0])
                self._check_vertex(et, vids[i], pos, int(col[i]), vt)
        kslot = group.kernel_slot(kernel)
        start = group.append(vids, meas, info, kslot, data, levels)
        if self.groups.setdefault((et, id(group.params)), group) is group:
            group.level = self.level
        return start

    def _check_vertex(self, et: type[BaseEdge], ids: np.ndarray, pos: int, vid: int,
                      vt: type[BaseVertex]) -> None:
        if vid not in self.ids:
            raise GraphError(f"{et.__name__} on vertices {ids.tolist()}: vertex {vid} "
                             f"(position {pos}) does not exist")
        st = self.ids[vid][0]
        if not issubclass(st.vtype, vt):
            raise GraphError(f"{et.__name__} on vertices {ids.tolist()}: vertex {vid} is a "
                             f"{st.vtype.__name__}, position {pos} needs a {vt.__name__}")

    def flush(self) -> None:
        """Move objects added one at a time into the arrays (nothing to do yet)."""

    def edge_chi2(self, g: EdgeGroup) -> np.ndarray:
        """``(m,)`` ``eᵀΩe`` of every edge of a group (see :func:`~graphopt.edge_set.group_errors`).

        Args:
            g: The group.
        """
        return group_errors(self, g)[1]

    def edges(self) -> list[BaseEdge]:
        """The edges added one at a time (bulk edges live only as arrays)."""
        return list(self._edge_objects)

    # --- structure ---------------------------------------------------------------------------

    def structure_key(self) -> tuple[Any, ...]:
        """Changes whenever vertices, edges or fixed/marginalised flags change (not levels,
        kernels or estimates)."""
        return (tuple((id(s), len(s), s.flags_version, s.removals) for s in self.stores.values()),
                tuple((id(g), g.size, g.removals) for g in self.groups.values()))

    def set_level(self, level: int) -> None:
        """Make the edges of ``level`` the active ones (g2o's ``initializeOptimization(level)``).

        Args:
            level: A non-negative integer.
        """
        self.level = check_level(level)
        for g in self.groups.values():
            g.apply_level(self.level)

    # --- removing ----------------------------------------------------------------------------

    def remove_edges(self, group: EdgeGroup, index: np.ndarray) -> None:
        """Remove edges of a group (an emptied group leaves the graph).

        Args:
            group: The group.
            index: ``(r,)`` edge indices in the group.
        """
        if not len(index):
            return
        gone = group.uids[index]
        objs = [e for e in self._edge_objects if e._group is group]
        if objs:  # edge objects among them become free objects again (re-addable)
            hit = np.isin(np.array([e._uid for e in objs]), gone)
            for e, h in zip(objs, hit.tolist(), strict=True):
                if h:
                    e._detach()
            self._edge_objects = [e for e in self._edge_objects if e._group is not None]
        group.remove(index)
        if group.size == 0:
            self.groups.pop((group.etype, id(group.params)), None)

    def remove_vertices(self, ids: Any) -> None:
        """Remove vertices that no edge uses any more.

        Args:
            ids: Vertex ids.

        Raises:
            GraphError: an unknown id, or edges still using some of them (naming them).
        """
        arr = np.atleast_1d(np.asarray(ids))
        if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
            raise GraphError(f"remove_vertices: ids must be integers, got {ids!r}")
        wanted = np.unique(arr.astype(np.int64))
        unknown = [v for v in wanted.tolist() if v not in self.ids]
        if unknown:
            raise GraphError(f"remove_vertices: no vertex with id {unknown[:10]}")
        for g in self.groups.values():
            g.finalize()
            used = np.isin(g.vertex_ids, wanted).any(axis=1)
            if used.any():
                busy = np.intersect1d(g.vertex_ids[used], wanted)
                raise GraphError(
                    f"remove_vertices: vertices {busy[:10].tolist()} are still used by "
                    f"{int(used.sum())} {g.etype.__name__} edges (first on vertices "
                    f"{g.vertex_ids[int(np.flatnonzero(used)[0])].tolist()}); remove those first")
        by_store: dict[int, tuple[VertexStore, list[int]]] = {}
        for vid in wanted.tolist():
            st, slot = self.ids.pop(vid)
            by_store.setdefault(id(st), (st, []))[1].append(slot)
            v = self._objects.pop(vid, None)
            if v is not None:
                v._detach()
        for st, slots in by_store.values():
            new = st.remove(np.array(slots))
            if len(st) == 0:
                del self.stores[st.vtype]
            for vid, slot in zip(st.ids.tolist(), range(len(st)), strict=True):
                self.ids[vid] = (st, slot)
                v = self._objects.get(vid)
                if v is not None:
                    v._slot = slot
            del new

    # --- structure ---------------------------------------------------------------------------

    def _lookup(self, st: VertexStore) -> tuple[np.ndarray, np.ndarray]:
        """A store's ids sorted, and the slots in that order (cached per store content)."""
        key = (len(st), st.removals)
        hit = self._lookups.get(id(st))
        if hit is None or hit[0] != key or hit[1] is not st:
            order = np.argsort(st.ids)
            hit = (key, st, st.ids[order], order)
            self._lookups[id(st)] = hit
        return hit[2], hit[3]

    def group_slots(self, g: EdgeGroup, rows: slice | np.ndarray = slice(None)
                    ) -> list[tuple[VertexStore, np.ndarray]]:
        """Per vertex position of some edges of a group, their store and slots.

        Args:
            g: A finalised group.
            rows: The edges (indices or a slice; at least one).

        Raises:
            GraphError: a position of an edge type that mixes vertex types.
        """
        out = []
        vids = g.vertex_ids[rows]
        for a in range(g.k):
            col = vids[:, a]
            first = self.ids[int(col[0])][0]
            sids, order = self._lookup(first)
            loc = np.searchsorted(sids, col).clip(0, max(len(sids) - 1, 0))
            ok = sids[loc] == col
            if not ok.all():
                bad = int(col[np.flatnonzero(~ok)[0]])
                other = self.ids[bad][0].vtype.__name__
                raise GraphError(
                    f"{g.etype.__name__}: position {a} mixes vertex types "
                    f"({first.vtype.__name__} and {other}, vertex {bad}); use one type per "
                    "position within an edge type"
                )
            out.append((first, order[loc]))
        return out

    def resolve(self) -> tuple[list[VertexStore], list[EdgeGroup], Positions]:
        """Finalise the groups and map every edge's vertex ids to store slots.

        Returns:
            ``(stores, groups, positions)``: the stores and groups in a fixed order, and per
            group, per vertex position, ``(store index, slots (m,))``.

        Raises:
            GraphError: a position of an edge type that mixes vertex types.
        """
        stores = list(self.stores.values())
        index = {id(s): i for i, s in enumerate(stores)}
        positions: Positions = []
        groups = list(self.groups.values())
        for g in groups:
            g.finalize()
            pos = []
            for st, slots in self.group_slots(g):
                # int32 where it fits: 4 bytes per edge and position fewer
                pos.append((index[id(st)], slots.astype(np.int32) if len(st) < 2**31 else slots))
            positions.append(pos)
        return stores, groups, positions

