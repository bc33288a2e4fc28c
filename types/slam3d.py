"""3D SLAM types after g2o's ``types/slam3d``: the ``VERTEX_SE3:QUAT`` pose, pose-pose edges,
point observations through a sensor offset (``PARAMS_SE3OFFSET``) and a pose prior, with
analytic Jacobians.

**Estimate layout.** A :class:`VertexSE3` estimate is a ``(3, 4)`` matrix ``[R | t]`` (the
top of g2o's ``Isometry3``; all poses of the type: ``(n, 3, 4)``), not ``[t, q]``:

* g2o keeps the matrix, builds it from a file's quaternion *as written* and composes matrices;
  keeping the same matrix is what makes chi2 agree with g2o's to ~1e-15 rather than ~1e-6
  (see :mod:`graphopt.types.isometry3`);
* the edges need rotation matrices anyway (to rotate translations, and in every Jacobian
  block); from quaternions each edge would first build two or three of them. The one
  quaternion an edge needs, that of its error rotation, is one matrix-to-quaternion conversion.

**Update** (g2o's ``VertexSE3::oplusImpl``): ``X ← X · Δ(δ)``, right-multiplied, where
``δ = [δt, δq]`` ``(n, 6)`` and ``Δ = [R(√(1 − |δq|²), δq) | δt]`` (``fromVectorMQT``; the
identity rotation where ``|δq| > 1``).

**Periodic re-normalisation.** g2o counts the updates of each vertex and applies
``R ← R − ½R(RᵀR − I)`` after every 1000th, against rounding drift. A batched ``oplus`` is a
pure function of the estimates it is given (numeric differentiation and rejected trial steps
call it too) and keeps no per-vertex count, so it re-normalises *by need* instead: every call
measures ``max |RᵀR − I|`` of each updated rotation (one stacked 3x3 product, ~15 % of
``oplus``) and applies g2o's step to those above :attr:`VertexSE3.orthonormalize_tolerance`
(``1e-5``). Rounding drift, ~1e-16 per update, stays far below that, as it does below g2o's
1000 updates; what it keeps is the deviation (≤ 4e-6) of a rotation built from a quaternion
written with 6 digits, which g2o keeps too. Re-normalising those at the first update instead
(tolerance ``0``: every call) moves the optimum of ``known_landmark_localization_20`` by
8e-6 relative from g2o's.

**Errors** are ``[t, q_vec]`` of a pose with the quaternion normalised and sign-flipped to
``q_w ≥ 0`` (g2o's ``toVectorMQT``): ``EdgeSE3`` ``Z⁻¹·Xi⁻¹·Xj``, ``EdgeSE3Prior``
``Z⁻¹·X·P``, and ``EdgeSE3PointXYZ`` ``(X·P)⁻¹·p − z``, ``P`` the sensor offset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import EdgeContext, Linearization
from graphopt.lie import hat
from graphopt.types.isometry3 import (
    compact_quaternion,
    from_compact_quaternion,
    orthonormalize,
    pose_from_qt,
    pose_to_qt,
)
from graphopt.types.slam2d import EdgeFromParts
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgeSE3",
    "EdgeSE3PointXYZ",
    "EdgeSE3Prior",
    "ParameterSE3Offset",
    "VertexSE3",
]


def _rt(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R (n, 3, 3), t (n, 3))`` views of ``(n, 3, 4)`` poses."""
    return T[:, :, :3], T[:, :, 3]


def _tr(R: np.ndarray) -> np.ndarray:
    return np.swapaxes(R, -1, -2)


