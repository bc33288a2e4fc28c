"""More of g2o's ``types/slam3d`` (the ones the official ``g2opy`` wheel exposes): point-point
and point priors, a translation prior on a pose, pose-pose edges through sensor offsets, depth
and disparity observations through a camera parameter, and the variable-arity
``EdgeSE3LotsOfXYZ``; all with analytic Jacobians.

Conventions are those of :mod:`graphopt.types.slam3d`: a :class:`~graphopt.types.slam3d.VertexSE3`
estimate is ``(3, 4)`` ``[R | t]`` updated as ``X·Δ(δ)`` with ``δ = [δt, δq]`` and
``R(δq) ≈ I + 2[δq]×``; a point vertex is :class:`~graphopt.types.vertices.VertexPointXYZ`.
Errors are g2o's (``estimate − measurement`` where g2o writes it so).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.lie import hat
from graphopt.types.point_edges import (
    PointDifferenceEdge,
    PointPriorEdge,
    points_family,
    scatter_point_jacobians,
)
from graphopt.types.slam2d import EdgeFromParts
from graphopt.types.slam3d import EdgeSE3, ParameterSE3Offset, VertexSE3, _mv, _tr
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgePointXYZ",
    "EdgeSE3LotsOfXYZ",
    "EdgeSE3Offset",
    "EdgeSE3PointXYZDepth",
    "EdgeSE3PointXYZDisparity",
    "EdgeSE3XYZPrior",
    "EdgeXYZPrior",
    "ParameterCamera",
]


class EdgePointXYZ(PointDifferenceEdge):
    """The difference of two 3D points (g2o's ``EdgePointXYZ``): ``e = p_j − p_i − z``.

    Jacobians ``−I`` and ``I`` (:class:`~graphopt.types.point_edges.PointDifferenceEdge`).

    Args:
        vertices: ``(p_i, p_j)`` :class:`VertexPointXYZ` or ids.
        measurement: ``(3,)`` expected ``p_j − p_i``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexPointXYZ, VertexPointXYZ)


