"""Dense Cholesky (LAPACK through scipy)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from graphopt.block_ops import NotPositiveDefiniteError
from graphopt.solvers.base import LinearSolver


class LinearSolverDense(LinearSolver):
    """Dense Cholesky factorisation; the fastest choice for small reduced systems."""

    name = "dense"

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        A = self.matrix(data).toarray()
        try:
            c = sla.cho_factor(A, lower=True, check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise NotPositiveDefiniteError(str(exc)) from exc
        x = sla.cho_solve(c, rhs, check_finite=False)
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("dense Cholesky produced non-finite values")
        return x
