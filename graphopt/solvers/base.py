"""The linear-solver interface: analyse a fixed pattern once, then solve with new numbers."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from graphopt.linear.pattern import with_data


class LinearSolver:
    """Solves ``A x = b`` for symmetric positive definite ``A`` in a fixed sparsity pattern.

    ``analyze`` sees the pattern once (at ``initialize_optimization``); ``solve`` is called every
    iteration with new values in that pattern.
    """

    name = "base"

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Prepare for matrices with this pattern (symbolic work happens here).

        Args:
            pattern: Full symmetric CSC pattern (both triangles).
            block_sizes: Sizes of the diagonal blocks, in order.
        """
        self.pattern = pattern
        self.block_sizes = block_sizes

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
            NotPositiveDefiniteError: if the matrix is not positive definite.
        """
        raise NotImplementedError
