"""Edges of one g2o class and parameters as arrays: what ``initialize_optimization`` hands to
graphopt (one ``add_edges`` call per batch, the edges of the active level) and what the edges'
own getters read (``chi2``, ``error``, ``is_depth_positive`` for every edge of the batch at once,
once per state; ``set_level`` and ``set_robust_kernel`` as one entry of an array)."""

from __future__ import annotations

import math
import weakref
from itertools import repeat
from operator import is_
from typing import Any

import numpy as np

from graphopt.edge import EdgeContext
from graphopt.edge_group import EdgeGroup
from graphopt.edge_set import group_errors
from graphopt.errors import GraphError

from .edges import BaseEdge
from .raw import joined
from .solvers import RobustKernelBase, graphopt_kernel
from .vertices import Bank

__all__ = ["Batch", "stack_information", "stack_measurements"]


def kernel_key(kernel: Any) -> Any:
    """Edges whose kernels have equal keys share one graphopt kernel."""
    if kernel is None:
        return None
    if isinstance(kernel, RobustKernelBase):
        return (type(kernel), kernel._delta)
    return ("object", id(kernel))


class Batch:
    """All edges of one g2o edge class with equal parameters.

    The batch points at its optimizer weakly and not at its records (the optimizer holds them):
    records point at their batch, so anything else would be a reference cycle.

    Args:
        owner: The g2o optimizer.
        cls: The g2o edge class.
        gtype: graphopt's edge type.
        params: graphopt's parameter object for the group.
        records: The edge records, in order (given their batch and index, not kept).
        vids: ``(m, k)`` vertex ids in graphopt's position order.
        banks: The bank of each graphopt position.
        meas: ``(m, *measurement_shape)``.
        info: ``None`` (identity), ``(e, e)`` or ``(m, e, e)``.
        data: Per-edge arrays.
    """

    def __init__(self, owner: Any, cls: type, gtype: type, params: Any, records: list[Any],
                 vids: np.ndarray, banks: list[Bank], meas: np.ndarray, info: np.ndarray | None,
                 data: dict[str, np.ndarray]) -> None:
        self._owner = weakref.ref(owner)
        self.cls, self.gtype, self.params = cls, gtype, params
        self.vids, self.banks = vids, banks
        self.meas, self.info, self.data = meas, info, data
        self.m = m = len(records)
        self.slots = []
        for p, b in enumerate(banks):  # a vertex of another type at this position
            slots, ok = b.slots_of(vids[:, p])
            self.slots.append(slots)
            bad = ~ok
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise GraphError(f"{cls.__name__} on vertices {vids[i].tolist()}: vertex "
                                 f"{int(vids[i, p])} is not a {b.gtype.__name__} like the "
                                 "other edges' vertices at its position")
        levels = [r._level for r in records]
        self.levels = (np.zeros(m, dtype=np.int64) if levels.count(0) == m  # the usual case
                       else np.array(levels, dtype=np.int64))
        self.kernels: list[Any] = []  # graphopt kernels by code
        self._codes: dict[Any, int] = {}
        # (kernel, its width, code) of code()'s last g2o kernel.
        self._last_code: tuple[Any, float, int] = (None, math.nan, -1)
        kernels = [r._kernel for r in records]
        first = kernels[0] if m else None
        if all(map(is_, kernels, repeat(first))) or (  # one object (or None) for all: one code
                isinstance(first, RobustKernelBase) and self._one_key(kernels)):
            self.kcodes = np.full(m, self.code(first), dtype=np.int64)
        else:
            self.kcodes = np.fromiter((self.code(k) for k in kernels), dtype=np.int64, count=m)
        self.group: EdgeGroup | None = None
        self.rows = np.zeros(0, np.int64)  # the edges' indices in the group
        self.kernels_dirty = self.levels_dirty = False
        self._measured: tuple[np.ndarray | None] | None = None  # see measured
        self._cache: tuple[Any, ...] | None = None
        # (state, chi2 as Python floats, depth tests as Python bools or None): what the per-edge
        # getters index, valid while the state is.
        self._lists: tuple[Any, list[float], list[bool] | None] | None = None
        self._bank1 = banks[0] if len(banks) == 1 else None
        self._bank2 = (banks[0], banks[1]) if len(banks) == 2 else None
        # The per-edge getters' fast path (one or two vertex types, a core built): the stores
        # (the one twice for one type), chi2 and depth tests as Python lists, and the stores'
        # estimate versions they are valid for. Set by add_to.
        self._st0: Any = None
        self._st1: Any = None
        self._fchi2: list[float] | None = None
        self._fdepth: list[bool] | None = None
        self._fv0 = self._fv1 = -1
        for i, r in enumerate(records):  # every record's batch and index (one loop: half
            r._batch = self  # the cost of two C passes of setattr)
            r._idx = i

    @property
    def measured(self) -> np.ndarray | None:
        """The type's ``measurement_derived`` values (the batch's own evaluation only: made when
        first read)."""
        if self._measured is None:
            self._measured = (self.gtype.measurement_derived(self.meas) if self.m else None,)
        return self._measured[0]

    # --- kernels and levels ------------------------------------------------------------------

    @staticmethod
    def _one_key(kernels: list[Any]) -> bool:
        """Whether g2o kernels (one object per edge, as programs make them) all have the first's
        :func:`kernel_key` — one comparison per edge instead of a key and a lookup."""
        d0 = kernels[0]._delta
        # Sets in C loops (5,000 kernels: 0.4 → 0.1 ms); a NaN width equals nothing.
        return (len(set(map(type, kernels))) == 1 and d0 == d0
                and len({k._delta for k in kernels}) == 1)

    def code(self, kernel: Any) -> int:
        """The batch's code of a kernel (-1: none)."""
        if kernel is None:
            return -1
        last = self._last_code  # the kernel of the last call, unchanged: an outlier pass
        if kernel is last[0] and kernel._delta == last[1]:  # giving every edge one object
            return last[2]
        key = kernel_key(kernel)
        c = self._codes.get(key)
        if c is None:
            c = self._codes[key] = len(self.kernels)
            self.kernels.append(graphopt_kernel(kernel))
        if isinstance(kernel, RobustKernelBase):
            self._last_code = (kernel, kernel._delta, c)
        return c

    def set_kernel(self, i: int, kernel: Any) -> None:
        """Edge ``i``'s kernel; it reaches the optimizer's group before the group's next use.

        Args:
            i: Index in the batch.
            kernel: A g2o kernel or ``None``.
        """
        self.kcodes[i] = -1 if kernel is None else self.code(kernel)  # None: outlier passes
        if self.group is not None and not self.kernels_dirty:
            self.kernels_dirty = True
            self._notify()

    def set_level(self, i: int, level: int) -> None:
        """Edge ``i``'s level; it reaches the optimizer at the next ``initialize_optimization``
        (g2o selects the active edges there).

        Args:
            i: Index in the batch.
            level: The level (non-negative).
        """
        if level < 0:
            raise GraphError(f"{self.cls.__name__}: level must be a non-negative integer, got "
                             f"{level}")
        self.levels[i] = level
        if self.group is not None and not self.levels_dirty:
            self.levels_dirty = True
            self._notify()

    def _notify(self) -> None:
        """Tell the optimizer (if it still exists) that the batch has changes to write."""
        owner = self._owner()
        if owner is not None:
            owner._batch_changed(self)

    def sync(self, levels: bool) -> None:
        """Write the kernels (and the levels) into the optimizer's group: one assignment per
        distinct kernel, one for all levels. The structure stays.

        Args:
            levels: Also the levels (only ``initialize_optimization`` does).
        """
        if self.group is None:
            return
        whole = self._whole()
        if self.kernels_dirty:
            self.kernels_dirty = False
            kc = self.kcodes
            c0 = int(kc[0]) if len(kc) else -1
            if (kc == c0).all():  # one kernel (or none) for all: no sort, no mask
                self.group.set_kernel(whole if whole is not None else self.rows,
                                      None if c0 < 0 else self.kernels[c0])
            else:
                for c in np.unique(kc).tolist():
                    self.group.set_kernel(self.rows[kc == c], None if c < 0 else self.kernels[c])
        if levels and self.levels_dirty:
            self.levels_dirty = False
            self.group.set_levels(whole if whole is not None else self.rows, self.levels)

    def _whole(self) -> slice | None:
        """``slice(None)`` if the batch's edges are its group's, in order (one g2o class and
        parameters per graphopt group, nothing removed: the usual case), else ``None``."""
        g, r = self.group, self.rows
        if g is None or len(r) != g.size:
            return None
        return slice(None) if not len(r) or (int(r[0]) == 0 and int(r[-1]) == len(r) - 1) \
            else None

    def add_to(self, core: Any) -> None:
        """Add every edge to the graphopt optimizer ``core`` (one ``add_edges``), with its
        level and kernel.

        Args:
            core: A :class:`graphopt.SparseOptimizer` holding the banks' stores.
        """
        self._fchi2 = self._fdepth = None  # the stores are new
        if len(self.banks) <= 2:
            self._st0, self._st1 = self.banks[0].store, self.banks[-1].store
        if not self.m:
            return
        kc = self.kcodes
        c0 = int(kc[0])
        one = bool((kc == c0).all())  # one kernel (or none) for all: given to add_edges
        # The graph's add_edges (the optimizer's wraps it in an EdgeSet): every vertex at a
        # position is in its bank's store (checked at filing), so only the stores' types are.
        group, start, m = core.graph.add_edges(
            self.gtype, self.vids, self.meas, self.info,
            self.kernels[c0] if one and c0 >= 0 else None, self.params, self.data or None,
            vertex_stores=[b.store for b in self.banks])
        self.group, self.rows = group, group.index_of(np.arange(start, start + m))
        if self.levels.any():
            whole = self._whole()
            self.group.set_levels(whole if whole is not None else self.rows, self.levels)
        self.kernels_dirty = not one
        self.levels_dirty = False
        self.sync(levels=False)

    # --- evaluation --------------------------------------------------------------------------

    def _state(self) -> tuple[Any, ...]:
        """The stores behind the banks and their estimate versions (tuples compare by identity
        first: a check costs a few attribute reads)."""
        b = self._bank1
        if b is not None:  # one vertex type (the pose-only edges): no loop
            s = b.store
            return (s, s.version if s is not None else -1)
        if self._bank2 is not None:  # two (the projections): no loop either
            s0, s1 = self._bank2[0].store, self._bank2[1].store
            if s0 is not None and s1 is not None:
                return (s0, s0.version, s1, s1.version)
        return tuple([(b.store, b.store.version if b.store is not None else -1)
                      for b in self.banks])

    def chi2_of(self, i: int) -> float:
        """Edge ``i``'s ``eᵀΩe`` (no kernel) at the current estimates: one state check and a
        list index while the estimates are unchanged.

        Args:
            i: Index in the batch.
        """
        st0 = self._st0
        if st0 is not None:  # one or two stores: their versions
            st1 = self._st1
            if self._fchi2 is None or st0.version != self._fv0 or st1.version != self._fv1:
                self._fchi2, self._fdepth = self.chi2().tolist(), None
                self._fv0, self._fv1 = st0.version, st1.version
            return self._fchi2[i]
        state = self._state()
        lists = self._lists
        if lists is None or lists[0] != state:
            lists = self._lists = (state, self.chi2().tolist(), None)
        return lists[1][i]

    def depth_positive_of(self, i: int) -> bool:
        """Edge ``i``'s depth test at the current estimates (as :meth:`chi2_of`).

        Args:
            i: Index in the batch.
        """
        self.chi2_of(i)  # the lists at the current state
        if self._st0 is not None:
            if self._fdepth is None:
                self._fdepth = self.depth_positive().tolist()
            return self._fdepth[i]
        lists = self._lists
        assert lists is not None
        if lists[2] is None:
            lists = self._lists = (lists[0], lists[1], self.depth_positive().tolist())
        return lists[2][i]

    def _evaluate(self) -> tuple[np.ndarray, np.ndarray]:
        """Errors and ``eᵀΩe`` of every edge at the current estimates, once per state: the
        optimizer's own evaluation of the group when it has one at this state (it keeps every
        edge's, whatever its level), else the batch's."""
        state = self._state()
        if self._cache is None or self._cache[0] != state:
            owner = self._owner()
            g, core = self.group, (owner._core if owner is not None else None)
            if g is not None and core is not None and self.banks[0].store is not None:
                e_all, s_all = group_errors(core.graph, g)
                r = self.rows  # (sorted, unique) the group is this batch, in order:
                whole = len(r) == len(e_all) and (not len(r) or int(r[-1]) == len(r) - 1)
                e, chi2 = (e_all, s_all) if whole else (e_all[self.rows], s_all[self.rows])
                self._cache = (state, e, chi2, None, None)
            else:
                x = self._gather()
                ctx = EdgeContext(self.params, self.data, measured=self.measured)
                e = np.asarray(self.gtype.error(x, self.meas, ctx), dtype=float)
                if self.info is None:
                    chi2 = np.einsum("mi,mi->m", e, e)
                elif self.info.ndim == 2:
                    chi2 = np.einsum("mi,ij,mj->m", e, self.info, e)
                else:
                    chi2 = np.einsum("mi,mij,mj->m", e, self.info, e)
                self._cache = (state, e, chi2, x, None)
        return self._cache[1], self._cache[2]

    def _gather(self) -> list[np.ndarray]:
        """The estimates of every position, ``(m, *shape)`` each."""
        return [b.estimates()[s] for b, s in zip(self.banks, self.slots, strict=True)]

    def errors(self) -> np.ndarray:
        """``(m, e)`` errors at the current estimates."""
        return self._evaluate()[0]

    def chi2(self) -> np.ndarray:
        """``(m,)`` ``eᵀΩe`` at the current estimates (no kernel)."""
        return self._evaluate()[1]

    def depth_positive(self) -> np.ndarray:
        """``(m,)`` whether each edge's point is in front of its camera."""
        self._evaluate()
        assert self._cache is not None
        if self._cache[4] is None:
            x = self._cache[3] if self._cache[3] is not None else self._gather()
            if self.cls._depth is not BaseEdge._depth:  # the g2o class's own test
                ok = self.cls._depth(x, self.data, self.params)
            else:  # graphopt's type's (the Sim3 projections, ...)
                ctx = EdgeContext(self.params, self.data, measured=self.measured)
                ok = np.asarray(self.gtype.depth_positive(x, self.meas, ctx), dtype=bool)
            self._cache = (*self._cache[:4], ok)
        return self._cache[4]

    def information_of(self, i: int) -> np.ndarray:
        """Edge ``i``'s information matrix.

        Args:
            i: Index in the batch.
        """
        if self.info is None:
            return np.eye(self.gtype.dimension)
        return (self.info if self.info.ndim == 2 else self.info[i]).copy()


