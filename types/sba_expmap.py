"""The remaining projection edges of g2o's ``types_six_dof_expmap`` on
:class:`~graphopt.types.vertices.VertexSE3Expmap` poses: the stereo ``EdgeProjectXYZ2UVU`` and
the anchored inverse-depth ``EdgeProjectPSI2UV``, with g2o's ``CameraParameters`` (one focal
length, a principal point and a baseline) as :class:`SBACameraParameters`.

Conventions of :mod:`graphopt.types.projection`: ``T_cw`` poses updated as ``exp(δ)·T``,
``δ = [ω, υ]``; errors ``measurement − prediction`` (g2o's sign for these edges); the pose
before the point in the vertex order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.lie import transform_points
from graphopt.types.projection import (
    CameraParameters,
    EdgeInverseDepthProjection,
    _cross_matrix_rows,
)
from graphopt.types.sba_cam import stereo_projection
from graphopt.types.vertices import VertexPointXYZ, VertexSE3Expmap
from graphopt.vertex import BaseVertex

__all__ = ["EdgeProjectPSI2UV", "EdgeProjectXYZ2UVU", "SBACameraParameters"]


@dataclass(frozen=True)
class SBACameraParameters(CameraParameters):
    """g2o's ``CameraParameters`` (``types/sba``): pinhole intrinsics and a stereo baseline.

    g2o's has one focal length; :meth:`from_g2o` builds one from its arguments. Being a
    :class:`~graphopt.types.projection.CameraParameters`, it also serves the monocular edges.

    Args:
        fx: Focal length x.
        fy: Focal length y.
        cx: Principal point x.
        cy: Principal point y.
        baseline: Distance of the right camera along +x.
    """

    baseline: float = 0.0

    @classmethod
    def from_g2o(cls, focal_length: float, principal_point: Sequence[float],
                 baseline: float = 0.0) -> SBACameraParameters:
        """g2o's ``CameraParameters(focal_length, principle_point, baseline)``.

        Args:
            focal_length: Focal length (both axes).
            principal_point: ``(cx, cy)``.
            baseline: Stereo baseline.
        """
        cx, cy = (float(v) for v in principal_point)
        f = float(focal_length)
        return cls(f, f, cx, cy, float(baseline))

    @staticmethod
    def coerce_stereo(params: Any, name: str) -> SBACameraParameters:
        """The group's stereo parameters; a clear error for anything else.

        Args:
            params: ``ctx.params``.
            name: The edge type's name, for the message.
        """
        if isinstance(params, SBACameraParameters):
            return params
        raise TypeError(f"{name} needs params=SBACameraParameters(fx, fy, cx, cy, baseline), "
                        f"got {type(params).__name__}")


class EdgeProjectXYZ2UVU(BaseEdge):
    """Stereo projection of a world point into a posed camera (g2o's ``EdgeProjectXYZ2UVU``,
    whose own Jacobians are numeric): ``e = z − [u, v, u_r]`` ``(m, 3)`` of ``P = T p``, ``u_r``
    the right camera's column (g2o's ``stereocam_uvu_map``).

    Jacobians: ``−D·[−[P]×, I]`` (pose) and ``−D·R`` (point), ``D`` the projection's derivative.

    Args:
        vertices: ``(pose, point)`` (g2o: ``(point, pose)``).
        measurement: ``(3,)`` ``[u, v, u_right]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
        params: :class:`SBACameraParameters`.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3Expmap, VertexPointXYZ)

    @classmethod
    def _project(cls, x: Sequence[np.ndarray], z: np.ndarray,
                 ctx: EdgeContext) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = SBACameraParameters.coerce_stereo(ctx.params, cls.__name__)
        P = transform_points(x[0], x[1])
        k, D = stereo_projection(P, c.fx, c.fy, c.cx, c.cy, c.baseline)
        return z - k, D, P

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 3)`` errors.

        Args:
            x: ``(T_cw (m, 4, 4), points (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: ``ctx.params``: the :class:`SBACameraParameters`.
        """
        return cls._project(x, measurement, ctx)[0]

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: As in :meth:`error`.
            measurement: ``(m, 3)``.
            ctx: As in :meth:`error`.

        Returns:
            ``(e (m, 3), (J_pose (m, 3, 6), J_point (m, 3, 3)))``.
        """
        e, D, P = cls._project(x, measurement, ctx)
        J_pose = np.concatenate([-_cross_matrix_rows(D, P), -D], axis=2)
        return Linearization(e, (J_pose, -(D @ x[0][:, :3, :3])))


class EdgeProjectPSI2UV(EdgeInverseDepthProjection):
    """g2o's ``EdgeProjectPSI2UV``: a point by inverse depth ``ψ = [α, β, ρ]`` in an anchor
    camera, ``x_a = [α, β, 1]/ρ``, projected into an observing camera:
    ``e = z − π(T_cw·T_aw⁻¹·x_a)`` ``(m, 2)``.

    This is :class:`~graphopt.types.projection.EdgeInverseDepthProjection` (evaluated on
    ``ρ·P``, the same pixel for any ``ρ ≠ 0``) with g2o's vertex type for ``ψ``, a
    :class:`VertexPointXYZ` (no ``ρ > 0`` check), and the vertices in graphopt's order.
    ``params``: a :class:`~graphopt.types.projection.CameraParameters` (an
    :class:`SBACameraParameters` from g2o's ``CameraParameters``).

    Args:
        vertices: ``(anchor T_aw, observing T_cw, ψ)`` (g2o: ``(ψ, observing, anchor)``).
        measurement: ``(2,)`` pixel.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
        params: The intrinsics.
    """

    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (
        VertexSE3Expmap, VertexSE3Expmap, VertexPointXYZ)
