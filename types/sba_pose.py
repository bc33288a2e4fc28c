"""g2o's motion-only, stereo and pose-pose ``types/sba`` edges, as ORB-SLAM uses them:
``EdgeSE3ProjectXYZOnlyPose``, ``EdgeStereoSE3ProjectXYZ``,
``EdgeStereoSE3ProjectXYZOnlyPose`` and ``EdgeSE3Expmap``, with analytic Jacobians.

Conventions as :mod:`graphopt.types.projection`: poses are
:class:`~graphopt.types.vertices.VertexSE3Expmap` ``T_cw`` updated as ``exp([ω, υ]) T``, errors
are ``measurement − projection``, and a binary projection edge takes ``(pose, point)`` like
graphopt's :class:`~graphopt.types.projection.EdgeSE3ProjectXYZ` (g2o: ``(point, pose)``).

* The *only-pose* edges keep the world point of each edge in ``data={"Xw": (m, 3)}`` (g2o's
  ``Xw`` member) and the intrinsics in the group's ``params``.
* Stereo measurements are ``(u, v, u_r)`` with ``u_r = u − bf/z``; ``params`` is a
  :class:`StereoCameraParameters` ``(fx, fy, cx, cy, bf)``. g2o passes ``bf`` to the binary
  edge's projection as a ``float`` and rounds ``1/z`` to a ``float`` in the only-pose edge;
  these types compute in double (with a ``bf`` that a float holds exactly, such as 40.0,
  the binary edge's chi2 equals g2o's to ~1e-15; the only-pose edge's differs from g2o's by
  its float rounding, ~1e-7 of a pixel coordinate).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from graphopt.compiled import CompiledUnary, load
from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError
from graphopt.lie import transform_inverse, transform_points
from graphopt.types.projection import (
    CameraParameters,
    _pinhole_terms,
    camera_params,
    monomial_pose_jacobian,
    normalised_projection,
    pose_jacobian,
    projected_rows,
    projection_base,
)
from graphopt.types.sim3_lie import log_left_jacobian, se3quat_log, sim3_adjoint
from graphopt.types.vertices import VertexPointXYZ, VertexSE3Expmap
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgeSE3Expmap",
    "EdgeSE3ProjectXYZOnlyPose",
    "EdgeStereoSE3ProjectXYZ",
    "EdgeStereoSE3ProjectXYZOnlyPose",
    "StereoCameraParameters",
]


@dataclass(frozen=True)
class StereoCameraParameters(CameraParameters):
    """Rectified stereo intrinsics: the left camera's pinhole and ``bf`` = baseline × fx.

    Args:
        fx: Focal length along x (pixels).
        fy: Focal length along y.
        cx: Principal point x.
        cy: Principal point y.
        bf: Baseline times ``fx`` (pixels × metres).
    """

    bf: float = 0.0

    @classmethod
    def coerce(cls, params: Any) -> StereoCameraParameters:
        """Accept a :class:`StereoCameraParameters`, a mapping or a 5-sequence.

        Args:
            params: The edge group's ``ctx.params``.
        """
        if isinstance(params, StereoCameraParameters):
            return params
        if params is None or isinstance(params, CameraParameters):
            raise ValueError("stereo edges need the baseline: StereoCameraParameters(fx, fy, "
                             "cx, cy, bf)")
        if isinstance(params, dict):
            return cls(*(float(params[k]) for k in ("fx", "fy", "cx", "cy", "bf")))
        fx, fy, cx, cy, bf = (float(v) for v in params)
        return cls(fx, fy, cx, cy, bf)


def _world_points(ctx: EdgeContext, etype: type, m: int) -> np.ndarray:
    """``ctx.data["Xw"]`` ``(m, 3)``, or a :class:`GraphError` naming the type."""
    Xw = ctx.data.get("Xw")
    if Xw is None or np.shape(Xw) != (m, 3):
        got = "nothing" if Xw is None else f"shape {np.shape(Xw)}"
        raise GraphError(f"{etype.__name__} needs data={{'Xw': (m, 3) world points}}, got {got}")
    return Xw


def _stereo(P: np.ndarray, z: np.ndarray, cam: StereoCameraParameters) -> np.ndarray:
    """Error ``z − [u, v, u − bf/z]`` ``(m, 3)`` (the Jacobians: the edge's ``linearize``)."""
    e2 = _pinhole_terms((P[:, 0], P[:, 1], P[:, 2]), z, cam)[0]
    iz = 1.0 / P[:, 2]
    e = np.empty((len(P), 3), like=P)            # like=: jets stay jets (graphopt.autodiff)
    e[:, :2] = e2
    e[:, 2] = z[:, 2] - (z[:, 0] - e2[:, 0] - cam.bf * iz)
    return e


class _OnlyPose(BaseEdge):
    """Unary projection edges on one pose; the world point per edge in ``data["Xw"]``.

    The most frequent call of a SLAM system (every frame, every iteration), so written with
    few numpy calls: g2o's closed-form Jacobian rows as one product of per-edge monomials with
    a constant matrix (:func:`~graphopt.types.projection.pose_jacobian`), not ``∂e/∂P·[−[P]×, I]``.
    """

    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3Expmap,)
    stereo: ClassVar[bool] = False

    @classmethod
    def _point(cls, x: Sequence[np.ndarray], ctx: EdgeContext) -> np.ndarray:
        return transform_points(x[0], _world_points(ctx, cls, len(x[0])))

    @classmethod
    def _camera(cls, ctx: EdgeContext) -> tuple[CameraParameters, float | None]:
        """The intrinsics and ``bf`` (stereo) or ``None``."""
        cam = camera_params(cls, ctx.params, StereoCameraParameters if cls.stereo
                            else CameraParameters)
        return cam, cam.bf if cls.stereo else None  # type: ignore[attr-defined]

    @classmethod
    def _camera_point(cls, x: Sequence[np.ndarray], ctx: EdgeContext
                      ) -> tuple[np.ndarray, CameraParameters, float | None]:
        """The camera-frame points, the intrinsics and ``bf`` (stereo) or ``None``."""
        return cls._point(x, ctx), *cls._camera(ctx)

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``z − π(P_c)`` (stereo: ``z − [u, v, u_r]``) ``(m, 2|3)`` for all edges.

        Args:
            x: ``(T_cw (m, 4, 4),)``.
            measurement: ``(m, 2)`` pixels (stereo: ``(m, 3)``).
            ctx: ``params`` (intrinsics) and ``data["Xw"]``.
        """
        P, cam, bf = cls._camera_point(x, ctx)
        return normalised_projection(P, measurement, cam, bf)[0]

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and the analytic pose Jacobian ``(m, 2|3, 6)``.

        Args:
            x: ``(T_cw (m, 4, 4),)``.
            measurement: ``(m, 2)`` pixels (stereo: ``(m, 3)``).
            ctx: ``params`` and ``data["Xw"]``.
        """
        P, cam, bf = cls._camera_point(x, ctx)
        e, a = projection_base(P, measurement, cam, bf)
        return Linearization(e, (monomial_pose_jacobian(a, cam, bf),))

    @classmethod
    def compiled_unary(cls, measurement: np.ndarray, ctx: EdgeContext) -> CompiledUnary | None:
        """The loop of :mod:`graphopt.types.pose_only_compiled` (the same errors and Jacobian
        rows as :meth:`linearize`, to rounding), or ``None`` without numba.

        Args:
            measurement: ``(m, 2|3)`` pixels.
            ctx: ``params`` and ``data["Xw"]``.
        """
        mod = load("graphopt.types.pose_only_compiled")
        if mod is None:
            return None
        cam, bf = cls._camera(ctx)
        Xw = np.ascontiguousarray(_world_points(ctx, cls, len(measurement)), dtype=float)
        z = np.ascontiguousarray(measurement, dtype=float)
        params = np.array([cam.fx, cam.fy, cam.cx, cam.cy, bf or 0.0], dtype=float)
        return CompiledUnary(mod.pose_only_terms, (Xw, z, params), cls.dimension)

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """g2o's ``isDepthPositive``: ``(m,)`` True where ``(T_cw X_w)_z > 0``.

        Args:
            x: ``(T_cw (m, 4, 4),)``.
            measurement: Unused.
            ctx: ``ctx.data["Xw"]`` ``(m, 3)``.
        """
        return cls._point(x, ctx)[:, 2] > 0


