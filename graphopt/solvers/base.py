"""The linear-solver interface: analyse a fixed pattern once, then solve with new numbers.

The direct solvers report a rank-deficient system by one rule, :mod:`graphopt.solvers.rank`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.linear.pattern import with_data

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex


class LinearSolver:
    """Solves ``A x = b`` for symmetric positive definite ``A`` in a fixed sparsity pattern.

    ``analyze`` sees the pattern once (at ``initialize_optimization``); ``solve`` is called every
    iteration with new values in that pattern.
    """

    name = "base"
    #: Whether the solver works on products with ``S`` alone (an operator instead of values in
    #: a pattern): then ``S``'s fill, the Schur strategies and any factorisation are never built.
    matrix_free = False
    #: Whether :meth:`choose_matrix_free` decides from the block index (``auto``); else the
    #: answer is :attr:`matrix_free`, known before the index is built (it then numbers the V
    #: blocks for the products it will compute).
    decides_matrix_free = False

    def choose_matrix_free(self, index: BlockIndex) -> bool:
        """Whether this solver wants the matrix-free system, asked once before ``S``'s pattern
        is built (a solver that chooses, like ``auto``, decides here).

        Args:
            index: The block index, its U, V and W blocks numbered, without a pattern yet.
        """
        return self.matrix_free

    def block_order(self, keys: np.ndarray, block_sizes: np.ndarray) -> np.ndarray | None:
        """An order of the unknowns' blocks this solver wants the pattern built in, asked once
        before the pattern exists (problems without marginalised vertices only); ``None``
        (the default): the graph's order.

        Args:
            keys: The non-zero blocks of the system as sorted unique keys
                ``col · n_blocks + row`` (both triangles and the diagonal).
            block_sizes: Size of every block.

        Returns:
            The block placed at each position, or ``None``.
        """
        return None

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Prepare for matrices with this pattern (symbolic work happens here).

        Args:
            pattern: Full symmetric CSC pattern (both triangles; the direct solvers and PCG
                need every diagonal entry). A pattern built by graphopt carries the data
                position of every diagonal entry as ``pattern.diag_pos`` (checked here, in
                ``n`` reads instead of a pass over all entries).
            block_sizes: Sizes of the diagonal blocks, in order.
        """
        self.pattern = pattern
        self.block_sizes = block_sizes
        n = pattern.shape[0]
        diag_pos = getattr(pattern, "diag_pos", None)
        if isinstance(diag_pos, np.ndarray) and len(diag_pos) == n:
            ip = pattern.indptr
            ok = np.all((diag_pos >= ip[:-1]) & (diag_pos < ip[1:])) and np.array_equal(
                pattern.indices[diag_pos], np.arange(n))
            if ok:
                self._diag_pos = np.asarray(diag_pos)
                return
        cols = np.repeat(np.arange(n), np.diff(pattern.indptr))
        found = np.flatnonzero(pattern.indices == cols)
        self._diag_pos = found if len(found) == n else None

    @property
    def diag_pos(self) -> np.ndarray:
        """Data position of every diagonal entry ``A_kk``, ``k = 0..n-1``, in the pattern.

        Raises:
            ValueError: if the analysed pattern lacks one (the rank rule reads ``A``'s diagonal).
        """
        if self._diag_pos is None:
            raise ValueError(f"{self.name}: the pattern lacks diagonal entries")
        return self._diag_pos

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The matrix with ``data`` in the analysed pattern.

        Args:
            data: Values, ``(nnz,)``.
        """
        return with_data(self.pattern, data)

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Solve with the given values.

        Args:
            data: Values in the analysed pattern.
            rhs: ``(n,)`` or ``(n, k)`` right-hand side.

        Raises:
            SingularSystemError: if the matrix is positive semi-definite but rank deficient.
            NotPositiveDefiniteError: if the matrix is not positive definite.
        """
        raise NotImplementedError
