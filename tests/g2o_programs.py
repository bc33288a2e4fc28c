"""g2opy programs written once, run with ``g2o`` = the g2opy wheel or ``graphopt.g2o``.

Ports of g2o's Python examples (``python/examples`` of uoip/g2opy: ``ba_demo.py``,
``ba_anchored_inverse_depth_demo.py``) with their synthetic scenes drawn from a seeded
generator, so that both runs see the same numbers. Each returns what the tests compare.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

#: The clock the timed programs (``local_ba``, ``motion_only``) read; ``benchmarks/bench_g2o_api.py
#: --clock cpu`` sets ``time.process_time`` (robust to other processes on a shared machine).
clock = time.perf_counter


def _scene(seed: int, n_points: int = 500, n_poses: int = 15) -> tuple[Any, ...]:
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.random(n_points) * 3 - 1.5, rng.random(n_points) - 0.5,
                              rng.random(n_points) + 3])
    return rng, points, n_poses


def _ba_demo_graph(g2o: Any, num_pose: int) -> tuple[Any, Any, list[Any]]:
    """The start both BA demos share: a Levenberg optimizer on ``BlockSolverSE3``, the camera
    (parameter 0), ``num_pose`` ``VertexSE3Expmap`` 4 cm apart along x (the first two fixed).

    Returns:
        ``(optimizer, cam, true_poses)``.
    """
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
    return optimizer, cam, true_poses


def _in_image(observations: Any) -> list[tuple[int, np.ndarray]]:
    """The ``(pose index, pixel)`` observations that fall inside the 640x480 image."""
    return [(j, z) for j, z in observations if 0 <= z[0] < 640 and 0 <= z[1] < 480]


def _dense_levenberg(g2o: Any) -> Any:
    """An optimizer with Levenberg on a dense ``BlockSolverX`` (the small test programs)."""
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(
        g2o.BlockSolverX(g2o.LinearSolverDenseX())))
    return opt


def _edge_chi2s(opt: Any, edges: dict[str, Any]) -> dict[str, float]:
    """``{name: chi2}`` of each edge at the current estimates."""
    opt.initialize_optimization()
    opt.compute_active_errors()
    for e in edges.values():
        e.compute_error()
    return {name: float(e.chi2()) for name, e in edges.items()}


def _rotation(rng: np.random.Generator) -> np.ndarray:
    """A random proper rotation ``(3, 3)`` (QR of a Gaussian matrix, reflected if needed)."""
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    return R if np.linalg.det(R) > 0 else -R


def ba_demo(g2o: Any, seed: int = 0, noise: float = 1.0, outlier_ratio: float = 0.0,
            robust: bool = False, iterations: int = 10, n_points: int = 500) -> dict[str, Any]:
    """g2o's ``ba_demo``: 15 poses (2 fixed), points marginalised, ``EdgeProjectXYZ2UV``.

    Returns:
        ``chi2`` (final active chi2), ``rmse_before``/``rmse_after`` of the inlier points,
        ``iterations``, ``edges``.
    """
    rng, true_points, num_pose = _scene(seed, n_points)
    optimizer, cam, true_poses = _ba_demo_graph(g2o, num_pose)
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    point_id, inliers, sse0 = num_pose, {}, 0.0
    for i, point in enumerate(true_points):
        visible = _in_image((j, cam.cam_map(pose * point)) for j, pose in enumerate(true_poses))
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
                edge.set_robust_kernel(g2o.RobustKernelHuber(np.sqrt(5.991)))
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


def _invert_depth(x: np.ndarray) -> np.ndarray:
    return np.array([x[0], x[1], 1.0]) / x[2]


def ba_anchored_inverse_depth(g2o: Any, seed: int = 0, noise: float = 1.0,
                              iterations: int = 10, n_points: int = 300) -> dict[str, Any]:
    """g2o's ``ba_anchored_inverse_depth_demo``: points as ``[u, v, ρ]`` in their first
    observer's frame, ``EdgeProjectPSI2UV`` on (point, pose, anchor).

    Returns:
        ``chi2``, ``rmse_before``/``rmse_after`` (world points), ``iterations``.
    """
    rng, true_points, num_pose = _scene(seed, n_points)
    optimizer, cam, true_poses = _ba_demo_graph(g2o, num_pose)
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    point_id, inliers, sse0 = num_pose, {}, 0.0
    for i, point in enumerate(true_points):
        visible = _in_image((j, cam.cam_map(pose * point)) for j, pose in enumerate(true_poses))
        if len(visible) < 2:
            continue
        vp = point_cls()
        vp.set_id(point_id)
        vp.set_marginalized(True)
        anchor = visible[0][0]
        point2 = true_poses[anchor] * (point + rng.standard_normal(3) * 0.1)
        vp.set_estimate(_invert_depth(point2))
        optimizer.add_vertex(vp)
        for j, z in visible:
            edge = g2o.EdgeProjectPSI2UV()
            edge.resize(3)
            edge.set_vertex(0, vp)
            edge.set_vertex(1, optimizer.vertex(j))
            edge.set_vertex(2, optimizer.vertex(anchor))
            edge.set_measurement(z + rng.standard_normal(2) * noise)
            edge.set_information(np.identity(2))
            edge.set_parameter_id(0, 0)
            optimizer.add_edge(edge)
        inliers[point_id] = (i, anchor)
        err = true_poses[anchor].inverse() * _invert_depth(vp.estimate()) - true_points[i]
        sse0 += float(np.sum(err**2))
        point_id += 1
    optimizer.initialize_optimization()
    its = optimizer.optimize(iterations)
    optimizer.compute_active_errors()
    sse1 = 0.0
    for i, (k, anchor) in inliers.items():
        va = optimizer.vertex(anchor).estimate()
        err = va.inverse() * _invert_depth(optimizer.vertex(i).estimate()) - true_points[k]
        sse1 += float(np.sum(err**2))
    return {"chi2": optimizer.active_chi2(), "rmse_before": np.sqrt(sse0 / len(inliers)),
            "rmse_after": np.sqrt(sse1 / len(inliers)), "iterations": its}


def se2_chain(g2o: Any, poses: list[tuple[float, float, float]], measurement: Any,
              information: np.ndarray) -> Any:
    """A chain of ``VertexSE2`` built object by object (the first fixed), an ``EdgeSE2`` with
    ``measurement`` and ``information`` between each and the next."""
    opt = g2o.SparseOptimizer()
    for i, p in enumerate(poses):
        v = g2o.VertexSE2()
        v.set_id(i)
        v.set_estimate(g2o.SE2(*p))
        v.set_fixed(i == 0)
        opt.add_vertex(v)
    for i in range(len(poses) - 1):
        e = g2o.EdgeSE2()
        e.set_vertex(0, opt.vertex(i))
        e.set_vertex(1, opt.vertex(i + 1))
        e.set_measurement(measurement)
        e.set_information(information)
        opt.add_edge(e)
    return opt


def pose_graph_se2(g2o: Any, seed: int = 0, n: int = 200, iterations: int = 10
                   ) -> dict[str, Any]:
    """A 2D pose graph built object by object: a noisy square-ish loop of ``VertexSE2`` with
    odometry and loop-closure ``EdgeSE2``s, the first pose fixed; landmarks by
    ``EdgeSE2PointXY``.

    Returns:
        ``chi2``, ``chi2_before``, ``rmse_before``/``rmse_after`` of the positions,
        ``iterations``.
    """
    rng = np.random.default_rng(seed)
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    truth = np.column_stack([10 * np.cos(th), 10 * np.sin(th), th + np.pi / 2])

    def rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        c, s = np.cos(a[2]), np.sin(a[2])
        d = b[:2] - a[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1],
                         np.arctan2(np.sin(b[2] - a[2]), np.cos(b[2] - a[2]))])

    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(
        g2o.BlockSolverSE2(g2o.LinearSolverEigenSE2())))
    est = truth[0].copy()
    start = []
    for i in range(n):
        v = g2o.VertexSE2()
        v.set_id(i)
        v.set_estimate(g2o.SE2(*est))
        start.append(est.copy())
        v.set_fixed(i == 0)
        opt.add_vertex(v)
        if i + 1 < n:
            z = rel(truth[i], truth[i + 1]) + rng.standard_normal(3) * [0.05, 0.05, 0.01]
            c, s = np.cos(est[2]), np.sin(est[2])
            est = np.array([est[0] + c * z[0] - s * z[1], est[1] + s * z[0] + c * z[1],
                            est[2] + z[2]])
    info = np.diag([400.0, 400.0, 10000.0])
    pairs = [(i, i + 1) for i in range(n - 1)] + [(i, (i + n // 2) % n) for i in range(0, n, 10)]
    for a, b in pairs:
        e = g2o.EdgeSE2()
        e.set_vertex(0, opt.vertex(a))
        e.set_vertex(1, opt.vertex(b))
        e.set_measurement(g2o.SE2(*(rel(truth[a], truth[b])
                                    + rng.standard_normal(3) * [0.05, 0.05, 0.01])))
        e.set_information(info)
        opt.add_edge(e)
    lm = rng.random((20, 2)) * 20 - 10
    for k, p in enumerate(lm):
        v = g2o.VertexPointXY()
        v.set_id(n + k)
        v.set_estimate(p + rng.standard_normal(2))
        opt.add_vertex(v)
        for i in range(k, n, 20):
            c, s = np.cos(truth[i, 2]), np.sin(truth[i, 2])
            d = p - truth[i, :2]
            e = g2o.EdgeSE2PointXY()
            e.set_vertex(0, opt.vertex(i))
            e.set_vertex(1, v)
            e.set_measurement(np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
                              + rng.standard_normal(2) * 0.05)
            e.set_information(np.identity(2) * 400.0)
            opt.add_edge(e)
    opt.initialize_optimization()
    opt.compute_active_errors()
    chi0 = opt.active_chi2()
    its = opt.optimize(iterations)
    opt.compute_active_errors()
    after = np.array([opt.vertex(i).estimate().to_vector()[:2] for i in range(n)])
    rm = lambda p: float(np.sqrt(np.mean(np.sum((p - truth[:, :2]) ** 2, axis=1))))  # noqa: E731
    return {"chi2": opt.active_chi2(), "chi2_before": chi0,
            "rmse_before": rm(np.array(start)[:, :2]), "rmse_after": rm(after),
            "iterations": its}


def gicp_demo(g2o: Any, seed: int = 0, noise: float = 0.02, n_points: int = 1000,
              iterations: int = 5, plane_to_plane: bool = False) -> dict[str, Any]:
    """g2o's ``gicp_demo``: two ``VertexSE3`` 1 m apart (the first fixed), point matches as
    ``Edge_V_V_GICP`` with ``EdgeGICP`` measurements, the second camera moved to z = 0.2.

    Returns:
        ``chi2_before``, ``chi2``, ``t_after`` (the second camera's translation; truth
        ``[0, 0, 1]``), ``iterations``.
    """
    rng = np.random.default_rng(seed)
    optimizer = _dense_levenberg(g2o)
    true_points = np.column_stack([rng.random(n_points) * 3 - 1.5, rng.random(n_points) - 0.5,
                                   rng.random(n_points) + 10])
    for i in range(2):
        vc = g2o.VertexSE3()
        vc.set_id(i)
        vc.set_estimate(g2o.Isometry3d(np.identity(3), np.array([[0.0], [0.0], [float(i)]])))
        vc.set_fixed(i == 0)
        optimizer.add_vertex(vc)
    trans0 = optimizer.vertex(0).estimate().inverse()
    trans1 = optimizer.vertex(1).estimate().inverse()
    edge_cls = getattr(g2o, "Edge_V_V_GICP", None) or g2o.EdgeVVGicp
    for i in range(n_points):
        pt0 = trans0 * true_points[i] + rng.standard_normal(3) * noise
        pt1 = trans1 * true_points[i] + rng.standard_normal(3) * noise
        nm = np.array([0.0, float(i), 1.0])
        nm /= np.linalg.norm(nm)
        meas = g2o.EdgeGICP()
        meas.pos0, meas.pos1, meas.normal0, meas.normal1 = pt0, pt1, nm, nm
        edge = edge_cls()
        edge.set_vertex(0, optimizer.vertex(0))
        edge.set_vertex(1, optimizer.vertex(1))
        edge.set_measurement(meas)
        if plane_to_plane:
            edge.pl_pl = True
            edge.cov0, edge.cov1 = meas.cov0(0.01), meas.cov1(0.01)
            edge.set_information(np.identity(3))
        else:
            edge.set_information(meas.prec0(0.01))
        optimizer.add_edge(edge)
    vc = optimizer.vertex(1)
    vc.set_estimate(g2o.Isometry3d(vc.estimate().R, np.array([[0.0], [0.0], [0.2]])))
    optimizer.initialize_optimization()
    optimizer.compute_active_errors()
    chi0 = optimizer.chi2()
    its = optimizer.optimize(iterations)
    optimizer.compute_active_errors()
    return {"chi2_before": chi0, "chi2": optimizer.chi2(),
            "t_after": np.asarray(optimizer.vertex(1).estimate().t).ravel(), "iterations": its}


def sensor_types_chi2(g2o: Any, seed: int = 0) -> dict[str, float]:
    """One edge of each of g2o's simpler slam2d/slam3d/sclam2d types on random vertices.

    Returns:
        ``{edge class: chi2}`` after ``compute_active_errors``.
    """
    rng = np.random.default_rng(seed)
    opt = _dense_levenberg(g2o)
    off = g2o.ParameterSE3Offset()
    off.set_id(0)
    opt.add_parameter(off)
    verts: dict[str, list[Any]] = {}
    vid = 0
    for cls, make, n in (("VertexSE2", lambda: g2o.SE2(*rng.normal(0, 1, 3)), 3),
                         ("VertexPointXY", lambda: rng.normal(0, 2, 2), 2),
                         ("VertexPointXYZ", lambda: rng.normal(0, 2, 3), 2),
                         ("VertexSE3", lambda: g2o.Isometry3d(
                             np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1],
                             rng.normal(0, 1, (3, 1))), 1)):
        verts[cls] = []
        for _ in range(n):
            v = getattr(g2o, cls)()
            v.set_id(vid)
            est = make()
            if cls == "VertexSE3":  # a proper rotation
                R = est.R if hasattr(est, "R") else est.rotation_matrix()
                if np.linalg.det(R) < 0:
                    est = g2o.Isometry3d(-R, rng.normal(0, 1, (3, 1)))
            v.set_estimate(est)
            opt.add_vertex(v)
            verts[cls].append(v)
            vid += 1
    se2, xy, xyz, se3 = (verts[c] for c in ("VertexSE2", "VertexPointXY", "VertexPointXYZ",
                                            "VertexSE3"))
    specs = [("EdgePointXY", [xy[0], xy[1]], 2), ("EdgeXYPrior", [xy[0]], 2),
             ("EdgeSE2XYPrior", [se2[0]], 2), ("EdgeSE2PointXYBearing", [se2[0], xy[0]], 1),
             ("EdgeSE2PointXYCalib", [se2[0], xy[1], se2[2]], 2),
             ("EdgePointXYZ", [xyz[0], xyz[1]], 3), ("EdgeXYZPrior", [xyz[0]], 3),
             ("EdgeSE3XYZPrior", [se3[0]], 3), ("EdgeSE2SensorCalib", [se2[0], se2[1], se2[2]], 3)]
    edges = {}
    for name, vs, d in specs:
        e = getattr(g2o, name)()
        for i, v in enumerate(vs):
            e.set_vertex(i, v)
        if name == "EdgeSE2SensorCalib":
            e.set_measurement(g2o.SE2(*rng.normal(0, 1, 3)))
        elif d == 1:
            e.set_measurement(float(rng.normal()))
        else:
            e.set_measurement(rng.normal(0, 1, d))
        A = rng.normal(size=(d, d))
        e.set_information(A @ A.T + d * np.identity(d))
        if name == "EdgeSE3XYZPrior":
            e.set_parameter_id(0, 0)
        opt.add_edge(e)
        edges[name] = e
    cam = g2o.CameraParameters(450.0, np.array([320.0, 240.0]), 0.12)
    cam.set_id(1)
    opt.add_parameter(cam)
    pose = g2o.VertexSE3Expmap()
    pose.set_id(vid)
    pose.set_estimate(g2o.SE3Quat(np.identity(3), np.array([0.1, -0.2, 0.3])))
    opt.add_vertex(pose)
    point = g2o.VertexPointXYZ()
    point.set_id(vid + 1)
    point.set_estimate(np.array([0.4, 0.2, 4.0]))
    opt.add_vertex(point)
    e = g2o.EdgeProjectXYZ2UVU()
    e.set_vertex(0, point)
    e.set_vertex(1, pose)
    e.set_measurement(np.array([380.0, 230.0, 370.0]))
    e.set_information(np.identity(3))
    e.set_parameter_id(0, 1)
    opt.add_edge(e)
    edges["EdgeProjectXYZ2UVU"] = e
    return _edge_chi2s(opt, edges)


# --- ORB-SLAM's procedures (benchmarks/bench_g2o_api.py times them) ---

FX = FY = 500.0
CX, CY = 320.0, 240.0
CHI2_MONO = 5.991


def _rot(rng: np.random.Generator, scale: float) -> np.ndarray:
    w = rng.normal(0, scale, 3)
    th = np.linalg.norm(w)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def scene(n_kf: int, n_points: int, obs_per_point: int, seed: int = 0) -> dict[str, Any]:
    """Keyframes on a line looking down +z at points 4–8 m away; each point seen by
    ``obs_per_point`` keyframes; 10 % of the observations replaced by random pixels."""
    rng = np.random.default_rng(seed)
    R = [_rot(rng, 0.02) for _ in range(n_kf)]
    C = np.column_stack([np.linspace(-2, 2, n_kf), rng.normal(0, 0.05, n_kf), np.zeros(n_kf)])
    t = [-(R[i] @ C[i]) for i in range(n_kf)]
    X = np.column_stack([rng.uniform(-3, 3, n_points), rng.uniform(-2, 2, n_points),
                         rng.uniform(4, 8, n_points)])
    obs = []
    for p in range(n_points):
        near = np.argsort(np.abs(C[:, 0] - X[p, 0]))[:obs_per_point]
        for k in near:
            Xc = R[k] @ X[p] + t[k]
            uv = np.array([FX * Xc[0] / Xc[2] + CX, FY * Xc[1] / Xc[2] + CY])
            uv = uv + rng.normal(0, 1, 2) if rng.random() > 0.1 else rng.uniform(0, 640, 2)
            obs.append((p, int(k), uv))
    noisy_R = [_rot(rng, 0.01) @ r for r in R]
    noisy_t = [ti + rng.normal(0, 0.05, 3) for ti in t]
    return {"R": R, "t": t, "X": X, "obs": obs, "R0": noisy_R, "t0": noisy_t,
            "X0": X + rng.normal(0, 0.1, X.shape)}


def _drop_kernel(g2o: Any, edge: Any) -> None:
    """``set_robust_kernel(None)``; the g2opy wheel refuses ``None``: a Huber kernel whose δ no
    error reaches is the same function there."""
    try:
        edge.set_robust_kernel(None)
    except TypeError:
        edge.set_robust_kernel(g2o.RobustKernelHuber(1e12))


def _algorithm(g2o: Any) -> Any:
    return g2o.OptimizationAlgorithmLevenberg(g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3()))


def local_ba(g2o: Any, sc: dict[str, Any], n_free: int) -> tuple[float, float, float, int]:
    """ORB-SLAM's local BA; returns (build s, optimise s, final active chi2, inliers)."""
    t0 = clock()
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(_algorithm(g2o))
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    kfs = []
    for i, (R, t) in enumerate(zip(sc["R0"], sc["t0"], strict=True)):
        v = g2o.VertexSE3Expmap()
        v.set_estimate(g2o.SE3Quat(R, t))
        v.set_id(i)
        v.set_fixed(i >= n_free)
        opt.add_vertex(v)
        kfs.append(v)
    n_kf = len(kfs)
    pts = []
    for j, X in enumerate(sc["X0"]):
        v = point_cls()
        v.set_estimate(X)
        v.set_id(n_kf + j)
        v.set_marginalized(True)
        opt.add_vertex(v)
        pts.append(v)
    info = np.identity(2)
    delta = np.sqrt(CHI2_MONO)
    edges = []
    for p, k, uv in sc["obs"]:
        e = g2o.EdgeSE3ProjectXYZ()
        e.set_vertex(0, pts[p])
        e.set_vertex(1, kfs[k])
        e.set_measurement(uv)
        e.set_information(info)
        e.set_robust_kernel(g2o.RobustKernelHuber(delta))
        e.fx, e.fy, e.cx, e.cy = FX, FY, CX, CY
        opt.add_edge(e)
        edges.append(e)
    t1 = clock()
    opt.initialize_optimization()
    opt.optimize(5)
    for e in edges:
        if e.chi2() > CHI2_MONO or not e.is_depth_positive():
            e.set_level(1)
        _drop_kernel(g2o, e)
    opt.initialize_optimization(0)
    opt.optimize(10)
    opt.compute_active_errors()
    chi2 = opt.active_chi2()
    inliers = sum(1 for e in edges if e.level() == 0)
    return t1 - t0, clock() - t1, chi2, inliers


