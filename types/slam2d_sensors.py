"""More of g2o's ``types/slam2d`` (the ones the official ``g2opy`` wheel exposes): point-point
and point priors, a position prior on a pose, bearing-only observations, pose-pose and
pose-point edges through sensor offsets (``ParameterSE2Offset``), an observation through a
calibrated sensor vertex, two points at once and the variable-arity ``EdgeSE2LotsOfXY``; all
with analytic Jacobians.

Conventions are those of :mod:`graphopt.types.slam2d`: a :class:`~graphopt.types.slam2d.VertexSE2`
is ``[x, y, θ]`` updated additively (world-frame translation increment), angles of errors are
wrapped with :func:`~graphopt.types.slam2d.normalize_theta`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.types.point_edges import (
    PointDifferenceEdge,
    PointPriorEdge,
    points_family,
    scatter_point_jacobians,
)
from graphopt.types.slam2d import (
    EdgeFromParts,
    EdgeSE2,
    EdgeSE2PointXY,
    VertexPointXY,
    VertexSE2,
    _by_offset,
    _by_pose,
    _sensor_pose,
    normalize_theta,
)
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgePointXY",
    "EdgeSE2LotsOfXY",
    "EdgeSE2Offset",
    "EdgeSE2PointXYBearing",
    "EdgeSE2PointXYCalib",
    "EdgeSE2PointXYOffset",
    "EdgeSE2TwoPointsXY",
    "EdgeSE2XYPrior",
    "EdgeXYPrior",
    "ParameterSE2Offset",
]


class EdgePointXY(PointDifferenceEdge):
    """The difference of two 2D points (g2o's ``EdgePointXY``): ``e = p_j − p_i − z``,
    Jacobians ``(−I, I)`` (:class:`~graphopt.types.point_edges.PointDifferenceEdge`).

    Args:
        vertices: ``(p_i, p_j)``.
        measurement: ``(2,)``.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexPointXY, VertexPointXY)


