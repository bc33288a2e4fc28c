"""g2o's ``types/icp``: generalised-ICP point correspondences between two
:class:`~graphopt.types.slam3d.VertexSE3` (``Edge_V_V_GICP``, the wheel's ``EdgeVVGicp``, with
its measurement ``EdgeGICP``), and the stereo camera ``VertexSCam`` with its projection edge
``Edge_XYZ_VSC`` (the wheel's ``EdgeXyzVsc``). Analytic Jacobians.

**GICP.** A measurement pairs a point ``pos0`` in the frame of vertex 0 with ``pos1`` in the
frame of vertex 1 (and their surface normals, which only shape the information). The error is
``e = X0⁻¹·X1·pos1 − pos0``. g2o's ``pl_pl`` mode (plane to plane) replaces the information,
at every evaluation, by ``(cov0 + R cov1 Rᵀ)⁻¹`` with ``R`` the rotation of ``X0⁻¹X1``; here
that is its own type, :class:`EdgeVVGicpPlaneToPlane`, which whitens the error by that matrix
(``e_w = Lᵀe``, ``LLᵀ = (cov0 + R cov1 Rᵀ)⁻¹``; ``e_wᵀe_w`` is g2o's chi2) and treats ``L`` as
constant in its Jacobians, as g2o's linearisation treats the information. Its information
must be the identity.

:func:`gicp_normal_frame`, :func:`gicp_precision` and :func:`gicp_covariance` are ``EdgeGICP``'s
``makeRot0``, ``prec0`` and ``cov0`` over many normals at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import EdgeContext, Linearization
from graphopt.errors import GraphError
from graphopt.lie import hat
from graphopt.types.sba_cam import stereo_projection
from graphopt.types.slam2d import EdgeFromParts
from graphopt.types.slam3d import VertexSE3
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgeVVGicp",
    "EdgeVVGicpPlaneToPlane",
    "EdgeXyzVsc",
    "SCamParameters",
    "VertexSCam",
    "gicp_covariance",
    "gicp_normal_frame",
    "gicp_precision",
]

#: ``EdgeGICP::ySquaredBnd``: below it the frame is built from the x axis instead of y.
_Y_SQUARED_BOUND = 0.1


def gicp_normal_frame(normals: np.ndarray) -> np.ndarray:
    """``EdgeGICP::makeRot0``: rotations whose third row is the normal.

    Args:
        normals: ``(n, 3)`` unit normals.

    Returns:
        ``(n, 3, 3)`` rotations ``R`` (rows: two tangent directions, the normal).
    """
    n = np.asarray(normals, dtype=float)
    R = np.empty((len(n), 3, 3))
    R[:, 2] = n
    y = np.array([0.0, 1.0, 0.0]) - n[:, 1:2] * n
    y2 = np.einsum("ni,ni->n", y, y)
    use_y = y2 >= _Y_SQUARED_BOUND
    with np.errstate(divide="ignore", invalid="ignore"):
        R[:, 1] = y / np.sqrt(y2)[:, None]
        R[:, 0] = np.cross(n, R[:, 1])
        x = np.array([-1.0, 0.0, 0.0]) + n[:, 0:1] * n
        x = x / np.linalg.norm(x, axis=1, keepdims=True)
    other = ~use_y
    if other.any():
        R[other, 0] = x[other]
        R[other, 1] = -np.cross(n[other], x[other])
    return R


def gicp_precision(normals: np.ndarray, e: float) -> np.ndarray:
    """``EdgeGICP::prec0(e)``: ``Rᵀ diag(e, e, 1) R`` (tight along the normal).

    Args:
        normals: ``(n, 3)`` unit normals.
        e: Weight of the tangent directions.

    Returns:
        ``(n, 3, 3)`` information matrices.
    """
    R = gicp_normal_frame(normals)
    return np.swapaxes(R, 1, 2) @ (np.array([e, e, 1.0])[:, None] * R)


def gicp_covariance(normals: np.ndarray, e: float) -> np.ndarray:
    """``EdgeGICP::cov0(e)``: ``Rᵀ diag(1, 1, e) R`` (small along the normal).

    Args:
        normals: ``(n, 3)`` unit normals.
        e: Variance along the normal.

    Returns:
        ``(n, 3, 3)`` covariance matrices.
    """
    R = gicp_normal_frame(normals)
    return np.swapaxes(R, 1, 2) @ (np.array([1.0, 1.0, e])[:, None] * R)


def _relative(x: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` of ``X0⁻¹·X1``."""
    X0, X1 = x
    R0T = np.swapaxes(X0[:, :, :3], 1, 2)
    return R0T @ X1[:, :, :3], np.matmul(R0T, (X1[:, :, 3] - X0[:, :, 3])[:, :, None])[:, :, 0]