class EdgeSE3ProjectXYZOnlyPose(_OnlyPose):
    """g2o's ``EdgeSE3ProjectXYZOnlyPose``: ``e = z − π(K T_cw X_w)``, the pose alone.

    Vertex ``(VertexSE3Expmap T_cw,)``; ``data={"Xw": (m, 3)}``; ``params`` =
    :class:`~graphopt.types.projection.CameraParameters` (g2o's ``fx, fy, cx, cy`` members).

    Args:
        vertices: ``(pose,)`` vertex or id.
        measurement: ``(2,)`` pixel.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
        data: ``{"Xw": (3,)}``.
    """

    dimension: ClassVar[int] = 2


class EdgeStereoSE3ProjectXYZOnlyPose(_OnlyPose):
    """g2o's ``EdgeStereoSE3ProjectXYZOnlyPose``: ``e = z − [u, v, u − bf/z]`` of ``T_cw X_w``.

    Vertex ``(VertexSE3Expmap T_cw,)``; ``data={"Xw": (m, 3)}``; ``params`` =
    :class:`StereoCameraParameters`.

    Args:
        vertices: ``(pose,)`` vertex or id.
        measurement: ``(3,)`` ``(u, v, u_r)``.
        information: ``(3, 3)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`StereoCameraParameters`.
        data: ``{"Xw": (3,)}``.
    """

    dimension: ClassVar[int] = 3
    stereo: ClassVar[bool] = True


