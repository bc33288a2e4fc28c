"""g2o's Python API on graphopt: ``import graphopt.g2o as g2o`` runs g2opy programs.

Both dialects are served: the official ``g2opy`` wheel's names (``VertexPointXYZ``,
``EdgeXyzVsc``…) and the old ``uoip/g2opy`` bindings' (``VertexSBAPointXYZ``,
``LinearSolverCholmodSE3``, ``Edge_XYZ_VSC``…), with lists, tuples, ints and column vectors
accepted where the old bindings took them. A g2o type graphopt does not support raises
``NotImplementedError`` naming it when constructed. See ``docs/g2o_api.md``.
"""

from __future__ import annotations

from typing import Any as _Any

from .edges import UNSUPPORTED as _UNSUPPORTED
from .edges import unsupported as _unsupported
from .edges_icp import ICP_EDGES as _ICP
from .edges_sba import SBA_EDGES as _SBA
from .edges_slam import SLAM_EDGES as _SLAM
from .geometry import SE2, Isometry3d, SE3Quat
from .optimizer import SparseOptimizer
from .params import (
    CameraParameters,
    Parameter,
    ParameterCamera,
    ParameterSE2Offset,
    ParameterSE3Offset,
    StereoCameraParameters,
)
from .rotations import AngleAxis, Quaternion
from .sba_cam import SBA_CAM_CLASSES as _SBA_CAM
from .sim3 import Sim3
from .solvers import ALGORITHMS as _ALGORITHMS
from .solvers import BLOCK_SOLVERS as _BLOCK_SOLVERS
from .solvers import KERNEL_CLASSES as _KERNELS
from .solvers import LINEAR_SOLVERS as _LINEAR_SOLVERS
from .solvers import (
    BlockSolver,
    Flag,
    IoFormat,
    LinearSolver,
    OptimizationAlgorithm,
    RobustKernelBase,
)
from .vertices import VERTEX_CLASSES as _VERTICES
from .vertices import BaseVertex

_EDGES = {**_SBA, **_SLAM, **_ICP}
BaseEdge = _EDGES["EdgeSE2"].__mro__[1]
RobustKernel = RobustKernelBase
Isometry = Isometry3d

_NAMES: dict[str, _Any] = {
    **_VERTICES, **_EDGES, **_SBA_CAM, **_ALGORITHMS, **_BLOCK_SOLVERS, **_LINEAR_SOLVERS,
    **_KERNELS, **{name: _unsupported(name) for name in _UNSUPPORTED},
}
globals().update(_NAMES)

__all__ = [
    "SE2", "AngleAxis", "BaseEdge", "BaseVertex", "BlockSolver", "CameraParameters", "Flag",
    "IoFormat",
    "Isometry", "Isometry3d", "LinearSolver", "OptimizationAlgorithm", "Parameter",
    "ParameterCamera", "ParameterSE2Offset", "ParameterSE3Offset", "Quaternion", "RobustKernel",
    "SE3Quat", "Sim3", "SparseOptimizer", "StereoCameraParameters",
]
__all__ += sorted(_NAMES)


def __dir__() -> list[str]:
    return __all__
