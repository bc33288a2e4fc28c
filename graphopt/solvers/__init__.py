"""Linear solvers by name: ``auto``, ``cholmod``, ``dense``, ``pcg``, ``scipy`` and the
matrix-free ``iterative-schur`` (alias ``implicit-schur``)."""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp

from graphopt.solvers.auto import ReducedCostModel, choose_implicit
from graphopt.solvers.base import LinearSolver
from graphopt.solvers.cholmod import (
    CHOLMOD_AVAILABLE,
    CHOLMOD_IMPORT_ERROR,
    LinearSolverCholmod,
    cholmod_blas,
)
from graphopt.solvers.dense import LinearSolverDense
from graphopt.solvers.implicit_schur import ImplicitSchurConfig, LinearSolverImplicitSchur
from graphopt.solvers.pcg import LinearSolverPCG, PCGConfig
from graphopt.solvers.scipy_sparse import LinearSolverScipy

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex

#: The names the apps offer (``make_solver`` also takes ``implicit-schur``).
SOLVERS = ("auto", "cholmod", "dense", "pcg", "scipy", "iterative-schur")


class LinearSolverAuto(LinearSolver):
    """Implicit-Schur PCG when the explicit reduced system would not fit or would be slower;
    otherwise dense Cholesky for small, dense-ish reduced systems and CHOLMOD (or its
    fallback) for the rest.

    The first choice is made in :meth:`choose_matrix_free`, before ``S``'s pattern exists, by
    :func:`~graphopt.solvers.auto.choose_implicit` (a measured memory and time model; its
    facts are kept in ``decision``). The second in :meth:`analyze`, from the pattern: dense
    when ``n ≤ dense_max_size`` and at least ``dense_min_fill`` of the entries are
    structurally non-zero (LAPACK on a 441x441 system is several times faster than a sparse
    factorisation).

    Args:
        dense_max_size: Largest system size solved densely.
        dense_min_fill: Smallest fill ratio ``nnz / n²`` solved densely.
        model: Constants of the explicit/implicit choice (default: the measured ones).
    """

    name = "auto"

    def __init__(self, dense_max_size: int = 2000, dense_min_fill: float = 0.05,
                 model: ReducedCostModel | None = None) -> None:
        self.dense_max_size = dense_max_size
        self.dense_min_fill = dense_min_fill
        self.model = model or ReducedCostModel()
        self.chosen: LinearSolver | None = None
        self.decision: dict[str, Any] = {}

    decides_matrix_free = True

    def choose_matrix_free(self, index: BlockIndex) -> bool:
        """Choose implicit-Schur PCG by the cost model (see the class).

        Args:
            index: The block index, without a pattern yet.
        """
        implicit, self.decision = choose_implicit(index, self.model)
        self.chosen = LinearSolverImplicitSchur() if implicit else None
        return implicit

    def _choose_direct(self, n: int, nnz: float) -> LinearSolver:
        """Dense or CHOLMOD (or its fallback) for a system of ``n`` unknowns, ``nnz`` entries."""
        dense = n <= self.dense_max_size and nnz >= self.dense_min_fill * n * n
        return LinearSolverDense() if dense else make_solver("cholmod")

    def block_order(self, keys: np.ndarray, block_sizes: np.ndarray) -> np.ndarray | None:
        """Choose the direct solver now (the pattern's size and entries follow from the
        blocks) and pass on its wish (see :meth:`LinearSolver.block_order`).

        Args:
            keys: Sorted unique block keys ``col · n_blocks + row``, both triangles.
            block_sizes: Size of every block.
        """
        if isinstance(self.chosen, LinearSolverImplicitSchur):
            return None
        nb = max(len(block_sizes), 1)
        sizes = np.asarray(block_sizes, dtype=np.float64)
        nnz = float(sizes[keys % nb] @ sizes[keys // nb]) if len(keys) else 0.0
        self.chosen = self._choose_direct(int(sizes.sum()), nnz)
        return self.chosen.block_order(keys, block_sizes)

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Choose (unless implicit-Schur PCG or :meth:`block_order` chose) and analyse.

        Args:
            pattern: Full symmetric CSC pattern.
            block_sizes: Diagonal block sizes.
        """
        if self.chosen is None:
            self.chosen = self._choose_direct(pattern.shape[0], pattern.nnz)
        assert self.chosen is not None
        self.chosen.analyze(pattern, block_sizes)
        self.pattern, self.block_sizes = pattern, block_sizes

    def solve(self, data: Any, rhs: np.ndarray) -> np.ndarray:
        """Solve with the chosen solver.

        Args:
            data: Values in the analysed pattern (or the operator, when matrix-free).
            rhs: Right-hand side.
        """
        assert self.chosen is not None
        return self.chosen.solve(data, rhs)


_warned = False


def make_solver(name: str | LinearSolver) -> LinearSolver:
    """Create a linear solver by name, falling back (once, with a warning) if CHOLMOD is missing.

    Args:
        name: ``auto``, ``cholmod``, ``dense``, ``pcg``, ``scipy``, ``iterative-schur`` (or
            ``implicit-schur``), or a solver instance (returned as is).
    """
    global _warned
    if isinstance(name, LinearSolver):
        return name
    key = str(name).lower()
    if key == "cholmod":
        if CHOLMOD_AVAILABLE:
            return LinearSolverCholmod()
        if not _warned:
            warnings.warn(
                "graphopt: CHOLMOD (scikit-sparse) is not available "
                f"({CHOLMOD_IMPORT_ERROR}); using the 'scipy' sparse solver instead. "
                "Install libsuitesparse-dev and 'scikit-sparse>=0.4.16,<0.5' for CHOLMOD.",
                RuntimeWarning,
                stacklevel=2,
            )
            _warned = True
        return LinearSolverScipy()
    if key == "dense":
        return LinearSolverDense()
    if key == "auto":
        return LinearSolverAuto()
    if key == "pcg":
        return LinearSolverPCG()
    if key == "scipy":
        return LinearSolverScipy()
    if key in ("iterative-schur", "implicit-schur"):
        return LinearSolverImplicitSchur()
    raise ValueError(f"unknown linear solver {name!r}; choose one of {', '.join(SOLVERS)}")


__all__ = [
    "CHOLMOD_AVAILABLE",
    "ImplicitSchurConfig",
    "LinearSolver",
    "LinearSolverAuto",
    "LinearSolverCholmod",
    "LinearSolverDense",
    "LinearSolverImplicitSchur",
    "LinearSolverPCG",
    "LinearSolverScipy",
    "PCGConfig",
    "ReducedCostModel",
    "SOLVERS",
    "cholmod_blas",
    "make_solver",
]
