"""The graph: vertices and edges by id, checked on the way in, stored as arrays.

:class:`Graph` owns the stores (one per vertex type) and groups (one per edge type and parameter
object) of :mod:`graphopt.storage`, the id → (store, slot) map and the buffers of objects added
one at a time (taken into the arrays in bulk by :meth:`Graph.flush`, see
:mod:`graphopt.object_batch`). Every input is validated here, once, with messages that name the
type and the ids; :meth:`Graph.resolve` then turns the edges' vertex ids into store slots for
the numeric layers.
"""

from __future__ import annotations

import gc
from typing import Any

import numpy as np

from graphopt.edge import BaseEdge
from graphopt.edge_object import check_level
from graphopt.edge_set import group_depth_positive, group_errors
from graphopt.errors import GraphError
from graphopt.linear.indexing import IdLookup
from graphopt.object_batch import BatchError, checked_information, edge_batch, vertex_batch
from graphopt.robust_kernel import RobustKernel
from graphopt.storage import EdgeGroup, VertexStore
from graphopt.vertex import BaseVertex

#: Per edge group, per vertex position: ``(store index, slots (m,))``.
Positions = list[list[tuple[int, np.ndarray]]]


def _flags(vtype: type[BaseVertex], name: str, value: Any, n: int) -> np.ndarray:
    """``(n,)`` flags from one flag or ``n`` of them, else a :class:`GraphError`."""
    if type(value) is bool:  # one flag (the usual call): no broadcast
        return np.full(n, value)
    arr = np.asarray(value, dtype=bool)
    if arr.shape not in ((), (n,)):
        raise GraphError(f"{vtype.__name__}: {name} must be one flag or {n} of them, got shape "
                         f"{arr.shape}")
    return arr.copy() if arr.ndim else np.full(n, bool(arr))  # (broadcast_to: 3 µs)


