"""g2o's ``types/sim3`` (``types_seven_dof_expmap``): a similarity vertex, the 7-D relative
Sim(3) edge and the two Sim(3) reprojection edges of ORB-SLAM's loop closing, with analytic
Jacobians (g2o differentiates all three edges numerically).

**The vertex.** :class:`VertexSim3Expmap` keeps ``S = [[sR, t], [f, 0, 0, 1]]`` ``(4, 4)``
(``S·x = s R x + t``; for ORB-SLAM ``S_cw``, world to camera) and updates it as g2o does,
``S ← exp([ω, υ, σ]) · S`` (``Sim3(update) * estimate``, tangent order rotation, translation,
log-scale; :func:`graphopt.types.sim3_lie.sim3_exp`).

**The fix-scale flag** (g2o's ``_fix_scale``: stereo and RGB-D systems fix the scale, monocular
ones do not) is the bottom-left entry ``f`` of the estimate, 0 (free) or 1 (fixed). A batched
``oplus`` sees only the estimates and the steps, so the flag has to travel with the estimate:
this keeps one store for a mix of fixed- and free-scale vertices, and ``add_vertices``,
``set_estimates_of`` and the estimates an optimizer returns carry it. Where ``f = 1``,
``oplus`` zeroes the step's σ (as g2o) and the edges zero their Jacobian's σ column (as g2o's
numeric Jacobian through that ``oplus`` does). Build estimates with
:func:`~graphopt.types.sim3_lie.sim3_matrix` ``(R, t, s, fix_scale)``; on one vertex object,
``VertexSim3Expmap(id, S, fix_scale=True)`` or ``v.set_fix_scale()`` (``set_estimate`` keeps
the vertex's flag, like g2o's ``setEstimate``). No edge reads ``f``'s row otherwise.

**Vertex order.** g2o declares both projection edges
``BaseBinaryEdge<2, Vector2, VertexPointXYZ, VertexSim3Expmap>``: ``(point, sim3)``, and so do
these (a g2o file or g2o-API port keeps its vertex order). The intrinsics g2o keeps on the
vertex (``_focal_length1``/``_principle_point1`` for :class:`EdgeSim3ProjectXYZ`, ``…2`` for
:class:`EdgeInverseSim3ProjectXYZ`) are the edge group's ``params``,
:class:`~graphopt.types.projection.CameraParameters` ``(fx, fy, cx, cy)``: camera 1's for the
first group, camera 2's for the second. (g2opy 2.3.0 exposes neither the vertex's intrinsics,
which stay ``f = 1, c = 0``, nor ``_fix_scale``.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.types.projection import (
    CameraParameters,
    _cross_matrix_rows,
    camera_params,
    normalised_projection,
    pose_jacobian,
    projected_rows,
)
from graphopt.types.sim3_lie import (
    log_left_jacobian,
    sim3_adjoint,
    sim3_exp,
    sim3_exp_one,
    sim3_inverse,
    sim3_log,
    sim3_parts,
    sim3_product,
)
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = ["EdgeInverseSim3ProjectXYZ", "EdgeSim3", "EdgeSim3ProjectXYZ", "VertexSim3Expmap"]


def _free_scale(S: np.ndarray) -> np.ndarray:
    """``(n,)`` 1.0 where the scale is free, 0.0 where fixed."""
    return 1.0 - S[:, 3, 0]


def _oplus_one(S: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """:meth:`VertexSim3Expmap.oplus` of one vertex (``(1, 4, 4)``, ``(1, 7)``)."""
    d = delta[0]
    if S[0, 3, 0] == 1.0:
        d = d.copy()
        d[6] = 0.0
    sR_e, t_e = sim3_exp_one(d)
    out = S.copy()
    out[0, :3, :3] = sR_e @ S[0, :3, :3]
    out[0, :3, 3] = sR_e @ S[0, :3, 3] + t_e
    return out


class VertexSim3Expmap(BaseVertex):
    """A similarity ``S = [[sR, t], [f, 0, 0, 1]]``, ``f`` the fix-scale flag (module docstring).

    Update: ``S ← exp([ω, υ, σ]) · S`` with ``σ = 0`` where ``f = 1``.

    Args:
        id: Vertex id.
        estimate: ``(4, 4)`` similarity (its ``f`` is replaced by ``fix_scale``).
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
        fix_scale: g2o's ``_fix_scale``.
    """

    dimension: ClassVar[int] = 7
    estimate_shape: ClassVar[tuple[int, ...]] = (4, 4)

    def __init__(self, id: int | None = None, estimate: Any = None, fixed: bool = False,
                 marginalized: bool = False, fix_scale: bool = False) -> None:
        super().__init__(id, estimate, fixed, marginalized)
        self._fix_scale = bool(fix_scale)
        if self._estimate is not None:
            self._estimate = self._flagged(self._estimate, self._fix_scale)

    @staticmethod
    def _flagged(value: np.ndarray, fix: bool) -> np.ndarray:
        out = np.array(value, dtype=float)
        if out.shape == (4, 4):
            out[3, 0] = float(fix)
        return out

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """``exp(δ) · S`` for all vertices, ``δ_σ`` zeroed where the scale is fixed.

        Args:
            estimates: ``(n, 4, 4)`` similarities.
            deltas: ``(n, 7)`` tangents ``[ω, υ, σ]``.
        """
        if len(estimates) == 1 and type(deltas) is np.ndarray and type(estimates) is np.ndarray:
            return _oplus_one(estimates, deltas)
        flag = estimates[:, 3, 0]
        keep = np.ones((len(flag), 7))
        keep[:, 6] = 1.0 - flag
        out = sim3_product(sim3_exp(deltas * keep), estimates)   # (a product: jets stay jets)
        out[:, 3, 0] = flag
        return out

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Finite, ``sR`` a positive multiple of a rotation (1e-6), bottom row ``[f, 0, 0, 1]``
        with ``f`` 0 or 1.

        Args:
            estimates: ``(n, 4, 4)``.
        """
        ok = super().validate(estimates)
        S = np.where(ok[:, None, None], estimates, np.eye(4))
        R, _, s = sim3_parts(S)
        with np.errstate(invalid="ignore", divide="ignore"):
            orth = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2)) < 1e-6
            det = np.linalg.det(R) > 0
        bottom = np.abs(S[:, 3, 1:] - [0, 0, 1]).max(axis=1) < 1e-12
        flag = (S[:, 3, 0] == 0.0) | (S[:, 3, 0] == 1.0)
        return ok & (s > 0) & orth & det & bottom & flag

    def fix_scale(self) -> bool:
        """g2o's ``_fix_scale``."""
        if self._store is not None:
            return bool(self._store.estimates[self._slot, 3, 0] == 1.0)
        return self._fix_scale

    def set_fix_scale(self, fix: bool = True) -> None:
        """Fix (or free) the scale of this vertex's updates.

        Args:
            fix: True to fix.
        """
        if self._store is not None:
            self._store.set_estimate(self._slot, self._flagged(self.estimate, fix), self.id)
        else:
            self._fix_scale = bool(fix)
            if self._estimate is not None:
                self._estimate = self._flagged(self._estimate, fix)

    def set_estimate(self, value: Any) -> None:
        """Set the estimate, keeping the vertex's fix-scale flag (as g2o's ``setEstimate``).

        Args:
            value: ``(4, 4)`` similarity.
        """
        super().set_estimate(self._flagged(value, self.fix_scale()))


