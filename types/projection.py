"""Pinhole reprojection edges (g2o's ``EdgeSE3ProjectXYZ`` / ``EdgeProjectXYZ2UV`` and an
inverse-depth variant) with analytic Jacobians.

Conventions (as in g2o's ``types_six_dof_expmap``):

* The pose vertex is :class:`~graphopt.types.vertices.VertexSE3Expmap`, ``T_cw`` (world to
  camera), updated as ``T ← exp(δ) T`` with ``δ = [ω, υ]``; the camera looks down +z (OpenCV).
* The error is ``measurement − project(P_c)`` (g2o's sign; χ² does not depend on it).
* Intrinsics ``fx, fy, cx, cy`` are shared by an edge group: pass a :class:`CameraParameters`
  (or a 4-sequence ``(fx, fy, cx, cy)``) as ``params`` to ``add_edges``.

Unlike g2o, whose ``EdgeSE3ProjectXYZ`` takes ``(point, pose)``, the vertex order here is
``(pose, point)`` — pose first, like the BAL edge — so that the marginalised vertex is always last.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError
from graphopt.lie import relative_transform, transform_points
from graphopt.types.pinhole import (
    monomial_pose_jacobian,
    normalised_projection,
    pose_jacobian,
    pose_jacobian_map,
    projected_rows,
    projection_base,
)
from graphopt.types.vertices import VertexPointInverseDepth, VertexPointXYZ, VertexSE3Expmap
from graphopt.vertex import BaseVertex

__all__ = [
    "CameraParameters",
    "camera_params",
    "monomial_pose_jacobian",
    "normalised_projection",
    "pose_jacobian",
    "projection_base",
    "pose_jacobian_map",
    "projected_rows",
    "EdgeInverseDepthProjection",
    "EdgeProjectXYZ2UV",
    "EdgeSE3ProjectXYZ",
]


@dataclass(frozen=True)
class CameraParameters:
    """Pinhole intrinsics in pixels.

    Args:
        fx: Focal length along x.
        fy: Focal length along y.
        cx: Principal point x.
        cy: Principal point y.
    """

    fx: float
    fy: float
    cx: float
    cy: float

    @cached_property
    def focal(self) -> np.ndarray:
        """``[fx, fy]`` (computed once: batched edges scale ``(m, 2)`` arrays by it)."""
        return np.array([self.fx, self.fy])

    @cached_property
    def centre(self) -> np.ndarray:
        """``[cx, cy]``."""
        return np.array([self.cx, self.cy])

    @classmethod
    def coerce(cls, params: Any) -> CameraParameters:
        """Accept a :class:`CameraParameters`, a mapping or a 4-sequence ``(fx, fy, cx, cy)``.

        Args:
            params: The edge group's ``ctx.params``.
        """
        if isinstance(params, CameraParameters):
            return params
        if params is None:
            raise ValueError("projection edges need params=CameraParameters(fx, fy, cx, cy)")
        if isinstance(params, dict):
            return cls(*(float(params[k]) for k in ("fx", "fy", "cx", "cy")))
        fx, fy, cx, cy = (float(v) for v in params)
        return cls(fx, fy, cx, cy)


def camera_params(etype: type, params: Any,
                  kind: type[CameraParameters] = CameraParameters) -> CameraParameters:
    """``kind.coerce(params)`` for an edge type, or a :class:`GraphError` naming the type.

    Args:
        etype: The edge type (for the message).
        params: The group's ``ctx.params``.
        kind: :class:`CameraParameters` or a subclass (stereo).
    """
    try:
        return kind.coerce(params)
    except (ValueError, TypeError, KeyError) as exc:
        raise GraphError(f"{etype.__name__} needs params={kind.__name__}(...), got {params!r} "
                         f"({exc})") from None


def _pinhole(
    h: tuple[np.ndarray, np.ndarray, np.ndarray], measurement: np.ndarray, cam: CameraParameters
) -> tuple[np.ndarray, np.ndarray]:
    """Error ``z − π(h)`` and ``∂e/∂h`` ``(m, 2, 3)`` for camera-frame (homogeneous) points."""
    e, iz, u, v = _pinhole_terms(h, measurement, cam)
    D = np.zeros((len(iz), 2, 3), like=iz)
    D[:, 0, 0] = -cam.fx * iz
    D[:, 0, 2] = cam.fx * u * iz
    D[:, 1, 1] = -cam.fy * iz
    D[:, 1, 2] = cam.fy * v * iz
    return e, D


def _pinhole_terms(
    h: tuple[np.ndarray, np.ndarray, np.ndarray], measurement: np.ndarray, cam: CameraParameters
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Error ``z − π(h)`` ``(m, 2)`` and the shared ``1/h_z``, ``u``, ``v`` ``(m,)`` (an error
    alone needs no ``∂e/∂h``: on jets, automatic differentiation records none of it)."""
    hx, hy, hz = h
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / hz
    u, v = hx * iz, hy * iz
    e = np.empty((len(hx), 2), like=hx)  # like=: jets stay jets (graphopt.autodiff)
    e[:, 0] = measurement[:, 0] - (cam.fx * u + cam.cx)
    e[:, 1] = measurement[:, 1] - (cam.fy * v + cam.cy)
    return e, iz, u, v


