"""g2o's sparse-bundle-adjustment camera (``types/sba``: ``VertexCam`` holding an ``SBACam``)
and its edges: monocular and stereo projections (``EdgeProjectP2MC``, ``EdgeProjectP2SC``),
relative pose (``EdgeSBACam``) and distance (``EdgeSBAScale``) between cameras; and
``VertexIntrinsics``. Analytic Jacobians.

**The camera.** A :class:`VertexCam` estimate is ``(12,)``
``[tx ty tz qx qy qz qw fx fy cx cy baseline]``: g2o's ``SBACam``, the camera's pose in the
world (camera to world: ``R(q)``, ``t``) followed by its intrinsics ``K`` and stereo baseline,
which g2o keeps in the estimate too and never updates. World points map to the camera as
``p_c = Rᵀ(p − t)`` (g2o's ``w2n``) and to the image as ``K p_c`` (``w2i``).

**Update** (g2o's ``SBACam::update``): ``t ← t + δt`` (world frame) and
``q ← normalise(q ⊗ (√(1 − |δq|²), δq))``, ``δ = [δt, δq]``; so ``∂p_c/∂δ = [−Rᵀ, 2[p_c]×]``
and ``∂p_c/∂p = Rᵀ``.

**Vertex order.** g2o's projection edges take ``(point, camera)``; here the camera comes first,
``(camera, point)``, like graphopt's other projection edges (the marginalised vertex last).
Errors are g2o's, ``prediction − measurement``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from graphopt.edge import EdgeContext, Linearization
from graphopt.lie import hat, quat_to_rot
from graphopt.types.slam2d import EdgeFromParts
from graphopt.types.slam3d import EdgeSE3
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgeProjectP2MC",
    "EdgeProjectP2SC",
    "EdgeSBACam",
    "EdgeSBAScale",
    "VertexCam",
    "VertexIntrinsics",
    "stereo_projection",
]


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a ⊗ b`` of ``(n, 4)`` ``[x, y, z, w]`` quaternions."""
    av, aw, bv, bw = a[:, :3], a[:, 3:], b[:, :3], b[:, 3:]
    # concatenated, not written into np.empty_like(a): a jet b gives a jet (graphopt.autodiff)
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv),
                           aw * bw - np.einsum("ni,ni->n", av, bv)[:, None]], axis=1)


class VertexCam(BaseVertex):
    """g2o's ``VertexCam``: an ``SBACam`` pose with fixed intrinsics (see the module
    docstring for the layout and the update).

    Estimate ``(n, 12)`` ``[t (3), q (4, xyzw), fx, fy, cx, cy, baseline]``; increments
    ``(n, 6)`` ``[δt, δq]``. :meth:`derived` gives each camera's ``Rᵀ`` (world to camera) to
    its edges.

    Args:
        id: Vertex id.
        estimate: ``(12,)`` (:meth:`make` builds one).
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 6
    estimate_shape: ClassVar[tuple[int, ...]] = (12,)

    @staticmethod
    def make(t: Sequence[float], q: Sequence[float], fx: float = 1.0, fy: float = 1.0,
             cx: float = 0.5, cy: float = 0.5, baseline: float = 0.0) -> np.ndarray:
        """One ``(12,)`` estimate (g2o's ``SBACam`` defaults for the intrinsics).

        Args:
            t: ``(3,)`` camera position in the world.
            q: ``(4,)`` orientation ``[qx, qy, qz, qw]`` (camera to world; normalised here).
            fx: Focal length x.
            fy: Focal length y.
            cx: Principal point x.
            cy: Principal point y.
            baseline: Stereo baseline.
        """
        qq = np.asarray(q, dtype=float)
        return np.concatenate([np.asarray(t, float), qq / np.linalg.norm(qq),
                               [fx, fy, cx, cy, baseline]])

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """g2o's ``SBACam::update`` for all cameras (the identity rotation where
        ``|δq| > 1``, where g2o would take the root of a negative number).

        Args:
            estimates: ``(n, 12)``.
            deltas: ``(n, 6)`` ``[δt, δq]``.
        """
        out = np.empty(estimates.shape, like=deltas)  # like=: a jet δ gives a jet
        out[...] = estimates
        out[:, :3] += deltas[:, :3]
        w2 = 1.0 - np.einsum("ni,ni->n", deltas[:, 3:], deltas[:, 3:])
        dq = np.where((w2 < 0.0)[:, None], [0.0, 0.0, 0.0, 1.0],
                      np.column_stack([deltas[:, 3:], np.sqrt(np.maximum(w2, 0.0))]))
        q = _quat_mul(estimates[:, 3:7], dq)
        out[:, 3:7] = q / np.linalg.norm(q, axis=1, keepdims=True)
        return out

    @classmethod
    def derived(cls, estimates: np.ndarray) -> np.ndarray:
        """``Rᵀ`` per camera, flattened ``(n, 9)``.

        Args:
            estimates: ``(n, 12)``.
        """
        return np.swapaxes(quat_to_rot(estimates[:, 3:7]), 1, 2).reshape(-1, 9)

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Finite with a non-zero quaternion.

        Args:
            estimates: ``(n, 12)``.
        """
        return super().validate(estimates) & (np.abs(estimates[:, 3:7]).sum(axis=1) > 0)


