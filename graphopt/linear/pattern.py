"""The scalar CSC pattern of the reduced matrix ``S`` and the maps of blocks into its data.

``S`` has a fixed pattern (both triangles): every diagonal U block, the U-U blocks that edges
couple and the fill of the Schur complement. Everything that adds blocks into ``S`` does so
through data positions resolved here, once.

The pattern is built and looked up block by block: a scalar column of block column ``c``
lists the rows of ``c``'s blocks one after the other, so the position of an entry is its
column's start, plus the rows of the blocks above it in that column, plus its row within its
block. Nothing is kept per scalar entry but the CSC indices (the pattern's data is zeros that
the OS allocates on first touch).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from graphopt.linear.indexing import concat_ranges

#: Largest ``n_ublocks²`` for which block positions are looked up in a dense table.
POSMAP_MAX = 4_000_000


def with_data(pattern: sp.csc_matrix, data: np.ndarray) -> sp.csc_matrix:
    """The matrix with ``data`` in a CSC pattern (no copy of the index arrays).

    Args:
        pattern: The CSC pattern.
        data: ``(nnz,)`` values.
    """
    return sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape)


class ReducedPattern:
    """The CSC pattern of ``S`` over the U blocks, with position lookups.

    Args:
        uoffset: ``(n_ublocks + 1,)`` scalar offset of every U block, then ``n``.
        udims: ``(n_ublocks,)`` dimension of every U block.
        block_keys: Sorted unique ``col · n_ublocks + row`` of every non-zero U block of ``S``
            (symmetric: a block and its transpose).

    Attributes:
        csc: The pattern as a CSC matrix of zeros (``int32`` indices).
        nnz: Stored entries.
        diag_pos: ``(n,)`` data position of every diagonal entry.
    """

    def __init__(self, uoffset: np.ndarray, udims: np.ndarray, block_keys: np.ndarray) -> None:
        self.uoffset, self.udims = uoffset, udims
        self.block_keys = np.asarray(block_keys, dtype=np.int64)
        if len(udims) == 1 and len(self.block_keys) == 1 and udims[0] > 0:
            self._one_block(int(udims[0]))
            return
        n, nb = int(uoffset[-1]), max(len(udims), 1)
        self.n, self._nb = n, nb
        bc, br = self.block_keys // nb, self.block_keys % nb
        rdim = udims[br] if len(br) else np.zeros(0, np.int64)
        # Rows of the blocks above each block in its block column (keys are sorted by column).
        col_first = np.searchsorted(self.block_keys, np.arange(nb + 1) * nb)
        above = np.cumsum(rdim) - rdim
        self._rowoff = above - above[np.repeat(col_first[:-1], np.diff(col_first))]
        col_rows = np.bincount(bc, weights=rdim, minlength=nb).astype(np.int64)[:len(udims)]
        # Scalar column j of block column c holds col_rows[c] entries.
        per_col = np.repeat(col_rows, udims) if len(udims) else np.zeros(0, np.int64)
        self._indptr = np.concatenate([[0], np.cumsum(per_col)]).astype(np.int64)
        self.nnz = int(self._indptr[-1])
        idx_t = np.int32 if max(n, self.nnz) < 2**31 else np.int64
        # Block positions in the index type: half the memory of int64 for the (q, d1, d2)
        # arrays every U term's destinations are built from.
        self._ptr = self._indptr.astype(idx_t)
        self._rowoff = self._rowoff.astype(idx_t)
        # Small systems: a dense block → key-rank table is faster than binary searches.
        self._table: np.ndarray | None = None
        if nb * nb <= POSMAP_MAX:
            self._table = np.full(nb * nb, -1, dtype=np.int32)
            self._table[self.block_keys] = np.arange(len(self.block_keys))
        # Every scalar column of block column c lists the same rows: those of c's blocks, in
        # order (one list per block column, in key order), read once per scalar column.
        rows = concat_ranges(uoffset[br], rdim)
        first = np.cumsum(col_rows) - col_rows  # where block column c's list starts
        colblock = np.repeat(np.arange(len(udims)), udims)
        indices = rows[concat_ranges(first[colblock], col_rows[colblock])].astype(idx_t)
        self.csc = sp.csc_matrix((np.zeros(self.nnz), indices, self._ptr.copy()),
                                 shape=(n, n))
        diag = np.arange(n)
        self.diag_pos = self.positions(diag, diag)
        self.csc.diag_pos = self.diag_pos  # for the linear solvers' analyze (they check it)

    def _one_block(self, d: int) -> None:
        """The general construction's result for one dense ``(d, d)`` block (a pose, a Sim3),
        in a few numpy calls: ``S`` is built at every initialisation of a motion-only BA."""
        self.n, self._nb, self.nnz = d, 1, d * d
        self._indptr = np.arange(0, d * d + 1, d, dtype=np.int64)
        self._ptr = self._indptr.astype(np.int32)
        self._rowoff = np.zeros(1, dtype=np.int32)
        self._table = np.zeros(1, dtype=np.int32)
        indices = np.tile(np.arange(d, dtype=np.int32), d)
        self.csc = sp.csc_matrix((np.zeros(self.nnz), indices, self._ptr.copy()), shape=(d, d))
        self.diag_pos = np.arange(d, dtype=np.int64) * (d + 1)
        self.csc.diag_pos = self.diag_pos

    def _lookup(self, keys: np.ndarray) -> np.ndarray:
        """Rank of every block key among ``block_keys`` (−1: not in the pattern)."""
        if self._table is not None:
            return self._table[keys]
        k = np.minimum(np.searchsorted(self.block_keys, keys), max(len(self.block_keys) - 1, 0))
        return np.where(self.block_keys[k] == keys, k, -1) if len(self.block_keys) else \
            np.full(len(keys), -1, dtype=np.int64)

    def _block_positions(self, br: np.ndarray, bc: np.ndarray, rank: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Data positions ``(q, d1·d2)`` (row-major within a block) of blocks ``(br, bc)`` of
        one shape, and their ranks (computed unless given)."""
        if rank is None:
            rank = self._lookup(bc.astype(np.int64) * self._nb + br)
        d1, d2 = int(self.udims[br[0]]), int(self.udims[bc[0]])
        start = self._ptr[self.uoffset[bc][:, None] + np.arange(d2)] + self._rowoff[rank][:, None]
        # (q, i, j) → column j's start + i
        pos = start[:, None, :] + np.arange(d1, dtype=start.dtype)[None, :, None]
        return pos.reshape(len(br), d1 * d2), rank

    def positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Data positions of scalar entries ``(rows, cols)`` (which must be in the pattern).

        Args:
            rows: Scalar rows.
            cols: Scalar columns, same shape.
        """
        rows, cols = np.asarray(rows), np.asarray(cols)
        br = np.searchsorted(self.uoffset, rows, side="right") - 1
        bc = np.searchsorted(self.uoffset, cols, side="right") - 1
        rank = self._lookup(bc.astype(np.int64) * self._nb + br)
        return self._indptr[cols] + self._rowoff[rank] + (rows - self.uoffset[br])

    def has_blocks(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Whether every U block ``(rows[i], cols[i])`` is in the pattern.

        Args:
            rows: Row U blocks.
            cols: Column U blocks.
        """
        return self._lookup(np.asarray(cols, dtype=np.int64) * self._nb + rows) >= 0

    def block_entries(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scalar (row, col) of every entry of blocks ``(r, c)`` (all of one shape),
        row-major within a block, as two ``(len(r), d1·d2)`` arrays.

        Args:
            r: Row U blocks.
            c: Column U blocks.
        """
        if len(r) == 0:
            return np.zeros((0, 0), np.int64), np.zeros((0, 0), np.int64)
        d1, d2 = int(self.udims[r[0]]), int(self.udims[c[0]])
        rows = self.uoffset[r][:, None, None] + np.arange(d1)[None, :, None]
        cols = self.uoffset[c][:, None, None] + np.arange(d2)[None, None, :]
        rows, cols = np.broadcast_arrays(rows, cols)
        return rows.reshape(len(r), -1), cols.reshape(len(r), -1)

    def dest(self, br: np.ndarray, bc: np.ndarray, transposes: bool = True
             ) -> tuple[np.ndarray, np.ndarray | None]:
        """Data positions of blocks ``(br, bc)`` and of their transposes, entry-aligned.

        Args:
            br: Row U blocks (all of one dimension).
            bc: Column U blocks (all of one dimension).
            transposes: Also the transposes' positions (else ``None``: diagonal blocks).
        """
        if len(br) == 0:
            return np.zeros((0, 0), np.int64), np.zeros((0, 0), np.int64) if transposes else None
        pos, _ = self._block_positions(br, bc)
        if not transposes:
            return pos, None
        post, _ = self._block_positions(bc, br)  # (q, j, i) of the transpose
        d1, d2 = int(self.udims[br[0]]), int(self.udims[bc[0]])
        return pos, post.reshape(len(br), d2, d1).transpose(0, 2, 1).reshape(len(br), -1)

    def to_s(self, tu1: np.ndarray, tu2: np.ndarray) -> sp.csr_matrix:
        """The constant 0/1 matrix that sums result blocks ``(tu1, tu2)`` (row-major, one after
        the other) into ``S``'s data: both triangles for ``tu1 != tu2``.

        Args:
            tu1: Row U block of every result block.
            tu2: Column U block of every result block.
        """
        pos, post = self.dest(tu1, tu2)
        assert post is not None
        off = tu1 != tu2
        src = np.arange(pos.size).reshape(pos.shape)
        rows = np.concatenate([pos.ravel(), post[off].ravel()])
        cols = np.concatenate([src.ravel(), src[off].ravel()])
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.nnz, pos.size))