class EdgeVVGicp(EdgeFromParts):
    """A GICP correspondence between two poses (g2o's ``Edge_V_V_GICP`` with ``pl_pl`` off):
    ``e = X0⁻¹·X1·pos1 − pos0`` ``(m, 3)`` with the given information (g2o's examples set
    ``EdgeGICP.prec0(ε)``, :func:`gicp_precision`).

    With ``y = X0⁻¹X1·pos1`` and ``R = R0ᵀR1``: ``∂e/∂δ_0 = [−I, 2[y]×]``,
    ``∂e/∂δ_1 = [R, −2R[pos1]×]``.

    Args:
        vertices: ``(X0, X1)``.
        measurement: ``(2, 3)`` ``[pos0, pos1]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3, VertexSE3)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (2, 3)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        R, t = _relative(x)
        y = np.matmul(R, z[:, 1, :, None])[:, :, 0] + t
        return y - z[:, 0], y, R

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(X0 (m, 3, 4), X1 (m, 3, 4))``.
            measurement: ``(m, 2, 3)``.
            ctx: Unused.

        Returns:
            ``(e (m, 3), (J_0 (m, 3, 6), J_1 (m, 3, 6)))``.
        """
        e, y, R = cls._parts(x, measurement, ctx)
        m = len(e)
        J0 = np.empty((m, 3, 6))
        J0[:, :, :3] = -np.eye(3)
        J0[:, :, 3:] = 2.0 * hat(y)
        J1 = np.empty((m, 3, 6))
        J1[:, :, :3] = R
        J1[:, :, 3:] = -2.0 * (R @ hat(measurement[:, 1]))
        return Linearization(e, (J0, J1))


