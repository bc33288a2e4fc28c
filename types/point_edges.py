"""Euclidean point edges of any dimension, shared by :mod:`graphopt.types.slam2d_sensors` and
:mod:`graphopt.types.slam3d_sensors`: the point-point difference, the point prior, and the
pieces of the variable-arity "one pose, ``k`` points" families (g2o's ``EdgeSE2LotsOfXY`` and
``EdgeSE3LotsOfXYZ``).

The public g2o types stay in their modules as subclasses that set ``dimension`` and
``vertex_types`` (the point vertex type); the numbers are computed here once for both.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext
from graphopt.vertex import BaseVertex

__all__ = ["PointDifferenceEdge", "PointPriorEdge", "identity_jacobians", "points_family",
           "scatter_point_jacobians"]


def identity_jacobians(m: int, d: int) -> np.ndarray:
    """``(m, d, d)`` identities (writable).

    Args:
        m: Number of edges.
        d: Dimension.
    """
    return np.broadcast_to(np.eye(d), (m, d, d)).copy()


class PointDifferenceEdge(BaseEdge):
    """The difference of two points of dimension ``d = dimension``: ``e = p_j − p_i − z``,
    Jacobians ``−I`` and ``I``. A subclass sets ``dimension`` and ``vertex_types``.
    """

    dimension: ClassVar[int] = 0
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = ()

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, d)`` errors.

        Args:
            x: ``(p_i (m, d), p_j (m, d))``.
            measurement: ``(m, d)`` expected ``p_j − p_i``.
            ctx: Unused.
        """
        return x[1] - x[0] - measurement

    @classmethod
    def jacobians(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        """``(−I, I)``, each ``(m, d, d)``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: Unused.
        """
        eye = identity_jacobians(len(measurement), cls.dimension)
        return -eye, eye


class PointPriorEdge(BaseEdge):
    """A prior on a point of dimension ``d = dimension``: ``e = p − z``, Jacobian ``I``. A
    subclass sets ``dimension`` and ``vertex_types``.
    """

    dimension: ClassVar[int] = 0
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = ()

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, d)`` errors.

        Args:
            x: ``(points (m, d),)``.
            measurement: ``(m, d)`` the prior position.
            ctx: Unused.
        """
        return x[0] - measurement

    @classmethod
    def jacobians(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        """``(I,)`` ``(m, d, d)``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: Unused.
        """
        return (identity_jacobians(len(measurement), cls.dimension),)


def points_family(base: type[BaseEdge], k: int, pose: type[BaseVertex],
                  point: type[BaseVertex], d: int) -> type:
    """The subclass of ``base`` for edges of one pose and ``k`` points of dimension ``d``
    (named ``<base>_<k>``, in ``base``'s module); the caller caches it per ``k``.

    Args:
        base: The family's class (``EdgeSE2LotsOfXY``, ``EdgeSE3LotsOfXYZ``).
        k: Number of points, ``k ≥ 1``.
        pose: The pose vertex type.
        point: The point vertex type.
        d: The point dimension.

    Raises:
        ValueError: ``k < 1``.
    """
    if int(k) < 1:
        raise ValueError(f"{base.__name__} needs at least one point, got {k}")
    k = int(k)
    return type(f"{base.__name__}_{k}", (base,), {
        "points": k, "dimension": d * k,
        "vertex_types": (pose,) + (point,) * k, "__module__": base.__module__})


def scatter_point_jacobians(blocks: np.ndarray) -> list[np.ndarray]:
    """The Jacobians by each of ``k`` points of a stacked error whose rows ``d·i … d·i + d``
    depend on point ``i`` alone.

    Args:
        blocks: ``(m, k, d, d)`` the derivative of point ``i``'s rows by point ``i``.

    Returns:
        ``k`` arrays ``(m, d·k, d)``, zero outside point ``i``'s rows.
    """
    m, k, d, _ = blocks.shape
    out: list[np.ndarray] = []
    for i in range(k):
        Ji = np.zeros((m, d * k, d))
        Ji[:, d * i:d * i + d] = blocks[:, i]
        out.append(Ji)
    return out
