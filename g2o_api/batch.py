"""Edges of one g2o class and parameters as arrays: what ``initialize_optimization`` hands to
graphopt (one ``add_edges`` call per batch, the edges of the active level) and what the edges'
own getters read (``chi2``, ``error``, ``is_depth_positive`` for every edge of the batch at once,
once per state; ``set_level`` and ``set_robust_kernel`` as one entry of an array)."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.edge import EdgeContext
from graphopt.errors import GraphError
from graphopt.storage import EdgeGroup

from .solvers import RobustKernelBase, graphopt_kernel
from .vertices import Bank

__all__ = ["Batch"]


def kernel_key(kernel: Any) -> Any:
    """Edges whose kernels have equal keys share one graphopt kernel."""
    if kernel is None:
        return None
    if isinstance(kernel, RobustKernelBase):
        return (type(kernel), kernel._delta)
    return ("object", id(kernel))


class Batch:
    """All edges of one g2o edge class with equal parameters.

    Args:
        owner: The g2o optimizer.
        cls: The g2o edge class.
        gtype: graphopt's edge type.
        params: graphopt's parameter object for the group.
        records: The edge records, in order.
        vids: ``(m, k)`` vertex ids in graphopt's position order.
        banks: The bank of each graphopt position.
        meas: ``(m, *measurement_shape)``.
        info: ``None`` (identity), ``(e, e)`` or ``(m, e, e)``.
        data: Per-edge arrays.
    """

    def __init__(self, owner: Any, cls: type, gtype: type, params: Any, records: list[Any],
                 vids: np.ndarray, banks: list[Bank], meas: np.ndarray, info: np.ndarray | None,
                 data: dict[str, np.ndarray]) -> None:
        self.owner, self.cls, self.gtype, self.params = owner, cls, gtype, params
        self.records, self.vids, self.banks = records, vids, banks
        self.meas, self.info, self.data = meas, info, data
        m = len(records)
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
        self.levels = np.fromiter((r._level for r in records), dtype=np.int64, count=m)
        self.kernels: list[Any] = []  # graphopt kernels by code
        self._codes: dict[Any, int] = {}
        kernels = [r._kernel for r in records]
        first = kernels[0] if m else None
        if all(k is first for k in kernels):  # one object (or None) for all: one code
            self.kcodes = np.full(m, self.code(first), dtype=np.int64)
        else:
            self.kcodes = np.fromiter((self.code(k) for k in kernels), dtype=np.int64, count=m)
        self.group: EdgeGroup | None = None
        self.kernels_dirty = False
        self.core_pos = np.full(m, -1, dtype=np.int64)
        self.measured = gtype.measurement_derived(meas) if m else None
        self._cache: tuple[Any, ...] | None = None
        for i, r in enumerate(records):
            r._batch, r._idx = self, i

    # --- kernels and levels ------------------------------------------------------------------

    def code(self, kernel: Any) -> int:
        """The batch's code of a kernel (-1: none)."""
        key = kernel_key(kernel)
        if key is None:
            return -1
        c = self._codes.get(key)
        if c is None:
            c = self._codes[key] = len(self.kernels)
            self.kernels.append(graphopt_kernel(kernel))
        return c

    def set_kernel(self, i: int, kernel: Any) -> None:
        """Edge ``i``'s kernel, in the optimizer's arrays too when it is active.

        Args:
            i: Index in the batch.
            kernel: A g2o kernel or ``None``.
        """
        self.kcodes[i] = self.code(kernel)
        if self.core_pos[i] >= 0 and not self.kernels_dirty:
            self.kernels_dirty = True  # reaches the optimizer's arrays before its next use
            self.owner._kernels_changed(self)

    def sync_kernels(self) -> None:
        """Write the kernels of the active edges into the optimizer's group (one assignment
        per distinct kernel)."""
        self.kernels_dirty = False
        if self.group is None:
            return
        sub = np.flatnonzero(self.core_pos >= 0)
        codes = self.kcodes[sub]
        for c in np.unique(codes).tolist():
            self.group.set_kernel(self.core_pos[sub[codes == c]], None if c < 0 else
                                  self.kernels[c])

    def set_level(self, i: int, level: int) -> None:
        """Edge ``i``'s level (applied at the next ``initialize_optimization``).

        Args:
            i: Index in the batch.
            level: The level.
        """
        self.levels[i] = level
        self.owner._levels_changed()

    def add_to(self, core: Any, level: int) -> None:
        """Add the edges of ``level`` to the graphopt optimizer ``core`` (one ``add_edges``).

        Args:
            core: A :class:`graphopt.SparseOptimizer` holding the banks' stores.
            level: The active level.
        """
        sub = np.flatnonzero(self.levels == level)
        self.core_pos[:] = -1
        self.group = None
        if not len(sub):
            return
        info = self.info if self.info is None or self.info.ndim == 2 else self.info[sub]
        data = {k: v[sub] for k, v in self.data.items()} or None
        key = (self.gtype, id(self.params))
        start = core.graph.groups[key].size if key in core.graph.groups else 0
        core.add_edges(self.gtype, self.vids[sub], self.meas[sub], info, None, self.params, data)
        self.group = core.graph.groups[key]
        self.core_pos[sub] = start + np.arange(len(sub))
        codes = self.kcodes[sub]
        for c in np.unique(codes[codes >= 0]).tolist():
            self.group.set_kernel(self.core_pos[sub[codes == c]], self.kernels[c])

    def active_ids(self, level: int) -> np.ndarray:
        """Vertex ids used by the edges of ``level``.

        Args:
            level: The level.
        """
        return self.vids[self.levels == level].ravel()

    # --- evaluation --------------------------------------------------------------------------

    def _state(self) -> tuple[Any, ...]:
        return tuple((id(b.store), b.store.version if b.store is not None else -1)
                     for b in self.banks)

    def _evaluate(self) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        state = self._state()
        if self._cache is None or self._cache[0] != state:
            x = [b.estimates()[s] for b, s in zip(self.banks, self.slots, strict=True)]
            ctx = EdgeContext(self.params, self.data, measured=self.measured)
            e = np.asarray(self.gtype.error(x, self.meas, ctx), dtype=float)
            if self.info is None:
                chi2 = np.einsum("mi,mi->m", e, e)
            elif self.info.ndim == 2:
                chi2 = np.einsum("mi,ij,mj->m", e, self.info, e)
            else:
                chi2 = np.einsum("mi,mij,mj->m", e, self.info, e)
            self._cache = (state, e, chi2, x, None)
        return self._cache[1], self._cache[2], self._cache[3]

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
            self._cache = (*self._cache[:4], self.cls._depth(self._cache[3], self.data,
                                                             self.params))
        return self._cache[4]

    def information_of(self, i: int) -> np.ndarray:
        """Edge ``i``'s information matrix.

        Args:
            i: Index in the batch.
        """
        if self.info is None:
            return np.eye(self.gtype.dimension)
        return (self.info if self.info.ndim == 2 else self.info[i]).copy()