def _camera_frame(cam: np.ndarray, p: np.ndarray,
                  ctx: EdgeContext) -> tuple[np.ndarray, np.ndarray]:
    """``(p_c (m, 3), Rᵀ (m, 3, 3))`` of world points in their cameras."""
    d = ctx.derived[0] if ctx.derived is not None else None
    RT = (d.reshape(-1, 3, 3) if d is not None
          else np.swapaxes(quat_to_rot(cam[:, 3:7]), 1, 2))
    return np.matmul(RT, (p - cam[:, :3])[:, :, None])[:, :, 0], RT


def stereo_projection(pc: np.ndarray, fx: np.ndarray | float, fy: np.ndarray | float,
                      cx: np.ndarray | float, cy: np.ndarray | float,
                      baseline: np.ndarray | float | None) -> tuple[np.ndarray, np.ndarray]:
    """g2o's projection of camera-frame points: ``[u, v]`` of ``K p_c`` and, with a baseline,
    the right camera's ``u_r`` of ``K (p_c − [b, 0, 0])``; and its derivative by ``p_c``.

    Args:
        pc: ``(m, 3)`` points in the camera frame.
        fx: Focal length x (scalar or ``(m,)``); likewise ``fy``, ``cx``, ``cy``.
        fy: Focal length y.
        cx: Principal point x.
        cy: Principal point y.
        baseline: ``None`` for the monocular ``[u, v]``; else the baseline (scalar or ``(m,)``).

    Returns:
        ``(k (m, 2 or 3), ∂k/∂p_c (m, 2 or 3, 3))``.
    """
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / z
    rows = 2 if baseline is None else 3
    k = np.empty((len(pc), rows), like=pc)  # like=: jets stay jets (graphopt.autodiff)
    D = np.zeros((len(pc), rows, 3), like=pc)
    k[:, 0] = fx * x * iz + cx
    k[:, 1] = fy * y * iz + cy
    D[:, 0, 0] = fx * iz
    D[:, 0, 2] = -fx * x * iz * iz
    D[:, 1, 1] = fy * iz
    D[:, 1, 2] = -fy * y * iz * iz
    if baseline is not None:
        k[:, 2] = fx * (x - baseline) * iz + cx
        D[:, 2, 0] = D[:, 0, 0]
        D[:, 2, 2] = -fx * (x - baseline) * iz * iz
    return k, D


class EdgeProjectP2MC(EdgeFromParts):
    """Monocular projection into a :class:`VertexCam` (g2o's ``EdgeProjectP2MC``):
    ``e = π(K_c R_cᵀ(p − t_c)) − z`` ``(m, 2)``, the camera's own intrinsics.

    Args:
        vertices: ``(camera, point)`` (g2o: ``(point, camera)``).
        measurement: ``(2,)`` pixel.
        information: ``(2, 2)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexCam, VertexPointXYZ)
    uses_derived: ClassVar[bool] = True
    #: The stereo projection (a third row, the right camera's column).
    _stereo: ClassVar[bool] = False

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        cam, p = x
        pc, RT = _camera_frame(cam, p, ctx)
        k, D = stereo_projection(pc, cam[:, 7], cam[:, 8], cam[:, 9], cam[:, 10],
                                 cam[:, 11] if cls._stereo else None)
        return k - z, D, pc, RT

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(cameras (m, 12), points (m, 3))``.
            measurement: ``(m, 2)`` (``(m, 3)`` stereo).
            ctx: ``derived``: the cameras' ``Rᵀ`` when the optimizer has them.

        Returns:
            ``(e, (J_camera (m, r, 6), J_point (m, r, 3)))``.
        """
        e, D, pc, RT = cls._parts(x, measurement, ctx)
        DR = D @ RT
        Jc = np.concatenate([-DR, 2.0 * (D @ hat(pc))], axis=2)
        return Linearization(e, (Jc, DR))