def _mv(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R_i v_i`` for stacks of 3x3 matrices (or one matrix) and vectors."""
    return np.matmul(R, v[..., None])[..., 0]


def _mqt(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """g2o's ``toVectorMQT``: the ``(m, 6)`` error ``[t, q_vec]`` and ``Q = q_w I + [q_vec]×``
    ``(m, 3, 3)``, the derivative of ``q_vec`` under a right-multiplied rotation ``(1, u)``."""
    q = compact_quaternion(R)
    e = np.concatenate([t, q[:, :3]], axis=1)
    Q = hat(q[:, :3])
    Q[:, [0, 1, 2], [0, 1, 2]] = q[:, 3:4]
    return e, Q


class VertexSE3(BaseVertex):
    """A 3D pose (g2o's ``VertexSE3``, file tag ``VERTEX_SE3:QUAT``).

    Estimate layout ``(n, 3, 4)`` ``[R | t]``; increments ``(n, 6)`` ``[δt, δq]`` (see the
    module docstring for the update and the re-normalisation).

    Args:
        id: Vertex id.
        estimate: ``(3, 4)`` pose ``[R | t]`` (:func:`graphopt.types.isometry3.pose_from_qt`
            converts ``[x y z qx qy qz qw]``).
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 6
    estimate_shape: ClassVar[tuple[int, ...]] = (3, 4)
    #: Re-normalise the rotations that deviate from orthonormal by more than this (``0``:
    #: all, on every call); see the module docstring.
    orthonormalize_tolerance: ClassVar[float] = 1e-5

    @classmethod
    def oplus(cls, estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:  # type: ignore[override]
        """``X · Δ(δ)`` for all poses.

        Args:
            estimates: ``(n, 3, 4)`` poses.
            deltas: ``(n, 6)`` increments ``[δt, δq]``.

        Returns:
            ``(n, 3, 4)`` updated poses.
        """
        R, t = _rt(estimates)
        out = np.empty(estimates.shape, like=deltas)  # like=: a jet δ gives a jet
        out[:, :, :3] = orthonormalize(R @ from_compact_quaternion(deltas[:, 3:]),
                                       cls.orthonormalize_tolerance)
        out[:, :, 3] = t + _mv(R, deltas[:, :3])
        return out

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Finite, with ``|RᵀR − I| < 1e-4`` (a quaternion written with a few digits is
        accepted as g2o takes it) and ``det R > 0``.

        Args:
            estimates: ``(n, 3, 4)`` poses.
        """
        ok = super().validate(estimates)
        R = np.where(ok[:, None, None], estimates[:, :, :3], np.eye(3))
        orth = np.abs(_tr(R) @ R - np.eye(3)).max(axis=(1, 2)) < 1e-4
        return ok & orth & (np.linalg.det(R) > 0)


@dataclass(eq=False)
class ParameterSE3Offset:
    """A sensor offset ``P`` (g2o's ``ParameterSE3Offset``, file tag ``PARAMS_SE3OFFSET``):
    the sensor's pose in the frame of the vertex that carries it.

    Pass one object per parameter id as ``params`` of ``add_edges``: graphopt groups edges by
    ``(type, params object)``.

    Args:
        offset: ``(3, 4)`` ``[R | t]``; identity by default.
        id: The parameter id in the file.
    """

    offset: np.ndarray = field(default_factory=lambda: np.eye(3, 4))
    id: int = 0

    def __post_init__(self) -> None:
        self.offset = np.asarray(self.offset, dtype=float).reshape(3, 4)

    @classmethod
    def from_qt(cls, values: Any, id: int = 0) -> ParameterSE3Offset:
        """From ``[x y z qx qy qz qw]`` (quaternion as written, like g2o 2.3.0).

        Args:
            values: ``(7,)`` offset.
            id: Parameter id.
        """
        return cls(pose_from_qt(np.asarray(values, dtype=float).reshape(1, 7))[0], int(id))

    def to_qt(self) -> np.ndarray:
        """``(7,)`` ``[x y z qx qy qz qw]``."""
        return pose_to_qt(self.offset[None])[0]

    @staticmethod
    def coerce(params: Any) -> ParameterSE3Offset:
        """The edge group's offset: a :class:`ParameterSE3Offset`, or the identity for
        ``None``.

        Args:
            params: ``ctx.params``.
        """
        if params is None:
            return _IDENTITY_OFFSET
        if isinstance(params, ParameterSE3Offset):
            return params
        raise TypeError(f"expected a ParameterSE3Offset as params, got {type(params).__name__}")


_IDENTITY_OFFSET = ParameterSE3Offset()


class EdgeSE3(EdgeFromParts):
    """Relative pose between two :class:`VertexSE3` (g2o's ``EdgeSE3``, tag
    ``EDGE_SE3:QUAT``).

    Error ``e = toVectorMQT(Z⁻¹·Xi⁻¹·Xj)`` ``(m, 6)`` ``[t, q_vec]``, ``q_w ≥ 0``. With
    ``Y = Xi⁻¹Xj``, ``E = Z⁻¹Y`` and ``Q = q_w I + [q_vec]×`` of ``E``'s quaternion, the
    Jacobians for the right-multiplied update are ``∂e/∂δ_j = [[R_E, 0], [0, Q]]`` and
    ``∂e/∂δ_i = [[−R_Zᵀ, 2 R_Zᵀ [t_Y]×], [0, −Q R_Yᵀ]]``.

    Args:
        vertices: ``(from, to)`` vertices or ids.
        measurement: ``(3, 4)`` relative pose ``[R | t]``.
        information: ``(6, 6)`` information matrix (translation first).
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 6
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3, VertexSE3)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (3, 4)

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        (Ri, ti), (Rj, tj), (Rz, tz) = _rt(x[0]), _rt(x[1]), _rt(z)
        RiT, RzT = _tr(Ri), _tr(Rz)
        RY = RiT @ Rj
        tY = _mv(RiT, tj - ti)
        RE = RzT @ RY
        e, Q = _mqt(RE, _mv(RzT, tY - tz))
        return e, Q, RE, RY, RzT, tY

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(Xi (m, 3, 4), Xj (m, 3, 4))``.
            measurement: ``(m, 3, 4)`` relative poses.
            ctx: Unused.

        Returns:
            ``(e (m, 6), (J_i (m, 6, 6), J_j (m, 6, 6)))``.
        """
        e, Q, RE, RY, RzT, tY = cls._parts(x, measurement, ctx)
        m = len(e)
        Ji = np.zeros((m, 6, 6))
        Jj = np.zeros((m, 6, 6))
        Jj[:, :3, :3] = RE
        Jj[:, 3:, 3:] = Q
        Ji[:, :3, :3] = -RzT
        Ji[:, :3, 3:] = 2.0 * (RzT @ hat(tY))
        Ji[:, 3:, 3:] = -(Q @ _tr(RY))
        return Linearization(e, (Ji, Jj))


class EdgeSE3PointXYZ(EdgeFromParts):
    """A 3D point observed by a sensor on a pose (g2o's ``EdgeSE3PointXYZ``, tag
    ``EDGE_SE3_TRACKXYZ``).

    Error ``e = (X·P)⁻¹·p − z`` ``(m, 3)``, ``P`` the group's :class:`ParameterSE3Offset`
    (``params``; identity if ``None``): the point in the sensor frame minus the measurement. With
    ``p_X = R_Xᵀ(p − t_X)`` (the point in the pose frame), the Jacobians are
    ``∂e/∂δ = R_Pᵀ [−I, 2[p_X]×]`` and ``∂e/∂p = R_Pᵀ R_Xᵀ``.

    Args:
        vertices: ``(pose, point)`` vertices or ids.
        measurement: ``(3,)`` the point in the sensor frame.
        information: ``(3, 3)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: The :class:`ParameterSE3Offset`.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3, VertexPointXYZ)

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        RP, tP = _rt(ParameterSE3Offset.coerce(ctx.params).offset[None])
        (RX, tX), p = _rt(x[0]), x[1]
        RNT = _tr(RX @ RP[0])  # (X·P)⁻¹ rotation, as g2o's cache computes it
        tN = _mv(RX, np.broadcast_to(tP, tX.shape)) + tX
        return _mv(RNT, p - tN) - z, RX, RP[0], p - tX

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(poses (m, 3, 4), points (m, 3))``.
            measurement: ``(m, 3)`` points in the sensor frame.
            ctx: ``ctx.params``: the offset.

        Returns:
            ``(e (m, 3), (J_pose (m, 3, 6), J_point (m, 3, 3)))``.
        """
        e, RX, RP, d = cls._parts(x, measurement, ctx)
        RXT = _tr(RX)
        RPT = RP.T
        Jx = np.empty((len(e), 3, 6))
        Jx[:, :, :3] = -RPT
        Jx[:, :, 3:] = 2.0 * (RPT @ hat(_mv(RXT, d)))
        return Linearization(e, (Jx, RPT @ RXT))


class EdgeSE3Prior(EdgeFromParts):
    """A prior on a pose seen through a sensor offset (g2o's ``EdgeSE3Prior``).

    Error ``e = toVectorMQT(Z⁻¹·X·P)`` ``(m, 6)``, ``P`` the group's :class:`ParameterSE3Offset`
    (identity if ``params`` is ``None``). With ``E = Z⁻¹XP``, ``M = R_Zᵀ R_X`` and
    ``Q = q_w I + [q_vec]×`` of ``E``: ``∂e/∂δ = [[M, −2 M [t_P]×], [0, Q R_Pᵀ]]``.

    Args:
        vertices: ``(pose,)`` vertex or id.
        measurement: ``(3, 4)`` the prior pose of the sensor ``[R | t]``.
        information: ``(6, 6)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: The :class:`ParameterSE3Offset`.
    """

    dimension: ClassVar[int] = 6
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE3,)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (3, 4)

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        P = ParameterSE3Offset.coerce(ctx.params).offset
        (RX, tX), (Rz, tz) = _rt(x[0]), _rt(z)
        RzT = _tr(Rz)
        M = RzT @ RX
        e, Q = _mqt(M @ P[:, :3], _mv(RzT, _mv(RX, np.broadcast_to(P[:, 3], tX.shape))
                                          + tX - tz))
        return e, Q, M, P

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and the analytic Jacobian.

        Args:
            x: ``(poses (m, 3, 4),)``.
            measurement: ``(m, 3, 4)`` prior sensor poses.
            ctx: ``ctx.params``: the offset.

        Returns:
            ``(e (m, 6), (J (m, 6, 6),))``.
        """
        e, Q, M, P = cls._parts(x, measurement, ctx)
        J = np.zeros((len(e), 6, 6))
        J[:, :3, :3] = M
        J[:, :3, 3:] = -2.0 * (M @ hat(P[None, :, 3])[0])
        J[:, 3:, 3:] = Q @ P[:, :3].T
        return Linearization(e, (J,))
