"""Small batched linear-algebra kernels and the constant-structure sparse contractions."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """A block or the reduced system is not positive definite."""


def batched_inverse_spd(A: np.ndarray) -> np.ndarray:
    """Inverse of many small symmetric positive definite matrices.

    Closed forms for sizes 1–3 (cofactors; Sylvester's criterion checks definiteness), batched
    Cholesky otherwise.

    Args:
        A: ``(n, d, d)`` symmetric matrices.

    Returns:
        ``(n, d, d)`` inverses.

    Raises:
        NotPositiveDefiniteError: if any block is not positive definite.
    """
    n, d, _ = A.shape
    if n == 0:
        return A.copy()
    if d == 1:
        if np.any(~(A[:, 0, 0] > 0)):
            raise NotPositiveDefiniteError("a 1x1 block is not positive")
        return 1.0 / A
    if d == 2:
        a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 1, 1]
        det = a * c - b * b
        if np.any(~(a > 0)) or np.any(~(det > 0)):
            raise NotPositiveDefiniteError("a 2x2 block is not positive definite")
        inv = np.empty_like(A)
        inv[:, 0, 0], inv[:, 1, 1] = c / det, a / det
        inv[:, 0, 1] = inv[:, 1, 0] = -b / det
        return inv
    if d == 3:
        a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
        a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        m2 = a00 * a11 - a01 * a01
        if np.any(~(a00 > 0)) or np.any(~(m2 > 0)) or np.any(~(det > 0)):
            raise NotPositiveDefiniteError("a 3x3 block is not positive definite")
        inv = np.empty_like(A)
        r = 1.0 / det
        inv[:, 0, 0] = c00 * r
        inv[:, 0, 1] = inv[:, 1, 0] = c01 * r
        inv[:, 0, 2] = inv[:, 2, 0] = c02 * r
        inv[:, 1, 1] = (a00 * a22 - a02 * a02) * r
        inv[:, 1, 2] = inv[:, 2, 1] = (a01 * a02 - a00 * a12) * r
        inv[:, 2, 2] = m2 * r
        return inv
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError as exc:
        raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite") from exc
    Linv = np.linalg.inv(L)
    return np.swapaxes(Linv, 1, 2) @ Linv


def batched_cholesky_inverse(A: np.ndarray) -> np.ndarray:
    """``L⁻¹`` for many SPD matrices ``A = L Lᵀ`` (``L`` lower triangular).

    Closed forms for sizes 1–3, batched LAPACK otherwise.

    Args:
        A: ``(n, d, d)`` symmetric positive definite matrices.

    Returns:
        ``(n, d, d)`` lower-triangular inverses of the Cholesky factors.

    Raises:
        NotPositiveDefiniteError: if any block is not positive definite.
    """
    n, d, _ = A.shape
    out = np.zeros_like(A)
    with np.errstate(invalid="ignore", divide="ignore"):
        if d == 1:
            out[:, 0, 0] = 1.0 / np.sqrt(A[:, 0, 0])
        elif d in (2, 3):
            l00 = np.sqrt(A[:, 0, 0])
            l10 = A[:, 1, 0] / l00
            l11 = np.sqrt(A[:, 1, 1] - l10 * l10)
            m00, m11 = 1.0 / l00, 1.0 / l11
            out[:, 0, 0], out[:, 1, 1] = m00, m11
            out[:, 1, 0] = -l10 * m00 * m11
            if d == 3:
                l20 = A[:, 2, 0] / l00
                l21 = (A[:, 2, 1] - l20 * l10) / l11
                m22 = 1.0 / np.sqrt(A[:, 2, 2] - l20 * l20 - l21 * l21)
                out[:, 2, 2] = m22
                out[:, 2, 1] = -l21 * m11 * m22
                out[:, 2, 0] = -(l20 * m00 + l21 * out[:, 1, 0]) * m22
        else:
            try:
                return np.linalg.inv(np.linalg.cholesky(A))
            except np.linalg.LinAlgError as exc:
                raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite") from exc
    if not np.isfinite(out.sum()):
        raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite")
    return out


class _CscContraction:
    """A constant-structure CSC operator ``M`` (rows ``(t, i)``, ``shape[1]`` rows of ``B``) whose
    values come from ``A``: ``out[t] = Σ A-blocksᵀ · B-blocks`` is ``M @ B``, the scatter-add
    done by SciPy's C loop. Subclasses set ``indices``, ``indptr``, ``shape``, ``n_targets``,
    ``d1`` and say how ``A`` becomes the data array."""

    indices: np.ndarray
    indptr: np.ndarray
    shape: tuple[int, int]
    n_targets: int
    d1: int

    def _values(self, A: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def matrix(self, A: np.ndarray) -> sp.csc_matrix:
        """The CSC operator filled with values from ``A`` (reusable for several ``B``).

        Args:
            A: ``(nA, r, d1)`` blocks (C-contiguous).
        """
        return sp.csc_matrix((self._values(A), self.indices, self.indptr), shape=self.shape,
                             copy=False)

    def apply(self, M: sp.csc_matrix, B: np.ndarray) -> np.ndarray:
        """``M @ B`` reshaped to ``(n_targets, d1, d2)``.

        Args:
            M: From :meth:`matrix`.
            B: ``(nB, r, d2)`` blocks.
        """
        d2 = B.shape[-1]
        out = M @ B.reshape(self.shape[1], d2)
        return np.asarray(out).reshape(self.n_targets, self.d1, d2)

    def __call__(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """``out[t]`` as ``(n_targets, d1, d2)``.

        Args:
            A: ``(nA, r, d1)`` blocks.
            B: ``(nB, r, d2)`` blocks.
        """
        return self.apply(self.matrix(A), B)


class BlockContraction(_CscContraction):
    """``out[t] = Σ_{q: target[q]=t} A[a_idx[q]]ᵀ · B[b_idx[q]]`` for fixed index arrays.

    ``A`` holds blocks ``(nA, r, d1)`` and ``B`` blocks ``(nB, r, d2)``. The sum is one product of
    a CSC matrix — rows ``(t, i)``, columns ``(b_idx, k)``, values from ``A`` — with ``B`` viewed
    as ``(nB·r, d2)``: the scatter-add happens inside SciPy's C loop, and ``B`` is never gathered.
    Column ``(b, k)`` lists, for every term with ``b_idx = b``, the row ``A[a][k, :]``, so the
    values are gathered as whole ``d1``-long rows of ``A`` (one index per row, not per value).
    The layout and the row index are computed once, here.

    Args:
        target: ``(q,)`` output block of every term.
        a_idx: ``(q,)`` block of ``A`` of every term.
        b_idx: ``(q,)`` block of ``B`` of every term.
        n_targets: Number of output blocks.
        r: Shared inner dimension.
        d1: Columns of an ``A`` block (rows of an output block).
        n_b: Number of ``B`` blocks.
    """

    def __init__(
        self,
        target: np.ndarray,
        a_idx: np.ndarray,
        b_idx: np.ndarray,
        n_targets: int,
        r: int,
        d1: int,
        n_b: int,
    ) -> None:
        target = np.asarray(target, dtype=np.int64)
        a_idx, b_idx = np.asarray(a_idx, dtype=np.int64), np.asarray(b_idx, dtype=np.int64)
        order = np.lexsort((target, b_idx))
        target, a_idx, b_idx = target[order], a_idx[order], b_idx[order]
        self.n_targets, self.r, self.d1, self.n_b = n_targets, r, d1, n_b
        count = np.bincount(b_idx, minlength=n_b)  # terms per B block
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        # Columns (b, k) in order; column (b, k) holds count[b] runs of d1 entries.
        col_len = np.repeat(count * d1, r)
        indptr = np.concatenate([[0], np.cumsum(col_len)])
        k = np.arange(r)
        q_in_b = np.arange(len(b_idx)) - start[b_idx]
        # Run (b, k, q): source row a·r + k of A viewed as (nA·r, d1); output rows t·d1 + i.
        run_pos = indptr[b_idx[:, None] * r + k[None, :]] // d1 + q_in_b[:, None]
        n_runs = len(b_idx) * r
        self.rows = np.empty(n_runs, dtype=np.int64)
        self.rows[run_pos.ravel()] = (a_idx[:, None] * r + k[None, :]).ravel()
        run_target = np.empty(n_runs, dtype=np.int64)
        run_target[run_pos.ravel()] = np.broadcast_to(target[:, None], (len(b_idx), r)).ravel()
        idx_t = np.int32 if n_targets * d1 < 2**31 else np.int64
        self.indices = (run_target[:, None] * d1 + np.arange(d1)[None, :]).astype(idx_t).ravel()
        self.indptr = indptr.astype(idx_t if indptr[-1] < 2**31 else np.int64)
        self.shape = (n_targets * d1, n_b * r)

    def _values(self, A: np.ndarray) -> np.ndarray:
        return np.take(A.reshape(-1, self.d1), self.rows, axis=0).reshape(-1)


class EdgeContraction(_CscContraction):
    """``out[t] = Σ_{e ∈ sel, target[e]=t} A[e]ᵀ · B[e]``: :class:`BlockContraction` for the case
    where every term has its own ``A`` and ``B`` block (edge blocks).

    Stored as CSC with columns ``(e, k)``, whose data order is exactly ``A``'s memory order, so
    ``A`` is used as is — no gather — when every edge takes part.

    Args:
        sel: ``(q,)`` sorted edge indices that take part.
        target: ``(q,)`` output block of every selected edge.
        n_targets: Number of output blocks.
        m: Number of edges (blocks of ``A`` and ``B``).
        r: Shared inner dimension (the error dimension).
        d1: Columns of an ``A`` block.
    """

    def __init__(self, sel: np.ndarray, target: np.ndarray, n_targets: int, m: int, r: int,
                 d1: int) -> None:
        sel = np.asarray(sel, dtype=np.int64)
        self.all = len(sel) == m
        self.sel = sel
        self.n_targets, self.m, self.r, self.d1 = n_targets, m, r, d1
        count = np.zeros(m * r, dtype=np.int64)
        count.reshape(m, r)[sel] = d1
        self.indptr = np.concatenate([[0], np.cumsum(count)]).astype(np.int32)
        rows = (np.asarray(target)[:, None, None] * d1 + np.arange(d1)[None, None, :]).astype(
            np.int32)
        self.indices = np.broadcast_to(rows, (len(sel), r, d1)).ravel()
        self.shape = (n_targets * d1, m * r)

    def _values(self, A: np.ndarray) -> np.ndarray:
        return A.reshape(-1) if self.all else A[self.sel].reshape(-1)