def pose_only_graph(g2o: Any, sc: dict[str, Any], obs: list[tuple[int, Any]]
                    ) -> tuple[Any, Any, Any, list[Any]]:
    """ORB-SLAM's ``PoseOptimization`` graph: keyframe 0's pose (from its noisy start) and one
    ``EdgeSE3ProjectXYZOnlyPose`` with a Huber kernel per ``(point, pixel)`` of ``obs``.

    Returns:
        ``(optimizer, pose vertex, start SE3Quat, edges)``.
    """
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(_algorithm(g2o))
    v = g2o.VertexSE3Expmap()
    start = g2o.SE3Quat(sc["R0"][0], sc["t0"][0])
    v.set_estimate(start)
    v.set_id(0)
    opt.add_vertex(v)
    edges = []
    delta = np.sqrt(CHI2_MONO)
    for p, uv in obs:
        e = g2o.EdgeSE3ProjectXYZOnlyPose()
        e.set_vertex(0, v)
        e.set_measurement(uv)
        e.set_information(np.identity(2))
        e.set_robust_kernel(g2o.RobustKernelHuber(delta))
        e.fx, e.fy, e.cx, e.cy = FX, FY, CX, CY
        e.Xw = sc["X"][p].copy()
        opt.add_edge(e)
        edges.append(e)
    return opt, v, start, edges