def _pinhole_error(P: np.ndarray, measurement: np.ndarray, ctx: EdgeContext) -> np.ndarray:
    """The error of :func:`_pinhole_ctx` alone."""
    cam = CameraParameters.coerce(ctx.params)
    return _pinhole_terms((P[:, 0], P[:, 1], P[:, 2]), measurement, cam)[0]


def _pinhole_ctx(
    P: np.ndarray, measurement: np.ndarray, ctx: EdgeContext
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_pinhole` for ``(m, 3)`` points with the intrinsics from ``ctx.params``."""
    return _pinhole((P[:, 0], P[:, 1], P[:, 2]), measurement, CameraParameters.coerce(ctx.params))


def _cross_matrix_rows(D: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``D · (−[p]×)`` for ``D`` ``(m, r, 3)``: row ``k`` becomes ``p × D_k``."""
    px, py, pz = p[:, 0, None], p[:, 1, None], p[:, 2, None]
    rx, ry, rz = D[:, :, 0], D[:, :, 1], D[:, :, 2]
    return np.stack([py * rz - pz * ry, pz * rx - px * rz, px * ry - py * rx], axis=2)


class EdgeSE3ProjectXYZ(BaseEdge):
    """Pinhole projection of a world point into a posed camera: ``e = z − π(K (R X + t))``.

    Vertices ``(VertexSE3Expmap T_cw, VertexPointXYZ X)``; ``params`` = :class:`CameraParameters`.
    Jacobians: pose ``∂e/∂P · [−[P]×, I]`` (left perturbation ``[ω, υ]``), point ``∂e/∂P · R``.

    Args:
        vertices: ``(pose, point)`` vertices or ids.
        measurement: ``(2,)`` pixel ``(u, v)``.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3Expmap, VertexPointXYZ)

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``z − π(P_c)`` for all edges.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params`` holds the intrinsics.
        """
        P = transform_points(x[0], x[1])
        return _pinhole_error(P, measurement, ctx)

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params`` holds the intrinsics.

        Returns:
            ``(e (m, 2), (J_pose (m, 2, 6), J_point (m, 2, 3)))``.
        """
        T, X = x
        P = transform_points(T, X)
        px, py, pz = P[:, 0], P[:, 1], P[:, 2]
        cam = CameraParameters.coerce(ctx.params)
        e, iz, u, v = _pinhole_terms((px, py, pz), measurement, cam)
        # ∂e/∂P has two zeros, rows (a, 0, b) and (0, c, d): the pose block [−[P]× rows, ∂e/∂P]
        # and the point block ∂e/∂P·R written entry by entry (no (m, 2, 3) products, no stacking:
        # the most frequent call of a BA; the pose block has the bits of the general formula).
        a, b = -cam.fx * iz, cam.fx * u * iz
        c, d = -cam.fy * iz, cam.fy * v * iz
        J_pose = np.empty((len(P), 2, 6))
        J_pose[:, 0, 0] = py * b
        J_pose[:, 0, 1] = pz * a - px * b
        J_pose[:, 0, 2] = -(py * a)
        J_pose[:, 0, 3], J_pose[:, 0, 4], J_pose[:, 0, 5] = a, 0.0, b
        J_pose[:, 1, 0] = py * d - pz * c
        J_pose[:, 1, 1] = -(px * d)
        J_pose[:, 1, 2] = px * c
        J_pose[:, 1, 3], J_pose[:, 1, 4], J_pose[:, 1, 5] = 0.0, c, d
        R = T[:, :3, :3]
        J_point = np.empty((len(P), 2, 3))
        J_point[:, 0] = a[:, None] * R[:, 0] + b[:, None] * R[:, 2]
        J_point[:, 1] = c[:, None] * R[:, 1] + d[:, None] * R[:, 2]
        return Linearization(e, (J_pose, J_point))

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """g2o's ``isDepthPositive``: ``(m,)`` True where the camera-frame point has ``z > 0``.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: ``(m, 2)`` (unused).
            ctx: Unused.
        """
        return transform_points(x[0], x[1])[:, 2] > 0


class EdgeProjectXYZ2UV(EdgeSE3ProjectXYZ):
    """g2o's name for the same pinhole reprojection edge (see :class:`EdgeSE3ProjectXYZ`).

    g2o's ``EdgeProjectXYZ2UV`` takes one focal length and a principal point from its
    ``CameraParameters``; pass ``CameraParameters(f, f, cx, cy)`` for that.

    Args:
        vertices: ``(pose, point)`` vertices or ids.
        measurement: ``(2,)`` pixel ``(u, v)``.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
    """


class EdgeInverseDepthProjection(BaseEdge):
    """Projection of an inverse-depth point into an observing camera.

    Vertices ``(anchor T_aw, observing T_cw, VertexPointInverseDepth [a, b, ρ])``. The point is
    ``X_a = [a, b, 1] / ρ`` in the anchor frame. With ``T_ca = T_cw T_aw⁻¹`` the projection is
    evaluated on the scaled point ``h = ρ P_c = R_ca [a, b, 1] + ρ t_ca`` (same pixel, since π is
    scale-invariant for ``ρ > 0``), which stays finite for points at infinity (``ρ → 0``).

    Jacobians of ``h`` (left perturbations ``[ω, υ]`` of both poses):
    observing ``[−[h]×, ρ I]``; anchor ``[R_ca [q]×, −ρ R_ca]`` with ``q = [a, b, 1]``;
    point ``[R_ca e_x, R_ca e_y, t_ca]``. When the observing camera is the anchor itself,
    ``T_ca = I`` and the two pose Jacobians cancel, as they should.

    Args:
        vertices: ``(anchor, observing, point)`` vertices or ids.
        measurement: ``(2,)`` pixel ``(u, v)``.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (
        VertexSE3Expmap,
        VertexSE3Expmap,
        VertexPointInverseDepth,
    )

    @classmethod
    def _scaled_point(
        cls, x: Sequence[np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        T_aw, T_cw, ip = x
        R_ca, t_ca = relative_transform(T_aw, T_cw)
        q = np.ones((len(ip), 3), like=ip)
        q[:, :2] = ip[:, :2]
        rho = ip[:, 2]
        h = np.einsum("nij,nj->ni", R_ca, q) + rho[:, None] * t_ca
        return h, R_ca, t_ca, q

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``z − π(h)`` for all edges.

        Args:
            x: ``(T_aw (m, 4, 4), T_cw (m, 4, 4), [a, b, ρ] (m, 3))``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params`` holds the intrinsics.
        """
        h = cls._scaled_point(x)[0]
        return _pinhole_error(h, measurement, ctx)

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians.

        Args:
            x: ``(T_aw, T_cw, [a, b, ρ])``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params`` holds the intrinsics.

        Returns:
            ``(e, (J_anchor (m, 2, 6), J_observing (m, 2, 6), J_point (m, 2, 3)))``.
        """
        h, R_ca, t_ca, q = cls._scaled_point(x)
        rho = x[2][:, 2]
        e, D = _pinhole_ctx(h, measurement, ctx)
        DR = D @ R_ca
        J_obs = np.concatenate([_cross_matrix_rows(D, h), rho[:, None, None] * D], axis=2)
        # D R_ca [q]× = −(D R_ca)(−[q]×): row r becomes −(q × r).
        J_anchor = np.concatenate([-_cross_matrix_rows(DR, q), -rho[:, None, None] * DR], axis=2)
        Dt = np.einsum("nij,nj->ni", D, t_ca)[:, :, None]
        J_point = np.concatenate([DR[:, :, :2], Dt], axis=2)
        return Linearization(e, (J_anchor, J_obs, J_point))

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``(m,)`` True where the point lies in front of the observing camera: ``h_z > 0``
        (``h = ρ P_c`` with ``ρ > 0``, so the sign is the depth's).

        Args:
            x: ``(T_aw, T_cw, [a, b, ρ])``.
            measurement: ``(m, 2)`` (unused).
            ctx: Unused.
        """
        return cls._scaled_point(x)[0][:, 2] > 0

