"""Photometric patch edges for direct bundle adjustment.

The error of a point ``p`` seen in image ``j`` is the difference between the point's reference
patch ``C`` and the image sampled around the projection:

    e_k = C[k] − I_j(π(K T_j p) + (dx, dy)),   k = P (dx + P/2) + (dy + P/2),

with ``dx, dy ∈ {−P/2, …, P/2 − 1}`` (dx outer, dy inner — the order of the task's points.txt),
bilinear interpolation and ``T_j = T_cw``. The projection and the patch sampling (one
``(P+1) × (P+1)`` window per edge) are in :mod:`graphopt.types.image_sampling`, the
struct-of-arrays geometry and projection Jacobians in :mod:`graphopt.types.photometric_geometry`.

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
from graphopt.reduction import reduce2
from graphopt.types.image_sampling import (
    PhotometricParams,
    patch_residuals,
    project_points,
    sample_patches,
)
from graphopt.types.photometric_geometry import (
    MINUS_IDENTITY,
    Triangle,
    anchor_point,
    apply,
    camera_rows,
    cross_rows,
    inverse_depth_jacobian,
    jacobian,
    pose_jacobian,
    pose_rows,
    safe_rows,
    times_rotation,
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
# errors and the reduction


def _finish(meas: np.ndarray, val: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``C − I`` (``val`` pixel-major ``(P², m)``) with inactive rows zeroed."""
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
        """Camera-frame points ``(3, m)``, an extra activity mask (or ``None``) and what
        :meth:`_projection_rows` needs besides."""
        raise NotImplementedError

    @classmethod
    def _projection_rows(
        cls, pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any, prm: PhotometricParams,
        s: Triangle,
    ) -> tuple[np.ndarray, ...]:
        """``S ∂(u, v)/∂δ`` of every vertex position as ``(m, 2, d_i)``, at safe points ``pc``
        ``(3, m)`` (see :mod:`graphopt.types.photometric_geometry`)."""
        raise NotImplementedError

    @classmethod
    def _project(
        cls, x: Sequence[np.ndarray], ctx: EdgeContext
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple]:
        """Pixel coordinates ``u, v``, image indices, the activity mask and what
        :meth:`_rows` needs."""
        prm = cls._check(ctx)
        pc, extra_ok, geo = cls._geometry(x)
        u, v, iz, ok = project_points(pc.T, prm, extra_ok)
        return u, v, _image_index(ctx, len(u)), ok, (pc, iz, ok, geo, prm)

    @classmethod
    def _rows(cls, proj: tuple, s: Triangle) -> tuple[np.ndarray, ...]:
        """``S ∂(u,v)/∂δ`` as ``(m, 2, d_i)`` from what :meth:`_project` returned."""
        pc, iz, ok, geo, prm = proj
        return cls._projection_rows(safe_rows(pc, ok), iz, ok, geo, prm, s)

    @classmethod
    def _residuals(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext, grad: bool
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, tuple]:
        """Errors ``(m, P²)`` (inactive rows zeroed), with ``grad`` the Gauss–Newton terms of
        :func:`~graphopt.types.image_sampling.patch_residuals`, the activity mask and what
        :meth:`_rows` needs."""
        u, v, image, ok, proj = cls._project(x, ctx)
        e, terms = patch_residuals(u, v, image, measurement, proj[-1], grad)
        if not ok.all():
            e[~ok] = 0.0
        return e, terms, ok, proj

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
        e, _, ok, _ = cls._residuals(x, measurement, ctx, grad=False)
        return Linearization(e, active=ok)

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
        u, v, image, ok, proj = cls._project(x, ctx)
        val, gu, gv = sample_patches(u, v, image, proj[-1], grad=True)
        e = _finish(measurement, val, ok)
        g = np.stack([gu.T, gv.T], axis=2)
        if not ok.all():
            g[~ok] = 0.0
        return e, g, cls._rows(proj, MINUS_IDENTITY), ok

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and the reduced linearisation (2 rows, see ``linearization_rows``).

        The ``(m, P², d_i)`` Jacobians factor as image gradients times a ``(2, d_i)``
        projection factor (:meth:`linearize_factored`); the normal equations need only ``GᵀG``,
        so 2 rows carry them. This computes what
        :func:`graphopt.reduction.factored_to_reduced` would from the factored form, fused:
        ``GᵀG`` and ``Gᵀe`` straight from the pixel-major gradients, and ``J̃_i = R F_i`` from
        the projection's ``∂(u,v)/∂P_c`` (2×3) before it meets any ``∂P_c/∂δ``, without
        building ``G (m, P², 2)`` or ``F_i``.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.
        """
        e, terms, ok, proj = cls._residuals(x, measurement, ctx, grad=True)
        s, e_lin = _reduce_patch(terms, ok)  # type: ignore[arg-type]
        return Linearization(e, cls._rows(proj, s), e_lin, ok)  # J̃ = R (−F) = (−R) F

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


def _reduce_patch(terms: np.ndarray, ok: np.ndarray) -> tuple[Triangle, np.ndarray]:
    """:func:`graphopt.reduction.reduce2` of ``terms = [a, b, c, ru, rv]`` ``(5, m)``
    (``GᵀG = [[a, b], [b, c]]``, ``Gᵀe = [ru, rv]``; inactive edges are zeroed here): ``−R``
    (negated for ``J_i = −G F_i``) as ``(−r00, −r01, −r11)`` and ``e_lin`` ``(m, 2)``."""
    if not ok.all():
        terms[:, ~ok] = 0.0
    (r00, r01, r11), e_lin = reduce2(*terms)  # factored_to_reduced's tolerance
    return (-r00, -r01, -r11), e_lin


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
        R, t = pose_rows(x[0])
        return apply(R, t, [x[1][:, 0], x[1][:, 1], x[1][:, 2]]), None, R

    @classmethod
    def _projection_rows(
        cls, pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any, prm: PhotometricParams,
        s: Triangle,
    ) -> tuple[np.ndarray, ...]:
        M = camera_rows(pc, iz, prm, s)
        (jp, jp_rows), (jx, jx_rows) = jacobian(len(iz), 6), jacobian(len(iz), 3)
        pose_jacobian(pc, M, jp_rows)
        times_rotation(M, geo, jx_rows)
        return jp, jx


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
        Ra, ta = pose_rows(x[0])
        Rb, tb = pose_rows(x[1])
        pa, irho, ok = anchor_point(x[2])
        # P_c = R_j R_aᵀ (P_a − t_a) + t_j, as two rotations: cheaper than forming R_j R_aᵀ.
        Rat = [[Ra[j][i] for j in range(3)] for i in range(3)]
        pw = apply(Rat, None, [pa[i] - ta[i] for i in range(3)])
        return apply(Rb, tb, pw), ok, (Rat, Rb, pa, irho)

    @classmethod
    def _projection_rows(
        cls, pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any, prm: PhotometricParams,
        s: Triangle,
    ) -> tuple[np.ndarray, ...]:
        Rat, Rb, pa, irho = geo
        pa = safe_rows(pa, ok)
        M = camera_rows(pc, iz, prm, s)
        d = times_rotation(times_rotation(M, Rb), Rat)  # S ∂(u,v)/∂P_a
        m = len(iz)
        (ja, ja_rows), (jj, jj_rows), (jq, jq_rows) = jacobian(m, 6), jacobian(m, 6), jacobian(m, 3)
        # ∂P_c/∂ξ_a = R_ja [[P_a]×, −I]; a row d·[P_a]× equals d × P_a.
        cross_rows(d, pa, ja_rows)
        np.negative(d, out=ja_rows[:, 3:])
        pose_jacobian(pc, M, jj_rows)
        inverse_depth_jacobian(d, pa, irho, jq_rows)
        return ja, jj, jq


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
        pa, irho, ok = anchor_point(x[1])
        return pa, ok, irho

    @classmethod
    def _projection_rows(
        cls, pc: np.ndarray, iz: np.ndarray, ok: np.ndarray, geo: Any, prm: PhotometricParams,
        s: Triangle,
    ) -> tuple[np.ndarray, ...]:
        jq, jq_rows = jacobian(len(iz), 3)
        inverse_depth_jacobian(camera_rows(pc, iz, prm, s), pc, geo, jq_rows)
        return np.zeros((len(iz), 2, 6)), jq


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
         "linearization_rows": None, "linearize_on_trial": False,
         "differentiation": "numeric"},
    )