class EdgeXYPrior(PointPriorEdge):
    """A prior on a 2D point (g2o's ``EdgeXYPrior``): ``e = p − z``, Jacobian ``I``
    (:class:`~graphopt.types.point_edges.PointPriorEdge`).

    Args:
        vertices: ``(point,)``.
        measurement: ``(2,)``.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexPointXY,)


class EdgeSE2XYPrior(BaseEdge):
    """A prior on the position of a 2D pose (g2o's ``EdgeSE2XYPrior``): ``e = t − z``,
    Jacobian ``[I, 0]``.

    Args:
        vertices: ``(pose,)``.
        measurement: ``(2,)``.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2,)

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 2)`` errors.

        Args:
            x: ``(poses (m, 3),)``.
            measurement: ``(m, 2)``.
            ctx: Unused.
        """
        return x[0][:, :2] - measurement

    @classmethod
    def jacobians(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        """``([I, 0],)`` ``(m, 2, 3)``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: Unused.
        """
        J = np.zeros((len(measurement), 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = 1.0
        return (J,)


class EdgeSE2PointXYBearing(EdgeFromParts):
    """The bearing of a 2D point seen from a pose (g2o's ``EdgeSE2PointXYBearing``, tag
    ``EDGE_BEARING_SE2_XY``).

    Error ``e = normalize(z − atan2(d_y', d_x'))`` ``(m, 1)`` with ``d' = Xi⁻¹·p`` (note g2o's
    sign: measurement minus prediction). With ``d = p − t``, ``r² = |d|²``:
    ``∂e/∂x = [−d_y/r², d_x/r², 1]`` and ``∂e/∂p = [d_y/r², −d_x/r²]``.

    Args:
        vertices: ``(pose, point)``.
        measurement: ``(1,)`` bearing in radians, in the pose's frame.
        information: ``(1, 1)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 1
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexPointXY)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        X, p = x
        d = p - X[:, :2]
        c, s = np.cos(X[:, 2]), np.sin(X[:, 2])
        u, v = c * d[:, 0] + s * d[:, 1], c * d[:, 1] - s * d[:, 0]
        return normalize_theta(z[:, 0] - np.arctan2(v, u))[:, None], d

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(poses (m, 3), points (m, 2))``.
            measurement: ``(m, 1)`` bearings.
            ctx: Unused.

        Returns:
            ``(e (m, 1), (J_pose (m, 1, 3), J_point (m, 1, 2)))``.
        """
        e, d = cls._parts(x, measurement, ctx)
        with np.errstate(divide="ignore", invalid="ignore"):
            g = d / np.einsum("mi,mi->m", d, d)[:, None]
        Jx = np.empty((len(e), 1, 3))
        Jx[:, 0, 0] = -g[:, 1]
        Jx[:, 0, 1] = g[:, 0]
        Jx[:, 0, 2] = 1.0
        Jp = np.stack([g[:, 1], -g[:, 0]], axis=1)[:, None, :]
        return Linearization(e, (Jx, Jp))


@dataclass(eq=False)
class ParameterSE2Offset:
    """A sensor offset on a 2D pose (g2o's ``ParameterSE2Offset``, tag ``PARAMS_SE2OFFSET``).

    Pass one object per parameter id as ``params``: edges are grouped by the object.

    Args:
        offset: ``(3,)`` ``[x, y, θ]`` of the sensor in the pose's frame (zero by default).
        id: Parameter id.
    """

    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    id: int = 0

    def __post_init__(self) -> None:
        self.offset = np.asarray(self.offset, dtype=float).reshape(3)

    @staticmethod
    def coerce(params: Any) -> ParameterSE2Offset:
        """The offset of a group: a :class:`ParameterSE2Offset`, or zero for ``None``.

        Args:
            params: ``ctx.params`` (or one element of a pair).
        """
        if params is None:
            return _ZERO_OFFSET
        if isinstance(params, ParameterSE2Offset):
            return params
        raise TypeError(f"expected a ParameterSE2Offset as params, got {type(params).__name__}")


_ZERO_OFFSET = ParameterSE2Offset()


class EdgeSE2Offset(EdgeFromParts):
    """Relative pose of two sensors on two :class:`VertexSE2` (g2o's ``EdgeSE2Offset``):
    ``e = t2v(Z⁻¹·(Xi·Pi)⁻¹·(Xj·Pj))`` ``(m, 3)``, :class:`EdgeSE2`'s error of the sensor
    poses; its Jacobians chained through ``∂(X·P)/∂X``.

    ``params``: the pair ``(Pi, Pj)`` of :class:`ParameterSE2Offset` (``None`` for zero; one
    offset alone is used at both ends); give edges that share it the same tuple.

    Args:
        vertices: ``(from, to)``.
        measurement: ``(3,)`` relative sensor pose ``[x, y, θ]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: ``(offset_from, offset_to)``.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexSE2)

    @classmethod
    def _sensors(cls, x: Sequence[np.ndarray], ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        p = ctx.params
        if p is None or isinstance(p, ParameterSE2Offset):
            pi = pj = ParameterSE2Offset.coerce(p)
        else:
            try:
                a, b = p
            except (TypeError, ValueError):
                raise TypeError("EdgeSE2Offset takes params=(offset_from, offset_to), got "
                                f"{type(p).__name__}") from None
            pi, pj = ParameterSE2Offset.coerce(a), ParameterSE2Offset.coerce(b)
        # One offset for every edge of the group.
        A, ra = _sensor_pose(x[0], np.broadcast_to(pi.offset, (len(x[0]), 3)))
        B, rb = _sensor_pose(x[1], np.broadcast_to(pj.offset, (len(x[1]), 3)))
        return A, B, ra, rb

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        A, B, _, _ = cls._sensors(x, ctx)
        return (EdgeSE2.error((A, B), z, EdgeContext()),)

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(Xi (m, 3), Xj (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``ctx.params``: the offsets.

        Returns:
            ``(e (m, 3), (J_i (m, 3, 3), J_j (m, 3, 3)))``.
        """
        A, B, ra, rb = cls._sensors(x, ctx)
        lin = EdgeSE2.linearize((A, B), measurement, EdgeContext())
        Ji, Jj = lin.jacobians
        return Linearization(lin.error, (_by_pose(Ji, ra), _by_pose(Jj, rb)))


class EdgeSE2PointXYOffset(EdgeSE2PointXY):
    """g2o's ``EdgeSE2PointXYOffset`` as g2o 2.3.0 evaluates it: its error is
    ``Xi⁻¹·p − z``, **without** the offset (its cache's ``w2l`` is the pose's inverse; checked
    with g2opy, whose chi2 this reproduces), i.e. :class:`EdgeSE2PointXY`'s. ``params`` (the
    :class:`ParameterSE2Offset`) is accepted and, like g2o, not used. The Jacobians are those
    of this error (g2o's own ``linearizeOplus`` includes the offset's rotation, which does not
    match its error).

    Args:
        vertices: ``(pose, point)``.
        measurement: ``(2,)``.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
        params: A :class:`ParameterSE2Offset` (unused).
    """


class EdgeSE2PointXYCalib(EdgeFromParts):
    """A 2D point seen through a sensor whose offset is estimated (g2o's
    ``EdgeSE2PointXYCalib``): ``e = (Xi·C)⁻¹·p − z`` ``(m, 2)``, ``C`` a :class:`VertexSE2`.

    With ``S = Xi·C`` (``t_S = t_i + R_i t_C``, ``θ_S = θ_i + θ_C``) and ``EdgeSE2PointXY``'s
    Jacobians ``(J_S, J_p)`` at ``S``: ``∂e/∂x_i = J_S·∂S/∂x_i``, ``∂e/∂p = J_p``,
    ``∂e/∂c = J_S·[[R_i, 0], [0, 1]]``.

    Args:
        vertices: ``(pose, point, calibration)``.
        measurement: ``(2,)``.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexPointXY, VertexSE2)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        return (EdgeSE2PointXY.error((_sensor_pose(x[0], x[2])[0], x[1]), z, EdgeContext()),)

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(poses (m, 3), points (m, 2), calibrations (m, 3))``.
            measurement: ``(m, 2)``.
            ctx: Unused.

        Returns:
            ``(e (m, 2), (J_pose (m, 2, 3), J_point (m, 2, 2), J_calib (m, 2, 3)))``.
        """
        S, rt = _sensor_pose(x[0], x[2])
        lin = EdgeSE2PointXY.linearize((S, x[1]), measurement, EdgeContext())
        JS, Jp = lin.jacobians
        return Linearization(lin.error, (_by_pose(JS, rt), Jp, _by_offset(JS, x[0][:, 2])))


class EdgeSE2LotsOfXY(BaseEdge):
    """One pose observing ``k`` 2D points at once (g2o's ``EdgeSE2LotsOfXY``): a family of
    types, one per ``k``, made by :meth:`of` (cached). :class:`EdgeSE2TwoPointsXY` is ``k = 2``
    under g2o's other name.

    Error ``(m, 2k)``: ``[Xi⁻¹·p_1 − z_1, …, Xi⁻¹·p_k − z_k]``; each pair of rows has
    :class:`EdgeSE2PointXY`'s Jacobians.

    Args:
        vertices: ``(pose, p_1, …, p_k)``.
        measurement: ``(2k,)``.
        information: ``(2k, 2k)``.
        robust_kernel: Optional robust kernel.
    """

    #: Points per edge (set on the classes :meth:`of` makes).
    points: ClassVar[int] = 0

    @staticmethod
    @cache
    def of(k: int) -> type[EdgeSE2LotsOfXY]:
        """The type of edges with ``k`` points.

        Args:
            k: Number of points, ``k ≥ 1``.
        """
        return points_family(EdgeSE2LotsOfXY, k, VertexSE2, VertexPointXY, 2)

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 2k)`` errors.

        Args:
            x: ``(poses (m, 3), p_1 (m, 2), …, p_k (m, 2))``.
            measurement: ``(m, 2k)``.
            ctx: Unused.
        """
        return cls.linearize(x, measurement, ctx, with_jacobians=False).error

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext, with_jacobians: bool = True) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: As in :meth:`error`.
            measurement: ``(m, 2k)``.
            ctx: Unused.
            with_jacobians: ``False`` for the errors alone.

        Returns:
            ``(e (m, 2k), (J_pose (m, 2k, 3), J_p1 (m, 2k, 2), …))``.
        """
        X = x[0]
        m, k = len(X), cls.points
        pts = np.stack(x[1:], axis=1)  # (m, k, 2)
        ctx0 = EdgeContext()
        # The errors alone need no Jacobians (and then run on jets: graphopt.autodiff).
        run = EdgeSE2PointXY.linearize if with_jacobians else EdgeSE2PointXY.evaluate
        lin = run((np.repeat(X, k, axis=0), pts.reshape(-1, 2)), measurement.reshape(-1, 2), ctx0)
        e = lin.error.reshape(m, 2 * k)
        if not with_jacobians:
            return Linearization(e)
        Jx, Jp = lin.jacobians
        out = [Jx.reshape(m, 2 * k, 3), *scatter_point_jacobians(Jp.reshape(m, k, 2, 2))]
        return Linearization(e, tuple(out))


class EdgeSE2TwoPointsXY(EdgeSE2LotsOfXY):
    """Two 2D points seen from a pose (g2o's ``EdgeSE2TwoPointsXY``): ``e = [Xi⁻¹·p_1 − z_1,
    Xi⁻¹·p_2 − z_2]`` ``(m, 4)``, :class:`EdgeSE2LotsOfXY` with ``k = 2``.

    Args:
        vertices: ``(pose, p_1, p_2)``.
        measurement: ``(4,)``.
        information: ``(4, 4)``.
        robust_kernel: Optional robust kernel.
    """

    points: ClassVar[int] = 2
    dimension: ClassVar[int] = 4
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexPointXY,
                                                             VertexPointXY)