def motion_only(g2o: Any, sc: dict[str, Any], n: int) -> tuple[float, float, float, int]:
    """ORB-SLAM's pose optimisation of keyframe 0 against ``n`` fixed world points."""
    obs = [(p, uv) for p, k, uv in sc["obs"] if k == 0][:n]
    t0 = clock()
    opt, v, start, edges = pose_only_graph(g2o, sc, obs)
    t1 = clock()
    for it in range(4):
        v.set_estimate(start)
        opt.initialize_optimization(0)
        opt.optimize(10)
        for e in edges:
            if e.level() == 1:
                e.compute_error()
            e.set_level(1 if e.chi2() > CHI2_MONO else 0)
            if it == 2:
                _drop_kernel(g2o, e)
    opt.initialize_optimization(0)
    opt.compute_active_errors()
    chi2 = opt.active_chi2()
    inliers = sum(1 for e in edges if e.level() == 0)
    return t1 - t0, clock() - t1, chi2, inliers


def optimize_sim3(g2o: Any, seed: int = 0, n: int = 100, noise: float = 1e-3,
                  iterations: int = 5) -> dict[str, Any]:
    """ORB-SLAM's ``OptimizeSim3``: one ``VertexSim3Expmap`` ``S12`` (camera 2 → camera 1),
    fixed points in both cameras' frames, ``EdgeSim3ProjectXYZ`` (point of camera 2 seen by
    camera 1) and ``EdgeInverseSim3ProjectXYZ`` (point of camera 1 seen by camera 2); normalised
    image coordinates (the wheel keeps the vertex's intrinsics at f = 1, c = 0); 10 % outliers;
    ``iterations``, outliers removed, 10 more.

    Returns:
        ``chi2``, ``inliers``, ``scale`` and ``t`` of the estimate (truth 1.7, [0.3, -0.1, 0.2]).
    """
    rng = np.random.default_rng(seed)
    aa = np.array([0.05, -0.1, 0.08])
    th = np.linalg.norm(aa)
    K = np.array([[0, -aa[2], aa[1]], [aa[2], 0, -aa[0]], [-aa[1], aa[0], 0]]) / th
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    t, s = np.array([0.3, -0.1, 0.2]), 1.7
    X2 = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(3, 6, n)])
    X1 = s * X2 @ R.T + t
    opt = _dense_levenberg(g2o)
    v = g2o.VertexSim3Expmap()
    v.set_id(0)
    start = R @ np.array([[1.0, -0.02, 0.0], [0.02, 1.0, 0.0], [0.0, 0.0, 1.0]])
    start = np.linalg.qr(start)[0] * np.sign(np.diag(np.linalg.qr(start)[1]))
    v.set_estimate(g2o.Sim3(start, t + 0.05, 1.5))
    opt.add_vertex(v)
    edges = []
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    delta = np.sqrt(10.0) * 1e-3
    for i in range(n):
        p1, p2 = point_cls(), point_cls()
        p1.set_id(2 * i + 1)
        p1.set_estimate(X1[i])
        p1.set_fixed(True)
        p2.set_id(2 * i + 2)
        p2.set_estimate(X2[i])
        p2.set_fixed(True)
        opt.add_vertex(p1)
        opt.add_vertex(p2)
        obs1 = X1[i, :2] / X1[i, 2] + rng.normal(0, noise, 2)
        obs2 = X2[i, :2] / X2[i, 2] + rng.normal(0, noise, 2)
        if rng.random() < 0.1:
            obs1 = obs1 + rng.uniform(-0.2, 0.2, 2)
        e12 = g2o.EdgeSim3ProjectXYZ()
        e12.set_vertex(0, p2)
        e12.set_vertex(1, v)
        e12.set_measurement(obs1)
        e12.set_information(np.identity(2) * 1e6)
        e12.set_robust_kernel(g2o.RobustKernelHuber(delta * 1e3))
        e21 = g2o.EdgeInverseSim3ProjectXYZ()
        e21.set_vertex(0, p1)
        e21.set_vertex(1, v)
        e21.set_measurement(obs2)
        e21.set_information(np.identity(2) * 1e6)
        e21.set_robust_kernel(g2o.RobustKernelHuber(delta * 1e3))
        opt.add_edge(e12)
        opt.add_edge(e21)
        edges.append((e12, e21))
    opt.initialize_optimization()
    opt.optimize(iterations)
    inliers = 0
    def in_front(e: Any) -> bool:  # the wheel's Sim3 edges have no is_depth_positive
        return e.is_depth_positive() if hasattr(e, "is_depth_positive") else True

    for e12, e21 in edges:
        if e12.chi2() > 10.0 or e21.chi2() > 10.0 or not (in_front(e12) and in_front(e21)):
            opt.remove_edge(e12)
            opt.remove_edge(e21)
        else:
            inliers += 1
    opt.initialize_optimization()
    opt.optimize(10)
    opt.compute_active_errors()
    S = opt.vertex(0).estimate()
    return {"chi2": opt.active_chi2(), "inliers": inliers, "scale": S.scale(),
            "t": np.asarray(S.translation()).ravel()}


