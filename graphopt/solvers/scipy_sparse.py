"""Sparse LU from SciPy (SuperLU): the fallback when CHOLMOD is not installed."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse.linalg as spla

from graphopt.errors import NotPositiveDefiniteError
from graphopt.solvers.base import LinearSolver


class LinearSolverScipy(LinearSolver):
    """SuperLU in symmetric mode (no pivoting off the diagonal), so a non-positive pivot
    reveals a matrix that is not positive definite."""

    name = "scipy"

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        A = self.matrix(data)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", spla.MatrixRankWarning)
                lu = spla.splu(
                    A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True},
                )
        except (RuntimeError, spla.MatrixRankWarning) as exc:
            raise NotPositiveDefiniteError(f"sparse LU failed: {exc}") from exc
        x = lu.solve(np.asarray(rhs, dtype=float))
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("sparse LU produced non-finite values")
        # An indefinite matrix passes LU; reject steps that are not descent directions.
        d = lu.U.diagonal()
        if np.any(d <= 0):
            raise NotPositiveDefiniteError("the matrix is not positive definite")
        return x
