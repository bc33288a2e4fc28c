"""The scalar CSC pattern of the reduced matrix ``S`` and the maps of blocks into its data.

``S`` has a fixed pattern (both triangles): every diagonal U block, the U-U blocks that edges
couple and the fill of the Schur complement. Everything that adds blocks into ``S`` does so
through data positions resolved here, once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from graphopt.linear.indexing import sorted_unique

#: Largest ``n²`` for which data positions are looked up in a dense table.
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
        self.uoffset, self.udims, self.block_keys = uoffset, udims, block_keys
        n, nb = int(uoffset[-1]), max(len(udims), 1)
        self.n = n
        bc, br = block_keys // nb, block_keys % nb
        rows_l, cols_l = [], []
        for d1 in np.unique(udims):
            for d2 in np.unique(udims):
                sel = (udims[br] == d1) & (udims[bc] == d2)
                if sel.any():
                    r, c = self.block_entries(br[sel], bc[sel])
                    rows_l.append(r.ravel())
                    cols_l.append(c.ravel())
        rows = np.concatenate(rows_l) if rows_l else np.zeros(0, np.int64)
        cols = np.concatenate(cols_l) if cols_l else np.zeros(0, np.int64)
        keys = sorted_unique(cols.astype(np.int64) * n + rows)
        self._keys = keys
        # Small systems: a dense (col, row) → position table is faster than binary searches.
        self._posmap: np.ndarray | None = None
        if n * n <= POSMAP_MAX:
            self._posmap = np.full(n * n, -1, dtype=np.int64)
            self._posmap[keys] = np.arange(len(keys))
        indices = (keys % max(n, 1)).astype(np.int32)
        indptr = np.searchsorted(keys // max(n, 1), np.arange(n + 1)).astype(np.int32)
        self.csc = sp.csc_matrix((np.zeros(len(keys)), indices, indptr), shape=(n, n))
        self.nnz = len(keys)
        diag = np.arange(n)
        self.diag_pos = self.positions(diag, diag)

    def positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Data positions of scalar entries ``(rows, cols)`` (which must be in the pattern).

        Args:
            rows: Scalar rows.
            cols: Scalar columns, same shape.
        """
        k = cols.astype(np.int64) * self.n + rows
        if self._posmap is not None:
            return self._posmap[k]
        return np.searchsorted(self._keys, k)

    def has_blocks(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Whether every U block ``(rows[i], cols[i])`` is in the pattern.

        Args:
            rows: Row U blocks.
            cols: Column U blocks.
        """
        return np.isin(cols * max(len(self.udims), 1) + rows, self.block_keys)

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

    def dest(self, br: np.ndarray, bc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Data positions of blocks ``(br, bc)`` and of their transposes, entry-aligned.

        Args:
            br: Row U blocks (all of one dimension).
            bc: Column U blocks (all of one dimension).
        """
        r, c = self.block_entries(br, bc)
        d1, d2 = int(self.udims[br[0]]), int(self.udims[bc[0]])
        pos = self.positions(r, c)
        post = self.positions(c.reshape(-1, d1, d2), r.reshape(-1, d1, d2))
        return pos, post.reshape(len(br), -1)

    def to_s(self, tu1: np.ndarray, tu2: np.ndarray) -> sp.csr_matrix:
        """The constant 0/1 matrix that sums result blocks ``(tu1, tu2)`` (row-major, one after
        the other) into ``S``'s data: both triangles for ``tu1 != tu2``.

        Args:
            tu1: Row U block of every result block.
            tu2: Column U block of every result block.
        """
        pos, post = self.dest(tu1, tu2)
        off = tu1 != tu2
        src = np.arange(pos.size).reshape(pos.shape)
        rows = np.concatenate([pos.ravel(), post[off].ravel()])
        cols = np.concatenate([src.ravel(), src[off].ravel()])
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.nnz, pos.size))