def offset_types_chi2(g2o: Any, seed: int = 1) -> dict[str, float]:
    """One edge of each offset type (``EdgeSE2Offset``, ``EdgeSE2PointXYOffset``,
    ``EdgeSE3Offset``) with non-trivial ``ParameterSE2Offset``/``ParameterSE3Offset``
    (set through ``set_param``, the wheel's name).

    Returns:
        ``{edge class: chi2}`` after ``compute_active_errors``.
    """
    rng = np.random.default_rng(seed)
    opt = _dense_levenberg(g2o)
    for pid in (0, 1):
        p2 = g2o.ParameterSE2Offset()
        p2.set_id(pid)
        p2.set_param(g2o.SE2(*rng.normal(0, 0.5, 3)))
        opt.add_parameter(p2)
        p3 = g2o.ParameterSE3Offset()
        p3.set_id(10 + pid)
        R = _rotation(rng)
        p3.set_param(g2o.Isometry3d(R, rng.normal(0, 0.5, (3, 1))))
        opt.add_parameter(p3)
    vs = []
    for i in range(2):
        v = g2o.VertexSE2()
        v.set_id(i)
        v.set_estimate(g2o.SE2(*rng.normal(0, 1, 3)))
        opt.add_vertex(v)
        vs.append(v)
    pt = g2o.VertexPointXY()
    pt.set_id(2)
    pt.set_estimate(rng.normal(0, 2, 2))
    opt.add_vertex(pt)
    ps = []
    for i in range(2):
        v = g2o.VertexSE3()
        v.set_id(3 + i)
        v.set_estimate(g2o.Isometry3d(_rotation(rng), rng.normal(0, 1, (3, 1))))
        opt.add_vertex(v)
        ps.append(v)
    edges = {}
    e = g2o.EdgeSE2Offset()
    e.set_vertex(0, vs[0])
    e.set_vertex(1, vs[1])
    e.set_measurement(g2o.SE2(*rng.normal(0, 1, 3)))
    e.set_information(np.diag([4.0, 9.0, 16.0]))
    e.set_parameter_id(0, 0)
    e.set_parameter_id(1, 1)
    edges["EdgeSE2Offset"] = e
    e = g2o.EdgeSE2PointXYOffset()
    e.set_vertex(0, vs[0])
    e.set_vertex(1, pt)
    e.set_measurement(rng.normal(0, 1, 2))
    e.set_information(np.diag([4.0, 9.0]))
    e.set_parameter_id(0, 1)
    edges["EdgeSE2PointXYOffset"] = e
    e = g2o.EdgeSE3Offset()
    e.set_vertex(0, ps[0])
    e.set_vertex(1, ps[1])
    e.set_measurement(g2o.Isometry3d(_rotation(rng), rng.normal(0, 1, (3, 1))))
    e.set_information(np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    e.set_parameter_id(0, 10)
    e.set_parameter_id(1, 11)
    edges["EdgeSE3Offset"] = e
    for e in edges.values():
        opt.add_edge(e)
    return _edge_chi2s(opt, edges)


def sba_demo(g2o: Any, seed: int = 0, noise: float = 1.0, n_points: int = 300,
             iterations: int = 10) -> dict[str, Any]:
    """g2o's ``sba_demo``: stereo cameras (``VertexSCam``, static intrinsics) and points seen
    through ``Edge_XYZ_VSC`` (``[u, v, u_right]``), disparity noise 1/16 px.

    Returns:
        ``chi2``, ``rmse_before``/``rmse_after`` of the points, ``iterations``.
    """
    rng = np.random.default_rng(seed)
    optimizer = g2o.SparseOptimizer()
    optimizer.set_algorithm(g2o.OptimizationAlgorithmLevenberg(
        g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())))
    true_points = np.column_stack([rng.random(n_points) * 3 - 1.5, rng.random(n_points) - 0.5,
                                   rng.random(n_points) + 3])
    g2o.VertexSCam.set_cam(500.0, 500.0, 320.0, 240.0, 0.075)
    num_pose = 5
    for i in range(num_pose):
        v = g2o.VertexSCam()
        v.set_id(i)
        v.set_estimate(g2o.Isometry3d(np.identity(3), np.array([[i * 0.04 - 1], [0.0], [0.0]])))
        v.set_fixed(i < 2)
        v.set_all()
        optimizer.add_vertex(v)
    edge_cls = getattr(g2o, "Edge_XYZ_VSC", None) or g2o.EdgeXyzVsc
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    point_id, inliers, sse0 = num_pose, {}, 0.0
    for i, point in enumerate(true_points):
        visible = _in_image((j, optimizer.vertex(j).map_point(point)) for j in range(num_pose))
        if len(visible) < 2:
            continue
        vp = point_cls()
        vp.set_id(point_id)
        vp.set_marginalized(True)
        vp.set_estimate(point + rng.standard_normal(3) * 0.3)
        optimizer.add_vertex(vp)
        for j, z in visible:
            edge = edge_cls()
            edge.set_vertex(0, vp)
            edge.set_vertex(1, optimizer.vertex(j))
            edge.set_measurement(z + rng.standard_normal(3) * noise * np.array([1, 1, 1 / 16]))
            edge.set_information(np.identity(3))
            edge.set_parameter_id(0, 0)
            optimizer.add_edge(edge)
        inliers[point_id] = i
        sse0 += float(np.sum((vp.estimate() - true_points[i]) ** 2))
        point_id += 1
    optimizer.initialize_optimization()
    its = optimizer.optimize(iterations)
    optimizer.compute_active_errors()
    sse1 = sum(float(np.sum((optimizer.vertex(i).estimate() - true_points[k]) ** 2))
               for i, k in inliers.items())
    return {"chi2": optimizer.active_chi2(), "rmse_before": np.sqrt(sse0 / len(inliers)),
            "rmse_after": np.sqrt(sse1 / len(inliers)), "iterations": its}


