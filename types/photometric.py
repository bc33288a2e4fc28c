"""Photometric patch edges for direct bundle adjustment.

The error of a point ``p`` seen in image ``j`` is the difference between the point's reference
patch ``C`` and the image sampled around the projection:

    e_k = C[k] − I_j(π(K T_j p) + (dx, dy)),   k = P (dx + P/2) + (dy + P/2),

with ``dx, dy ∈ {−P/2, …, P/2 − 1}`` (dx outer, dy inner — the order of the task's points.txt),
bilinear interpolation and ``T_j = T_cw``. Because the offsets are integers, every pixel of a
patch shares the fractional part of the projection, so one edge needs a single
``(P+1) × (P+1)`` window of the image and four bilinear weights: the whole group is evaluated with
one flat fancy index into the (stacked, flattened) images.

Two parametrisations of the point:

* :class:`EdgePhotometricPatch` — vertices ``(VertexSE3Expmap, VertexPointXYZ)``, a world point.
* :class:`EdgePhotometricPatchInverseDepth` — vertices ``(anchor pose, observing pose,
  VertexPointInverseDepth)``; the point is ``T_a⁻¹ [a, b, 1]/ρ``.
  :class:`EdgePhotometricPatchInverseDepthHost` is the observation in the anchor image itself
  (the error does not depend on any pose there, only on ``[a, b, ρ]``).

Edges of every type take the image index from ``ctx.data["image"]`` and the images, intrinsics
and patch size from ``ctx.params`` (a :class:`PhotometricParams`). Use
:func:`photometric_edge_types` for patch sizes other than 4.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.reduction import factored_to_reduced
from graphopt.types.vertices import VertexPointInverseDepth, VertexPointXYZ, VertexSE3Expmap

#: Depths at or below this (in the camera frame) make an edge inactive (behind the camera).
MIN_DEPTH = 1e-6

GRADIENTS = ("central", "interpolated")


def central_gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image gradients by central differences, ``(I(x+1) − I(x−1)) / 2``.

    The outermost rows/columns use one-sided differences; they are never sampled by an active
    edge anyway (the margin keeps projections at least 4 px inside).

    Args:
        image: ``(H, W)`` image.

    Returns:
        ``(gx, gy)``: derivatives along columns (u) and rows (v), each ``(H, W)``.
    """
    gy, gx = np.gradient(np.asarray(image, dtype=np.float64))
    return gx, gy


@dataclass
class PhotometricParams:
    """Images, intrinsics and patch layout shared by a group of photometric edges.

    Args:
        images: ``(n, H, W)`` greyscale images (any real dtype; stored flattened as ``dtype``).
        fx: Focal length along u, pixels.
        fy: Focal length along v, pixels.
        cx: Principal point u.
        cy: Principal point v.
        patch: Patch side ``P`` (even: 2, 4, 6, 8).
        margin: An edge is active only while ``margin <= u <= W − margin`` and likewise for v.
            ``None`` (default) uses the task's 4 px, widened to ``P/2 + 2`` for large patches so
            that the interpolation and gradient stencil never leave the image.
        gradient: ``"central"`` (precomputed central-difference gradient images, bilinearly
            interpolated — the task's choice) or ``"interpolated"`` (the exact derivative of the
            bilinear interpolant; what a numeric Jacobian sees).
        dtype: Floating type of the stored images and of the interpolation. ``"float32"``
            (default) halves the memory traffic of the gathers, which dominate the cost; the
            geometry (projection, Jacobians of the projection) is always float64, and errors and
            Jacobians are returned as float64. Use ``"float64"`` to compare against numeric
            Jacobians with tiny steps.
    """

    images: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    patch: int = 4
    margin: float | None = None
    gradient: str = "central"
    dtype: str = "float32"
    # Derived in __post_init__.
    height: int = field(init=False)
    width: int = field(init=False)
    flat: np.ndarray = field(init=False, repr=False)
    window: np.ndarray = field(init=False, repr=False)
    window_ext: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        imgs = np.asarray(self.images, dtype=np.float64)
        if imgs.ndim == 2:
            imgs = imgs[None]
        if imgs.ndim != 3:
            raise ValueError(f"images must be (n, H, W), got shape {imgs.shape}")
        if self.patch < 2 or self.patch % 2:
            raise ValueError(f"patch size must be even and >= 2, got {self.patch}")
        if self.gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {GRADIENTS}, got {self.gradient!r}")
        half = self.patch // 2
        # The central-difference sampler reads P/2 + 1 pixels left/up of floor(u) and P/2 + 1
        # right/down of it, so the projection must stay P/2 + 2 px inside (the task's 4 for P=4).
        need = half + 2
        if self.margin is None:
            self.margin = float(max(4, need))
        if self.margin < need:
            raise ValueError(
                f"margin {self.margin} too small for a {self.patch}x{self.patch} patch "
                f"(needs {need})"
            )
        self.images = imgs
        _, self.height, self.width = imgs.shape
        self.flat = np.ascontiguousarray(imgs.reshape(-1), dtype=np.dtype(self.dtype))
        # Window of (P+1)² pixels around floor(u, v), laid out [wx, wy] so that reshaping the
        # interpolated (P, P) block row-major gives k = P·(dx + P/2) + (dy + P/2).
        w = np.arange(-half, half + 1)
        self.window = (w[:, None] + w[None, :] * self.width).ravel().astype(np.int64)
        # One more pixel on every side, for central differences of the interpolated image.
        w = np.arange(-half - 1, half + 2)
        self.window_ext = (w[:, None] + w[None, :] * self.width).ravel().astype(np.int64)

    @property
    def dimension(self) -> int:
        """Error dimension ``P²``."""
        return self.patch * self.patch

    @property
    def camera(self) -> np.ndarray:
        """``[fx, fy, cx, cy]``."""
        return np.array([self.fx, self.fy, self.cx, self.cy])


