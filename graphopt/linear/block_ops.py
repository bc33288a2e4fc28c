"""Small batched linear-algebra kernels and the constant-structure sparse contractions."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError

try:  # SciPy's C kernels of ``csr @ dense`` and ``csc @ dense``; they accumulate into a
    # given output array.
    from scipy.sparse._sparsetools import csc_matvec as _csc_matvec
    from scipy.sparse._sparsetools import csc_matvecs as _csc_matvecs
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
    from scipy.sparse._sparsetools import csr_matvecs as _csr_matvecs
except ImportError:  # pragma: no cover - private module: fall back to the public product
    _csr_matvecs = _csc_matvecs = _csr_matvec = _csc_matvec = None


def batched_cholesky_inverses(
    A: np.ndarray, diag: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``L⁻¹`` and ``(A + diag)⁻¹ = L⁻ᵀL⁻¹`` for many SPD matrices ``A + diag = LLᵀ``.

    For ``d ≤ 4`` Cholesky, the triangular inverse and the product are unrolled over the
    entries and vectorised over the blocks (a dozen array operations for ``d = 3``, no
    per-block LAPACK call); larger blocks use batched LAPACK. The damping ``diag`` is added on
    the fly, so ``A`` is neither copied nor changed.

    Args:
        A: ``(n, d, d)`` symmetric matrices (only the lower triangle is read).
        diag: Optional ``(n, d)`` added to the diagonals.

    Returns:
        ``(L⁻¹, A⁻¹)``, both ``(n, d, d)``; ``L⁻¹`` is lower triangular.

    Raises:
        NotPositiveDefiniteError: if any block is not positive definite.
    """
    n, d, _ = A.shape
    if d > 4:
        Ad = A.copy()
        if diag is not None:
            Ad[:, np.arange(d), np.arange(d)] += diag
        try:
            m_full = np.tril(np.linalg.inv(np.linalg.cholesky(Ad)))  # exact zeros above
        except np.linalg.LinAlgError as exc:
            raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite") from exc
        return m_full, np.swapaxes(m_full, 1, 2) @ m_full
    a = A.reshape(n, d * d)
    L: dict[tuple[int, int], np.ndarray] = {}
    m: dict[tuple[int, int], np.ndarray] = {}  # L⁻¹
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(d):  # Cholesky–Crout, column by column
            s = a[:, j * d + j] if diag is None else a[:, j * d + j] + diag[:, j]
            for k in range(j):
                s = s - L[j, k] * L[j, k]
            m[j, j] = 1.0 / np.sqrt(s)  # NaN or inf unless the pivot is positive
            for i in range(j + 1, d):
                t = a[:, i * d + j]
                for k in range(j):
                    t = t - L[i, k] * L[j, k]
                L[i, j] = t * m[j, j]
        for i in range(1, d):  # forward substitution for the strictly lower part of L⁻¹
            for j in range(i):
                t = L[i, j] * m[j, j]
                for k in range(j + 1, i):
                    t = t + L[i, k] * m[k, j]
                m[i, j] = -t * m[i, i]
        linv = np.zeros((n, d * d))
        inv = np.empty((n, d * d))
        for i in range(d):
            for j in range(i + 1):
                linv[:, i * d + j] = m[i, j]
                t = m[i, i] * m[i, j]
                for k in range(i + 1, d):
                    t = t + m[k, i] * m[k, j]
                inv[:, i * d + j] = t
                inv[:, j * d + i] = t
    if not np.isfinite(inv[:, :: d + 1].sum()):
        raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite")
    return linv.reshape(n, d, d), inv.reshape(n, d, d)


try:  # SciPy's block-sparse kernel (a dense product per block, in one C loop)
    from scipy.sparse._sparsetools import bsr_matvecs as _bsr_matvecs
except ImportError:  # pragma: no cover - private module: numpy's matmul instead
    _bsr_matvecs = None