def sba_cam_chi2(g2o: Any, seed: int = 2) -> dict[str, float]:
    """One edge of each of g2o's SBA camera types (``VertexCam`` holding an ``SBACam``).

    Returns:
        ``{edge class: chi2}`` after ``compute_active_errors``.
    """
    rng = np.random.default_rng(seed)
    opt = _dense_levenberg(g2o)
    cams = []
    for i in range(2):
        R = _rotation(rng)
        c = g2o.SBACam(g2o.SE3Quat(R, rng.normal(0, 0.3, 3)))
        c.set_cam(450.0 + 10 * i, 460.0, 320.0, 240.0, 0.1)
        v = g2o.VertexCam()
        v.set_id(i)
        v.set_estimate(c)
        opt.add_vertex(v)
        cams.append(v)
    p = g2o.VertexPointXYZ()
    p.set_id(2)
    p.set_estimate(cams[0].estimate().translation() + cams[0].estimate().rotation().matrix()
                   @ np.array([0.2, -0.1, 4.0]))
    opt.add_vertex(p)
    edges = {}
    for name, vs, z in (("EdgeProjectP2MC", [p, cams[0]], np.array([330.0, 230.0])),
                        ("EdgeProjectP2SC", [p, cams[0]], np.array([330.0, 230.0, 320.0])),
                        ("EdgeSBAScale", [cams[0], cams[1]], 0.4),
                        ("EdgeSBACam", [cams[0], cams[1]],
                         g2o.SE3Quat(np.identity(3), np.array([0.1, 0.2, 0.3])))):
        e = getattr(g2o, name)()
        for i, v in enumerate(vs):
            e.set_vertex(i, v)
        e.set_measurement(z)
        d = {"EdgeSBAScale": 1, "EdgeSBACam": 6, "EdgeProjectP2SC": 3}.get(name, 2)
        e.set_information(np.identity(d) * 2.0)
        opt.add_edge(e)
        edges[name] = e
    return _edge_chi2s(opt, edges)


