"""Struct-of-arrays storage behind the per-object API: one store per vertex type
(:class:`VertexStore`), one group per edge type and parameter object
(:class:`~graphopt.edge_group.EdgeGroup`, re-exported here).

Objects added one at a time and arrays added in bulk end up in the same arrays; chunks are
concatenated lazily, so adding many single objects stays linear in time.
"""

from __future__ import annotations

import numpy as np

from graphopt.edge_group import EdgeGroup
from graphopt.errors import GraphError
from graphopt.vertex import BaseVertex

__all__ = ["EdgeGroup", "VertexStore"]


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
        #: Incremented whenever vertices are removed (slots move; the structure is stale).
        self.removals = 0
        self._valid = b""  # the last estimate set_estimate validated (validity is the value's)

    def _consolidate(self) -> None:
        if self._pending:
            self.version += 1
            if len(self._pending) == 1 and not len(self._ids):  # the first chunk: taken as
                # it is (Graph._add hands over arrays of its own)
                self._ids, self._est, self._fixed, self._marg = self._pending[0]
                self._pending = []
                return
            ids, est, fixed, marg = zip(*self._pending, strict=True)
            self._ids = np.concatenate([self._ids, *ids])
            self._est = np.concatenate([self._est, *est])
            self._fixed = np.concatenate([self._fixed, *fixed])
            self._marg = np.concatenate([self._marg, *marg])
            self._pending = []

    def __len__(self) -> int:
        if not self._pending:
            return len(self._ids)
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
        self._pending.append((ids, estimates, fixed, marg))  # (the store's own from now)
        return start

    def remove(self, slots: np.ndarray) -> None:
        """Remove vertices; the others keep their order and move down to close the gaps.

        Args:
            slots: ``(r,)`` distinct slots to remove.
        """
        self._consolidate()
        keep = np.ones(len(self._ids), dtype=bool)
        keep[slots] = False
        self._ids, self._est = self._ids[keep], self._est[keep]
        self._fixed, self._marg = self._fixed[keep], self._marg[keep]
        self.removals += 1
        self.version += 1

    def check_estimates(self, estimates: np.ndarray, ids: np.ndarray) -> None:
        """Raise :class:`GraphError` naming the first invalid estimate.

        Args:
            estimates: ``(n, *estimate_shape)``.
            ids: Their ids.
        """
        ok = self.vtype.validate(estimates)
        if len(ok) == 1 and ok[0]:  # one vertex (a motion-only BA's pose): set_estimate of
            self._valid = estimates[0].tobytes()  # this value again is not checked again
            return
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
        seen = value.tobytes()
        if seen != self._valid:  # a SLAM system sets the same prediction every round
            self.check_estimates(value[None], np.array([vid]))
            self._valid = seen
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
