"""Photometric patch edges for direct bundle adjustment.

The error of a point ``p`` seen in image ``j`` is the difference between the point's reference
patch ``C`` and the image sampled around the projection:

    e_k = C[k] − I_j(π(K T_j p) + (dx, dy)),   k = P (dx + P/2) + (dy + P/2),

with ``dx, dy ∈ {−P/2, …, P/2 − 1}`` (dx outer, dy inner — the order of the task's points.txt),
bilinear interpolation and ``T_j = T_cw``. The projection and the patch sampling (one flat
gather of a ``(P+1) × (P+1)`` window per edge) are in :mod:`graphopt.types.image_sampling`.

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
from functools import cache
from typing import Any, ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.lie import relative_transform, transform_points
from graphopt.reduction import factored_to_reduced
from graphopt.types.image_sampling import (
    PhotometricParams,
    project_points,
    safe_points,
    sample_patches,
)
from graphopt.types.vertices import VertexPointInverseDepth, VertexPointXYZ, VertexSE3Expmap

__all__ = [
    "EdgePhotometricPatch",
    "EdgePhotometricPatchInverseDepth",
    "EdgePhotometricPatchInverseDepthHost",
    "PhotometricParams",
    "numeric_variant",
    "photometric_edge_types",
]

# --------------------------------------------------------------------------------------------
# projection Jacobians and error assembly


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
        u, v, _, ok = project_points(pc, prm, extra_ok)
        val, _, _ = sample_patches(u, v, _image_index(ctx, len(u)), prm, grad=False)
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
        u, v, iz, ok = project_points(pc, prm, extra_ok)
        val, gu, gv = sample_patches(u, v, _image_index(ctx, len(u)), prm, grad=True)
        e = _finish(measurement, val, ok)
        g = _gradients(gu, gv, ok)
        factors = cls._projection_jacobians(x, safe_points(pc, ok), iz, ok, geo, prm)
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
        return transform_points(x[0], x[1]), None, None

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
        R, t = relative_transform(x[0], x[1])
        pa, irho, ok = _anchor_point(x[2])
        pc = np.matmul(R, pa[:, :, None])[:, :, 0] + t
        return pc, ok, (R, pa, irho)

    @classmethod
    def _projection_jacobians(
        cls, x: Sequence[np.ndarray], pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any,
        prm: PhotometricParams,
    ) -> tuple[np.ndarray, ...]:
        R, pa, irho = geo
        pa = safe_points(pa, ok)
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