class EdgeSim3(BaseEdge):
    """g2o's ``EdgeSim3``: ``e = log(S_ji · S_i · S_j⁻¹)`` (g2o's Sim3 log), 7-D.

    Vertices ``(S_i, S_j)`` (:class:`VertexSim3Expmap`, ``S_·w``); the measurement ``S_ji``
    ``(4, 4)`` (``S_j S_i⁻¹`` when exact; g2o's ``setMeasurement`` takes it as is).
    Jacobians (exact, with ``E = S_ji S_i S_j⁻¹`` and ``D`` the derivative of the log,
    :func:`~graphopt.types.sim3_lie.log_left_jacobian`): ``J_i = D·Ad(S_ji)``,
    ``J_j = −D·Ad(E)`` (g2o's optional ``G2O_SIM3_JACOBIAN`` is their first-order form).

    Args:
        vertices: ``(i, j)`` vertices or ids.
        measurement: ``(4, 4)`` similarity ``S_ji``.
        information: ``(7, 7)`` information matrix.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 7
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSim3Expmap, VertexSim3Expmap)
    measurement_shape: ClassVar[tuple[int, ...] | None] = (4, 4)

    @classmethod
    def _relative(cls, x: Sequence[np.ndarray], measurement: np.ndarray) -> np.ndarray:
        return sim3_product(sim3_product(measurement, x[0]), sim3_inverse(x[1]))

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``log(S_ji S_i S_j⁻¹)`` for all edges.

        Args:
            x: ``(S_i (m, 4, 4), S_j (m, 4, 4))``.
            measurement: ``(m, 4, 4)`` ``S_ji``.
            ctx: Unused.
        """
        return sim3_log(cls._relative(x, measurement))

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians.

        Args:
            x: ``(S_i, S_j)``.
            measurement: ``(m, 4, 4)`` ``S_ji``.
            ctx: Unused.

        Returns:
            ``(e (m, 7), (J_i (m, 7, 7), J_j (m, 7, 7)))``.
        """
        E = cls._relative(x, measurement)
        _, D = log_left_jacobian(E)
        J_i = D @ sim3_adjoint(measurement)
        J_j = -(D @ sim3_adjoint(E))
        J_i[:, :, 6] *= _free_scale(x[0])[:, None]
        J_j[:, :, 6] *= _free_scale(x[1])[:, None]
        return Linearization(sim3_log(E), (J_i, J_j))


class _Sim3Projection(BaseEdge):
    """Shared code of the two Sim(3) reprojection edges (vertices ``(point, sim3)``)."""

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexPointXYZ, VertexSim3Expmap)
    inverse: ClassVar[bool] = False

    @classmethod
    def _camera_point(cls, x: Sequence[np.ndarray]
                      ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """``(P (m, 3), M, shared)``: the camera-frame points, ``∂P/∂X`` and, when every edge
        has the same Sim(3) (``S`` broadcast over the edges with stride 0, as in
        ``OptimizeSim3``), ``S``'s ``(R (3, 3), t (3,))`` for the inverse edge
        (the forward edge reads neither) — then ``M`` is that one ``(3, 3)`` and
        ``P`` one ``(m, 3) × (3, 3)`` product, not ``m`` small ones; else ``M`` is
        ``(m, 3, 3)`` and ``shared`` ``None``.
        """
        X, S = x
        one = type(S) is np.ndarray and type(X) is np.ndarray and len(X) > 0 and S.strides[0] == 0
        S1 = S[:1] if one else S
        if cls.inverse:                          # P = S⁻¹X = Rᵀ(X − t)/s
            R, t, s = sim3_parts(S1)
            M = np.swapaxes(R, 1, 2) / s[:, None, None]
            if one:
                return (X - t) @ M[0].T, M[0], (R[0], t[0])
            return np.matmul(M, (X - t)[:, :, None])[:, :, 0], M, None
        M = S1[:, :3, :3]                        # P = sRX + t
        if one:
            return X @ M[0].T + S1[0, :3, 3], M[0], (M[0], S1[0, :3, 3])
        return np.matmul(M, X[:, :, None])[:, :, 0] + S[:, :3, 3], M, None

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``z − π(P)`` for all edges.

        Args:
            x: ``(X (m, 3), S (m, 4, 4))``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params``: the camera's :class:`CameraParameters`.
        """
        cam = camera_params(cls, ctx.params)
        P = cls._camera_point(x)[0]
        return measurement - (P[:, :2] / P[:, 2:3] * cam.focal + cam.centre)

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians.

        Args:
            x: ``(X (m, 3), S (m, 4, 4))``.
            measurement: ``(m, 2)`` pixels.
            ctx: ``ctx.params``: the camera's :class:`CameraParameters`.

        Returns:
            ``(e (m, 2), (J_point (m, 2, 3), J_sim3 (m, 2, 7)))``.
        """
        X, S = x
        cam = camera_params(cls, ctx.params)
        P, M, shared = cls._camera_point(x)
        e, iz, uv = normalised_projection(P, measurement, cam)
        if shared is not None:
            return Linearization(e, cls._shared_jacobians(S[0], M, shared, iz, uv, cam))
        J_point = projected_rows(M, iz, uv, cam)  # ∂e/∂P · ∂P/∂X
        m = len(X)
        if cls.inverse:
            # S⁻¹ ← S⁻¹exp(−a): dP = M([X]× a_ω − a_υ − X a_σ).
            J_sim = np.empty((m, 2, 7))
            J_sim[:, :, :3] = -_cross_matrix_rows(J_point, X)
            J_sim[:, :, 3:6] = -J_point
            J_sim[:, :, 6] = -np.einsum("mij,mj->mi", J_point, X) * _free_scale(S)[:, None]
        else:
            # S ← exp(a)S: dP = −[P]× a_ω + a_υ + P a_σ; ∂e/∂P·P = 0 (the image of a point
            # does not change when the camera frame is scaled), so the σ column is zero.
            J_sim = np.zeros((m, 2, 7))
            J_sim[:, :, :6] = pose_jacobian(iz, uv, cam)
        return Linearization(e, (J_point, J_sim))

    @classmethod
    def _shared_jacobians(cls, S: np.ndarray, M: np.ndarray, Rt: tuple[np.ndarray, np.ndarray],
                          iz: np.ndarray, uv: np.ndarray, cam: CameraParameters
                          ) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobians when every edge has the same Sim(3) ``S`` (``M = ∂P/∂X``, ``Rt`` its
        rotation and translation), from
        the pose Jacobian's rows ``[−D[P]×, D]`` (``D = ∂e/∂P``) by two ``(2m, 6)``
        products instead of per-edge cross products.

        Inverse: ``M[X]× = [P]×Rᵀ + M[t]×`` (``X − t = sRP``) and ``D·P = 0`` (a pinhole
        image does not change when the point is scaled), so ``D M [X]× = −(−D[P]×)Rᵀ +
        D M[t]×`` and ``−D M X = −D M t``.
        """
        m = len(iz)
        pj = pose_jacobian(iz, uv, cam).reshape(2 * m, 6)
        J_point = (pj[:, 3:] @ M).reshape(m, 2, 3)
        if not cls.inverse:
            J_sim = np.zeros((m, 2, 7))
            J_sim[:, :, :6] = pj.reshape(m, 2, 6)
            return J_point, J_sim
        R, t = Rt
        tx, ty, tz = t.tolist()
        B = np.zeros((6, 7))
        B[:3, :3] = -R.T
        B[3:, :3] = M @ np.array([[0.0, -tz, ty], [tz, 0.0, -tx], [-ty, tx, 0.0]])  # M[t]×
        B[3:, 3:6] = -M
        B[3:, 6] = -(M @ t) * (1.0 - S[3, 0])  # the free-scale flag
        return J_point, (pj @ B).reshape(m, 2, 7)

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``(m,)`` True where the point lies in front of the camera (``P_z > 0``).

        Args:
            x: ``(X (m, 3), S (m, 4, 4))``.
            measurement: ``(m, 2)`` (unused).
            ctx: Unused.
        """
        return cls._camera_point(x)[0][:, 2] > 0


class EdgeSim3ProjectXYZ(_Sim3Projection):
    """g2o's ``EdgeSim3ProjectXYZ``: ``e = z − K₁ π(S X)`` (``S X = s R X + t``).

    Vertices ``(VertexPointXYZ X, VertexSim3Expmap S)`` — g2o's order. ``params``: camera 1's
    :class:`CameraParameters` (g2o's ``_focal_length1``, ``_principle_point1``).

    Args:
        vertices: ``(point, sim3)`` vertices or ids.
        measurement: ``(2,)`` pixel.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
    """


class EdgeInverseSim3ProjectXYZ(_Sim3Projection):
    """g2o's ``EdgeInverseSim3ProjectXYZ``: ``e = z − K₂ π(S⁻¹ X)``.

    Vertices ``(VertexPointXYZ X, VertexSim3Expmap S)`` — g2o's order. ``params``: camera 2's
    :class:`CameraParameters` (g2o's ``_focal_length2``, ``_principle_point2``).

    Args:
        vertices: ``(point, sim3)`` vertices or ids.
        measurement: ``(2,)`` pixel.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
        params: :class:`CameraParameters`.
    """

    inverse: ClassVar[bool] = True
