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
from functools import cached_property, lru_cache
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError
from graphopt.lie import relative_transform, transform_points
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


@lru_cache(maxsize=64)
def pose_jacobian_map(fx: float, fy: float, bf: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(M (12, 6k), C (6k,))`` with ``J.reshape(m, 6k) = F @ M + C``: g2o's pose Jacobian of
    a pinhole (or, with ``bf``, stereo) projection under ``T ← exp([ω, υ]) T``.

    ``F`` holds the products ``a_i b_j`` (index ``3i + j``) of ``a = [u, v, iz, 1]`` and
    ``b = [u, v, iz]`` (``u, v`` normalised image coordinates, ``iz = 1/z``): every entry of
    g2o's Jacobian rows is a combination of them (``k = 2``, or 3 rows with ``bf``)."""
    k = 2 if bf is None else 3
    M, C = np.zeros((12, 6 * k)), np.zeros(6 * k)
    U, V, IZ, ONE = 0, 1, 2, 3               # the factors of a
    u, v, iz = 0, 1, 2                       # the factors of b

    def put(row: int, col: int, i: int, j: int, coef: float) -> None:
        M[3 * i + j, 6 * row + col] += coef

    for row, f in [(0, fx)] + ([] if bf is None else [(2, fx)]):
        # fx·[uv, −(1 + u²), v, −iz, 0, u·iz]
        put(row, 0, U, v, f)
        C[6 * row + 1] = -f
        put(row, 1, U, u, -f)
        put(row, 2, ONE, v, f)
        put(row, 3, ONE, iz, -f)
        put(row, 5, U, iz, f)
    # fy·[1 + v², −uv, −u, 0, −iz, v·iz]
    C[6] = fy
    put(1, 0, V, v, fy)
    put(1, 1, U, v, -fy)
    put(1, 2, ONE, u, -fy)
    put(1, 4, ONE, iz, -fy)
    put(1, 5, V, iz, fy)
    if bf is not None:       # u_r = u − bf·iz: row 0 plus bf·[−v·iz, u·iz, 0, 0, 0, −iz²]
        put(2, 0, V, iz, -bf)
        put(2, 1, U, iz, bf)
        put(2, 5, IZ, iz, -bf)
    return M, C


#: Rows per product in :func:`pose_jacobian`: OpenBLAS runs a ``(rows, 16) × (16, 6k)``
#: product on several threads above ~4,000 rows, which costs milliseconds on a loaded machine.
_CHUNK = 2048


@lru_cache(maxsize=64)
def _pose_jacobian_map16(fx: float, fy: float, bf: float | None) -> np.ndarray:
    """:func:`pose_jacobian_map` as one ``(16, 6k)`` matrix over the products ``a_i a_j``
    (index ``4i + j``) of ``a = [u, v, iz, 1]``: the constant ``C`` is the row of ``1·1``."""
    M, C = pose_jacobian_map(fx, fy, bf)
    M16 = np.zeros((4, 4, M.shape[1]))
    M16[:, :3] = M.reshape(4, 3, -1)
    M16[3, 3] = C
    return M16.reshape(16, -1)


def pose_jacobian(iz: np.ndarray, uv: np.ndarray, cam: CameraParameters,
                  bf: float | None = None) -> np.ndarray:
    """g2o's pose Jacobian rows ``(m, 2|3, 6)`` of pinhole (or, with ``bf``, stereo)
    projections, as one product of per-edge monomials with :func:`pose_jacobian_map`.

    Args:
        iz: ``(m,)`` inverse depths ``1/z`` of the camera-frame points.
        uv: ``(m, 2)`` their normalised image coordinates ``(x/z, y/z)``.
        cam: The intrinsics.
        bf: Stereo baseline × ``fx``, or ``None`` (mono).
    """
    a = np.empty((4, len(iz)))                   # [u, v, iz, 1], one row each
    a[:2] = uv.T
    a[2] = iz
    a[3] = 1.0
    return monomial_pose_jacobian(a, cam, bf)


def monomial_pose_jacobian(a: np.ndarray, cam: CameraParameters, bf: float | None = None
                           ) -> np.ndarray:
    """:func:`pose_jacobian` of the monomial base ``a = [u; v; iz; 1]`` ``(4, m)`` (as
    :func:`projection_base` returns it).

    The monomials are formed edge-last, ``(16, m)``: an outer product over a long contiguous
    axis, 5x faster than over the 4 x 3 trailing axes at 500 edges (13 against 2.7 µs); the
    product reads their transpose without a copy.

    Args:
        a: ``(4, m)`` rows ``u``, ``v``, ``iz`` and ones.
        cam: The intrinsics.
        bf: Stereo baseline × ``fx``, or ``None`` (mono).
    """
    m = a.shape[1]
    F = (a[:, None, :] * a[None, :, :]).reshape(16, m)
    M = _pose_jacobian_map16(cam.fx, cam.fy, bf)
    if m <= _CHUNK:
        J = F.T @ M
    else:
        J = np.concatenate([F[:, i:i + _CHUNK].T @ M for i in range(0, m, _CHUNK)])
    return J.reshape(m, 2 if bf is None else 3, 6)


def projected_rows(M: np.ndarray, iz: np.ndarray, uv: np.ndarray,
                   cam: CameraParameters) -> np.ndarray:
    """``∂e/∂P · M`` ``(m, 2, k)`` for pinhole errors ``e = z − π(P)``: row ``r`` is
    ``−f_r·iz·(M_r − uv_r·M_2)`` (``M`` ``(m, 3, k)``, e.g. ``∂P/∂X``).

    Args:
        M: ``(m, 3, k)`` (a broadcast view too).
        iz: ``(m,)`` inverse depths of the points.
        uv: ``(m, 2)`` their normalised image coordinates.
        cam: The intrinsics.
    """
    return (M[:, :2, :] - uv[:, :, None] * M[:, 2:3, :]) * (-iz[:, None, None]
                                                          * cam.focal[:, None])


#: Edges up to which :func:`normalised_projection` works on whole ``(m, 2)`` arrays.
_ROWWISE_EDGES = 256


def normalised_projection(P: np.ndarray, z: np.ndarray, cam: CameraParameters,
                          bf: float | None = None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors ``z − [u, v]`` (with ``bf``: ``z − [u, v, u − bf/z]``) of camera-frame points,
    with the ``iz`` and ``uv`` that :func:`pose_jacobian` takes.

    Args:
        P: ``(m, 3)`` camera-frame points.
        z: ``(m, 2)`` pixels, or ``(m, 3)`` ``(u, v, u_r)`` with ``bf``.
        cam: The intrinsics.
        bf: Stereo baseline × ``fx``, or ``None`` (mono).

    Returns:
        ``(e (m, 2|3), iz (m,), uv (m, 2))``.
    """
    if type(P) is np.ndarray and len(P) <= _ROWWISE_EDGES:
        # Few edges: whole (m, 2) operations, fewer calls (100 edges: 4.7 against 5.7 µs);
        # the same operations per element, so the same bits.
        iz = 1.0 / P[:, 2]
        uv = P[:, :2] * iz[:, None]
        if bf is None:
            return z - (uv * cam.focal + cam.centre), iz, uv
        pix = np.empty((3, len(P)))  # stereo: the pixels as (3, m) rows (10 against 12 µs)
        np.multiply(uv.T, cam.focal[:, None], out=pix[:2])
        pix[:2] += cam.centre[:, None]
        np.subtract(pix[0], bf * iz, out=pix[2])
        return z - pix.T, iz, uv
    # Coordinate by coordinate over the edges (long inner loops): an (m, 2) operation with a
    # strided last axis of 2 runs 2-element loops (500 edges: 4.7 against 10.5 µs).
    PT = P.T
    iz = 1.0 / PT[2]
    uvT = PT[:2] * iz                            # normalised image coordinates, (2, m)
    e = np.empty((len(P), 2 if bf is None else 3), like=P)  # like=: jets stay jets
    pu = cam.fx * uvT[0] + cam.cx
    e[:, 0] = z[:, 0] - pu
    e[:, 1] = z[:, 1] - (cam.fy * uvT[1] + cam.cy)
    if bf is not None:
        e[:, 2] = z[:, 2] - (pu - bf * iz)
    return e, iz, uvT.T


def projection_base(P: np.ndarray, z: np.ndarray, cam: CameraParameters,
                    bf: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`normalised_projection`'s errors with ``iz`` and ``uv`` written into the monomial
    base ``a = [u; v; iz; 1]`` ``(4, m)`` that :func:`monomial_pose_jacobian` takes: a pose-only
    edge's linearisation without copying them there (the same operations per element, so the
    same bits).

    Args:
        P: ``(m, 3)`` camera-frame points (an ndarray).
        z: ``(m, 2)`` pixels, or ``(m, 3)`` ``(u, v, u_r)`` with ``bf``.
        cam: The intrinsics.
        bf: Stereo baseline × ``fx``, or ``None`` (mono).

    Returns:
        ``(e (m, 2|3), a (4, m))``.
    """
    m = len(P)
    a = np.empty((4, m))
    PT = P.T
    iz = np.divide(1.0, PT[2], out=a[2])
    np.multiply(PT[:2], iz, out=a[:2])
    a[3] = 1.0
    if m <= _ROWWISE_EDGES:  # the pixels as whole (2|3, m) operations: fewer calls
        pix = np.empty((2 if bf is None else 3, m))
        np.multiply(a[:2], cam.focal[:, None], out=pix[:2])
        pix[:2] += cam.centre[:, None]
        if bf is not None:
            np.subtract(pix[0], bf * iz, out=pix[2])
        return z - pix.T, a
    e = np.empty((m, 2 if bf is None else 3))    # coordinate by coordinate: long loops
    pu = cam.fx * a[0] + cam.cx
    e[:, 0] = z[:, 0] - pu
    e[:, 1] = z[:, 1] - (cam.fy * a[1] + cam.cy)
    if bf is not None:
        e[:, 2] = z[:, 2] - (pu - bf * iz)
    return e, a


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

