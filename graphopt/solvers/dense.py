"""Dense Cholesky (LAPACK through scipy)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.solvers.base import LinearSolver
from graphopt.solvers.rank import checked_solve, shift_diagonal


class LinearSolverDense(LinearSolver):
    """Dense Cholesky factorisation; the fastest choice for small reduced systems.

    ``dpotrf`` reports only a pivot that is not positive; the pivots ``L_kk²`` are also held to
    the rank rule of :mod:`graphopt.solvers.rank`, which rejects the positive pivot of rounding
    size that some BLAS kernels produce on a singular system.
    """

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
        # A full pattern (one pose's 6x6) is the column-major array itself: a copy, no scatter.
        self._full = bool(np.array_equal(self._flat, np.arange(n * n)))

    def _factor(self, data: np.ndarray) -> tuple[np.ndarray, int]:
        """``L`` (lower triangle of a column-major array; garbage above) and LAPACK's info."""
        n = self.pattern.shape[0]
        if self._full:
            flat = np.array(data, dtype=float)
        else:
            flat = np.zeros(n * n)
            flat[self._flat] = data
        return factor_in_place(flat, n)

    def _shifted_is_definite(self, data: np.ndarray, scale: np.ndarray) -> bool:
        """Whether ``A + τ·S`` has a Cholesky factor with positive, finite pivots."""
        return is_definite(self._factor(shift_diagonal(data, self.diag_pos, scale)))

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        return cholesky_solve(self.name, self._factor(data), data[self.diag_pos], rhs,
                              lambda s: self._shifted_is_definite(data, s))


def factor_in_place(flat: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """LAPACK's ``dpotrf`` of an ``(n, n)`` symmetric matrix given as its column-major data,
    factored in place (pass data of your own): ``(L in the lower triangle, info)``.

    Args:
        flat: ``(n²,)`` column-major data (a C array read as its transpose: no copy).
        n: The order.
    """
    return sla.lapack.dpotrf(flat.reshape(n, n).T, lower=1, overwrite_a=1, clean=0)


def is_definite(factor: tuple[np.ndarray, int]) -> bool:
    """Whether a ``dpotrf`` factor has positive, finite pivots (the rank rule's step 3).

    Args:
        factor: ``(L, info)``.
    """
    c, info = factor
    p = np.diagonal(c)
    return info == 0 and bool(np.all(np.isfinite(p)) and np.all(p > 0))


def cholesky_solve(name: str, factor: tuple[np.ndarray, int], diag: np.ndarray, rhs: np.ndarray,
                   shifted_is_definite: Callable[[np.ndarray], bool]) -> np.ndarray:
    """Solve with ``dpotrf``'s factor, held to the rank rule of :mod:`graphopt.solvers.rank`.

    Args:
        name: The solver's name, for messages.
        factor: ``(L, info)`` as ``dpotrf`` returned them (lower triangle).
        diag: The matrix's diagonal.
        rhs: The right-hand side.
        shifted_is_definite: See :func:`~graphopt.solvers.rank.checked_solve`.

    Raises:
        NotPositiveDefiniteError: the matrix is not positive definite (or singular), or the
            solution is not finite.
    """
    c, info = factor
    if info < 0:
        raise ValueError(f"dpotrf: illegal argument {-info}")
    done = info - 1 if info > 0 else len(c)  # dpotrf stops at pivot info - 1

    def apply_inverse(b: np.ndarray) -> np.ndarray:
        x, info = sla.lapack.dpotrs(c, b, lower=1)
        if info != 0:
            raise NotPositiveDefiniteError(f"dense Cholesky solve failed (LAPACK info {info})")
        return x

    x = checked_solve(name, c.diagonal()[:done] ** 2, diag, apply_inverse, rhs,
                      shifted_is_definite, stopped_at=None if info == 0 else done)
    if not np.isfinite(x).all():
        raise NotPositiveDefiniteError("dense Cholesky produced non-finite values")
    return x
