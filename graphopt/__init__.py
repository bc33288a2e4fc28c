"""graphopt: g2o-style graph optimisation with batched (struct-of-arrays) edges."""

from graphopt.algorithms import DoglegConfig, GaussNewtonConfig, LevenbergConfig
from graphopt.autodiff import Jet, JetError
from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.errors import GraphError, NotPositiveDefiniteError, SingularSystemError
from graphopt.jacobian_check import JacobianCheck, check_jacobians, edge_jacobians
from graphopt.linear import SchurConfig
from graphopt.numeric import numeric_jacobians
from graphopt.online import IncrementalConfig, IncrementalOptimizer, UpdateReport
from graphopt.optimizer import SparseOptimizer
from graphopt.problem import Problem
from graphopt.result import IterationInfo, OptimizationResult, StopReason
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
    ImplicitSchurConfig,
    LinearSolver,
    LinearSolverCholmod,
    LinearSolverDense,
    LinearSolverImplicitSchur,
    LinearSolverPCG,
    LinearSolverScipy,
    PCGConfig,
)
from graphopt.stopping import StoppingConfig
from graphopt.vertex import BaseVertex, VertexVector

__version__ = "0.1.0"

__all__ = [
    "BaseEdge",
    "BaseVertex",
    "DoglegConfig",
    "EdgeContext",
    "GaussNewtonConfig",
    "GraphError",
    "ImplicitSchurConfig",
    "IncrementalConfig",
    "IncrementalOptimizer",
    "IterationInfo",
    "JacobianCheck",
    "Jet",
    "JetError",
    "LevenbergConfig",
    "Linearization",
    "LinearSolver",
    "LinearSolverCholmod",
    "LinearSolverDense",
    "LinearSolverImplicitSchur",
    "LinearSolverPCG",
    "LinearSolverScipy",
    "NotPositiveDefiniteError",
    "SingularSystemError",
    "OptimizationResult",
    "PCGConfig",
    "Problem",
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
    "SchurConfig",
    "SparseOptimizer",
    "StopReason",
    "StoppingConfig",
    "UpdateReport",
    "VertexVector",
    "check_jacobians",
    "edge_jacobians",
    "make_kernel",
    "numeric_jacobians",
]