def stack_measurements(cls: type, recs: list[Any]) -> np.ndarray:
    """``(m, *measurement_shape)`` measurements of a batch's records; a bad one is named.

    Args:
        cls: The g2o edge class.
        recs: Its records.
    """
    raws = [r._meas for r in recs]
    if cls._raw_vector:  # set_measurement kept float arrays as bytes: one join
        arr = joined(raws, cls._mshape)
        if arr is not None:
            return arr
    try:
        if any(map(is_, raws, repeat(None))):  # C loops (5,000 edges: 0.3 ms less)
            raise ValueError
        return cls._measurements(raws)
    except (TypeError, ValueError):
        for e in recs:
            try:
                if e._meas is None:
                    raise ValueError("no measurement set")
                cls._measurements([e._meas])
            except (TypeError, ValueError) as exc:
                raise GraphError(f"{cls.__name__} on vertices {[v._id for v in e._v]}: "
                                 f"bad measurement ({exc})") from None
        raise


def _checked_one(cls: type, rec: Any, info: np.ndarray, d: int) -> np.ndarray:
    """A copy of the one information matrix of a batch, or a GraphError if it is not
    ``(d, d)``."""
    if info.shape != (d, d):
        raise GraphError(f"{cls.__name__} on vertices {[v._id for v in rec._v]}: "
                         f"information has shape {info.shape}, expected {(d, d)}")
    return info.copy()


