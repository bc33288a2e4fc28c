"""g2opy programs written once, run with ``g2o`` = the g2opy wheel or ``graphopt.g2o``.

Ports of g2o's Python examples (``python/examples`` of uoip/g2opy: ``ba_demo.py``,
``ba_anchored_inverse_depth_demo.py``) with their synthetic scenes drawn from a seeded
generator, so that both runs see the same numbers. Each returns what the tests compare.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _scene(seed: int, n_points: int = 500, n_poses: int = 15) -> tuple[Any, ...]:
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.random(n_points) * 3 - 1.5, rng.random(n_points) - 0.5,
                              rng.random(n_points) + 3])
    return rng, points, n_poses


def ba_demo(g2o: Any, seed: int = 0, noise: float = 1.0, outlier_ratio: float = 0.0,
            robust: bool = False, iterations: int = 10, n_points: int = 500) -> dict[str, Any]:
    """g2o's ``ba_demo``: 15 poses (2 fixed), points marginalised, ``EdgeProjectXYZ2UV``.

    Returns:
        ``chi2`` (final active chi2), ``rmse_before``/``rmse_after`` of the inlier points,
        ``iterations``, ``edges``.
    """
    rng, true_points, num_pose = _scene(seed, n_points)
    optimizer = g2o.SparseOptimizer()
    solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    optimizer.set_algorithm(g2o.OptimizationAlgorithmLevenberg(solver))
    cam = g2o.CameraParameters(1000.0, np.array([320.0, 240.0]), 0.0)
    cam.set_id(0)
    optimizer.add_parameter(cam)
    true_poses = []
    for i in range(num_pose):
        pose = g2o.SE3Quat(np.identity(3), np.array([i * 0.04 - 1, 0, 0]))
        true_poses.append(pose)
        v = g2o.VertexSE3Expmap()
        v.set_id(i)
        v.set_estimate(pose)
        v.set_fixed(i < 2)
        optimizer.add_vertex(v)
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    point_id, inliers, sse0 = num_pose, {}, 0.0
    for i, point in enumerate(true_points):
        visible = []
        for j, pose in enumerate(true_poses):
            z = cam.cam_map(pose * point)
            if 0 <= z[0] < 640 and 0 <= z[1] < 480:
                visible.append((j, z))
        if len(visible) < 2:
            continue
        vp = point_cls()
        vp.set_id(point_id)
        vp.set_marginalized(True)
        vp.set_estimate(point + rng.standard_normal(3))
        optimizer.add_vertex(vp)
        inlier = True
        for j, z in visible:
            if rng.random() < outlier_ratio:
                inlier = False
                z = rng.random(2) * [640, 480]
            z = z + rng.standard_normal(2) * noise
            edge = g2o.EdgeProjectXYZ2UV()
            edge.set_vertex(0, vp)
            edge.set_vertex(1, optimizer.vertex(j))
            edge.set_measurement(z)
            edge.set_information(np.identity(2))
            if robust:
                edge.set_robust_kernel(g2o.RobustKernelHuber())
            edge.set_parameter_id(0, 0)
            optimizer.add_edge(edge)
        if inlier:
            inliers[point_id] = i
            sse0 += float(np.sum((vp.estimate() - true_points[i]) ** 2))
        point_id += 1
    n_edges = len(optimizer.edges())
    optimizer.initialize_optimization()
    its = optimizer.optimize(iterations)
    optimizer.compute_active_errors()
    sse1 = sum(float(np.sum((optimizer.vertex(i).estimate() - true_points[k]) ** 2))
               for i, k in inliers.items())
    return {"chi2": optimizer.active_chi2(), "rmse_before": np.sqrt(sse0 / len(inliers)),
            "rmse_after": np.sqrt(sse1 / len(inliers)), "iterations": its, "edges": n_edges}
