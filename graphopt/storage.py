"""Struct-of-arrays storage behind the per-object API: one store per vertex type, one group per
edge type (and parameter object).

Objects added one at a time and arrays added in bulk end up in the same arrays; chunks are
concatenated lazily, so adding many single objects stays linear in time. A group made of one
bulk chunk keeps the arrays it was given (no copy: do not modify them afterwards), and one
robust kernel slot for all edges is one broadcast value, not a per-edge array.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext
from graphopt.errors import GraphError
from graphopt.robust_kernel import RobustKernel
from graphopt.vertex import BaseVertex


def _join(chunks: list[np.ndarray]) -> np.ndarray:
    """The chunks as one array: the only chunk itself, or their concatenation."""
    return chunks[0] if len(chunks) == 1 else np.concatenate(chunks)


class VertexStore:
    """All vertices of one type: ids, estimates, fixed and marginalised flags.

    Args:
        vtype: The vertex class.
    """

    def __init__(self, vtype: type[BaseVertex]) -> None:
        self.vtype = vtype
        shape = tuple(vtype.estimate_shape)
        self._ids = np.zeros(0, dtype=np.int64)
        self._est = np.zeros((0, *shape))
        self._fixed = np.zeros(0, dtype=bool)
        self._marg = np.zeros(0, dtype=bool)
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        #: Incremented whenever fixed/marginalized flags change (the structure is then stale).
        self.flags_version = 0
        #: Incremented whenever estimates are replaced or written (cached evaluations are stale).
        self.version = 0

    def _consolidate(self) -> None:
        if self._pending:
            self.version += 1
            ids, est, fixed, marg = zip(*self._pending, strict=True)
            self._ids = np.concatenate([self._ids, *ids])
            self._est = np.concatenate([self._est, *est])
            self._fixed = np.concatenate([self._fixed, *fixed])
            self._marg = np.concatenate([self._marg, *marg])
            self._pending = []

    def __len__(self) -> int:
        return len(self._ids) + sum(len(p[0]) for p in self._pending)

    @property
    def ids(self) -> np.ndarray:
        """``(n,)`` vertex ids by slot."""
        self._consolidate()
        return self._ids

    @property
    def estimates(self) -> np.ndarray:
        """``(n, *estimate_shape)`` estimates by slot (the live array)."""
        self._consolidate()
        return self._est

    @estimates.setter
    def estimates(self, value: np.ndarray) -> None:
        self._consolidate()
        self._est = value
        self.version += 1

    @property
    def fixed(self) -> np.ndarray:
        """``(n,)`` fixed flags."""
        self._consolidate()
        return self._fixed

    @property
    def marginalized(self) -> np.ndarray:
        """``(n,)`` marginalised flags."""
        self._consolidate()
        return self._marg

    def append(
        self, ids: np.ndarray, estimates: np.ndarray, fixed: np.ndarray, marg: np.ndarray
    ) -> int:
        """Append validated vertices; returns the first new slot.

        Args:
            ids: ``(n,)`` ids.
            estimates: ``(n, *estimate_shape)``.
            fixed: ``(n,)`` bool.
            marg: ``(n,)`` bool.
        """
        start = len(self)
        self._pending.append((ids, estimates, fixed, marg))
        return start

    def check_estimates(self, estimates: np.ndarray, ids: np.ndarray) -> None:
        """Raise :class:`GraphError` naming the first invalid estimate.

        Args:
            estimates: ``(n, *estimate_shape)``.
            ids: Their ids.
        """
        ok = self.vtype.validate(estimates)
        if not np.all(ok):
            i = int(np.flatnonzero(~ok)[0])
            raise GraphError(
                f"vertex {int(ids[i])} ({self.vtype.__name__}): invalid estimate "
                f"(non-finite or off the manifold): {np.array2string(estimates[i], threshold=20)}"
            )

    def set_estimate(self, slot: int, value: np.ndarray, vid: int) -> None:
        """Set one estimate, with shape and validity checks.

        Args:
            slot: Slot in the store.
            value: New estimate.
            vid: The vertex id (for messages).
        """
        shape = tuple(self.vtype.estimate_shape)
        if value.shape != shape:
            raise GraphError(
                f"vertex {vid} ({self.vtype.__name__}): estimate has shape {value.shape}, "
                f"expected {shape}"
            )
        self.check_estimates(value[None], np.array([vid]))
        self.estimates[slot] = value
        self.version += 1

    def set_flag(self, name: str, slot: int, value: bool) -> None:
        """Set ``fixed`` or ``marginalized`` of one vertex.

        Args:
            name: ``"fixed"`` or ``"marginalized"``.
            slot: Slot in the store.
            value: The flag.
        """
        arr = self.fixed if name == "fixed" else self.marginalized
        if bool(arr[slot]) != bool(value):
            arr[slot] = bool(value)
            self.flags_version += 1


class EdgeGroup:
    """All edges of one type sharing one parameter object, as arrays.

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
        self._data: list[dict[str, np.ndarray]] = []
        self.kernels: list[RobustKernel] = []
        self.size = 0
        self.dim = e
        # Filled by finalize():
        self.vertex_ids = np.zeros((0, self.k), dtype=np.int64)
        self.slots = np.zeros((0, self.k), dtype=np.int64)
        self.measurements = np.zeros((0, *self.mshape))
        self.information: np.ndarray | None = None  # (e, e) shared, or (m, e, e)
        self.info_is_identity = True
        self.info_diagonal: np.ndarray | None = None  # (e,) when the shared matrix is diagonal
        self.kernel_index = np.zeros(0, dtype=np.int64)
        self.data: dict[str, np.ndarray] = {}
        self.measured: np.ndarray | None = None  # the type's measurement_derived values
        self.last_chi2 = np.zeros(0)
        self.active_count = 0
        self._finalized_size = -1

    # --- adding ----------------------------------------------------------------------------

    def kernel_slot(self, kernel: RobustKernel | None) -> int:
        """Index of ``kernel`` in this group's kernel list (-1 for none).

        Args:
            kernel: A kernel or ``None``.
        """
        if kernel is None:
            return -1
        if not isinstance(kernel, RobustKernel):
            raise GraphError(
                f"{self.etype.__name__}: robust_kernel must be a RobustKernel, got {kernel!r}"
            )
        for i, k in enumerate(self.kernels):
            if k is kernel:
                return i
        self.kernels.append(kernel)
        return len(self.kernels) - 1

    def append(
        self,
        vids: np.ndarray,
        meas: np.ndarray,
        info: np.ndarray,
        kernel: int | np.ndarray,
        data: dict[str, np.ndarray],
    ) -> int:
        """Append validated edges; returns the index of the first one.

        Args:
            vids: ``(n, k)`` vertex ids.
            meas: ``(n, *measurement_shape)``.
            info: ``(e, e)`` shared or ``(n, e, e)``.
            kernel: Kernel slot for all, or per edge.
            data: Per-edge arrays.
        """
        n = len(vids)
        start = self.size
        if self._data and set(data) != set(self._data[0]):
            raise GraphError(
                f"{self.etype.__name__}: every add_edges call of a group must give the same data "
                f"keys ({sorted(self._data[0])}), got {sorted(data)}"
            )
        self._vids.append(vids)
        self._meas.append(meas)
        self._info.append(info)
        kern = np.asarray(kernel, dtype=np.int64)
        # One slot for the chunk: a broadcast value (no bytes per edge) until set_kernel.
        self._kern.append(np.broadcast_to(kern, (n,)) if kern.ndim == 0 else kern.copy())
        self._data.append(data)
        self.size += n
        return start

    def tail(self, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                        dict[str, np.ndarray]]:
        """The edges ``start:size`` read from the chunks, without finalising the group (what the
        incremental optimizer takes after each update: a few edges, not a concatenation of
        all).

        Args:
            start: First edge.

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
        joined = [_join(p) for p in parts]
        merged = {k: np.concatenate([d[k] for d in data]) for k in data[0]} if data else {}
        return joined[0], joined[1], joined[2], joined[3], merged

    # --- finalising --------------------------------------------------------------------------

    def finalize(self) -> None:
        """Concatenate chunks into the group's arrays (idempotent)."""
        if self._finalized_size == self.size:
            return
        self.vertex_ids = _join(self._vids) if self._vids else self.vertex_ids
        self.measurements = _join(self._meas) if self._meas else self.measurements
        if self._kern:
            values = {int(k[0]) for k in self._kern if len(k)}
            if len(values) == 1 and all(k.strides == (0,) for k in self._kern if len(k)):
                self.kernel_index = np.broadcast_to(np.int64(values.pop()), (self.size,))
            else:
                self.kernel_index = _join(self._kern)
        shared = [i for i in self._info if i.ndim == 2]
        if len(shared) == len(self._info) and all(np.array_equal(shared[0], i) for i in shared):
            self.information = shared[0] if shared else np.eye(self.dim)
        else:
            self.information = np.concatenate(
                [np.broadcast_to(i, (len(v), self.dim, self.dim)) for i, v in
                 zip(self._info, self._vids, strict=True)]
            )
        self.info_is_identity = self.information.ndim == 2 and np.array_equal(
            self.information, np.eye(self.dim)
        )
        self.info_diagonal = None
        if self.information.ndim == 2 and not np.count_nonzero(
                self.information - np.diag(np.diag(self.information))):
            self.info_diagonal = np.diag(self.information).copy()
        if self._data:
            self.data = {key: np.concatenate([d[key] for d in self._data]) for key in self._data[0]}
        self.measured = self.etype.measurement_derived(self.measurements) if self.size else None
        if self.measured is not None and (self.measured.ndim != 2
                                          or len(self.measured) != self.size):
            raise GraphError(f"{self.etype.__name__}.measurement_derived returned shape "
                             f"{self.measured.shape}, expected ({self.size}, k)")
        # Keep one chunk so further appends concatenate onto the consolidated arrays.
        self._vids, self._meas, self._kern = [self.vertex_ids], [self.measurements], [
            self.kernel_index
        ]
        self._info = [self.information]
        self._data = [self.data] if self._data else []
        self.last_chi2 = np.zeros(self.size)
        self._finalized_size = self.size

    def context(self) -> EdgeContext:
        """A fresh :class:`EdgeContext` over all edges of the group."""
        return EdgeContext(self.params, self.data, measured=self.measured)

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
        k = int(self.kernel_index[i])
        return None if k < 0 else self.kernels[k]

    def set_kernel(self, i: int | slice | np.ndarray, kernel: RobustKernel | None) -> None:
        """Set the robust kernel of some edges.

        Args:
            i: Edge index (or indices) in the group.
            kernel: The kernel or ``None``.
        """
        self.finalize()
        if not self.kernel_index.flags.writeable:  # one broadcast slot so far
            self.kernel_index = self.kernel_index.copy()
            self._kern = [self.kernel_index]
        self.kernel_index[i] = self.kernel_slot(kernel)
