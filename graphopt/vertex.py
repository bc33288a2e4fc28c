"""Vertex types: a manifold estimate with a vectorised ``oplus``.

A vertex *type* (a subclass of :class:`BaseVertex`) declares the shape of one estimate, the
dimension of its tangent space and ``oplus`` over **all vertices of the type at once**. Instances
are a thin per-object front (g2o's API) over the optimizer's struct-of-arrays storage.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np


def _own(value: Any) -> Any:
    """A copy of an array (a caller may reuse its buffer for the next object), else the value
    (lists and tuples are converted, and copied, in bulk later)."""
    return value.copy() if type(value) is np.ndarray else value


class _Store(Protocol):
    """What a bound vertex needs of its store (a :class:`~graphopt.storage._Store`)."""

    estimates: np.ndarray
    fixed: np.ndarray
    marginalized: np.ndarray

    def set_estimate(self, slot: int, value: np.ndarray, vid: int) -> None: ...

    def set_flag(self, name: str, slot: int, value: bool) -> None: ...


class BaseVertex:
    """Base class of all vertex types.

    Subclasses set ``dimension`` (tangent dimension) and ``estimate_shape`` (shape of one
    estimate) and implement :meth:`oplus`. They may override :meth:`validate` to reject estimates
    that are not on the manifold.

    Args:
        id: Unique integer id of the vertex within an optimizer.
        estimate: Initial estimate, of shape ``estimate_shape``.
        fixed: Whether the vertex is held constant.
        marginalized: Whether the vertex is eliminated by the Schur complement.
    """

    dimension: ClassVar[int] = 0
    estimate_shape: ClassVar[tuple[int, ...]] = ()

    # --- the batched type interface --------------------------------------------------------

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """Apply tangent-space increments to many estimates at once.

        Args:
            estimates: ``(n, *estimate_shape)`` current estimates.
            deltas: ``(n, dimension)`` increments.

        Returns:
            ``(n, *estimate_shape)`` updated estimates (a new array).
        """
        raise NotImplementedError

    @classmethod
    def derived(cls, estimates: np.ndarray) -> np.ndarray | None:
        """Per-vertex quantities that edges would otherwise recompute per edge, or ``None``.

        Computed once per state for the whole type (a rotation matrix per camera, say) and
        handed, gathered per edge, to edge types that set ``uses_derived`` (as
        ``EdgeContext.derived``). Optional: edges must give the same result without it.

        Args:
            estimates: ``(n, *estimate_shape)`` estimates.

        Returns:
            ``(n, k)`` values, or ``None`` (the default: nothing to share).
        """
        return None

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Return a boolean mask ``(n,)`` of estimates that are valid (finite by default).

        Args:
            estimates: ``(n, *estimate_shape)`` estimates to check.
        """
        flat = estimates.reshape(len(estimates), -1)
        return np.isfinite(flat).all(axis=1)

    # --- per-object front ------------------------------------------------------------------

    def __init__(
        self,
        id: int | None = None,
        estimate: Any = None,
        fixed: bool = False,
        marginalized: bool = False,
    ) -> None:
        # A thin record: the estimate is converted and checked when the optimizer takes the
        # vertices into its arrays (in bulk, at the next initialisation or query).
        self._id = None if id is None else int(id)
        self._estimate = _own(estimate)
        self._fixed = bool(fixed)
        self._marginalized = bool(marginalized)
        self._store: _Store | None = None
        self._slot = -1  # -1: not added; -2: added, waiting in the optimizer's buffer

    @classmethod
    def _bound(cls, store: _Store, slot: int, vid: int) -> BaseVertex:
        v = cls.__new__(cls)
        v._id, v._estimate, v._store, v._slot = vid, None, store, slot
        v._fixed = v._marginalized = False
        return v

    def _detach(self) -> None:
        """Keep the estimate on the object and leave the store (the vertex was removed)."""
        if self._store is not None:
            self._estimate = self._store.estimates[self._slot].copy()
            self._fixed = bool(self._store.fixed[self._slot])
            self._marginalized = bool(self._store.marginalized[self._slot])
        self._store, self._slot = None, -1

    @property
    def id(self) -> int:
        """The vertex id."""
        if self._id is None:
            raise ValueError(f"{type(self).__name__} has no id; call set_id() first")
        return self._id

    def set_id(self, id: int) -> None:
        """Set the id (before the vertex is added).

        Args:
            id: Unique integer id.
        """
        if self._store is not None or self._slot == -2:
            raise ValueError(f"vertex {self._id}: the id cannot change after add_vertex")
        self._id = int(id)

    @property
    def estimate(self) -> np.ndarray:
        """The current estimate (a copy once the vertex lives in an optimizer)."""
        if self._store is not None:
            return self._store.estimates[self._slot].copy()
        if self._estimate is None:
            raise ValueError(f"vertex {self._id} ({type(self).__name__}) has no estimate")
        return np.asarray(self._estimate, dtype=float)

    @estimate.setter
    def estimate(self, value: Any) -> None:
        self.set_estimate(value)

    def set_estimate(self, value: Any) -> None:
        """Set the estimate.

        Args:
            value: New estimate of shape ``estimate_shape``.
        """
        if self._store is not None:
            self._store.set_estimate(self._slot, np.asarray(value, dtype=float), self._id)
        else:
            self._estimate = _own(value)

    def fixed(self) -> bool:
        """Whether the vertex is held constant."""
        return bool(self._store.fixed[self._slot]) if self._store is not None else self._fixed

    def set_fixed(self, fixed: bool = True) -> None:
        """Hold the vertex constant (or release it).

        Args:
            fixed: True to fix.
        """
        if self._store is not None:
            self._store.set_flag("fixed", self._slot, fixed)
        else:
            self._fixed = bool(fixed)

    def marginalized(self) -> bool:
        """Whether the vertex is eliminated by the Schur complement."""
        if self._store is not None:
            return bool(self._store.marginalized[self._slot])
        return self._marginalized

    def set_marginalized(self, marginalized: bool = True) -> None:
        """Eliminate the vertex by the Schur complement (or not).

        Args:
            marginalized: True to marginalise.
        """
        if self._store is not None:
            self._store.set_flag("marginalized", self._slot, marginalized)
        else:
            self._marginalized = bool(marginalized)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(id={self._id})"


class VertexVector(BaseVertex):
    """A Euclidean vertex: ``oplus`` is addition. Subclass and set ``dimension``.

    Args:
        id: Unique integer id.
        estimate: Initial estimate, shape ``(dimension,)``.
        fixed: Whether the vertex is held constant.
        marginalized: Whether the vertex is eliminated by the Schur complement.
    """

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """Euclidean update ``x + δ``.

        Args:
            estimates: ``(n, d)`` estimates.
            deltas: ``(n, d)`` increments.
        """
        return estimates + deltas

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "estimate_shape" not in cls.__dict__:
            cls.estimate_shape = (cls.dimension,)