def variable_and_odometry_chi2(g2o: Any, seed: int = 3) -> dict[str, float]:
    """``EdgeSE2LotsOfXY`` (3 points, ``resize``), ``EdgeSE3LotsOfXYZ`` (2 points),
    ``EdgeSE2TwoPointsXY`` and ``EdgeSE2OdomDifferentialCalib`` (a ``VelocityMeasurement``).

    Returns:
        ``{edge class: chi2}`` after ``compute_active_errors``.
    """
    rng = np.random.default_rng(seed)
    opt = _dense_levenberg(g2o)
    vid = 0

    def add(cls: str, est: Any) -> Any:
        nonlocal vid
        v = getattr(g2o, cls)()
        v.set_id(vid)
        v.set_estimate(est)
        opt.add_vertex(v)
        vid += 1
        return v

    poses = [add("VertexSE2", g2o.SE2(*rng.normal(0, 1, 3))) for _ in range(2)]
    xy = [add("VertexPointXY", rng.normal(0, 2, 2)) for _ in range(3)]
    pose3 = add("VertexSE3", g2o.Isometry3d(_rotation(rng), rng.normal(0, 1, (3, 1))))
    xyz = [add("VertexPointXYZ", rng.normal(0, 2, 3)) for _ in range(2)]
    calib = add("VertexOdomDifferentialParams", np.array([1.02, 0.97, 0.5]))
    edges = {}
    specs = (("EdgeSE2LotsOfXY", [poses[0], *xy], 6), ("EdgeSE3LotsOfXYZ", [pose3, *xyz], 6),
             ("EdgeSE2TwoPointsXY", [poses[1], xy[0], xy[1]], 4),
             ("EdgeSE2OdomDifferentialCalib", [poses[0], poses[1], calib], 3))
    for name, vs, d in specs:
        e = getattr(g2o, name)()
        if "Lots" in name:
            e.resize(len(vs))
        for i, v in enumerate(vs):
            e.set_vertex(i, v)
        if name == "EdgeSE2OdomDifferentialCalib":
            e.set_measurement(g2o.VelocityMeasurement(0.8, 1.1, 0.5))
        else:
            e.set_measurement(rng.normal(0, 1, d))
        A = rng.normal(size=(d, d))
        e.set_information(A @ A.T + d * np.identity(d))
        opt.add_edge(e)
        edges[name] = e
    return _edge_chi2s(opt, edges)