# --------------------------------------------------------------------------------------------
# shared kernels


def _project(
    pc: np.ndarray, prm: PhotometricParams, extra_ok: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates, inverse depth and the activity mask of camera-frame points.

    Inactive projections are moved to a safe pixel so that later gathers stay in bounds and no
    NaN or inf is ever produced.
    """
    z = pc[:, 2]
    ok = z > MIN_DEPTH
    if extra_ok is not None:
        ok &= extra_ok
    iz = 1.0 / np.where(ok, z, 1.0)
    mg = prm.margin
    # Far-off or non-finite projections may overflow; they fail the margin test below.
    with np.errstate(over="ignore", invalid="ignore"):
        u = prm.fx * pc[:, 0] * iz + prm.cx
        v = prm.fy * pc[:, 1] * iz + prm.cy
        ok &= (u >= mg) & (u <= prm.width - mg) & (v >= mg) & (v <= prm.height - mg)
    if not ok.all():
        u = np.where(ok, u, mg)
        v = np.where(ok, v, mg)
        iz = np.where(ok, iz, 0.0)
    return u, v, iz, ok


def _safe_points(pc: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Replace the camera points of inactive edges by ``[0, 0, 1]`` (finite Jacobian inputs)."""
    if ok.all():
        return pc
    return np.where(ok[:, None], pc, np.array([0.0, 0.0, 1.0]))


def _sample(
    u: np.ndarray, v: np.ndarray, image: np.ndarray, prm: PhotometricParams, grad: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Bilinear patch samples (and gradients) for all edges, pixel-major.

    Arrays are laid out ``(P², m)`` (pixel first) so that every arithmetic operation runs over
    long contiguous rows; the caller transposes once at the end.

    With ``gradient="central"`` the image is interpolated on a ``(P+2)²`` grid (one pixel of
    extra border) and the gradients are central differences of that grid: bilinear
    interpolation commutes with integer shifts, so this equals bilinearly interpolating
    precomputed central-difference gradient images — with one gather instead of three.

    Returns ``(I, gu, gv)``, each ``(P², m)`` in k order; ``gu, gv`` are ``None`` unless asked.
    """
    p = prm.patch
    u0 = np.floor(u)
    v0 = np.floor(v)
    a = u - u0
    b = v - v0
    base = (image.astype(np.int64) * prm.height + v0.astype(np.int64)) * prm.width
    base += u0.astype(np.int64)
    ext = grad and prm.gradient == "central"
    window = prm.window_ext if ext else prm.window
    n = p + 3 if ext else p + 1  # raw window side
    # np.take is markedly faster than fancy indexing for a flat gather.
    win = np.take(prm.flat, window[:, None] + base[None, :]).reshape(n, n, -1)  # [wx, wy, edge]
    # Bilinear weights of the four corners, shared by every pixel of a patch.
    a = a.astype(prm.flat.dtype)
    b = b.astype(prm.flat.dtype)
    ia, ib = 1.0 - a, 1.0 - b
    w00, w10, w01, w11 = ia * ib, a * ib, ia * b, a * b
    k = n - 1
    c00, c10, c01, c11 = win[:k, :k], win[1:, :k], win[:k, 1:], win[1:, 1:]
    val = w00 * c00
    val += w10 * c10
    val += w01 * c01
    val += w11 * c11
    if not grad:
        return val.reshape(p * p, -1), None, None
    if ext:
        # val is the interpolated image at offsets −P/2−1 … P/2 (both axes).
        gu = 0.5 * (val[2:, 1:-1] - val[:-2, 1:-1])
        gv = 0.5 * (val[1:-1, 2:] - val[1:-1, :-2])
        val = val[1:-1, 1:-1]
        return val.reshape(p * p, -1), gu.reshape(p * p, -1), gv.reshape(p * p, -1)
    # Exact derivative of the bilinear interpolant.
    gu = ib * (c10 - c00) + b * (c11 - c01)
    gv = ia * (c01 - c00) + a * (c11 - c10)
    return val.reshape(p * p, -1), gu.reshape(p * p, -1), gv.reshape(p * p, -1)


def _uv_jacobian_camera(pc: np.ndarray, iz: np.ndarray, prm: PhotometricParams) -> np.ndarray:
    """``∂(u, v)/∂P_c``: ``(m, 2, 3)``."""
    m = len(pc)
    x = pc[:, 0] * iz
    y = pc[:, 1] * iz
    d = np.zeros((m, 2, 3))
    d[:, 0, 0] = prm.fx * iz
    d[:, 0, 2] = -prm.fx * x * iz
    d[:, 1, 1] = prm.fy * iz
    d[:, 1, 2] = -prm.fy * y * iz
    return d


def _uv_jacobian_pose(pc: np.ndarray, iz: np.ndarray, prm: PhotometricParams) -> np.ndarray:
    """``∂(u, v)/∂ξ`` for ``P_c ← exp(ξ) P_c``, ``ξ = [ω, υ]``: ``(m, 2, 6)``."""
    m = len(pc)
    x = pc[:, 0] * iz
    y = pc[:, 1] * iz
    fx, fy = prm.fx, prm.fy
    j = np.empty((m, 2, 6))
    j[:, 0, 0] = -fx * x * y
    j[:, 0, 1] = fx * (1.0 + x * x)
    j[:, 0, 2] = -fx * y
    j[:, 0, 3] = fx * iz
    j[:, 0, 4] = 0.0
    j[:, 0, 5] = -fx * x * iz
    j[:, 1, 0] = -fy * (1.0 + y * y)
    j[:, 1, 1] = fy * x * y
    j[:, 1, 2] = fy * x
    j[:, 1, 3] = 0.0
    j[:, 1, 4] = fy * iz
    j[:, 1, 5] = -fy * y * iz
    return j


def _gradients(gu: np.ndarray, gv: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Stack pixel-major gradients into ``(m, P², 2)``, zero rows of inactive edges."""
    m = gu.shape[1]
    g = np.empty((m, gu.shape[0], 2))
    g[:, :, 0] = gu.T
    g[:, :, 1] = gv.T
    if not ok.all():
        g[~ok] = 0.0
    return g


def _finish(meas: np.ndarray, val: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``C − I`` (``val`` pixel-major) with inactive rows zeroed."""
    e = np.subtract(meas, val.T, order="C")
    if not ok.all():
        e[~ok] = 0.0
    return e


def _image_index(ctx: EdgeContext, m: int) -> np.ndarray:
    img = ctx.data.get("image") if ctx.data else None
    if img is None:
        if len(ctx.params.images) != 1:
            raise ValueError("photometric edges need ctx.data['image'] (image index per edge)")
        return np.zeros(m, dtype=np.int64)
    return np.asarray(img)


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``R p + t`` for ``(m, 4, 4)`` transforms and ``(m, 3)`` points."""
    return np.matmul(T[:, :3, :3], p[:, :, None])[:, :, 0] + T[:, :3, 3]


def _relative(Ta: np.ndarray, Tj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of ``T_j T_a⁻¹``."""
    Ra, ta = Ta[:, :3, :3], Ta[:, :3, 3]
    Rj, tj = Tj[:, :3, :3], Tj[:, :3, 3]
    R = Rj @ np.swapaxes(Ra, 1, 2)
    t = tj - np.matmul(R, ta[:, :, None])[:, :, 0]
    return R, t


def _anchor_point(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point in the anchor frame ``[a, b, 1]/ρ``, ``1/ρ`` and the ``ρ > 0`` mask."""
    rho = q[:, 2]
    ok = rho > 0
    irho = 1.0 / np.where(ok, rho, 1.0)
    pa = np.stack([q[:, 0] * irho, q[:, 1] * irho, irho], axis=1)
    return pa, irho, ok


def _inverse_depth_point_jacobian(d: np.ndarray, pa: np.ndarray, irho: np.ndarray) -> np.ndarray:
    """``∂(u,v)/∂[a, b, ρ]`` from ``d = ∂(u,v)/∂P_a``: ``(m, 2, 3)``."""
    out = np.empty_like(d)
    out[:, :, 0] = d[:, :, 0] * irho[:, None]
    out[:, :, 1] = d[:, :, 1] * irho[:, None]
    out[:, :, 2] = -(d * pa[:, None, :]).sum(axis=2) * irho[:, None]
    return out


def _check_params(cls: type, ctx: EdgeContext) -> PhotometricParams:
    prm = ctx.params
    if not isinstance(prm, PhotometricParams):
        raise TypeError(f"{cls.__name__} needs PhotometricParams as params")
    if prm.patch != cls.patch:  # type: ignore[attr-defined]
        raise ValueError(
            f"{cls.__name__} is for {cls.patch}x{cls.patch} patches, "  # type: ignore[attr-defined]
            f"params say {prm.patch}"
        )
    return prm


# --------------------------------------------------------------------------------------------
# edge types


class _PatchEdge(BaseEdge):
    """What the photometric edges share: patch layout, parameter check, and the reduced
    linearisation built from :meth:`linearize_factored`.

    Every pixel of a patch shares the projection's Jacobian, so each Jacobian is the ``(P², 2)``
    image gradients times a ``(2, d_i)`` factor, ``J_i = G · F_i``, and
    ``J_iᵀ W J_j = F_iᵀ (Gᵀ W G) F_j`` needs a 2×2 middle instead of ``P²``-row products.
    """

    patch: ClassVar[int] = 4
    dimension: ClassVar[int] = 16
    linearization_rows: ClassVar[int | None] = 2  # J = G·F with G (P², 2)
    # Sampling dominates both error and linearize; linearising trial points makes an accepted
    # step's next linearisation free.
    linearize_on_trial: ClassVar[bool] = True

    @classmethod
    def _check(cls, ctx: EdgeContext) -> PhotometricParams:
        return _check_params(cls, ctx)

    @classmethod
    def _geometry(cls, x: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, Any]:
        """Camera-frame points ``(m, 3)``, an extra activity mask (or ``None``) and what
        :meth:`_projection_jacobians` needs besides."""
        raise NotImplementedError

    @classmethod
    def _projection_jacobians(
        cls, x: Sequence[np.ndarray], pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any,
        prm: PhotometricParams,
    ) -> tuple[np.ndarray, ...]:
        """``∂(u, v)/∂δ`` of every vertex position, ``(m, 2, d_i)``, at safe points ``pc``."""
        raise NotImplementedError

    @classmethod
    def evaluate(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Patch errors ``C − I(π(P_c) + offsets)``, zero for inactive edges, and the mask of
        active edges (in front of the camera, patch inside the image margin).

        Args:
            x: Per-position estimates (see the edge type).
            measurement: ``(m, P²)`` reference patches.
            ctx: Context with :class:`PhotometricParams` and ``data["image"]``.
        """
        prm = cls._check(ctx)
        pc, extra_ok, _ = cls._geometry(x)
        u, v, _, ok = _project(pc, prm, extra_ok)
        val, _, _ = _sample(u, v, _image_index(ctx, len(u)), prm, grad=False)
        return Linearization(_finish(measurement, val, ok), active=ok)

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """The errors of :meth:`evaluate`.

        Args:
            x: As in :meth:`evaluate`.
            measurement: As in :meth:`evaluate`.
            ctx: As in :meth:`evaluate`.
        """
        return cls.evaluate(x, measurement, ctx).error

    @classmethod
    def linearize_factored(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
        """Errors, image gradients ``G (m, P², 2)``, projection factors ``F_i (m, 2, d_i)`` and
        the activity mask.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.

        Returns:
            ``(e (m, P²), G (m, P², 2), (F_0 (m, 2, d_0), …), active (m,))``; rows of inactive
            edges are zero
            in ``e`` and ``G`` (inactive edges have ``iz = 0``, which zeroes only part of
            ``∂(u,v)/∂ξ``, so their gradients are zeroed instead).
        """
        prm = cls._check(ctx)
        pc, extra_ok, geo = cls._geometry(x)
        u, v, iz, ok = _project(pc, prm, extra_ok)
        val, gu, gv = _sample(u, v, _image_index(ctx, len(u)), prm, grad=True)
        e = _finish(measurement, val, ok)
        g = _gradients(gu, gv, ok)
        factors = cls._projection_jacobians(x, _safe_points(pc, ok), iz, ok, geo, prm)
        return e, g, tuple(-f for f in factors), ok

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and the reduced linearisation (2 rows, see ``linearization_rows``).

        The ``(m, P², d_i)`` Jacobians factor as image gradients times a ``(2, d_i)``
        projection factor (:meth:`linearize_factored`); the normal equations need only ``GᵀG``,
        so 2 rows carry them (:func:`graphopt.reduction.factored_to_reduced`).

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.
        """
        e, g, factors, ok = cls.linearize_factored(x, measurement, ctx)
        e, jac, e_lin = factored_to_reduced(e, g, factors)
        return Linearization(e, jac, e_lin, ok)

    @classmethod
    def jacobians(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        """The full ``(m, P², d_i)`` analytic Jacobians, ``G @ F_i``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.
        """
        _, g, factors, _ = cls.linearize_factored(x, measurement, ctx)
        return tuple(np.matmul(g, f) for f in factors)


class EdgePhotometricPatch(_PatchEdge):
    """Photometric 4×4 patch error of a world point in one image.

    Vertices: ``(VertexSE3Expmap T_cw, VertexPointXYZ)``. Measurement: the ``P²`` reference
    intensities. ``ctx.params``: :class:`PhotometricParams`; ``ctx.data["image"]``: image index
    of each edge. Analytic Jacobians (left perturbation of the pose).

    Args:
        vertices: Pose and point (objects or ids).
        measurement: ``(P²,)`` reference patch.
        information: ``(P², P²)`` information (identity by default).
        robust_kernel: Robust kernel or ``None``.
        params: :class:`PhotometricParams`.
        data: ``{"image": index}``.
    """

    vertex_types = (VertexSE3Expmap, VertexPointXYZ)

    @classmethod
    def _geometry(cls, x: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, Any]:
        return _transform(x[0], x[1]), None, None

    @classmethod
    def _projection_jacobians(
        cls, x: Sequence[np.ndarray], pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any,
        prm: PhotometricParams,
    ) -> tuple[np.ndarray, ...]:
        return (_uv_jacobian_pose(pc, iz, prm),
                _uv_jacobian_camera(pc, iz, prm) @ x[0][:, :3, :3])

class EdgePhotometricPatchInverseDepth(_PatchEdge):
    """Photometric patch error of an inverse-depth point seen from a non-anchor image.

    Vertices: ``(anchor VertexSE3Expmap T_aw, observing VertexSE3Expmap T_jw,
    VertexPointInverseDepth [a, b, ρ])``; the point in camera ``j`` is
    ``T_j T_a⁻¹ [a, b, 1]/ρ``. ``ρ ≤ 0`` or a projection behind camera ``j`` or outside the
    margin makes the edge inactive.

    Args:
        vertices: Anchor pose, observing pose, point.
        measurement: ``(P²,)`` reference patch.
        information: ``(P², P²)`` information (identity by default).
        robust_kernel: Robust kernel or ``None``.
        params: :class:`PhotometricParams`.
        data: ``{"image": index of the observing image}``.
    """

    vertex_types = (VertexSE3Expmap, VertexSE3Expmap, VertexPointInverseDepth)

    @classmethod
    def _geometry(cls, x: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, Any]:
        R, t = _relative(x[0], x[1])
        pa, irho, ok = _anchor_point(x[2])
        pc = np.matmul(R, pa[:, :, None])[:, :, 0] + t
        return pc, ok, (R, pa, irho)

    @classmethod
    def _projection_jacobians(
        cls, x: Sequence[np.ndarray], pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any,
        prm: PhotometricParams,
    ) -> tuple[np.ndarray, ...]:
        R, pa, irho = geo
        pa = _safe_points(pa, ok)
        d = _uv_jacobian_camera(pc, iz, prm) @ R  # ∂(u,v)/∂P_a
        # ∂P_c/∂ξ_a = R_ja [[P_a]×, −I]; a row d·[P_a]× equals d × P_a.
        ja = np.concatenate([np.cross(d, pa[:, None, :]), -d], axis=2)
        return ja, _uv_jacobian_pose(pc, iz, prm), _inverse_depth_point_jacobian(d, pa, irho)


class EdgePhotometricPatchInverseDepthHost(_PatchEdge):
    """Photometric patch error of an inverse-depth point in its own anchor image.

    Vertices: ``(anchor VertexSE3Expmap, VertexPointInverseDepth)``. The point in the anchor
    camera is ``[a, b, 1]/ρ`` whatever the pose, so the pose Jacobian is zero; the pose is a
    vertex only so that the anchor is the first vertex of every edge of the point.

    Args:
        vertices: Anchor pose, point.
        measurement: ``(P²,)`` reference patch.
        information: ``(P², P²)`` information (identity by default).
        robust_kernel: Robust kernel or ``None``.
        params: :class:`PhotometricParams`.
        data: ``{"image": index of the anchor image}``.
    """

    vertex_types = (VertexSE3Expmap, VertexPointInverseDepth)

    @classmethod
    def _geometry(cls, x: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, Any]:
        pa, irho, ok = _anchor_point(x[1])
        return pa, ok, irho

    @classmethod
    def _projection_jacobians(
        cls, x: Sequence[np.ndarray], pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any,
        prm: PhotometricParams,
    ) -> tuple[np.ndarray, ...]:
        jq = _inverse_depth_point_jacobian(_uv_jacobian_camera(pc, iz, prm), pc, geo)
        return np.zeros((len(pc), 2, 6)), jq

_BASES: tuple[type[BaseEdge], ...] = (
    EdgePhotometricPatch,
    EdgePhotometricPatchInverseDepth,
    EdgePhotometricPatchInverseDepthHost,
)


@cache
def photometric_edge_types(patch: int = 4) -> tuple[type[BaseEdge], type[BaseEdge], type[BaseEdge]]:
    """The three photometric edge types for a ``patch × patch`` patch.

    The error dimension is a class attribute, so each patch size is its own (cached) subclass;
    size 4 returns the module's classes themselves.

    Args:
        patch: Patch side (even, >= 2).

    Returns:
        ``(xyz edge, inverse-depth edge, inverse-depth host edge)``.
    """
    if patch < 2 or patch % 2:
        raise ValueError(f"patch size must be even and >= 2, got {patch}")
    if patch == 4:
        return _BASES  # type: ignore[return-value]
    out = tuple(
        type(f"{b.__name__}{patch}x{patch}", (b,), {"patch": patch, "dimension": patch * patch})
        for b in _BASES
    )
    return out  # type: ignore[return-value]


def numeric_variant(edge_type: type[BaseEdge]) -> type[BaseEdge]:
    """A subclass of ``edge_type`` that uses the framework's numeric Jacobians.

    It keeps ``error`` and drops the analytic ``linearize``/``jacobians`` (for the benchmark and
    the comparison of analytic against numeric Jacobians).

    Args:
        edge_type: A photometric edge type.
    """
    return type(
        f"{edge_type.__name__}Numeric",
        (edge_type,),
        {"linearize": BaseEdge.__dict__["linearize"], "jacobians": BaseEdge.__dict__["jacobians"],
         "linearization_rows": None, "linearize_on_trial": False},
    )
