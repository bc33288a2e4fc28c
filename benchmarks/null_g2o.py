"""A g2o module whose objects do nothing: what a g2opy program costs by itself.

``motion_only_floor.py --g2o-semantics`` runs ORB-SLAM's ``PoseOptimization`` program
(``slam_backend_g2o.py``) on these objects: its own Python — the loops, the object creations,
the setter and getter calls, the ``np.eye`` per edge — with nothing behind the calls. That time
plus bare numpy's optimisation is the floor of any implementation of g2o's API in Python. Only
the names that program uses are here.
"""

from __future__ import annotations

from typing import Any

import numpy as np

_IDENTITY = np.eye(4)


class _Nothing:
    """An algorithm, solver or kernel: made, never used."""

    def __init__(self, *args: Any) -> None:
        pass


OptimizationAlgorithmLevenberg = BlockSolverSE3 = LinearSolverDenseSE3 = _Nothing
LinearSolverEigenSE3 = RobustKernelHuber = _Nothing


class SE3Quat:
    """A pose, kept as given."""

    def __init__(self, R: Any, t: Any) -> None:
        self.R, self.t = R, t

    def to_homogeneous_matrix(self) -> np.ndarray:
        return _IDENTITY


class SparseOptimizer:
    """Takes vertices and edges; optimises nothing."""

    def set_algorithm(self, algorithm: Any) -> None:
        pass

    def add_vertex(self, v: Any) -> bool:
        return True

    def add_edge(self, e: Any) -> bool:
        return True

    def initialize_optimization(self, level: int = 0) -> bool:
        return True

    def optimize(self, iterations: int) -> int:
        return iterations


class _Vertex:
    def set_estimate(self, x: Any) -> None:
        self._x = x

    def estimate(self) -> Any:
        return self._x

    def set_id(self, i: int) -> None:
        self._id = i

    def set_fixed(self, fixed: bool) -> None:
        self._fixed = fixed


class VertexSE3Expmap(_Vertex):
    pass


class VertexPointXYZ(_Vertex):
    pass


class _Edge:
    _level = 0

    def set_vertex(self, i: int, v: Any) -> None:
        self._v = v

    def set_measurement(self, z: Any) -> None:
        self._z = z

    def set_information(self, info: Any) -> None:
        self._info = info

    def set_robust_kernel(self, k: Any) -> None:
        self._k = k

    def set_level(self, level: int) -> None:
        self._level = level

    def compute_error(self) -> None:
        pass

    def chi2(self) -> float:
        return 0.0


class EdgeSE3ProjectXYZOnlyPose(_Edge):
    pass


class EdgeStereoSE3ProjectXYZ(_Edge):
    pass