class EdgeXYZPrior(PointPriorEdge):
    """A prior on a 3D point (g2o's ``EdgeXYZPrior``): ``e = p − z``, Jacobian ``I``
    (:class:`~graphopt.types.point_edges.PointPriorEdge`).

    Args:
        vertices: ``(point,)``.
        measurement: ``(3,)`` the prior position.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexPointXYZ,)


class EdgeSE3XYZPrior(BaseEdge):
    """A prior on the position of a 3D pose (g2o's ``EdgeSE3XYZPrior``): ``e = t_X − z``.

    g2o's edge takes a ``ParameterSE3Offset`` but its error (2.3.0, checked with g2opy) does not
    use it; ``params`` is accepted and ignored likewise. Jacobian ``[R_X, 0]`` (the translation
    increment is in the pose's frame).

    Args:
        vertices: ``(pose,)`` :class:`VertexSE3`.
        measurement: ``(3,)`` the prior position.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: Ignored (g2o's offset parameter).
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3,)

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 3)`` errors.

        Args:
            x: ``(poses (m, 3, 4),)``.
            measurement: ``(m, 3)``.
            ctx: Unused.
        """
        return x[0][:, :, 3] - measurement

    @classmethod
    def jacobians(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        """``([R_X, 0],)`` ``(m, 3, 6)``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: Unused.
        """
        J = np.zeros((len(measurement), 3, 6))
        J[:, :, :3] = x[0][:, :, :3]
        return (J,)


def _offset_adjoint(P: np.ndarray) -> np.ndarray:
    """``(6, 6)`` map of a pose increment ``δ`` to the increment of ``X·P``:
    ``P⁻¹Δ(δ)P = Δ(A δ)`` to first order, ``A = [[R_Pᵀ, −2R_Pᵀ[t_P]×], [0, R_Pᵀ]]``."""
    RPT = P[:, :3].T
    A = np.zeros((6, 6))
    A[:3, :3] = RPT
    A[:3, 3:] = -2.0 * RPT @ hat(P[None, :, 3])[0]
    A[3:, 3:] = RPT
    return A


def _compose(X: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``X·P`` for ``(m, 3, 4)`` poses and one ``(3, 4)`` offset."""
    out = X[:, :, :3] @ P
    out[:, :, 3] += X[:, :, 3]
    return out


def _offset_pair(params: Any) -> tuple[ParameterSE3Offset, ParameterSE3Offset]:
    if params is None:
        return ParameterSE3Offset.coerce(None), ParameterSE3Offset.coerce(None)
    if isinstance(params, ParameterSE3Offset):
        return params, params
    try:
        a, b = params
    except (TypeError, ValueError):
        raise TypeError("EdgeSE3Offset takes params=(offset_from, offset_to), two "
                        f"ParameterSE3Offset (or None), got {type(params).__name__}") from None
    return ParameterSE3Offset.coerce(a), ParameterSE3Offset.coerce(b)


class EdgeSE3Offset(EdgeFromParts):
    """Relative pose of two sensors on two :class:`VertexSE3` (g2o's ``EdgeSE3Offset``, tag
    ``EDGE_SE3_OFFSET``).

    Error ``e = toVectorMQT(Z⁻¹·(Xi·Pi)⁻¹·(Xj·Pj))`` ``(m, 6)``: :class:`EdgeSE3`'s error of
    the sensor poses ``A = Xi·Pi`` and ``B = Xj·Pj``. Since ``X·Δ(δ)·P = (X·P)·Δ(Aδ)`` to first
    order (``A`` of :func:`_offset_adjoint`), the Jacobians are EdgeSE3's of ``(A, B)`` times
    ``A_Pi`` and ``A_Pj``.

    ``params``: the pair ``(Pi, Pj)`` of :class:`ParameterSE3Offset` (``None`` for an identity;
    one offset alone is used at both ends). Edges are grouped by the ``params`` object: give
    edges that share the pair the same tuple.

    Args:
        vertices: ``(from, to)``.
        measurement: ``(3, 4)`` relative sensor pose ``[R | t]``.
        information: ``(6, 6)`` (translation first).
        robust_kernel: Optional robust kernel.
        params: ``(offset_from, offset_to)``.
    """

    dimension: ClassVar[int] = 6
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3, VertexSE3)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (3, 4)

    @classmethod
    def _sensor_poses(cls, x: Sequence[np.ndarray],
                      ctx: EdgeContext) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pi, pj = _offset_pair(ctx.params)
        return _compose(x[0], pi.offset), _compose(x[1], pj.offset), pi.offset, pj.offset

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        A, B, _, _ = cls._sensor_poses(x, ctx)
        return (EdgeSE3.error((A, B), z, EdgeContext()),)

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(Xi (m, 3, 4), Xj (m, 3, 4))``.
            measurement: ``(m, 3, 4)``.
            ctx: ``ctx.params``: the offsets.

        Returns:
            ``(e (m, 6), (J_i (m, 6, 6), J_j (m, 6, 6)))``.
        """
        A, B, pi, pj = cls._sensor_poses(x, ctx)
        lin = EdgeSE3.linearize((A, B), measurement, EdgeContext())
        Ji, Jj = lin.jacobians
        return Linearization(lin.error, (Ji @ _offset_adjoint(pi), Jj @ _offset_adjoint(pj)))


@dataclass(eq=False)
class ParameterCamera(ParameterSE3Offset):
    """A camera on a pose (g2o's ``ParameterCamera``, tag ``PARAMS_CAMERACALIB``): the sensor
    offset of :class:`ParameterSE3Offset` and pinhole intrinsics ``K``.

    g2o's defaults are ``fx = fy = 1``, ``cx = cy = 0.5``. Pass one object per parameter id as
    ``params``.

    Args:
        offset: ``(3, 4)`` camera pose in the vertex frame.
        id: Parameter id.
        fx: Focal length x.
        fy: Focal length y.
        cx: Principal point x.
        cy: Principal point y.
    """

    fx: float = 1.0
    fy: float = 1.0
    cx: float = 0.5
    cy: float = 0.5

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def coerce_camera(params: Any, name: str) -> ParameterCamera:
        """The group's camera; a clear error for anything else.

        Args:
            params: ``ctx.params``.
            name: The edge type's name, for the message.
        """
        if isinstance(params, ParameterCamera):
            return params
        raise TypeError(f"{name} needs params=ParameterCamera(...), got {type(params).__name__}")


class _EdgeSE3Camera(EdgeFromParts):
    """Shared part of the depth and disparity edges: ``h = K·(X·P)⁻¹·p`` and its derivatives
    ``∂h/∂δ = K R_Pᵀ [−I, 2[p_X]×]`` and ``∂h/∂p = K R_Pᵀ R_Xᵀ``, ``p_X = R_Xᵀ(p − t_X)``."""

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3, VertexPointXYZ)

    @classmethod
    def _third(cls, hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The third error component from ``h_z`` and its derivative by ``h_z``."""
        raise NotImplementedError

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        cam = ParameterCamera.coerce_camera(ctx.params, cls.__name__)
        P = cam.offset
        X, p = x
        RX = X[:, :, :3]
        RN = RX @ P[:, :3]  # (X·P)'s rotation, as g2o's cache forms the inverse
        tN = _mv(RX, np.broadcast_to(P[:, 3], p.shape)) + X[:, :, 3]
        h = _mv(cam.K @ _tr(RN), p - tN)
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / h[:, 2]
        third, dthird = cls._third(h[:, 2])
        e = np.empty((len(z), 3), like=h)  # like=: jets stay jets (graphopt.autodiff)
        e[:, 0] = h[:, 0] * iz - z[:, 0]
        e[:, 1] = h[:, 1] * iz - z[:, 1]
        e[:, 2] = third - z[:, 2]
        return e, h, iz, dthird, cam, RX

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(poses (m, 3, 4), points (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``ctx.params``: the :class:`ParameterCamera`.

        Returns:
            ``(e (m, 3), (J_pose (m, 3, 6), J_point (m, 3, 3)))``.
        """
        e, h, iz, dthird, cam, RX = cls._parts(x, measurement, ctx)
        m = len(e)
        D = np.zeros((m, 3, 3))  # ∂e/∂h
        D[:, 0, 0] = iz
        D[:, 0, 2] = -h[:, 0] * iz * iz
        D[:, 1, 1] = iz
        D[:, 1, 2] = -h[:, 1] * iz * iz
        D[:, 2, 2] = dthird
        DK = D @ (cam.K @ cam.offset[:, :3].T)
        pX = _mv(_tr(RX), x[1] - x[0][:, :, 3])
        Jx = np.empty((m, 3, 6))
        Jx[:, :, :3] = -DK
        Jx[:, :, 3:] = 2.0 * (DK @ hat(pX))
        return Linearization(e, (Jx, DK @ _tr(RX)))


class EdgeSE3PointXYZDepth(_EdgeSE3Camera):
    """A 3D point seen by a camera on a pose as pixel and depth (g2o's
    ``EdgeSE3PointXYZDepth``, tag ``EDGE_PROJECT_DEPTH``).

    With ``h = K·(X·P)⁻¹·p`` (``P``, ``K`` of the group's :class:`ParameterCamera`):
    ``e = [h_x/h_z, h_y/h_z, h_z] − z`` ``(m, 3)``.

    Args:
        vertices: ``(pose, point)``.
        measurement: ``(3,)`` ``[u, v, depth]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: The :class:`ParameterCamera`.
    """

    @classmethod
    def _third(cls, hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return hz, np.ones_like(hz)


class EdgeSE3PointXYZDisparity(_EdgeSE3Camera):
    """A 3D point seen by a camera on a pose as pixel and inverse depth (g2o's
    ``EdgeSE3PointXYZDisparity``, tag ``EDGE_PROJECT_DISPARITY``).

    With ``h = K·(X·P)⁻¹·p``: ``e = [h_x/h_z, h_y/h_z, 1/h_z] − z`` ``(m, 3)``.

    Args:
        vertices: ``(pose, point)``.
        measurement: ``(3,)`` ``[u, v, 1/depth]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: The :class:`ParameterCamera`.
    """

    @classmethod
    def _third(cls, hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / hz
        return iz, -iz * iz


class EdgeSE3LotsOfXYZ(BaseEdge):
    """One pose observing ``k`` points at once (g2o's ``EdgeSE3LotsOfXYZ``): a family of types,
    one per ``k``, made by :meth:`of` (``EdgeSE3LotsOfXYZ.of(4)``; cached, so every call with
    the same ``k`` returns the same class and its edges share one group).

    Error ``(m, 3k)``: ``[X⁻¹·p_1 − z_1, …, X⁻¹·p_k − z_k]`` (no sensor offset). With
    ``p_X = R_Xᵀ(p_i − t_X)``: ``∂e_i/∂δ = [−I, 2[p_X]×]``, ``∂e_i/∂p_i = R_Xᵀ``. The
    information is ``(3k, 3k)`` and may couple the points.

    Args:
        vertices: ``(pose, p_1, …, p_k)``.
        measurement: ``(3k,)``.
        information: ``(3k, 3k)``.
        robust_kernel: Optional robust kernel.
    """

    #: Points per edge (set on the classes :meth:`of` makes).
    points: ClassVar[int] = 0

    @staticmethod
    @cache
    def of(k: int) -> type[EdgeSE3LotsOfXYZ]:
        """The type of edges with ``k`` points.

        Args:
            k: Number of points, ``k ≥ 1``.
        """
        return points_family(EdgeSE3LotsOfXYZ, k, VertexSE3, VertexPointXYZ, 3)

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 3k)`` errors.

        Args:
            x: ``(poses (m, 3, 4), p_1 (m, 3), …, p_k (m, 3))``.
            measurement: ``(m, 3k)``.
            ctx: Unused.
        """
        X = x[0]
        P = np.stack(x[1:], axis=1) - X[:, None, :, 3]  # (m, k, 3)
        local = np.einsum("mji,mkj->mki", X[:, :, :3], P)
        return local.reshape(len(X), -1) - measurement

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: As in :meth:`error`.
            measurement: ``(m, 3k)``.
            ctx: Unused.

        Returns:
            ``(e (m, 3k), (J_pose (m, 3k, 6), J_p1 (m, 3k, 3), …))``.
        """
        X = x[0]
        m, k = len(X), cls.points
        RXT = _tr(X[:, :, :3])
        local = np.einsum("mij,mkj->mki", RXT, np.stack(x[1:], axis=1) - X[:, None, :, 3])
        e = local.reshape(m, -1) - measurement
        Jx = np.empty((m, k, 3, 6))
        Jx[:, :, :, :3] = -np.eye(3)
        Jx[:, :, :, 3:] = 2.0 * hat(local.reshape(-1, 3)).reshape(m, k, 3, 3)
        Jp = np.broadcast_to(RXT[:, None], (m, k, 3, 3))  # every point's block is R_Xᵀ
        return Linearization(e, (Jx.reshape(m, 3 * k, 6), *scatter_point_jacobians(Jp)))
