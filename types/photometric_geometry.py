"""Struct-of-arrays geometry and projection Jacobians of the photometric edges.

Everything here works on ``(m,)`` rows, with points as ``(3, m)`` and Jacobian rows as
``(2, d, m)``: at tens of thousands of edges, elementwise arithmetic on contiguous rows is
several times faster than batched 3×3 matmuls or einsums over ``(m, 3, 3)`` (whose per-matrix
overhead dominates) or arithmetic on strided columns of ``(m, 4, 4)`` poses.

Jacobians are written through ``(2, d, m)`` views of their final ``(m, 2, d)`` arrays
(:func:`jacobian`): strided writes cost less than building ``(2, d, m)`` and transposing it.

The projection Jacobians are built already multiplied by a per-edge upper-triangular
``S = [[s00, s01], [0, s11]]`` on the left: ``S ∂(u,v)/∂δ``. With ``S = −I`` they are the
factors ``F_i`` of :meth:`~graphopt.types.photometric.EdgePhotometricPatch.linearize_factored`;
with ``S = −R`` (``RᵀR = GᵀG``) the reduced 2-row Jacobians. Folding ``S`` into the 2×3
``∂(u,v)/∂P_c`` first is cheaper than scaling every ``(2, d)`` factor afterwards.
"""

from __future__ import annotations

import numpy as np

from graphopt.types.image_sampling import PhotometricParams

#: Rotation entries ``R[i][j]`` and translation ``t[i]``, each ``(m,)``.
RotationRows = list[list[np.ndarray]]
#: The three entries of ``S = [[s00, s01], [0, s11]]``, arrays ``(m,)`` or scalars.
Triangle = tuple[np.ndarray | float, np.ndarray | float, np.ndarray | float]
#: ``S = −I``: the unreduced factors ``−∂(u,v)/∂δ``.
MINUS_IDENTITY: Triangle = (-1.0, 0.0, -1.0)