def stack_information(cls: type, recs: list[Any], d: int) -> np.ndarray | None:
    """The information matrices of a batch's records: ``None`` (all identity, unset), one
    ``(d, d)`` shared by all, or ``(m, d, d)``.

    Args:
        cls: The g2o edge class.
        recs: Its records.
        d: The error dimension.
    """
    infos = [r._info for r in recs]
    first = infos[0]
    if all(map(is_, infos, repeat(first))):  # one object (set_information's shared copies) or None
        return None if first is None else _checked_one(cls, recs[0], first, d)
    if all(i is None for i in infos):
        return None
    byid = dict(zip(map(id, infos), infos, strict=True))
    if len(byid) <= max(16, len(infos) // 8):
        # A few matrices shared by many edges (set_information's copies of σ⁻²·I per pyramid
        # level): each checked once, then gathered (500 edges: 0.2 → 0.03 ms).
        objs = list(byid.values())
        eye = np.eye(d)
        for i in objs:
            if i is not None and i.shape != (d, d):
                k = next(k for k, x in enumerate(infos) if x is i)
                _checked_one(cls, recs[k], i, d)  # raises, naming the edge
        arr = np.stack([eye if i is None else i for i in objs])
        if bool((arr == arr[0]).all()):
            return arr[0].copy()
        at = {k: n for n, k in enumerate(byid)}
        return arr[np.fromiter(map(at.__getitem__, map(id, infos)), np.intp, len(infos))]
    if first is not None and first.shape == (d, d) and bool((first == first).all()):
        # The usual case, one matrix value for all: compared as bytes (equal bytes, equal
        # values), without stacking m copies first.
        fb = first.tobytes()
        for i in infos:
            if i is None or i.shape != first.shape or i.tobytes() != fb:
                break
        else:
            return first.copy()
    eye = np.eye(d)
    for e, i in zip(recs, infos, strict=True):
        if i is not None and i.shape != (d, d):
            raise GraphError(f"{cls.__name__} on vertices {[v._id for v in e._v]}: "
                             f"information has shape {i.shape}, expected {(d, d)}")
    arr = np.stack([eye if i is None else i for i in infos])
    return arr[0].copy() if bool((arr == arr[0]).all()) else arr
