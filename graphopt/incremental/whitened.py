"""Whitened linearisations of a batch of edges: the rows the incremental factor absorbs.

An edge with error ``e``, Jacobians ``J_a`` and information ``Ω = UᵀU`` contributes the
whitened rows ``A_a = w·U J_a`` and the residual ``r = w·U e`` (``w = √ρ'(e'Ωe)`` for a robust
kernel, else 1): ``Σ A_aᵀ A_b`` are its Hessian blocks and ``Σ A_aᵀ r`` its gradient, and the
columns of ``A_aᵀ`` are exactly what a CHOLMOD rank update ``LLᵀ + CCᵀ`` takes. Everything is
batched over the edges of one type; the caller gathers the estimates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from graphopt.edge import BaseEdge, EdgeContext
from graphopt.robust_kernel import RobustKernel


@dataclass
class Whitened:
    """Whitened rows of ``m`` edges.

    Args:
        cols: Per vertex position, ``(m,)`` first unknown of the vertex (``-1``: fixed).
        blocks: Per position, ``(m, e, d)`` whitened Jacobians ``A_a``.
        residual: ``(m, e)`` whitened errors ``r``.
        chi2: ``(m,)`` ``e'Ωe`` (without the kernel).
        weight: ``(m,)`` the kernel's ``ρ'`` at the linearisation (ones without one).
    """

    cols: list[np.ndarray]
    blocks: list[np.ndarray]
    residual: np.ndarray
    chi2: np.ndarray
    weight: np.ndarray


def join(parts: Sequence[Whitened]) -> Whitened:
    """One :class:`Whitened` of the rows of several (same edge type), in order.

    Args:
        parts: The pieces.
    """
    if len(parts) == 1:
        return parts[0]
    k = len(parts[0].cols)
    return Whitened([np.concatenate([p.cols[a] for p in parts]) for a in range(k)],
                    [np.concatenate([p.blocks[a] for p in parts]) for a in range(k)],
                    *(np.concatenate([getattr(p, f) for p in parts])
                      for f in ("residual", "chi2", "weight")))


def negated(w: Whitened) -> Whitened:
    """``w`` with its residual negated (:func:`gradient_into` then subtracts ``Aᵀr``)."""
    return Whitened(w.cols, w.blocks, -w.residual, w.chi2, w.weight)


def sqrt_information(info: np.ndarray) -> np.ndarray:
    """``U`` with ``UᵀU = Ω`` for ``(m, e, e)`` information matrices (Cholesky; an
    eigen-decomposition for semi-definite ones).

    Args:
        info: ``(m, e, e)`` symmetric positive semi-definite matrices.

    Returns:
        ``(m, e, e)``.
    """
    if len(info) > 1 and (info.strides[0] == 0 or bool((info == info[0]).all())):
        return np.broadcast_to(sqrt_information(info[:1]), info.shape)
    if len(info) == 1:
        key = info.tobytes()
        hit = _SQRT_CACHE.get(key)
        if hit is None:
            hit = _SQRT_CACHE[key] = _sqrt(info)
            if len(_SQRT_CACHE) > 64:
                _SQRT_CACHE.pop(next(iter(_SQRT_CACHE)))
        return hit
    return _sqrt(info)


#: ``U`` of recently seen single information matrices (most graphs share a few).
_SQRT_CACHE: dict[bytes, np.ndarray] = {}


def _sqrt(info: np.ndarray) -> np.ndarray:
    try:
        return np.swapaxes(np.linalg.cholesky(info), 1, 2)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(info)
        return np.sqrt(np.clip(w, 0.0, None))[:, :, None] * np.swapaxes(v, 1, 2)


def robust_weights(chi2: np.ndarray, kernel_index: np.ndarray,
                   kernels: Sequence[RobustKernel]) -> np.ndarray | None:
    """``√ρ'(s)`` per edge (``None`` when no edge has a kernel).

    Args:
        chi2: ``(m,)`` ``s = e'Ωe``.
        kernel_index: ``(m,)`` kernel slot per edge (``-1``: none).
        kernels: The group's kernels.
    """
    if not len(kernels) or not (kernel_index >= 0).any():
        return None
    w = np.ones(len(chi2))
    for k in np.unique(kernel_index[kernel_index >= 0]).tolist():
        sel = kernel_index == k
        w[sel] = np.sqrt(np.maximum(kernels[k].robustify(chi2[sel])[1], 0.0))
    return w


def robust_cost(chi2: np.ndarray, kernel_index: np.ndarray,
                kernels: Sequence[RobustKernel]) -> np.ndarray:
    """``ρ(s)`` per edge (``s`` itself without a kernel): what the optimizer minimises.

    Args:
        chi2: ``(m,)`` ``s = e'Ωe``.
        kernel_index: ``(m,)`` kernel slot per edge (``-1``: none).
        kernels: The group's kernels.
    """
    if not len(kernels) or not (kernel_index >= 0).any():
        return chi2
    out = chi2.copy()
    for k in np.unique(kernel_index[kernel_index >= 0]).tolist():
        sel = kernel_index == k
        out[sel] = kernels[k].robustify(chi2[sel])[0]
    return out


def whiten(etype: type[BaseEdge], params: Any, x: Sequence[np.ndarray], measurements: np.ndarray,
           info: np.ndarray, cols: list[np.ndarray], kernel_index: np.ndarray,
           kernels: Sequence[RobustKernel], data: dict[str, np.ndarray]) -> Whitened:
    """Linearise ``m`` edges of one type at ``x`` and whiten them.

    Args:
        etype: The edge type.
        params: The group's shared parameters.
        x: Per vertex position, ``(m, *estimate_shape)`` estimates.
        measurements: ``(m, *measurement_shape)``.
        info: ``(m, e, e)`` information matrices.
        cols: Per position, ``(m,)`` first unknown of each vertex (``-1``: fixed).
        kernel_index: ``(m,)`` kernel slot per edge.
        kernels: The group's kernels.
        data: Per-edge data of these edges.

    Returns:
        The :class:`Whitened` rows.
    """
    lin = etype.linearize(list(x), measurements, EdgeContext(params, data))
    e = np.asarray(lin.error, float)
    U = sqrt_information(info)
    if len(U) > 1 and U.strides[0] == 0:  # one information matrix for all (broadcast)
        # One matrix against a stack: matmul takes half einsum's time (w10000's 64k edges:
        # 3.7 against 7.3 ms per Jacobian).
        U0 = U[0]
        r = e @ U0.T
        blocks = [np.matmul(U0, np.asarray(J, float)) for J in lin.jacobians]
    else:
        r = np.einsum("mij,mj->mi", U, e)
        blocks = [np.einsum("mij,mjk->mik", U, np.asarray(J, float)) for J in lin.jacobians]
    chi2 = np.einsum("mi,mi->m", r, r)
    w = robust_weights(chi2, kernel_index, kernels)
    if w is not None:
        r = r * w[:, None]
        blocks = [b * w[:, None, None] for b in blocks]
    return Whitened(cols, blocks, r, chi2, np.ones(len(chi2)) if w is None else w * w)


def edge_chi2(etype: type[BaseEdge], params: Any, x: Sequence[np.ndarray],
              measurements: np.ndarray, info: np.ndarray, data: dict[str, np.ndarray]
              ) -> np.ndarray:
    """``e'Ωe`` of ``m`` edges at ``x`` (errors only).

    Args:
        etype: The edge type.
        params: Shared parameters.
        x: Per position, ``(m, *estimate_shape)``.
        measurements: ``(m, *measurement_shape)``.
        info: ``(m, e, e)``.
        data: Per-edge data.

    Returns:
        ``(m,)``.
    """
    e = np.asarray(etype.evaluate(list(x), measurements, EdgeContext(params, data)).error, float)
    if len(info) > 1 and info.strides[0] == 0:  # one matrix for all (a broadcast view)
        return np.einsum("mi,mi->m", e @ info[0], e)
    return np.einsum("mi,mij,mj->m", e, info, e)


def determine(batches: Sequence[Whitened], first: int, count: int) -> bool:
    """Whether the rows determine the new unknowns ``first:first + count`` one vertex after
    the other: each new vertex has an edge whose block for it has full column rank and whose
    other vertices are fixed or numbered before it (new vertices are numbered in the order
    they came). Then, the unknowns before ``first`` being determined, so is each new vertex,
    and its pivots in the factor are positive — no need to read the factor's diagonal (which
    copies all of it: 0.1 ms per step on w10000).

    Args:
        batches: The whitened rows entering the factor.
        first: The first new unknown.
        count: New unknowns.
    """
    covered = np.zeros(count, bool)
    for wb in batches:
        for a, (c, A) in enumerate(zip(wb.cols, wb.blocks, strict=True)):
            m, e, d = A.shape
            hit = c >= first
            for b, other in enumerate(wb.cols):
                if b != a:
                    hit &= other < c
            if e < d or not hit.any():
                continue
            S = np.linalg.svd(A[hit], compute_uv=False)  # (k, d), descending
            full = S[:, -1] > 1e-9 * S[:, 0]
            start = c[hit][full] - first
            covered[(start[:, None] + np.arange(d)).ravel()] = True
    return bool(covered.all())


def update_columns(batches: Sequence[Whitened], n: int) -> sp.csc_matrix:
    """``C`` ``(n, Σ m·e)`` with ``CCᵀ = Σ AᵀA`` over the batches: one column per whitened
    row, holding the row's entries at its vertices' unknowns (a fixed vertex's left out).

    Built directly in CSC form with 32-bit indices (what CHOLMOD takes without a
    conversion): a COO or CSR detour costs more than the CHOLMOD update it feeds on a small
    step. A binary edge's vertices are put in the order of their unknowns (when they have
    the same dimension), so that the columns are sorted and flagged so: scikit-sparse sorts
    them otherwise (w10000: 60 µs per update).

    Args:
        batches: Whitened rows.
        n: Unknowns of the system.
    """
    data, index, counts = [], [], []
    uniform = True  # every column holds the same number of entries
    ordered = True  # every column's rows ascend
    width = -1
    for wb in batches:
        m, e = wb.residual.shape
        cols, blocks = wb.cols, wb.blocks
        if len(cols) == 2 and blocks[0].shape == blocks[1].shape:
            swap = cols[0] > cols[1]
            if swap.any():
                cols = [np.where(swap, cols[1], cols[0]), np.where(swap, cols[0], cols[1])]
                turn = swap[:, None, None]
                blocks = [np.where(turn, blocks[1], blocks[0]),
                          np.where(turn, blocks[0], blocks[1])]
        else:
            ordered = ordered and len(cols) == 1
        parts = list(zip(cols, blocks, strict=True))
        if any(bool((c < 0).any()) for c, _ in parts):  # fixed vertices: per-edge counts
            idx = np.concatenate([np.where((c >= 0)[:, None], c[:, None] + np.arange(
                A.shape[2]), -1) for c, A in parts], axis=1)
            keep = np.broadcast_to((idx >= 0)[:, None, :], (m, e, idx.shape[1]))
            vals = np.concatenate([A for _, A in parts], axis=2)
            data.append(vals[keep])
            index.append(np.broadcast_to(idx[:, None, :], keep.shape)[keep])
            counts.append(np.repeat((idx >= 0).sum(axis=1), e))
            uniform = False
            continue
        idx = np.concatenate([c[:, None] + np.arange(A.shape[2]) for c, A in parts], axis=1)
        k = idx.shape[1]
        data.append(np.concatenate([A for _, A in parts], axis=2).ravel())
        index.append(np.broadcast_to(idx[:, None, :], (m, e, k)).ravel())
        counts.append((m * e, k))
        uniform = uniform and width in (-1, k)
        width = k
    if uniform:
        cols = sum(c[0] for c in counts)
        indptr = np.arange(0, cols * width + 1, max(width, 1), dtype=np.int32)[:cols + 1]
    else:
        cnt = np.concatenate([np.full(*c) if isinstance(c, tuple) else c for c in counts])
        cols = len(cnt)
        indptr = np.zeros(cols + 1, np.int32)
        np.cumsum(cnt, out=indptr[1:])
    C = sp.csc_matrix(
        (np.concatenate(data) if len(data) > 1 else data[0] if data else np.zeros(0),
         (np.concatenate(index) if len(index) > 1 else index[0] if index else
          np.zeros(0)).astype(np.int32), indptr), shape=(n, cols))
    if ordered:
        C.has_sorted_indices = True
    return C


def gradient_into(g: np.ndarray, batches: Sequence[Whitened]) -> None:
    """``g += Σ A_aᵀ r`` at each vertex's unknowns.

    A batch step's every edge is summed by ``np.bincount`` (a fixed vertex's share goes to a
    slot past the end, dropped): ``np.add.at`` took several times as long.

    Args:
        g: ``(n,)`` gradient, updated in place.
        batches: Whitened rows.
    """
    n = len(g)
    idx, vals = [], []
    for wb in batches:
        for c, A in zip(wb.cols, wb.blocks, strict=True):
            idx.append((np.where(c < 0, n, c)[:, None] + np.arange(A.shape[2])).ravel())
            vals.append(np.einsum("mid,mi->md", A, wb.residual).ravel())
    if not idx:
        return
    i = np.concatenate(idx) if len(idx) > 1 else idx[0]
    v = np.concatenate(vals) if len(vals) > 1 else vals[0]
    if 8 * len(i) < n:  # a few edges: no pass over all of g
        keep = i < n
        np.add.at(g, i[keep], v[keep])
    else:
        g += np.bincount(i, weights=v, minlength=n)[:n]


def largest_diagonal(batches: Sequence[Whitened], n: int) -> float:
    """The largest diagonal entry of ``H = Σ AᵀA`` ``(n, n)`` (squared column norms of the
    blocks, summed per unknown), without forming ``H``.

    Args:
        batches: Whitened rows.
        n: Unknowns.
    """
    d = np.zeros(n + 1)
    for wb in batches:
        for c, A in zip(wb.cols, wb.blocks, strict=True):
            idx = np.where(c < 0, n, c)[:, None] + np.arange(A.shape[2])
            d += np.bincount(idx.ravel(), np.einsum("mij,mij->mj", A, A).ravel(),
                             minlength=n + 1)[:n + 1]
    return float(d[:n].max()) if n else 1.0


def hessian(batches: Sequence[Whitened], n: int) -> sp.csc_matrix:
    """``H = Σ AᵀA`` ``(n, n)`` (CSC, both triangles) of the batches.

    Args:
        batches: Whitened rows.
        n: Unknowns.
    """
    C = update_columns(batches, n)
    return (C @ C.T).tocsc()


def linear_residual(wb: Whitened, delta: np.ndarray) -> np.ndarray:
    """``r + Σ A_a Δ_a`` per edge ``(m, e)``: the whitened error of the linear model at ``Δ``.

    Args:
        wb: Whitened rows.
        delta: ``(n,)`` the step from the linearisation points.
    """
    out = wb.residual.copy()
    for c, A in zip(wb.cols, wb.blocks, strict=True):
        d = A.shape[2]
        fixed = c < 0
        if fixed.any():  # a fixed vertex's step is zero (gathered, then cleared: no copy of A)
            x = delta[np.where(fixed, 0, c)[:, None] + np.arange(d)]
            x[fixed] = 0.0
        else:
            x = delta[c[:, None] + np.arange(d)]
        out += np.einsum("mid,md->mi", A, x)
    return out
