"""Linear solvers by name: ``cholmod``, ``dense``, ``pcg``, ``scipy``."""

from __future__ import annotations

import warnings

from graphopt.solvers.base import LinearSolver
from graphopt.solvers.cholmod import CHOLMOD_AVAILABLE, CHOLMOD_IMPORT_ERROR, LinearSolverCholmod
from graphopt.solvers.dense import LinearSolverDense
from graphopt.solvers.pcg import LinearSolverPCG, PCGConfig
from graphopt.solvers.scipy_sparse import LinearSolverScipy

SOLVERS = ("cholmod", "dense", "pcg", "scipy")
_warned = False


def make_solver(name: str | LinearSolver) -> LinearSolver:
    """Create a linear solver by name, falling back (once, with a warning) if CHOLMOD is missing.

    Args:
        name: ``cholmod``, ``dense``, ``pcg``, ``scipy``, or a solver instance (returned as is).
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
    if key == "pcg":
        return LinearSolverPCG()
    if key == "scipy":
        return LinearSolverScipy()
    raise ValueError(f"unknown linear solver {name!r}; choose one of {', '.join(SOLVERS)}")


__all__ = [
    "CHOLMOD_AVAILABLE",
    "LinearSolver",
    "LinearSolverCholmod",
    "LinearSolverDense",
    "LinearSolverPCG",
    "LinearSolverScipy",
    "PCGConfig",
    "SOLVERS",
    "make_solver",
]