class EdgeStereoSE3ProjectXYZ(BaseEdge):
    """g2o's ``EdgeStereoSE3ProjectXYZ``: ``e = z − [u, v, u − bf/z]`` of ``T_cw X``.

    Vertices ``(VertexSE3Expmap T_cw, VertexPointXYZ X)`` (g2o: ``(point, pose)``);
    ``params`` = :class:`StereoCameraParameters`.

    Args:
        vertices: ``(pose, point)`` vertices or ids.
        measurement: ``(3,)`` ``(u, v, u_r)``.
        information: ``(3, 3)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`StereoCameraParameters`.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3Expmap, VertexPointXYZ)

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``z − [u, v, u_r]`` for all edges.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``params``.
        """
        return _stereo(transform_points(x[0], x[1]), measurement,
                       camera_params(cls, ctx.params, StereoCameraParameters))

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians ``(m, 3, 6)`` and ``(m, 3, 3)``.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``params``.
        """
        T, X = x
        cam = camera_params(cls, ctx.params, StereoCameraParameters)
        e, iz, uv = normalised_projection(transform_points(T, X), measurement, cam,
                                          cam.bf)  # type: ignore[attr-defined]
        m = len(e)
        # ∂e/∂P·R: rows −f_r·iz·(R_r − uv_r·R_2), the third the first − bf·iz²·R_2.
        R = T[:, :3, :3]
        J_point = np.empty((m, 3, 3))
        J_point[:, :2] = projected_rows(R, iz, uv, cam)
        J_point[:, 2] = J_point[:, 0] - (cam.bf * iz * iz)[:, None] * R[:, 2]  # type: ignore[attr-defined]
        return Linearization(e, (pose_jacobian(iz, uv, cam, cam.bf), J_point))  # type: ignore[attr-defined]

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """g2o's ``isDepthPositive``: ``(m,)`` True where ``(T_cw X)_z > 0``.

        Args:
            x: ``(T_cw (m, 4, 4), X (m, 3))``.
            measurement: Unused.
            ctx: Unused.
        """
        return transform_points(x[0], x[1])[:, 2] > 0


class EdgeSE3Expmap(BaseEdge):
    """g2o's ``EdgeSE3Expmap``: ``e = log(T_j⁻¹ · T_ij · T_i)`` (g2o's ``SE3Quat::log``), 6-D.

    Vertices ``(T_i, T_j)`` (:class:`~graphopt.types.vertices.VertexSE3Expmap`, ``T_·w``); the
    measurement ``T_ij`` ``(4, 4)`` is what g2o's ``setMeasurement`` takes: ``T_j T_i⁻¹`` when
    exact (g2o's file format stores its inverse). Jacobians (exact, ``D`` the derivative of the
    log, :func:`~graphopt.types.sim3_lie.log_left_jacobian`): ``J_i = D·Ad(T_j⁻¹ T_ij)``,
    ``J_j = −D·Ad(T_j⁻¹)``; g2o uses ``D = I`` (exact at zero error).

    Args:
        vertices: ``(i, j)`` vertices or ids.
        measurement: ``(4, 4)`` rigid transform ``T_ij``.
        information: ``(6, 6)`` information matrix.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 6
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3Expmap, VertexSE3Expmap)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (4, 4)

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``log(T_j⁻¹ T_ij T_i)`` for all edges.

        Args:
            x: ``(T_i (m, 4, 4), T_j (m, 4, 4))``.
            measurement: ``(m, 4, 4)`` ``T_ij``.
            ctx: Unused.
        """
        return se3quat_log(transform_inverse(x[1]) @ measurement @ x[0])

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians ``(m, 6, 6)`` each.

        Args:
            x: ``(T_i, T_j)``.
            measurement: ``(m, 4, 4)`` ``T_ij``.
            ctx: Unused.
        """
        Tj_inv = transform_inverse(x[1])
        A = Tj_inv @ measurement
        E = A @ x[0]
        _, D = log_left_jacobian(E, scaled=False)
        J_i = D @ sim3_adjoint(A, scaled=False)
        J_j = -(D @ sim3_adjoint(Tj_inv, scaled=False))
        return Linearization(se3quat_log(E), (J_i, J_j))