class EdgeVVGicpPlaneToPlane(EdgeVVGicp):
    """g2o's ``Edge_V_V_GICP`` with ``pl_pl = true``: the error of :class:`EdgeVVGicp`
    whitened by ``(cov0 + R cov1 Rᵀ)⁻¹``, ``R`` the rotation of ``X0⁻¹X1``, recomputed at every
    evaluation as g2o does (see the module docstring). Per-edge ``data``: ``cov0``, ``cov1``
    ``(3, 3)`` (g2o's ``Edge_V_V_GICP.cov0/cov1``, e.g. :func:`gicp_covariance`). The
    information must be the identity (g2o overwrites it).

    Args:
        vertices: ``(X0, X1)``.
        measurement: ``(2, 3)`` ``[pos0, pos1]``.
        information: The identity.
        robust_kernel: Optional robust kernel.
        data: ``{"cov0": (3, 3), "cov1": (3, 3)}``.
    """

    @classmethod
    def _whitener(cls, R: np.ndarray, ctx: EdgeContext) -> np.ndarray:
        """``Lᵀ`` ``(m, 3, 3)`` with ``LLᵀ = (cov0 + R cov1 Rᵀ)⁻¹``."""
        try:
            c0, c1 = ctx.data["cov0"], ctx.data["cov1"]
        except KeyError:
            raise GraphError(f"{cls.__name__} needs data={{'cov0': ..., 'cov1': ...}} "
                             "(per-edge 3x3 covariances)") from None
        C = c0 + R @ c1 @ np.swapaxes(R, 1, 2)
        # (LLᵀ)⁻¹ = C: with C = GGᵀ (Cholesky), L = G⁻ᵀ, so Lᵀ = G⁻¹.
        G = np.linalg.cholesky(C)
        return np.linalg.inv(G)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        e, y, R = super()._parts(x, z, ctx)
        W = cls._whitener(R, ctx)
        return np.matmul(W, e[:, :, None])[:, :, 0], y, R, W

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Whitened errors and Jacobians (``Lᵀ`` held constant).

        Args:
            x: ``(X0 (m, 3, 4), X1 (m, 3, 4))``.
            measurement: ``(m, 2, 3)``.
            ctx: ``ctx.data``: ``cov0``, ``cov1``.

        Returns:
            ``(e_w (m, 3), (J_0 (m, 3, 6), J_1 (m, 3, 6)))``.
        """
        ew, _, _, W = cls._parts(x, measurement, ctx)
        J0, J1 = EdgeVVGicp.linearize(x, measurement, ctx).jacobians
        return Linearization(ew, (W @ J0, W @ J1))


class VertexSCam(VertexSE3):
    """g2o's stereo camera vertex ``VertexSCam``: a :class:`VertexSE3` (the camera's pose in
    the world, same layout and update). g2o keeps the intrinsics in static members; here they
    are the :class:`SCamParameters` of the :class:`EdgeXyzVsc` group.

    Args:
        id: Vertex id.
        estimate: ``(3, 4)`` ``[R | t]``.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """


@dataclass(frozen=True)
class SCamParameters:
    """``VertexSCam``'s static ``Kcam`` and ``baseline`` (g2o's ``VertexSCam::setKcam``).

    Args:
        fx: Focal length x.
        fy: Focal length y.
        cx: Principal point x.
        cy: Principal point y.
        baseline: Stereo baseline (right camera at ``+baseline`` along x).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float

    @staticmethod
    def coerce(params: Any) -> SCamParameters:
        """The group's parameters: an :class:`SCamParameters` or ``(fx, fy, cx, cy, b)``.

        Args:
            params: ``ctx.params``.
        """
        if isinstance(params, SCamParameters):
            return params
        if params is None:
            raise TypeError("EdgeXyzVsc needs params=SCamParameters(fx, fy, cx, cy, baseline)")
        return SCamParameters(*(float(v) for v in params))


class EdgeXyzVsc(EdgeFromParts):
    """Stereo projection into a :class:`VertexSCam` (g2o's ``Edge_XYZ_VSC``, ``EdgeXyzVsc``):
    ``e = [u, v, u_r] − z`` ``(m, 3)`` of ``p_c = X⁻¹·p`` (``VertexSCam::mapPoint``).

    Jacobians: ``D·[−I, 2[p_c]×]`` (camera) and ``D·Rᵀ`` (point), ``D`` the projection's
    derivative (:func:`~graphopt.types.sba_cam.stereo_projection`).

    Args:
        vertices: ``(camera, point)`` (g2o: ``(point, camera)``).
        measurement: ``(3,)`` ``[u, v, u_right]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: :class:`SCamParameters`.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSCam, VertexPointXYZ)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        c = SCamParameters.coerce(ctx.params)
        X, p = x
        RT = np.swapaxes(X[:, :, :3], 1, 2)
        pc = np.matmul(RT, (p - X[:, :, 3])[:, :, None])[:, :, 0]
        k, D = stereo_projection(pc, c.fx, c.fy, c.cx, c.cy, c.baseline)
        return k - z, D, pc, RT

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(cameras (m, 3, 4), points (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``ctx.params``: the :class:`SCamParameters`.

        Returns:
            ``(e (m, 3), (J_camera (m, 3, 6), J_point (m, 3, 3)))``.
        """
        e, D, pc, RT = cls._parts(x, measurement, ctx)
        Jc = np.concatenate([-D, 2.0 * (D @ hat(pc))], axis=2)
        return Linearization(e, (Jc, D @ RT))
