"""Dense Cholesky (LAPACK through scipy)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.solvers.base import LinearSolver


class LinearSolverDense(LinearSolver):
    """Dense Cholesky factorisation; the fastest choice for small reduced systems."""

    name = "dense"

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Remember where every pattern entry goes in the dense matrix.

        Args:
            pattern: Full symmetric CSC pattern.
            block_sizes: Diagonal block sizes.
        """
        super().analyze(pattern, block_sizes)
        n = pattern.shape[0]
        cols = np.repeat(np.arange(n), np.diff(pattern.indptr))
        self._flat = cols.astype(np.int64) * n + pattern.indices  # column-major position

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        n = self.pattern.shape[0]
        flat = np.zeros(n * n)
        flat[self._flat] = data
        a = flat.reshape(n, n).T  # column-major view: LAPACK factorises it in place
        c, info = sla.lapack.dpotrf(a, lower=1, overwrite_a=1, clean=0)
        if info != 0:
            raise NotPositiveDefiniteError(f"dense Cholesky failed (LAPACK info {info})")
        x, info = sla.lapack.dpotrs(c, rhs, lower=1)
        if info != 0:
            raise NotPositiveDefiniteError(f"dense Cholesky solve failed (LAPACK info {info})")
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("dense Cholesky produced non-finite values")
        return x