def jacobian(m: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    """A new ``(m, 2, d)`` Jacobian and its ``(2, d, m)`` view to write rows into."""
    out = np.empty((m, 2, d))
    return out, out.transpose(1, 2, 0)


def pose_rows(T: np.ndarray) -> tuple[RotationRows, list[np.ndarray]]:
    """``R[i][j]`` and ``t[i]`` of ``(m, 4, 4)`` transforms as contiguous ``(m,)`` rows.

    One transposed copy of the 12 entries; every later use reads contiguous memory instead of
    one cache line per edge.
    """
    T2 = T.reshape(-1, 16)
    e = np.empty((12, len(T2)), like=T)  # like=: jets stay jets (graphopt.autodiff)
    for lo in range(0, len(T2), 2048):  # blocked: source and destination stay in cache
        e[:, lo:lo + 2048] = T2[lo:lo + 2048, :12].T
    return [[e[4 * i + j] for j in range(3)] for i in range(3)], [e[4 * i + 3] for i in range(3)]


def apply(R: RotationRows, t: list[np.ndarray] | None, p: list[np.ndarray]) -> np.ndarray:
    """``R p + t`` (``R p`` if ``t`` is ``None``) as ``(3, m)`` (a matmul's summation order)."""
    out = np.empty((3, len(p[0])), like=p[0])
    for i in range(3):
        np.multiply(R[i][0], p[0], out=out[i])
        out[i] += R[i][1] * p[1]
        out[i] += R[i][2] * p[2]
        if t is not None:
            out[i] += t[i]
    return out


def anchor_point(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point in the anchor frame ``[a, b, 1]/ρ`` as ``(3, m)``, ``1/ρ`` and the ``ρ > 0``
    mask of ``(m, 3)`` inverse-depth points."""
    rho = q[:, 2]
    ok = rho > 0
    irho = 1.0 / np.where(ok, rho, 1.0)
    pa = np.empty((3, len(q)), like=q)
    np.multiply(q[:, 0], irho, out=pa[0])
    np.multiply(q[:, 1], irho, out=pa[1])
    pa[2] = irho
    return pa, irho, ok


def safe_rows(P: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``(3, m)`` points with inactive edges' replaced by ``[0, 0, 1]`` (finite Jacobians), as
    :func:`graphopt.types.image_sampling.safe_points` does for ``(m, 3)``."""
    if ok.all():
        return P
    return np.where(ok, P, np.array([[0.0], [0.0], [1.0]]))


def camera_rows(P: np.ndarray, iz: np.ndarray, prm: PhotometricParams, s: Triangle) -> np.ndarray:
    """``M = S ∂(u,v)/∂P_c`` as ``(2, 3, m)``, ``∂(u,v)/∂P_c = [[fx/z, 0, −fx x/z],
    [0, fy/z, −fy y/z]]`` with ``x = X/z, y = Y/z`` (``iz = 1/z``, 0 for inactive edges)."""
    s00, s01, s11 = s
    a = prm.fx * iz
    b = prm.fy * iz
    ax = a * (P[0] * iz)
    by = b * (P[1] * iz)
    M = np.empty((2, 3, len(iz)))
    np.multiply(a, s00, out=M[0, 0])
    np.multiply(b, s01, out=M[0, 1])
    np.multiply(ax, s00, out=M[0, 2])
    M[0, 2] += by * s01
    np.negative(M[0, 2], out=M[0, 2])
    M[1, 0] = 0.0
    np.multiply(b, s11, out=M[1, 1])
    np.multiply(by, s11, out=M[1, 2])
    np.negative(M[1, 2], out=M[1, 2])
    return M


def cross_rows(d: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """``out[r] = d[r] × p`` for rows ``d`` ``(2, 3, m)`` and points ``p`` ``(3, m)``."""
    for k in range(3):
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        np.multiply(d[:, k1], p[k2], out=out[:, k])
        out[:, k] -= d[:, k2] * p[k1]


def pose_jacobian(P: np.ndarray, M: np.ndarray, out: np.ndarray) -> None:
    """``M ∂P_c/∂ξ`` into ``out`` ``(2, 6, m)`` for ``P_c ← exp(ξ) P_c``, ``ξ = [ω, υ]``:
    ``∂P_c/∂ξ = [−[P_c]×, I]`` and a row ``−m [P_c]×`` is ``P_c × m``."""
    for k in range(3):
        k1, k2 = (k + 1) % 3, (k + 2) % 3
        np.multiply(M[:, k2], P[k1], out=out[:, k])
        out[:, k] -= M[:, k1] * P[k2]
    out[:, 3:] = M


def times_rotation(M: np.ndarray, R: RotationRows, out: np.ndarray | None = None
                   ) -> np.ndarray:
    """``M R`` for rows ``M`` ``(2, 3, m)`` (into ``out`` if given)."""
    if out is None:
        out = np.empty_like(M)
    for j in range(3):
        np.multiply(M[:, 0], R[0][j], out=out[:, j])
        out[:, j] += M[:, 1] * R[1][j]
        out[:, j] += M[:, 2] * R[2][j]
    return out


def inverse_depth_jacobian(d: np.ndarray, pa: np.ndarray, irho: np.ndarray, out: np.ndarray
                           ) -> None:
    """``d ∂P_a/∂[a, b, ρ]`` into ``out`` ``(2, 3, m)`` for rows ``d`` ``(2, 3, m)`` against
    ``P_a = [a, b, 1]/ρ``: ``[d_0/ρ, d_1/ρ, −(d · P_a)/ρ]``."""
    np.multiply(d[:, 0], irho, out=out[:, 0])
    np.multiply(d[:, 1], irho, out=out[:, 1])
    dp = d[:, 0] * pa[0]
    dp += d[:, 1] * pa[1]
    dp += d[:, 2] * pa[2]
    np.negative(dp, out=dp)
    np.multiply(dp, irho, out=out[:, 2])