def slam_backend_types_chi2(g2o: Any, seed: int = 4) -> dict[str, float]:
    """One edge of each type ORB-SLAM uses besides ``EdgeSE3ProjectXYZ``: the pose-only and
    stereo projections, ``EdgeSE3Expmap`` and ``EdgeSim3``.

    Returns:
        ``{edge class: chi2}`` after ``compute_active_errors``.
    """
    rng = np.random.default_rng(seed)
    opt = _dense_levenberg(g2o)

    def rot() -> np.ndarray:
        R = _rotation(rng)
        w = np.array([[0, -0.1, 0.05], [0.1, 0, -0.02], [-0.05, 0.02, 0]])
        return np.eye(3) + w + 0.5 * w @ w if rng.random() < 2 else R  # near the identity

    poses = []
    for i in range(2):
        v = g2o.VertexSE3Expmap()
        v.set_id(i)
        v.set_estimate(g2o.SE3Quat(np.linalg.qr(rot())[0] * np.sign(np.diag(np.linalg.qr(
            rot())[1])), rng.normal(0, 0.2, 3)))
        opt.add_vertex(v)
        poses.append(v)
    sims = []
    for i in range(2):
        v = g2o.VertexSim3Expmap()
        v.set_id(2 + i)
        q = np.linalg.qr(rot())
        v.set_estimate(g2o.Sim3(q[0] * np.sign(np.diag(q[1])), rng.normal(0, 0.2, 3),
                                1.0 + 0.3 * i))
        opt.add_vertex(v)
        sims.append(v)
    point = g2o.VertexPointXYZ()
    point.set_id(4)
    point.set_estimate(np.array([0.2, -0.1, 4.0]))
    opt.add_vertex(point)
    edges = {}
    fx, fy, cx, cy, bf = 450.0, 455.0, 320.0, 240.0, 40.0
    for name, vs, z in (("EdgeSE3ProjectXYZOnlyPose", [poses[0]], np.array([345.0, 228.0])),
                        ("EdgeStereoSE3ProjectXYZOnlyPose", [poses[0]],
                         np.array([345.0, 228.0, 335.0])),
                        ("EdgeStereoSE3ProjectXYZ", [point, poses[1]],
                         np.array([345.0, 228.0, 335.0])),
                        ("EdgeSE3Expmap", [poses[0], poses[1]],
                         g2o.SE3Quat(np.identity(3), np.array([0.1, 0.0, 0.05]))),
                        ("EdgeSim3", [sims[0], sims[1]],
                         g2o.Sim3(np.identity(3), np.array([0.1, 0.0, 0.05]), 1.2))):
        e = getattr(g2o, name)()
        if "Project" in name and not hasattr(e, "fx"):
            continue  # the wheel's stereo pose-only edge has no intrinsics to set
        for i, v in enumerate(vs):
            e.set_vertex(i, v)
        e.set_measurement(z)
        d = {"EdgeSE3Expmap": 6, "EdgeSim3": 7}.get(name, len(z) if hasattr(z, "__len__")
                                                     else 2)
        e.set_information(np.identity(d) * 1.5)
        if "Project" in name:
            e.fx, e.fy, e.cx, e.cy = fx, fy, cx, cy
        if "Stereo" in name:
            e.bf = bf
        if "OnlyPose" in name:
            e.Xw = np.array([0.3, 0.1, 4.5])
        opt.add_edge(e)
        edges[name] = e
    return _edge_chi2s(opt, edges)