class EdgeProjectP2SC(EdgeProjectP2MC):
    """Stereo projection into a :class:`VertexCam` (g2o's ``EdgeProjectP2SC``):
    ``e = [u, v, u_r] − z`` ``(m, 3)``, ``u_r`` the right camera's column, ``baseline`` to the
    right (:func:`stereo_projection`).

    Args:
        vertices: ``(camera, point)`` (g2o: ``(point, camera)``).
        measurement: ``(3,)`` ``[u, v, u_right]``.
        information: ``(3, 3)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    _stereo: ClassVar[bool] = True


def _cam_poses(cams: np.ndarray) -> np.ndarray:
    """``(m, 3, 4)`` ``[R | t]`` of rows ``[t, q, …]``: cameras, or ``SE3Quat`` measurements."""
    T = np.empty((len(cams), 3, 4), like=cams)  # like=: jets stay jets (graphopt.autodiff)
    T[:, :, :3] = quat_to_rot(cams[:, 3:7])
    T[:, :, 3] = cams[:, :3]
    return T


class EdgeSBACam(EdgeFromParts):
    """Relative pose of two :class:`VertexCam` (g2o's ``EdgeSBACam``):
    ``e = [t, q_vec]`` of ``Z⁻¹·(C_i⁻¹·C_j)`` with ``q_w ≥ 0`` (:class:`EdgeSE3`'s error on the
    cameras' poses). The cameras' translation increments are in the world frame, so the
    Jacobians are EdgeSE3's times ``diag(Rᵀ, I)``.

    Args:
        vertices: ``(camera_i, camera_j)``.
        measurement: ``(7,)`` ``[tx ty tz qx qy qz qw]`` of ``C_i⁻¹·C_j`` (g2o's ``SE3Quat``;
            the quaternion is normalised).
        information: ``(6, 6)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 6
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexCam, VertexCam)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (7,)

    @classmethod
    def _poses(cls, x: Sequence[np.ndarray], z: np.ndarray) -> tuple[np.ndarray, ...]:
        return _cam_poses(x[0]), _cam_poses(x[1]), _cam_poses(z)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        Ci, Cj, Z = cls._poses(x, z)
        return (EdgeSE3.error((Ci, Cj), Z, EdgeContext()),)

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(cameras_i (m, 12), cameras_j (m, 12))``.
            measurement: ``(m, 7)``.
            ctx: Unused.

        Returns:
            ``(e (m, 6), (J_i (m, 6, 6), J_j (m, 6, 6)))``.
        """
        Ci, Cj, Z = cls._poses(x, measurement)
        lin = EdgeSE3.linearize((Ci, Cj), Z, EdgeContext())
        Ji, Jj = (J.copy() for J in lin.jacobians)
        Ji[:, :, :3] = Ji[:, :, :3] @ np.swapaxes(Ci[:, :, :3], 1, 2)
        Jj[:, :, :3] = Jj[:, :, :3] @ np.swapaxes(Cj[:, :, :3], 1, 2)
        return Linearization(lin.error, (Ji, Jj))


class EdgeSBAScale(EdgeFromParts):
    """The distance between two :class:`VertexCam` (g2o's ``EdgeSBAScale``):
    ``e = z − |t_j − t_i|`` ``(m, 1)``; Jacobians ``±[uᵀ, 0]``, ``u`` the unit direction.

    Args:
        vertices: ``(camera_i, camera_j)``.
        measurement: ``(1,)`` the distance.
        information: ``(1, 1)``.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 1
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexCam, VertexCam)

    @classmethod
    def _parts(cls, x: Sequence[np.ndarray], z: np.ndarray,
               ctx: EdgeContext) -> tuple[np.ndarray, ...]:
        d = x[1][:, :3] - x[0][:, :3]
        n = np.sqrt(np.einsum("mi,mi->m", d, d))
        return (z[:, 0] - n)[:, None], d, n

    @classmethod
    def linearize(cls, x: Sequence[np.ndarray], measurement: np.ndarray,
                  ctx: EdgeContext) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(cameras_i (m, 12), cameras_j (m, 12))``.
            measurement: ``(m, 1)``.
            ctx: Unused.

        Returns:
            ``(e (m, 1), (J_i (m, 1, 6), J_j (m, 1, 6)))``.
        """
        e, d, n = cls._parts(x, measurement, ctx)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = d / n[:, None]
        Jj = np.zeros((len(e), 1, 6))
        Jj[:, 0, :3] = -u
        return Linearization(e, (-Jj, Jj))


class VertexIntrinsics(BaseVertex):
    """g2o's ``VertexIntrinsics``: ``[fx, fy, cx, cy, baseline]`` of which the first four are
    estimated (additive update); the baseline is carried along, as in g2o. (No edge of the
    official wheel uses it; it is here for programs that create it.)

    Args:
        id: Vertex id.
        estimate: ``(5,)``.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 4
    estimate_shape: ClassVar[tuple[int, ...]] = (5,)

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """``[fx, fy, cx, cy] += δ``.

        Args:
            estimates: ``(n, 5)``.
            deltas: ``(n, 4)``.
        """
        out = estimates.copy()
        out[:, :4] += deltas
        return out

