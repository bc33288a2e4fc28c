"""graphopt: g2o-style graph optimisation with batched (struct-of-arrays) edges."""

from graphopt.algorithms import (
    DoglegConfig,
    GaussNewtonConfig,
    IterationInfo,
    LevenbergConfig,
)
from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError, NotPositiveDefiniteError
from graphopt.numeric import numeric_jacobians
from graphopt.optimizer import OptimizationResult, SparseOptimizer
from graphopt.robust_kernel import (
    RobustKernel,
    RobustKernelCauchy,
    RobustKernelDCS,
    RobustKernelFair,
    RobustKernelGemanMcClure,
    RobustKernelHuber,
    RobustKernelPseudoHuber,
    RobustKernelSaturated,
    RobustKernelTukey,
    RobustKernelWelsch,
    make_kernel,
)
from graphopt.solvers import (
    LinearSolver,
    LinearSolverCholmod,
    LinearSolverDense,
    LinearSolverPCG,
    LinearSolverScipy,
    PCGConfig,
)
from graphopt.vertex import BaseVertex, VertexVector

__version__ = "0.1.0"

__all__ = [
    "BaseEdge",
    "BaseVertex",
    "DoglegConfig",
    "EdgeContext",
    "GaussNewtonConfig",
    "GraphError",
    "IterationInfo",
    "LevenbergConfig",
    "Linearization",
    "LinearSolver",
    "LinearSolverCholmod",
    "LinearSolverDense",
    "LinearSolverPCG",
    "LinearSolverScipy",
    "NotPositiveDefiniteError",
    "OptimizationResult",
    "PCGConfig",
    "RobustKernel",
    "RobustKernelCauchy",
    "RobustKernelDCS",
    "RobustKernelFair",
    "RobustKernelGemanMcClure",
    "RobustKernelHuber",
    "RobustKernelPseudoHuber",
    "RobustKernelSaturated",
    "RobustKernelTukey",
    "RobustKernelWelsch",
    "SparseOptimizer",
    "VertexVector",
    "make_kernel",
    "numeric_jacobians",
]
