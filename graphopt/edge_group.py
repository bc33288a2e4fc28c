"""``EdgeGroup``: all edges of one type and parameter object, as arrays (struct of arrays).

Filled by chunks (one per ``add_edges`` call or object), concatenated lazily by
:meth:`EdgeGroup.finalize`. A group made of one bulk chunk keeps the arrays it was given (no
copy: do not modify them afterwards); one robust kernel slot or level for all edges is one
broadcast value, not a per-edge array. Levels, kernels and removals are edited here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.chunks import const_ints, join_chunks, join_values, per_edge
from graphopt.edge import BaseEdge, EdgeContext
from graphopt.errors import GraphError
from graphopt.robust_kernel import RobustKernel, kernel_changes, kernel_key


class EdgeGroup:
    """All edges of one type sharing one parameter object, as arrays.

    Every edge gets a *uid*, its serial number in the group: uids only grow, so ``uids`` is
    sorted and an edge's index is found by a search even after others were removed (an
    :class:`~graphopt.edge_set.EdgeSet` holds uids, not indices). Every edge has a *level*
    (g2o's ``setLevel``); the edges whose level is the initialised one are active
    (``active_edges``, ``None`` when all are).

    Args:
        etype: The edge class.
        params: The shared parameter object (see :class:`~graphopt.edge.EdgeContext`).
    """

    def __init__(self, etype: type[BaseEdge], params: Any) -> None:
        self.etype = etype
        self.params = params
        self.k = len(etype.vertex_types)
        self.mshape = tuple(etype.get_measurement_shape())
        e = etype.dimension
        self._vids: list[np.ndarray] = []
        self._meas: list[np.ndarray] = []
        self._info: list[np.ndarray] = []  # per chunk: (e, e) shared or (n, e, e)
        self._kern: list[np.ndarray] = []
        self._lvl: list[np.ndarray] = []
        self._data: list[dict[str, np.ndarray]] = []
        self._kernels: list[RobustKernel] = []  # see the kernels property
        self._kernel_keys: dict[Any, int] = {}
        # Per slot, every kernel object merged into it by value (the first is ``_kernels``'s),
        # and the kernel-width count they were last seen equal at (see _check_members).
        self._members: list[dict[int, RobustKernel]] = []
        self._members_checked = kernel_changes()
        self.size = 0
        self.dim = e
        self.next_uid = 0
        #: Incremented whenever edges are removed (indices move; the structure is stale).
        self.removals = 0
        # Filled by finalize():
        self.vertex_ids = np.zeros((0, self.k), dtype=np.int64)
        self.slots = np.zeros((0, self.k), dtype=np.int64)
        self.measurements = np.zeros((0, *self.mshape))
        self.information: np.ndarray | None = None  # (e, e) shared, or (m, e, e)
        self.info_is_identity = True
        # Diagonal information: (e,) of the shared matrix, or (m, e) of per-edge matrices.
        self.info_diagonal: np.ndarray | None = None
        self._kidx = np.zeros(0, dtype=np.int64)  # see the kernel_index property
        self.levels = np.zeros(0, dtype=np.int64)
        self.uids = np.zeros(0, dtype=np.int64)
        self.data: dict[str, np.ndarray] = {}
        self.measured: np.ndarray | None = None  # the type's measurement_derived values
        self.last_chi2 = np.zeros(0)
        self.active_count = 0
        #: The errors of every edge at the last evaluation, whatever its level: ``((versions
        #: of the stores of the vertex positions, next_uid, removals), errors (m, dimension))``
        #: — what :func:`~graphopt.edge_set.group_errors` reuses at the same estimates.
        self.raw_eval: tuple[tuple[tuple[int, ...], int, int], np.ndarray,
                             np.ndarray | None] | None = None
        #: The initialised level, the ``(m,)`` mask of the edges at that level (``None``: all
        #: are), and a counter of its changes.
        self.level = 0
        self._active: np.ndarray | None = None
        self._activity_stale = False  # the mask is recomputed when next read
        self._kernels_stale = False  # unused kernels are dropped when next read
        #: Counts the changes of levels, of the initialised level and of which kernel each
        #: edge has (see :attr:`activity_version`).
        self.activity_count = 0
        self._finalized_size = -1

    # --- adding ----------------------------------------------------------------------------

    def kernel_slot(self, kernel: RobustKernel | None) -> int:
        """Index of ``kernel`` in this group's kernel list (-1 for none).

        Kernels equal in type and parameters share a slot (one ``robustify`` call per distinct
        kernel and iteration, however many kernel objects the edges were given).

        Args:
            kernel: A kernel or ``None``.
        """
        if kernel is None:
            return -1
        if not isinstance(kernel, RobustKernel):
            raise GraphError(
                f"{self.etype.__name__}: robust_kernel must be a RobustKernel, got {kernel!r}"
            )
        key = kernel_key(kernel)
        for members in self._members:  # (re)assigned here: forget where it was merged before
            members.pop(id(kernel), None)
        slot = self._kernel_keys.get(key)
        if slot is None or kernel_key(self._kernels[slot]) != key:
            slot = next((i for i, k in enumerate(self._kernels)  # one changed since it was added
                         if kernel_key(k) == key), None)
        if slot is None:
            self._kernels.append(kernel)
            self._members.append({})
            slot = len(self._kernels) - 1
        self._kernel_keys[key] = slot
        self._members[slot][id(kernel)] = kernel
        return slot

    def add_kernel_members(self, slot: int, kernels: list[RobustKernel]) -> None:
        """Record more kernel objects given to edges of ``slot`` (equal to its kernel: a batch
        of edge objects filed by value passes one per value to :meth:`kernel_slot`).

        Args:
            slot: A slot from :meth:`kernel_slot`.
            kernels: The other objects of that value.
        """
        self._members[slot].update((id(k), k) for k in kernels)

    def _check_members(self) -> None:
        """Raise if kernel objects merged by value differ now (a ``set_delta`` on one of them
        after the edges were added): their edges would silently share one width."""
        changes = kernel_changes()
        if changes == self._members_checked:
            return
        for slot, members in enumerate(self._members):
            keys = {kernel_key(k) for k in members.values()}
            if len(keys) > 1:
                raise GraphError(
                    f"{self.etype.__name__}: {len(members)} robust kernel objects were equal "
                    f"when their edges were added and now differ ({self._kernels[slot]!r} and "
                    f"others): equal kernels are merged, so a width set afterwards "
                    f"(set_delta) would reach edges it was not given; set the changed kernel "
                    f"on its edges again (set_robust_kernel) after changing it")
        self._kernel_keys = {kernel_key(k): i for i, k in enumerate(self._kernels)}
        self._members_checked = changes

    def append(self, vids: np.ndarray, meas: np.ndarray, info: np.ndarray,
               kernel: int | np.ndarray, data: dict[str, np.ndarray],
               levels: int | np.ndarray = 0) -> int:
        """Append validated edges; returns the uid of the first one (the others follow).

        Args:
            vids: ``(n, k)`` vertex ids.
            meas: ``(n, *measurement_shape)``.
            info: ``(e, e)`` shared or ``(n, e, e)``.
            kernel: Kernel slot for all, or per edge.
            data: Per-edge arrays.
            levels: One level for all, or ``(n,)`` levels.
        """
        n = len(vids)
        start = self.next_uid
        if self._data and set(data) != set(self._data[0]):
            raise GraphError(
                f"{self.etype.__name__}: every add_edges call of a group must give the same data "
                f"keys ({sorted(self._data[0])}), got {sorted(data)}"
            )
        self._vids.append(vids)
        self._meas.append(meas)
        self._info.append(info)
        # One value for the chunk: a broadcast (no bytes per edge) until it is set per edge.
        self._kern.append(per_edge(kernel, n))
        self._lvl.append(per_edge(levels, n))
        self._data.append(data)
        self.size += n
        self.next_uid += n
        return start

    def tail(self, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                        dict[str, np.ndarray]]:
        """The edges ``start:size`` read from the chunks, without finalising the group (what the
        incremental optimizer takes after each update: a few edges, not a concatenation of
        all).

        Args:
            start: First edge (an index).

        Returns:
            ``(vertex ids (n, k), measurements, information (n, e, e), kernel index (n,),
            data)``.
        """
        first, at = len(self._vids), self.size
        while first > 0 and at > start:  # walk back over the newest chunks only
            first -= 1
            at -= len(self._vids[first])
        parts: list[list[np.ndarray]] = [[], [], [], []]
        data: list[dict[str, np.ndarray]] = []
        for c in range(first, len(self._vids)):
            lo = max(start - at, 0)
            at += len(self._vids[c])
            n = len(self._vids[c]) - lo
            info = self._info[c]
            parts[0].append(self._vids[c][lo:])
            parts[1].append(self._meas[c][lo:])
            parts[2].append(np.broadcast_to(info, (n, self.dim, self.dim)) if info.ndim == 2
                            else info[lo:])
            parts[3].append(self._kern[c][lo:])
            if self._data:
                data.append({k: v[lo:] for k, v in self._data[c].items()})
        if not parts[0]:
            return (np.zeros((0, self.k), np.int64), np.zeros((0, *self.mshape)),
                    np.zeros((0, self.dim, self.dim)), np.zeros(0, np.int64), {})
        joined = [join_chunks(p) for p in parts]
        merged = {k: np.concatenate([d[k] for d in data]) for k in data[0]} if data else {}
        return joined[0], joined[1], joined[2], joined[3], merged

    # --- finalising --------------------------------------------------------------------------

    def finalize(self) -> None:
        """Concatenate chunks into the group's arrays (idempotent)."""
        if self._finalized_size == self.size:
            return
        first_new = len(self.uids)
        self.vertex_ids = join_chunks(self._vids) if self._vids else self.vertex_ids
        self.measurements = join_chunks(self._meas) if self._meas else self.measurements
        if self._kern:
            self._kidx = join_values(self._kern, self.size)
        if self._lvl:
            self.levels = join_values(self._lvl, self.size)
        if self.size > first_new:  # uids of the edges appended since the last finalize
            new = np.arange(self.next_uid - self.size + first_new, self.next_uid)
            self.uids = np.concatenate([self.uids, new]) if first_new else new
        infos = self._info
        if len(infos) == 1 and infos[0].ndim == 2:  # one chunk, one matrix (the usual group)
            self.information = infos[0]
        elif len(infos) == 1 and len(infos[0]) == self.size:  # one chunk, a matrix per edge
            self.information = infos[0].copy()  # (what the concatenation below makes)
        elif len(infos) == sum(i.ndim == 2 for i in infos) and all(
                np.array_equal(infos[0], i) for i in infos):
            self.information = infos[0] if infos else np.eye(self.dim)
        else:
            self.information = np.concatenate(
                [np.broadcast_to(i, (len(v), self.dim, self.dim)) for i, v in
                 zip(infos, self._vids, strict=True)]
            )
        self.info_diagonal = None
        info = self.information
        if info.ndim == 2:
            # (Finite, checked on the way in.) Diagonal: as many nonzeros as its diagonal has.
            d = info.diagonal()
            nonzero = np.count_nonzero(info)
            if nonzero == np.count_nonzero(d):
                self.info_diagonal = d.copy()
            self.info_is_identity = nonzero == self.dim and bool((d == 1.0).all())
        else:
            self.info_is_identity = False
            if np.count_nonzero(info) == np.count_nonzero(diag := info.diagonal(0, 1, 2)):
                self.info_diagonal = np.ascontiguousarray(diag)  # σ⁻²·I per edge (a SLAM system's)
        if self._data:
            self.data = {key: join_chunks([d[key] for d in self._data]) for key in self._data[0]}
        self.measured = self.etype.measurement_derived(self.measurements) if self.size else None
        if self.measured is not None and (self.measured.ndim != 2
                                          or len(self.measured) != self.size):
            raise GraphError(f"{self.etype.__name__}.measurement_derived returned shape "
                             f"{self.measured.shape}, expected ({self.size}, k)")
        # Keep one chunk so further appends concatenate onto the consolidated arrays.
        self._vids, self._meas = [self.vertex_ids], [self.measurements]
        self._kern, self._lvl = [self._kidx], [self.levels]
        self._info = [self.information]
        self._data = [self.data] if self._data else []
        self.last_chi2 = np.zeros(self.size)
        self._finalized_size = self.size
        self.apply_level(self.level, force=True)

    def context(self) -> EdgeContext:
        """A fresh :class:`EdgeContext` over all edges of the group."""
        return EdgeContext(self.params, self.data, measured=self.measured)

    # --- addressing edges by uid ---------------------------------------------------------------

    def index_of(self, uids: np.ndarray) -> np.ndarray:
        """Current indices of edges given by uid.

        Args:
            uids: ``(r,)`` uids.

        Raises:
            GraphError: an edge was removed (naming how many).
        """
        self.finalize()
        if not self.removals:  # nothing removed: a uid is its index
            return uids
        pos = np.minimum(np.searchsorted(self.uids, uids), max(self.size - 1, 0))
        gone = (self.uids[pos] != uids) if self.size else np.ones(len(uids), dtype=bool)
        if gone.any():
            raise GraphError(f"{self.etype.__name__}: {int(gone.sum())} of these {len(uids)} "
                             "edges were removed")
        return pos

    def information_of(self, i: int) -> np.ndarray:
        """Information matrix of edge ``i``.

        Args:
            i: Edge index in the group.
        """
        self.finalize()
        assert self.information is not None
        return self.information.copy() if self.information.ndim == 2 else self.information[i].copy()

    def kernel_of(self, i: int) -> RobustKernel | None:
        """Robust kernel of edge ``i``.

        Args:
            i: Edge index in the group.
        """
        self.finalize()
        k = int(self._kidx[i])
        return None if k < 0 else self._kernels[k]

    # --- editing -----------------------------------------------------------------------------

    @property
    def kernels(self) -> list[RobustKernel]:
        """The distinct kernels of the group (those some edge uses).

        Raises:
            GraphError: kernel objects merged by value were made to differ since.
        """
        if self._kernels_stale:
            self._stale_kernels()
        if self._members_checked != kernel_changes():
            self._check_members()
        return self._kernels

    @property
    def kernel_index(self) -> np.ndarray:
        """``(m,)`` every edge's index in :attr:`kernels` (−1: none)."""
        if self._kernels_stale:
            self._stale_kernels()
        return self._kidx

    @property
    def sole_kernel(self) -> RobustKernel | None:
        """The kernel every edge has when one serves them all (a broadcast index, O(1) to
        recognise, or all zeros), else ``None``: no kernel, or edges with different ones."""
        kernels = self.kernels
        if len(kernels) != 1:
            return None
        ki = self.kernel_index
        return kernels[0] if (len(ki) and ki.strides == (0,) and ki[0] == 0) or not ki.any() \
            else None

    @property
    def activity_version(self) -> tuple[int, int]:
        """Changes whenever what weighs the edges changes — levels, the initialised level,
        which kernel each edge has, any kernel's width (``robust_kernel.kernel_changes``) —
        so that evaluations cached by it are stale."""
        return self.activity_count, kernel_changes()

    @property
    def active_edges(self) -> np.ndarray | None:
        """``(m,)`` the edges at the initialised level, ``None`` when all are."""
        if self._activity_stale:
            self._activity_stale = False
            lv = self.levels
            if lv.strides == (0,) and len(lv):  # one level for all
                act = None if int(lv[0]) == self.level else np.zeros(self.size, dtype=bool)
            else:
                act = lv == self.level
                act = None if act.all() else act
            self._active = act
        return self._active

    def set_kernel(self, i: int | slice | np.ndarray, kernel: RobustKernel | None) -> None:
        """Set the robust kernel of some edges (the structure stays; O(edges set), so one edge
        at a time is fine).

        Args:
            i: Edge index (or indices) in the group; ``slice(None)``: every edge.
            kernel: The kernel or ``None``.
        """
        self.finalize()
        slot = self.kernel_slot(kernel)
        whole = type(i) is slice and i == slice(None)
        if not self._kidx.flags.writeable:  # one broadcast slot so far
            if int(self._kidx[0]) == slot:
                return
            if not whole:
                self._kidx = self._kidx.copy()
                self._kern = [self._kidx]
        if whole:  # every edge: one broadcast slot (no bytes per edge)
            self._kidx = const_ints(slot, self.size)
            self._kern = [self._kidx]
        else:
            self._kidx[i] = slot
        self._kernels_stale = True
        self.activity_count += 1  # evaluations at the old kernels are stale

    def _stale_kernels(self) -> None:
        """Compact the kernels after an edit, with the edges appended since taken in first
        (``_kidx`` is the finalised edges' only)."""
        self.finalize()
        self._compact_kernels()

    def _compact_kernels(self) -> None:
        """Drop kernels no edge uses, so that an all-kernel-free group takes the fast path."""
        self._kernels_stale = False
        kidx = self._kidx
        one = bool(len(kidx)) and kidx.strides == (0,)  # one kernel (or none) for all: no sort
        used = kidx[:1] if one else np.unique(kidx)
        used = used[used >= 0]
        if len(used) != len(self._kernels):
            remap = np.full(len(self._kernels) + 1, -1, dtype=np.int64)
            remap[used] = np.arange(len(used))
            # (a broadcast stays one: its one value remapped)
            self._kidx = const_ints(int(remap[kidx[0]]), self.size) if one else remap[kidx]
            self._kernels = [self._kernels[int(u)] for u in used]
            self._members = [self._members[int(u)] for u in used]
            self._kernel_keys = {kernel_key(k): i for i, k in enumerate(self._kernels)}
        if not one and len(used) <= 1 and len(self._kidx):
            value = int(self._kidx[0])
            if (self._kidx == value).all():
                self._kidx = const_ints(value, self.size)
        self._kern = [self._kidx]

    def set_levels(self, i: int | slice | np.ndarray, levels: int | np.ndarray) -> None:
        """Set the level of some edges (validated by the caller); the structure stays (O(edges
        set): the active mask is recomputed when next read). Levels set to what they are change
        nothing, :attr:`activity_version` included (ORB-SLAM's outlier passes mostly repeat).

        Args:
            i: Edge indices in the group.
            levels: One level or one per edge.
        """
        self.finalize()
        if (self.levels[i] == levels).all():  # unchanged: what was evaluated at them holds
            return
        if not self.levels.flags.writeable:
            self.levels = self.levels.copy()
            self._lvl = [self.levels]
        self.levels[i] = levels
        self._activity_stale = True
        self.activity_count += 1

    def apply_level(self, level: int, force: bool = False) -> None:
        """Make the edges of ``level`` the active ones.

        Args:
            level: The initialised level.
            force: Recompute even if the level is the same (the levels changed).
        """
        if level == self.level and not force:
            return
        self.level = level
        self._activity_stale = True
        self.activity_count += 1

    def remove(self, index: np.ndarray) -> None:
        """Remove edges; the others keep their order and uids (the structure is stale).

        Args:
            index: ``(r,)`` indices of the edges to remove.
        """
        self.finalize()
        keep = np.ones(self.size, dtype=bool)
        keep[index] = False
        self.vertex_ids = self.vertex_ids[keep]
        self.measurements = self.measurements[keep]
        assert self.information is not None
        if self.information.ndim == 3:
            self.information = self.information[keep]
        self._kidx = np.ascontiguousarray(self._kidx[keep])
        self.levels = np.ascontiguousarray(self.levels[keep])
        self.uids = self.uids[keep]
        self.data = {key: v[keep] for key, v in self.data.items()}
        self.size = int(keep.sum())
        self._vids, self._meas, self._info = [self.vertex_ids], [self.measurements], [
            self.information]
        self._data = [self.data] if self._data else []
        self._compact_kernels()
        self._lvl = [self.levels]
        self.removals += 1
        self._finalized_size = -1
        self._active = None
        self.finalize()
        self.activity_count += 1