#: ``arange(n + 1)`` and ``arange(n)`` as int32, per ``n`` (the block-diagonal pattern).
_DIAGONAL: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def block_products(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A[i] @ B[i]`` for every ``i``: ``(n, p, q) x (n, q, k) -> (n, p, k)``.

    NumPy's stacked ``matmul`` pays about 60 ns per pair of small matrices; SciPy's BSR kernel
    on the block-diagonal matrix whose blocks are ``A`` does the same products in one C loop
    (2,807 pairs of 3x3 by 3x6: 163 -> 64 µs; 3x9: 175 -> 93 µs).

    Args:
        A: ``(n, p, q)`` blocks.
        B: ``(n, q, k)`` blocks.
    """
    n, p, q = A.shape
    k = B.shape[2]
    if _bsr_matvecs is None or n >= 2**31 or not n:
        return np.matmul(A, B)
    diag = _DIAGONAL.get(n)
    if diag is None:
        if len(_DIAGONAL) > 16:
            _DIAGONAL.clear()
        diag = _DIAGONAL[n] = (np.arange(n + 1, dtype=np.int32), np.arange(n, dtype=np.int32))
    out = np.zeros(n * p * k)
    _bsr_matvecs(n, n, k, p, q, diag[0], diag[1],
                 np.ascontiguousarray(A, dtype=float).reshape(-1),
                 np.ascontiguousarray(B, dtype=float).reshape(-1), out)
    return out.reshape(n, p, k)


def csr_product_into(
    n_rows: int,
    n_cols: int,
    width: int,
    indptr: np.ndarray,
    indices: np.ndarray,
    data: np.ndarray,
    b: np.ndarray,
    out: np.ndarray,
    csc: bool = False,
) -> None:
    """``out = A @ B`` for a CSR (or CSC) matrix ``A`` and a dense ``B``, written into ``out``.

    Writing into a preallocated (cache-resident) buffer instead of a new array saves an
    allocation and its page faults per product; SciPy's public product is the fallback.

    Args:
        n_rows: Rows of ``A``.
        n_cols: Columns of ``A`` (rows of ``B``).
        width: Columns of ``B``.
        indptr: ``A``'s row (column, for CSC) pointer (same integer type as ``indices``).
        indices: ``A``'s column (row) indices.
        data: ``A``'s values (float64).
        b: ``B`` flattened, C order, at least ``n_cols · width`` values (the first are used).
        out: Flat C-order output of ``n_rows · width`` values (overwritten).
        csc: ``A`` is given in CSC form.
    """
    kernel = _csc_matvecs if csc else _csr_matvecs
    if kernel is None:
        fmt = sp.csc_matrix if csc else sp.csr_matrix
        a = fmt((data, indices, indptr), shape=(n_rows, n_cols))
        out[:] = (a @ b[:n_cols * width].reshape(n_cols, width)).reshape(-1)
        return
    out.fill(0.0)
    if width == 1:  # the one-vector kernel: the same sums in the same order, a third faster
        (_csc_matvec if csc else _csr_matvec)(n_rows, n_cols, indptr, indices, data, b, out)
        return
    kernel(n_rows, n_cols, width, indptr, indices, data, b, out)


class _CscContraction:
    """A constant-structure CSC operator ``M`` (rows ``(t, i)``, ``shape[1]`` rows of ``B``) whose
    values come from ``A``: ``out[t] = Σ A-blocksᵀ · B-blocks`` is ``M @ B``, the scatter-add
    done by SciPy's C loop. Subclasses set ``indices``, ``indptr``, ``shape``, ``n_targets``,
    ``d1`` and say how ``A`` becomes the data array; ``single`` when every block of ``A`` and
    ``B``, in order, sums into one target (then ``AᵀB`` is one matrix product)."""

    indices: np.ndarray
    indptr: np.ndarray
    shape: tuple[int, int]
    n_targets: int
    d1: int
    single: bool = False

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

    def __call__(self, A: np.ndarray, B: np.ndarray, out: np.ndarray | None = None
                 ) -> np.ndarray:
        """``out[t]`` as ``(n_targets, d1, d2)``: SciPy's CSC kernel on the values directly
        (no ``csc_matrix`` object: its constructor's checks cost 20–40 µs a call, most of an
        assembly on small graphs).

        Args:
            A: ``(nA, r, d1)`` blocks.
            B: ``(nB, r, d2)`` blocks.
            out: Flat ``(n_targets · d1 · d2,)`` array to write into (overwritten); a new one
                when ``None``.
        """
        d2 = B.shape[-1]
        if self.single:  # one target summing every block: one BLAS product, no scatter
            res = np.matmul(A.reshape(-1, self.d1).T, B.reshape(-1, d2))
            if out is None:
                return res.reshape(1, self.d1, d2)
            out[:self.d1 * d2] = res.reshape(-1)
            return out[:self.d1 * d2].reshape(1, self.d1, d2)
        if self.indptr.dtype != self.indices.dtype:  # the kernel takes one index type
            res = self.apply(self.matrix(A), B)
            if out is not None:
                out[:] = res.reshape(-1)
            return res
        b = np.ascontiguousarray(B, dtype=float).reshape(-1)
        data = np.ascontiguousarray(self._values(A), dtype=float)
        if out is None:
            out = np.empty(self.shape[0] * d2)
        csr_product_into(self.shape[0], self.shape[1], d2, self.indptr, self.indices, data, b,
                         out, csc=True)
        return out[:self.n_targets * self.d1 * d2].reshape(self.n_targets, self.d1, d2)

    def out_size(self, d2: int) -> int:
        """Values an ``out`` buffer for ``B`` blocks of width ``d2`` needs (an
        :class:`EdgeContraction` with a scratch block needs one block more than the result).

        Args:
            d2: Columns of a ``B`` block.
        """
        return self.shape[0] * d2


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
    ``A`` is used as is — no gather — when every edge takes part. When most do (the edges of a
    fixed vertex left out), the others are summed into one scratch block past the targets
    rather than gathered out: ``A`` is still used as is (w10000, 64k edges, a pose fixed: the
    gathers of ``J`` cost 2.3 ms an iteration).

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
        # Scratch when the left-out edges are few: their products cost less than the gather.
        self.scratch = not self.all and 4 * len(sel) >= 3 * m
        if self.scratch:
            full = np.full(m, n_targets, dtype=np.int64)
            full[sel] = target
            sel, target = np.arange(m), full
        if len(sel) == m:  # every column holds d1 entries
            self.indptr = np.arange(m * r + 1, dtype=np.int32) * np.int32(d1)
        else:
            count = np.zeros(m * r, dtype=np.int64)
            count.reshape(m, r)[sel] = d1
            self.indptr = np.concatenate([[0], np.cumsum(count)]).astype(np.int32)
        rows = (np.asarray(target)[:, None, None] * d1 + np.arange(d1)[None, None, :]).astype(
            np.int32)
        self.indices = np.broadcast_to(rows, (len(sel), r, d1)).ravel()
        self.shape = ((n_targets + self.scratch) * d1, m * r)
        # A motion-only BA's pose block: all edges into one target.
        self.single = self.all and n_targets == 1

    def _values(self, A: np.ndarray) -> np.ndarray:
        return A.reshape(-1) if self.all or self.scratch else A[self.sel].reshape(-1)