class Graph:
    """Vertices and edges of one optimisation problem.

    The g2o-style facade (:class:`~graphopt.optimizer.SparseOptimizer`) forwards its
    ``add_*`` calls here. Objects added one at a time wait in buffers (``add_vertex`` and
    ``add_edge`` cost a few microseconds) until :meth:`flush` takes them into the arrays in
    bulk; ``stores``, ``groups`` and ``ids`` flush first, so every reader sees them.
    """

    def __init__(self) -> None:
        self._stores: dict[type[BaseVertex], VertexStore] = {}
        self._groups: dict[tuple[type[BaseEdge], int], EdgeGroup] = {}
        self._ids: dict[int, tuple[VertexStore, int]] = {}
        self._objects: dict[int, BaseVertex] = {}
        self._edge_objects: list[BaseEdge] = []
        # Buffered objects: vertices by id (and by type), edges by group key.
        self._vbuf: dict[int, BaseVertex] = {}
        self._ebuf: dict[tuple[type[BaseEdge], int], tuple[EdgeGroup, list[BaseEdge]]] = {}
        #: The initialised level: the edges of this level are active.
        self.level = 0
        #: Incremented by every removal of edges or vertices (indices into the arrays move).
        self.removals = 0
        self._lookups: dict[int, tuple[Any, ...]] = {}
        self._evals: dict[int, tuple[Any, ...]] = {}  # per group: errors at a state

    @property
    def stores(self) -> dict[type[BaseVertex], VertexStore]:
        """The vertex stores by type (buffered objects included)."""
        if self._vbuf or self._ebuf:
            self.flush()
        return self._stores

    @property
    def groups(self) -> dict[tuple[type[BaseEdge], int], EdgeGroup]:
        """The edge groups by ``(type, id(params))`` (buffered objects included)."""
        if self._vbuf or self._ebuf:
            self.flush()
        return self._groups

    @property
    def ids(self) -> dict[int, tuple[VertexStore, int]]:
        """Vertex id → ``(store, slot)`` (buffered objects included)."""
        if self._vbuf or self._ebuf:
            self.flush()
        return self._ids

    # --- vertices ----------------------------------------------------------------------------

    def _store(self, vtype: type[BaseVertex]) -> VertexStore:
        store = self._stores.get(vtype)
        if store is not None:
            return store
        if not (isinstance(vtype, type) and issubclass(vtype, BaseVertex)):
            raise GraphError(f"not a vertex type: {vtype!r}")
        if vtype.dimension <= 0:
            raise GraphError(f"{vtype.__name__}: dimension must be a positive integer")
        store = self._stores[vtype] = VertexStore(vtype)
        return store

    def add_vertex(self, vertex: BaseVertex) -> None:
        """Add one vertex object (g2o's ``addVertex``); its estimate is checked when the
        buffered objects are taken into the arrays (:meth:`flush`).

        Args:
            vertex: The vertex, with id and estimate set.

        Raises:
            GraphError: duplicate id, no estimate (at once); a malformed or invalid estimate
                (at the flush, naming the vertex).
        """
        vid = vertex._id
        if vertex._slot != -1:
            raise GraphError(f"vertex {vid} ({type(vertex).__name__}) is already added")
        if vid is None:
            raise GraphError(f"{type(vertex).__name__} has no id; call set_id() first")
        if vertex._estimate is None:
            raise GraphError(f"vertex {vid} ({type(vertex).__name__}) has no estimate")
        if vid in self._ids or vid in self._vbuf:
            raise GraphError(f"duplicate vertex id {vid} ({type(vertex).__name__})")
        self._store(type(vertex))
        self._vbuf[vid] = vertex
        vertex._slot = -2

    def add_vertices(self, vtype: type[BaseVertex], ids: Any, estimates: Any, fixed: Any = False,
                     marginalized: Any = False, new_ids: bool = False) -> None:
        """Add many vertices of one type (see :meth:`SparseOptimizer.add_vertices`).

        Args:
            vtype: The vertex class.
            ids: ``(n,)`` unique integer ids.
            estimates: ``(n, *estimate_shape)``.
            fixed: One flag for all or ``(n,)`` flags.
            marginalized: One flag for all or ``(n,)`` flags.
            new_ids: The caller vouches for the ids being distinct and new (graphopt.g2o's,
                into a new graph): not checked (the estimates are).
        """
        self.flush()
        ids_arr = np.asarray(ids)
        if ids_arr.ndim != 1 or ids_arr.dtype.kind not in "iu":  # (issubdtype: 2 µs)
            raise GraphError(f"{vtype.__name__}: ids must be a 1-D integer array")
        self._add(vtype, ids_arr.astype(np.int64), estimates, fixed, marginalized, new_ids=new_ids)

    def _add(self, vtype: type[BaseVertex], ids: np.ndarray, estimates: Any, fixed: Any,
             marg: Any, checked: bool = False, new_ids: bool = False) -> int:
        """Validate (unless ``checked``; ids not with ``new_ids``); returns the first slot."""
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
        if n > 1 and not new_ids:  # (a sort: not for the one pose of a motion-only BA)
            uniq, counts = np.unique(ids, return_counts=True)
            if np.any(counts > 1):
                raise GraphError(f"duplicate vertex id {int(uniq[counts > 1][0])} "
                                 f"({vtype.__name__})")
        if not checked:
            dup = None if new_ids else next((v for v in ids.tolist() if v in self._ids), None)
            if dup is not None:
                raise GraphError(f"duplicate vertex id {dup} ({vtype.__name__})")
            store.check_estimates(est, ids)
        fixed_arr, marg_arr = (_flags(vtype, name, v, n) for name, v in (("fixed", fixed),
                                                                          ("marginalized", marg)))
        start = store.append(ids, est, fixed_arr, marg_arr)
        self._ids.update(zip(ids.tolist(), ((store, s) for s in range(start, start + n)),
                             strict=True))
        return start

    def vertex(self, vid: int) -> BaseVertex | None:
        """The vertex object with this id (created on demand for bulk vertices), or ``None``.

        Args:
            vid: The id.
        """
        vid = int(vid)
        v = self._objects.get(vid)
        if v is not None:
            return v
        if vid in self._vbuf:
            return self._vbuf[vid]
        if vid not in self._ids:
            return None
        store, slot = self._ids[vid]
        v = store.vtype._bound(store, slot, vid)
        self._objects[vid] = v
        return v

    # --- edges -------------------------------------------------------------------------------

    def _group(self, etype: type[BaseEdge], params: Any) -> EdgeGroup:
        """The group of ``(etype, params)``, new (not yet registered) if there is none."""
        group = self._groups.get((etype, id(params)))
        if group is not None:
            return group
        if not (isinstance(etype, type) and issubclass(etype, BaseEdge)):
            raise GraphError(f"not an edge type: {etype!r}")
        if etype.dimension <= 0 or not etype.vertex_types:
            raise GraphError(f"{etype.__name__}: set dimension and vertex_types")
        return EdgeGroup(etype, params)

    def add_edge(self, edge: BaseEdge) -> None:
        """Add one edge object (g2o's ``addEdge``); its values are checked when the buffered
        objects are taken into the arrays (:meth:`flush`).

        Args:
            edge: The edge with its vertices, measurement and (optionally) information/kernel.

        Raises:
            GraphError: a vertex or the measurement not set (at once); a missing vertex or
                malformed values (at the flush, naming the edge's vertices).
        """
        if edge._group is not None:
            raise GraphError(f"{edge!r} is already added")
        if None in edge._vertices:
            i = edge._vertices.index(None)
            raise GraphError(f"{type(edge).__name__}: vertex {i} is not set")
        if edge._measurement is None:
            raise GraphError(f"{edge!r}: no measurement set")
        key = (type(edge), id(edge.params))
        buf = self._ebuf.get(key)
        if buf is None:
            buf = self._ebuf[key] = (self._group(type(edge), edge.params), [])
        buf[1].append(edge)
        edge._group, edge._uid, edge._graph = buf[0], -2, self
        self._edge_objects.append(edge)

    def add_edges(self, etype: type[BaseEdge], vertex_ids: Any, measurements: Any,
                  information: Any = None, robust_kernel: RobustKernel | None = None,
                  params: Any = None, data: dict[str, Any] | None = None,
                  vertex_stores: list[VertexStore] | None = None
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
            vertex_stores: The caller vouches for every vertex at position ``p`` being in
                ``vertex_stores[p]`` (graphopt.g2o's banks): the stores' types are checked.

        Returns:
            ``(group, uid of the first edge, number of edges)``.
        """
        self.flush()
        group = self._group(etype, params)
        vids = np.asarray(vertex_ids)
        k = len(etype.vertex_types)
        if vids.ndim != 2 or vids.shape[1] != k or vids.dtype.kind not in "iu":
            raise GraphError(
                f"{etype.__name__}: vertex_ids must be an integer array of shape (m, {k}), "
                f"got {vids.shape}"
            )
        m = len(vids)
        e = etype.dimension
        if information is None:
            info = np.eye(e)
        else:
            try:
                info = np.asarray(information, dtype=float)
            except (TypeError, ValueError) as exc:
                raise GraphError(f"{etype.__name__}: information is not numeric: {exc}") from None
            if info.shape not in ((e, e), (m, e, e)):
                raise GraphError(
                    f"{etype.__name__}: information has shape {info.shape}, expected {(e, e)} "
                    f"or {(m, e, e)}"
                )
        try:
            meas = np.asarray(measurements, dtype=float)
        except (TypeError, ValueError) as exc:
            raise GraphError(f"{etype.__name__}: measurements are not numeric: {exc}") from None
        if meas.shape != (m, *group.mshape):
            raise GraphError(f"{etype.__name__}: measurement has shape {meas.shape}, expected "
                             f"{(m, *group.mshape)}")
        arrays = {}
        for key, val in (data or {}).items():
            arr = np.asarray(val)
            if arr.shape[:1] != (m,):
                raise GraphError(f"{etype.__name__}: data[{key!r}] must have first dimension {m}")
            arrays[key] = arr
        kslot = group.kernel_slot(robust_kernel)
        known = vertex_stores is not None and len(vertex_stores) == k and all(
            self._stores.get(st.vtype) is st and issubclass(st.vtype, vt)
            for st, vt in zip(vertex_stores, etype.vertex_types, strict=True))
        start = self._add_edges(group, vids.astype(np.int64), meas, info, kslot, arrays,
                                known_vertices=known)
        return group, start, m

    def _add_edges(self, group: EdgeGroup, vids: np.ndarray, meas: np.ndarray, info: np.ndarray,
                   kslot: int | np.ndarray, data: dict[str, np.ndarray],
                   levels: int | np.ndarray = 0, known_vertices: bool = False) -> int:
        """Validate (the vertex ids not with ``known_vertices``) and append; the group is
        registered only once something was added.

        Raises:
            BatchError: a check failed for one edge (its index as ``culprit``); a
                ``GraphError`` when it failed for a matrix shared by all.

        Returns:
            The uid of the first edge appended.
        """
        et = group.etype
        m = len(vids)
        if m == 0:
            return group.next_uid  # nothing to add (and no empty group to register)

        def blame(i: int, what: str) -> BatchError:
            return BatchError(f"{et.__name__} on vertices {vids[i].tolist()}: {what}", i)

        if not np.isfinite(meas).all():  # per edge only to name one
            bad = ~np.isfinite(meas.reshape(m, -1)).all(axis=1)
            raise blame(int(np.flatnonzero(bad)[0]), "non-finite measurement")
        info = checked_information(et, vids, info)
        for pos, vt in enumerate(() if known_vertices else et.vertex_types):
            # Check each distinct id once; report the first edge that names a bad one.
            col = vids[:, pos]
            first = col[0]  # one vertex at this position (a pose's unary edges): no sort
            # A few edges (an online step's): a set of ints beats np.unique's sort.
            distinct = ([int(first)] if (col == first).all() else set(col.tolist()) if m <= 64
                        else np.unique(col).tolist())
            bad_ids = [v for v in distinct
                       if v not in self._ids or not issubclass(self._ids[v][0].vtype, vt)]
            if bad_ids:
                i = int(np.flatnonzero(np.isin(col, bad_ids))[0])
                vid = int(col[i])
                if vid not in self._ids:
                    raise blame(i, f"vertex {vid} (position {pos}) does not exist")
                raise blame(i, f"vertex {vid} is a {self._ids[vid][0].vtype.__name__}, position "
                               f"{pos} needs a {vt.__name__}")
        start = group.append(vids, meas, info, kslot, data, levels)
        if self._groups.setdefault((et, id(group.params)), group) is group:
            group.level = self.level
        return start

    # --- buffered objects --------------------------------------------------------------------

    def flush(self) -> None:
        """Take the buffered vertex and edge objects into the arrays, one batch per type
        (edge group), with the checks of ``add_vertices``/``add_edges``.

        Raises:
            GraphError: naming the first invalid object, which leaves the buffer (it is not
                added; fix it and add it again). The others stay buffered.
        """
        if not (self._vbuf or self._ebuf):
            return
        # The batches allocate a container or two per object and free them at once: the
        # cyclic collector, which such allocations trigger, would scan every live object
        # each time (2-3x the flush's own time on 25,000 edges); nothing here makes cycles.
        enabled = gc.isenabled()
        gc.disable()
        try:
            self._flush()
        finally:
            if enabled:
                gc.enable()

    def _flush(self) -> None:
        if self._vbuf:
            by_type: dict[type[BaseVertex], list[BaseVertex]] = {}
            for v in self._vbuf.values():
                by_type.setdefault(type(v), []).append(v)
            for vtype, objs in by_type.items():
                try:
                    batch = vertex_batch(vtype, objs)
                except BatchError as exc:
                    self._vbuf.pop(exc.culprit._id)
                    exc.culprit._slot = -1
                    raise
                start = self._add(vtype, *batch, checked=True)
                store = self._stores[vtype]
                for slot, v in enumerate(objs, start):
                    v._store, v._slot, v._estimate = store, slot, None
                self._objects.update(zip(batch[0].tolist(), objs, strict=True))
                self._vbuf = {k: v for k, v in self._vbuf.items() if v._slot == -2}
        while self._ebuf:
            key, (group, objs) = next(iter(self._ebuf.items()))
            try:
                b = edge_batch(group, objs)
                start = self._add_edges(group, b["vids"], b["meas"], b["info"], b["kernel"],
                                        b["data"], b["levels"])
            except BatchError as exc:
                bad = exc.culprit if isinstance(exc.culprit, BaseEdge) else objs[exc.culprit]
                objs.remove(bad)
                if not objs:
                    del self._ebuf[key]
                bad._detach()
                self._edge_objects.remove(bad)
                raise BatchError(str(exc), bad) from None
            del self._ebuf[key]
            for uid, o in enumerate(objs, start):
                o._uid = uid

    def edge_chi2(self, g: EdgeGroup) -> np.ndarray:
        """``(m,)`` ``eᵀΩe`` of every edge of a group (see :func:`~graphopt.edge_set.group_errors`).

        Args:
            g: The group.
        """
        return group_errors(self, g)[1]

    def edge_depth_positive(self, g: EdgeGroup) -> np.ndarray:
        """``(m,)`` the depth test of every edge of a group (see
        :func:`~graphopt.edge_set.group_depth_positive`).

        Args:
            g: The group.
        """
        return group_depth_positive(self, g)

    def edges(self) -> list[BaseEdge]:
        """The edges added one at a time (bulk edges live only as arrays)."""
        return list(self._edge_objects)

    # --- structure ---------------------------------------------------------------------------

    def structure_key(self) -> tuple[Any, ...]:
        """Changes whenever vertices, edges or fixed/marginalised flags change (not levels,
        kernels or estimates)."""
        st, gs = self.stores.values(), self.groups.values()
        return (tuple([(id(s), len(s), s.flags_version, s.removals) for s in st]),
                tuple([(id(g), g.size, g.removals) for g in gs]))

    def set_level(self, level: int) -> None:
        """Make the edges of ``level`` the active ones (g2o's ``initializeOptimization(level)``).

        Args:
            level: A non-negative integer.
        """
        self.level = check_level(level)
        for g in self.groups.values():
            g.apply_level(self.level)

    def _lookup(self, st: VertexStore) -> IdLookup:
        """A store's id → slot lookup (cached per store content)."""
        key, hit = (len(st), st.removals), self._lookups.get(id(st))
        if hit is None or hit[0] != key or hit[1] is not st:
            hit = self._lookups[id(st)] = (key, st, IdLookup(st.ids))
        return hit[2]

    def group_slots(self, g: EdgeGroup, rows: slice | np.ndarray = slice(None)
                    ) -> list[tuple[VertexStore, np.ndarray]]:
        """Per vertex position of some edges of a group, their store and slots.

        Args:
            g: A finalised group.
            rows: The edges (indices or a slice; at least one).

        Raises:
            GraphError: a position of an edge type that mixes vertex types.
        """
        out, vids, ids = [], g.vertex_ids[rows], self.ids
        for a in range(g.k):
            col = vids[:, a]
            first = ids[int(col[0])][0]
            slots, ok = self._lookup(first)(col)
            if not ok.all():
                bad = int(col[np.flatnonzero(~ok)[0]])
                raise GraphError(
                    f"{g.etype.__name__}: position {a} mixes vertex types "
                    f"({first.vtype.__name__} and {ids[bad][0].vtype.__name__}, vertex {bad}); "
                    "use one type per position within an edge type"
                )
            out.append((first, slots))
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

