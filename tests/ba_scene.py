"""A synthetic local-BA window (ORB-SLAM's ``LocalBundleAdjustment`` shape) with known truth.

Free and fixed keyframes (``VertexSE3Expmap``, ``T_cw``) on a line looking down +z, points
(``VertexPointXYZ``, marginalised) in front of them, pinhole observations
(``EdgeSE3ProjectXYZ``) with pixel noise and a share of gross outliers. Used by the editing
tests and ``benchmarks/bench_editing.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphopt import RobustKernelHuber, SparseOptimizer
from graphopt.edge_set import EdgeSet
from graphopt.lie import make_transform, so3_exp, transform_points
from graphopt.types import CameraParameters, EdgeSE3ProjectXYZ, VertexPointXYZ, VertexSE3Expmap

CAMERA = CameraParameters(500.0, 500.0, 320.0, 240.0)


@dataclass
class Scene:
    """Args:
        poses: ``(c, 4, 4)`` initial ``T_cw`` (noisy for the free ones).
        fixed: ``(c,)`` fixed keyframes.
        points: ``(p, 3)`` initial points (noisy).
        ids: ``(m, 2)`` ``(pose id, point id)`` of every observation; points have ids ``c + j``.
        meas: ``(m, 2)`` pixels.
        outlier: ``(m,)`` gross outliers.
    """

    poses: np.ndarray
    fixed: np.ndarray
    points: np.ndarray
    ids: np.ndarray
    meas: np.ndarray
    outlier: np.ndarray


def local_ba_scene(free: int = 4, fixed: int = 2, points: int = 60, per_point: int = 4,
                   outliers: float = 0.1, seed: int = 0) -> Scene:
    """A window of ``free + fixed`` keyframes and ``points`` points seen ``per_point`` times.

    Args:
        free: Free keyframes.
        fixed: Fixed keyframes.
        points: Points.
        per_point: Observations of every point (≤ keyframes).
        outliers: Share of observations replaced by random pixels.
        seed: Random seed.
    """
    rng = np.random.default_rng(seed)
    c = free + fixed
    centres = np.column_stack([np.linspace(0, 0.3 * c, c), rng.normal(0, 0.05, (c, 2))])
    R = so3_exp(rng.normal(0, 0.02, (c, 3)))
    T = make_transform(R, -np.einsum("cij,cj->ci", R, centres))
    X = np.column_stack([rng.uniform(-2, 2 + 0.3 * c, points), rng.uniform(-1.5, 1.5, points),
                         rng.uniform(4, 8, points)])
    cams = np.stack([rng.choice(c, per_point, replace=False) for _ in range(points)])
    ids = np.column_stack([cams.ravel(), c + np.repeat(np.arange(points), per_point)])
    Pc = transform_points(T[ids[:, 0]], X[ids[:, 1] - c])
    meas = np.column_stack([CAMERA.fx * Pc[:, 0] / Pc[:, 2] + CAMERA.cx,
                            CAMERA.fy * Pc[:, 1] / Pc[:, 2] + CAMERA.cy])
    meas += rng.normal(0, 1.0, meas.shape)
    bad = rng.random(len(ids)) < outliers
    meas[bad] += rng.uniform(-60, 60, (int(bad.sum()), 2))
    is_fixed = np.arange(c) >= free
    noisy = T.copy()
    dT = make_transform(so3_exp(rng.normal(0, 0.005, (c, 3))), rng.normal(0, 0.03, (c, 3)))
    noisy[~is_fixed] = dT[~is_fixed] @ T[~is_fixed]
    return Scene(noisy, is_fixed, X + rng.normal(0, 0.05, X.shape), ids, meas, bad)


def build(scene: Scene, rows: np.ndarray | None = None, kernel: bool = True,
          algorithm: str = "lm", solver: str = "auto",
          only_used: bool = False) -> tuple[SparseOptimizer, EdgeSet]:
    """An optimizer over the scene's observations ``rows`` (all by default).

    Args:
        scene: The scene.
        rows: The observations to add.
        kernel: Huber kernels (δ² = 5.991, ORB-SLAM's) on the observations.
        algorithm: The algorithm.
        solver: The linear solver.
        only_used: Add only the points those observations see.
    """
    rows = np.arange(len(scene.ids)) if rows is None else rows
    c = len(scene.poses)
    opt = SparseOptimizer(algorithm, solver)
    opt.add_vertices(VertexSE3Expmap, np.arange(c), scene.poses, fixed=scene.fixed)
    pts = np.arange(len(scene.points))
    if only_used:
        pts = np.unique(scene.ids[rows, 1] - c)
    opt.add_vertices(VertexPointXYZ, c + pts, scene.points[pts], marginalized=True)
    es = opt.add_edges(EdgeSE3ProjectXYZ, scene.ids[rows], scene.meas[rows], params=CAMERA,
                       robust_kernel=RobustKernelHuber(np.sqrt(5.991)) if kernel else None)
    return opt, es
