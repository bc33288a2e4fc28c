"""Sparse LU from SciPy (SuperLU): the fallback when CHOLMOD is not installed."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from graphopt.errors import NotPositiveDefiniteError
from graphopt.solvers.base import LinearSolver
from graphopt.solvers.rank import checked_solve, shift_diagonal


class LinearSolverScipy(LinearSolver):
    """SuperLU in symmetric mode with diagonal pivots (``diag_pivot_thresh=0``): the column
    ordering is applied to the rows too, so ``U``'s diagonal holds the pivots ``D_k`` of
    ``PAPᵀ = LDLᵀ``, held to the rank rule of :mod:`graphopt.solvers.rank`. SuperLU leaves the
    diagonal only where its pivot is exactly zero (then ``perm_r ≠ perm_c``); that, or a zero
    column ("exactly singular"), counts as a non-positive pivot."""

    name = "scipy"

    @staticmethod
    def _lu(a: sp.csc_matrix) -> spla.SuperLU | None:
        """The LU factors, or ``None`` where SuperLU finds a zero column."""
        try:
            return spla.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True})
        except RuntimeError:  # "Factor is exactly singular"
            return None

    @staticmethod
    def _pivots(lu: spla.SuperLU) -> tuple[np.ndarray, np.ndarray, int | None]:
        """The pivots, the unknown of each step and the first step whose pivot left the
        diagonal (``None`` if none did)."""
        order = np.argsort(lu.perm_c)  # step k eliminates column order[k]
        rows = np.argsort(lu.perm_r)
        off = np.flatnonzero(rows != order)
        return lu.U.diagonal(), order, int(off[0]) if len(off) else None

    def _shifted_is_definite(self, data: np.ndarray, scale: np.ndarray) -> bool:
        """Whether ``A + τ·S`` factorises with positive, finite diagonal pivots."""
        lu = self._lu(self.matrix(shift_diagonal(data, self.diag_pos, scale)))
        if lu is None:
            return False
        d, _, off = self._pivots(lu)
        return off is None and bool(np.all(np.isfinite(d)) and np.all(d > 0))

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side.
        """
        diag = data[self.diag_pos]

        def shifted(scale: np.ndarray) -> bool:
            return self._shifted_is_definite(data, scale)

        lu = self._lu(self.matrix(data))
        if lu is None:  # SuperLU does not say at which step; step 3 decides (and raises)
            return checked_solve(self.name, np.empty(0), diag, np.asarray, rhs, shifted,
                                 stopped_at=-1)
        pivots, order, off = self._pivots(lu)
        x = checked_solve(self.name, pivots[:off], diag, lu.solve,
                          np.asarray(rhs, dtype=float), shifted, unknowns=order, stopped_at=off)
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("sparse LU produced non-finite values")
        return x
