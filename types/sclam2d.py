"""g2o's ``types/sclam2d`` (calibration in 2D SLAM, exposed by the official ``g2opy`` wheel):
odometry through an estimated laser offset (``EdgeSE2SensorCalib``) and odometry of a
differential drive whose wheel factors and axle length are estimated
(``EdgeSE2OdomDifferentialCalib`` with ``VertexOdomDifferentialParams``).

Conventions of :mod:`graphopt.types.slam2d` (``[x, y, θ]`` poses, additive update, wrapped
angles).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.types.slam2d import (
    EdgeFromParts,
    EdgeSE2,
    VertexSE2,
    _by_offset,
    _by_pose,
    _sensor_pose,
)
from graphopt.vertex import BaseVertex, VertexVector

__all__ = [
    "EdgeSE2OdomDifferentialCalib",
    "EdgeSE2SensorCalib",
    "VertexOdomDifferentialParams",
    "differential_motion",
]


class EdgeSE2SensorCalib(EdgeFromParts):
    """Odometry of a sensor whose offset on the robot is estimated (g2o's
    ``EdgeSE2SensorCalib``): ``e = t2v(Z⁻¹·(X1·L)⁻¹·(X2·L))`` ``(m, 3)``, ``L`` a third
    :class:`VertexSE2`. Analytic Jacobians: :class:`EdgeSE2`'s of the sensor poses, chained.

    Args:
        vertices: ``(X1, X2, L)``.
        measurement: ``(3,)`` relative sensor pose.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexSE2, VertexSE2)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        A, _ = _sensor_pose(x[0], x[2])
        B, _ = _sensor_pose(x[1], x[2])
        return (EdgeSE2.error((A, B), z, EdgeContext()),)

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(X1 (m, 3), X2 (m, 3), L (m, 3))``.
            measurement: ``(m, 3)``.
            ctx: Unused.

        Returns:
            ``(e (m, 3), (J_1, J_2, J_L))``, each ``(m, 3, 3)``.
        """
        A, ra = _sensor_pose(x[0], x[2])
        B, rb = _sensor_pose(x[1], x[2])
        lin = EdgeSE2.linearize((A, B), measurement, EdgeContext())
        JA, JB = lin.jacobians
        JL = _by_offset(JA, x[0][:, 2]) + _by_offset(JB, x[1][:, 2])
        return Linearization(lin.error, (_by_pose(JA, ra), _by_pose(JB, rb), JL))


class VertexOdomDifferentialParams(VertexVector):
    """g2o's ``VertexOdomDifferentialParams``: ``[k_l, k_r, b]``, the left and right wheel
    factors and the axle length of a differential drive; additive update.

    Args:
        id: Vertex id.
        estimate: ``(3,)``.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 3


def differential_motion(vl: np.ndarray, vr: np.ndarray, dt: np.ndarray,
                        axle: np.ndarray) -> np.ndarray:
    """g2o's ``OdomConvert::convertToMotion``: the motion ``[x, y, θ]`` of a differential
    drive from its wheel speeds over ``dt`` (an arc; straight where ``|v_r − v_l| ≤ 1e-7``).

    Args:
        vl: ``(m,)`` left wheel speeds.
        vr: ``(m,)`` right wheel speeds.
        dt: ``(m,)`` durations.
        axle: ``(m,)`` axle lengths.

    Returns:
        ``(m, 3)`` motions.
    """
    turning = np.abs(vr - vl) > 1e-7
    dv = np.where(turning, vr - vl, 1.0)
    radius = axle * 0.5 * (vl + vr) / dv
    theta = np.where(turning, dv / axle * dt, 0.0)
    straight = 0.5 * (vr + vl) * dt
    x = np.where(turning, radius * np.sin(theta), straight)
    y = np.where(turning, radius * (1.0 - np.cos(theta)), 0.0)
    return np.column_stack([x, y, theta])


class EdgeSE2OdomDifferentialCalib(BaseEdge):
    """Wheel odometry with calibrated wheel factors and axle (g2o's
    ``EdgeSE2OdomDifferentialCalib``): with ``K = differential_motion(k_l·v_l, k_r·v_r, dt, b)``,
    ``e = t2v(K⁻¹·X1⁻¹·X2)`` ``(m, 3)``.

    **Numeric Jacobians** (the motion model's branches make the analytic ones long; g2o's are
    numeric too).

    Args:
        vertices: ``(X1, X2, params)`` (:class:`VertexOdomDifferentialParams`).
        measurement: ``(3,)`` ``[v_l, v_r, dt]`` (g2o's ``VelocityMeasurement``).
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (
        VertexSE2, VertexSE2, VertexOdomDifferentialParams)

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
              ctx: EdgeContext) -> np.ndarray:
        """``(m, 3)`` errors.

        Args:
            x: ``(X1 (m, 3), X2 (m, 3), params (m, 3))``.
            measurement: ``(m, 3)`` ``[v_l, v_r, dt]``.
            ctx: Unused.
        """
        k = x[2]
        K = differential_motion(measurement[:, 0] * k[:, 0], measurement[:, 1] * k[:, 1],
                                measurement[:, 2], k[:, 2])
        return EdgeSE2.error((x[0], x[1]), K, EdgeContext())
