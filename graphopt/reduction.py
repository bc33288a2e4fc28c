"""Reduced linearisations from factored Jacobians ``J_i = G · F_i``.

When every row of an edge's Jacobian shares a few directions — the 16 pixels of a photometric
patch all move with one 2-D projection, so ``J_i = G F_i`` with ``G`` the ``(16, 2)`` image
gradients — the normal equations only need ``GᵀG``: with ``RᵀR = GᵀG`` (``R`` upper triangular),
``J̃_i = R F_i`` and ``e_lin = R⁻ᵀ Gᵀ e`` give ``J̃ᵀJ̃ = JᵀJ`` and ``J̃ᵀe_lin = Jᵀe`` with 2 rows
instead of 16. See :attr:`graphopt.edge.BaseEdge.linearization_rows`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Default share of ``GᵀG``'s largest entry below which a direction counts as absent.
REL_TOL = 1e-12


def _upper_factor(a: np.ndarray) -> np.ndarray:
    """``R`` upper triangular with ``RᵀR = a`` for PSD ``(m, k, k)``; rank-deficient allowed."""
    m, k, _ = a.shape
    if k == 1:
        return np.sqrt(np.maximum(a, 0.0))
    if k == 2:
        r = np.zeros_like(a)
        r00 = np.sqrt(np.maximum(a[:, 0, 0], 0.0))
        safe = r00 > 1e-300
        r01 = np.where(safe, a[:, 0, 1] / np.where(safe, r00, 1.0), 0.0)
        r11 = np.sqrt(np.maximum(a[:, 1, 1] - r01 * r01, 0.0))
        r[:, 0, 0], r[:, 0, 1], r[:, 1, 1] = r00, r01, r11
        return r
    # General size: R = √Λ Qᵀ is not triangular but satisfies RᵀR = a, which is all we need.
    lam, q = np.linalg.eigh(a)
    return np.sqrt(np.maximum(lam, 0.0))[:, :, None] * np.swapaxes(q, 1, 2)


def factored_to_reduced(
    e: np.ndarray, g: np.ndarray, factors: Sequence[np.ndarray], rel_tol: float = REL_TOL
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """Turn ``(e, G, (F_i))`` into the reduced linearisation ``(e, (J̃_i), e_lin)``.

    Args:
        e: ``(m, n)`` errors.
        g: ``(m, n, k)`` shared row factor ``G``.
        factors: Per vertex position ``(m, k, d_i)`` factors ``F_i``.
        rel_tol: Directions of ``GᵀG`` below ``rel_tol`` times its largest entry are treated as
            absent (a textureless direction, an inactive edge with ``G = 0``).

    Returns:
        ``(e, (J̃_i (m, k, d_i)), e_lin (m, k))`` for an edge type with
        ``linearization_rows = k``.
    """
    if g.shape[2] == 2:
        return _reduce2(e, g, factors, rel_tol)
    gtg = np.matmul(np.swapaxes(g, 1, 2), g)
    r = _upper_factor(gtg)
    gte = np.einsum("mnk,mn->mk", g, e)
    k = g.shape[2]
    if k <= 2:
        # Forward substitution Rᵀ e_lin = Gᵀe; a zero pivot has a zero right-hand side.
        scale = np.abs(gtg).max(axis=(1, 2)) if k else np.zeros(len(e))
        tol = np.sqrt(rel_tol * scale)
        e_lin = np.zeros_like(gte)
        for i in range(k):  # rows of a 2x2 triangle
            rhs = gte[:, i] - np.einsum("mj,mj->m", r[:, :i, i], e_lin[:, :i])
            piv = r[:, i, i]
            ok = piv > tol
            e_lin[:, i] = np.where(ok, rhs / np.where(ok, piv, 1.0), 0.0)
    else:
        lam, q = np.linalg.eigh(gtg)
        s = np.sqrt(np.maximum(lam, 0.0))
        ok = s > np.sqrt(rel_tol * np.maximum(lam.max(axis=1, keepdims=True), 0.0))
        proj = np.einsum("mkj,mk->mj", q, gte)
        e_lin = np.where(ok, proj / np.where(ok, s, 1.0), 0.0)
    return e, tuple(np.matmul(r, f) for f in factors), e_lin


def reduce2(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, ru: np.ndarray, rv: np.ndarray,
    rel_tol: float = REL_TOL,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """The two-row reduction in elementwise closed forms (the hot path of photometric edges:
    no batched 2x2 matmuls): ``R = [[r00, r01], [0, r11]]`` with ``RᵀR = GᵀG = [[a, b], [b, c]]``
    and ``e_lin = R⁻ᵀ Gᵀe`` for ``Gᵀe = [ru, rv]``, per edge.

    Args:
        a: ``(m,)`` ``g0·g0``.
        b: ``(m,)`` ``g0·g1``.
        c: ``(m,)`` ``g1·g1``.
        ru: ``(m,)`` ``g0·e``.
        rv: ``(m,)`` ``g1·e``.
        rel_tol: Pivots at most ``rel_tol · max(a, c)`` count as zero (their row of ``R`` and
            ``e_lin`` is zero).

    Returns:
        ``((r00, r01, r11), e_lin (m, 2))``.
    """
    tol = rel_tol * np.maximum(a, c)
    ok0 = a > tol
    r00 = np.sqrt(a)
    inv00 = np.where(ok0, 1.0 / np.where(ok0, r00, 1.0), 0.0)
    r01 = b * inv00
    d = c - r01 * r01
    ok1 = d > tol
    r11 = np.sqrt(np.where(ok1, d, 0.0))
    inv11 = np.where(ok1, 1.0 / np.where(ok1, r11, 1.0), 0.0)
    e_lin = np.empty((len(a), 2))
    np.multiply(ru, inv00, out=e_lin[:, 0])
    np.multiply(rv - r01 * e_lin[:, 0], inv11, out=e_lin[:, 1])
    return (r00, r01, r11), e_lin


def _reduce2(
    e: np.ndarray, g: np.ndarray, factors: Sequence[np.ndarray], rel_tol: float
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """:func:`factored_to_reduced` for ``k = 2`` by :func:`reduce2`."""
    g0, g1 = g[:, :, 0], g[:, :, 1]
    (r00, r01, r11), e_lin = reduce2(
        np.einsum("mn,mn->m", g0, g0), np.einsum("mn,mn->m", g0, g1),
        np.einsum("mn,mn->m", g1, g1), np.einsum("mn,mn->m", g0, e),
        np.einsum("mn,mn->m", g1, e), rel_tol)
    out = []
    for f in factors:
        j = np.empty_like(f)
        j[:, 0] = r00[:, None] * f[:, 0] + r01[:, None] * f[:, 1]
        j[:, 1] = r11[:, None] * f[:, 1]
        out.append(j)
    return e, tuple(out), e_lin
