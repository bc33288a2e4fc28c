"""ORB-SLAM2's four back-end procedures with g2opy 2.3.0, written as ORB-SLAM writes them (one
object per vertex and edge, per-edge loops for the outlier checks), for
``benchmarks/bench_slam_backend.py``. Each takes a ``stamp`` callback, called just before the
first ``initialize_optimization`` (the end of the build), and returns, besides ORB-SLAM's
results, a function that computes the report's quality numbers (each edge's error evaluated
afresh), for the benchmark to call after it has stopped the clock.

Where g2opy 2.3.0 lacks a member ORB-SLAM sets (see the benchmark's docstring), the closest
equal computation is used.
"""

from __future__ import annotations

from collections.abc import Callable

import g2opy as g2o
import numpy as np
import slam_backend_scenes as scenes

CHI2_MONO, CHI2_STEREO = 5.991, 7.815
#: ``setRobustKernel(0)``: g2opy takes no null kernel; Huber's identity region reaches 1e24.
NO_KERNEL = g2o.RobustKernelHuber(1e12)


def _se3(T: np.ndarray) -> g2o.SE3Quat:
    return g2o.SE3Quat(np.asfortranarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


def _mat(q: g2o.SE3Quat) -> np.ndarray:
    return np.asarray(q.to_homogeneous_matrix())


def _sim3(S: np.ndarray) -> g2o.Sim3:
    sR = S[:3, :3]
    s = float(np.sqrt((sR * sR).sum() / 3.0))
    return g2o.Sim3(np.asfortranarray(sR / s), np.ascontiguousarray(S[:3, 3]), s)


def _sim3_mat(q: g2o.Sim3) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = q.scale() * q.rotation().matrix()
    S[:3, 3] = q.translation()
    return S


def _levenberg(block: object) -> g2o.SparseOptimizer:
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(block))
    return opt


def pose_optimization(T_init: np.ndarray, Xw: np.ndarray, z: np.ndarray,
                      inv_sigma2: np.ndarray, stamp: Callable[[], None]
                      ) -> tuple[np.ndarray, np.ndarray, Callable[[], float]]:
    """``Optimizer::PoseOptimization``: 4 rounds × 10 iterations, pose reset each round."""
    stereo = z.shape[1] == 3
    th = CHI2_STEREO if stereo else CHI2_MONO
    opt = _levenberg(g2o.BlockSolverSE3(g2o.LinearSolverDenseSE3()))
    v = g2o.VertexSE3Expmap()
    v.set_estimate(_se3(T_init))
    v.set_id(0)
    v.set_fixed(False)
    opt.add_vertex(v)
    delta = float(np.sqrt(th))
    edges = []
    for i in range(len(z)):
        if stereo:   # EdgeStereoSE3ProjectXYZOnlyPose's Xw, bf: not in g2opy
            p = g2o.VertexPointXYZ()
            p.set_id(i + 1)
            p.set_estimate(Xw[i])
            p.set_fixed(True)
            opt.add_vertex(p)
            e = g2o.EdgeStereoSE3ProjectXYZ()
            e.set_vertex(0, p)
            e.set_vertex(1, v)
            e.bf = scenes.BF
        else:
            e = g2o.EdgeSE3ProjectXYZOnlyPose()
            e.set_vertex(0, v)
            e.Xw = Xw[i]
        e.set_measurement(z[i])
        e.set_information(np.eye(z.shape[1]) * inv_sigma2[i])
        e.set_robust_kernel(g2o.RobustKernelHuber(delta))
        e.fx, e.fy, e.cx, e.cy = scenes.FX, scenes.FY, scenes.CX, scenes.CY
        opt.add_edge(e)
        edges.append(e)
    stamp()
    outlier = [False] * len(edges)
    for it in range(4):
        v.set_estimate(_se3(T_init))
        opt.initialize_optimization(0)
        opt.optimize(10)
        active = [not o for o in outlier]
        for i, e in enumerate(edges):
            if outlier[i]:
                e.compute_error()
            chi2 = e.chi2()
            if chi2 > th:
                outlier[i] = True
                e.set_level(1)
            else:
                outlier[i] = False
                e.set_level(0)
            if it == 2:
                e.set_robust_kernel(NO_KERNEL)
    T = _mat(v.estimate())
    return T, ~np.array(outlier), lambda: _active_chi2(edges, active)


def _active_chi2(edges: list, active: list[bool]) -> float:
    total = 0.0
    for e, a in zip(edges, active, strict=True):
        if a:
            e.compute_error()
            total += e.chi2()
    return total


def local_bundle_adjustment(T: np.ndarray, fixed: np.ndarray, X: np.ndarray, kf: np.ndarray,
                            pt: np.ndarray, z: np.ndarray, inv_sigma2: np.ndarray,
                            stamp: Callable[[], None]
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Callable]:
    """``Optimizer::LocalBundleAdjustment``: 5 iterations, outliers to level 1, kernels
    dropped, 10 iterations."""
    opt = _levenberg(g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3()))
    n = len(T)
    kfs, pts = [], []
    for k in range(n):
        v = g2o.VertexSE3Expmap()
        v.set_estimate(_se3(T[k]))
        v.set_id(k)
        v.set_fixed(bool(fixed[k]))
        opt.add_vertex(v)
        kfs.append(v)
    for p in range(len(X)):
        v = g2o.VertexPointXYZ()
        v.set_estimate(X[p])
        v.set_id(n + p)
        v.set_marginalized(True)
        opt.add_vertex(v)
        pts.append(v)
    delta = float(np.sqrt(CHI2_MONO))
    edges = []
    for o in range(len(z)):
        e = g2o.EdgeSE3ProjectXYZ()
        e.set_vertex(0, pts[pt[o]])
        e.set_vertex(1, kfs[kf[o]])
        e.set_measurement(z[o])
        e.set_information(np.eye(2) * inv_sigma2[o])
        e.set_robust_kernel(g2o.RobustKernelHuber(delta))
        e.fx, e.fy, e.cx, e.cy = scenes.FX, scenes.FY, scenes.CX, scenes.CY
        opt.add_edge(e)
        edges.append(e)
    stamp()
    opt.initialize_optimization()
    opt.optimize(5)
    active = []
    for e in edges:
        bad = e.chi2() > CHI2_MONO or not e.is_depth_positive()
        if bad:
            e.set_level(1)
        e.set_robust_kernel(NO_KERNEL)
        active.append(not bad)
    opt.initialize_optimization(0)
    opt.optimize(10)
    orb_inlier = [not (e.chi2() > CHI2_MONO or not e.is_depth_positive()) for e in edges]
    T_out = np.stack([_mat(v.estimate()) for v in kfs])
    X_out = np.stack([np.asarray(v.estimate()) for v in pts])

    def report() -> tuple[float, np.ndarray]:
        """(final active chi2, inliers), every error evaluated at the final estimate (ORB-SLAM's
        own check, ``orb_inlier``, reads the errors of the excluded edges as they were)."""
        inlier = []
        for e in edges:
            e.compute_error()
            inlier.append(e.chi2() <= CHI2_MONO and e.is_depth_positive())
        return _active_chi2(edges, active), np.array(inlier)

    return T_out, X_out, np.array(orb_inlier), report


def optimize_sim3(S12: np.ndarray, P1c: np.ndarray, P2c: np.ndarray, z1: np.ndarray,
                  z2: np.ndarray, inv_sigma2_1: np.ndarray, inv_sigma2_2: np.ndarray,
                  stamp: Callable[[], None], th2: float = 10.0
                  ) -> tuple[np.ndarray, np.ndarray, Callable[[], float]]:
    """``Optimizer::OptimizeSim3`` (monocular: free scale). g2opy keeps the vertex's
    intrinsics at ``f = 1, c = 0``: measurements are normalised, information ``f²``-scaled."""
    opt = _levenberg(g2o.BlockSolverX(g2o.LinearSolverDenseX()))
    vs = g2o.VertexSim3Expmap()
    vs.set_estimate(_sim3(S12))
    vs.set_id(0)
    vs.set_fixed(False)
    opt.add_vertex(vs)
    c = np.array([scenes.CX, scenes.CY])
    f = scenes.FX
    delta = float(np.sqrt(th2))
    e12s, e21s = [], []
    for i in range(len(P1c)):
        p1 = g2o.VertexPointXYZ()
        p1.set_estimate(P1c[i])
        p1.set_id(2 * i + 1)
        p1.set_fixed(True)
        opt.add_vertex(p1)
        p2 = g2o.VertexPointXYZ()
        p2.set_estimate(P2c[i])
        p2.set_id(2 * i + 2)
        p2.set_fixed(True)
        opt.add_vertex(p2)
        e12 = g2o.EdgeSim3ProjectXYZ()
        e12.set_vertex(0, p2)
        e12.set_vertex(1, vs)
        e12.set_measurement((z1[i] - c) / f)
        e12.set_information(np.eye(2) * inv_sigma2_1[i] * f * f)
        e12.set_robust_kernel(g2o.RobustKernelHuber(delta))
        opt.add_edge(e12)
        e21 = g2o.EdgeInverseSim3ProjectXYZ()
        e21.set_vertex(0, p1)
        e21.set_vertex(1, vs)
        e21.set_measurement((z2[i] - c) / f)
        e21.set_information(np.eye(2) * inv_sigma2_2[i] * f * f)
        e21.set_robust_kernel(g2o.RobustKernelHuber(delta))
        opt.add_edge(e21)
        e12s.append(e12)
        e21s.append(e21)
    stamp()
    opt.initialize_optimization()
    opt.optimize(5)
    n_bad = 0
    kept = [True] * len(e12s)
    for i, (e12, e21) in enumerate(zip(e12s, e21s, strict=True)):
        if e12.chi2() > th2 or e21.chi2() > th2:
            opt.remove_edge(e12)
            opt.remove_edge(e21)
            kept[i] = False
            n_bad += 1
    opt.initialize_optimization()
    opt.optimize(10 if n_bad > 0 else 5)
    inlier = np.zeros(len(e12s), dtype=bool)
    for i, (e12, e21) in enumerate(zip(e12s, e21s, strict=True)):
        if kept[i]:
            inlier[i] = e12.chi2() <= th2 and e21.chi2() <= th2
    return (_sim3_mat(vs.estimate()), inlier,
            lambda: _active_chi2(e12s, kept) + _active_chi2(e21s, kept))


def optimize_essential_graph(S: np.ndarray, ij: np.ndarray, S_ji: np.ndarray, loop_kf: int,
                             stamp: Callable[[], None]
                             ) -> tuple[np.ndarray, Callable[[], float]]:
    """``Optimizer::OptimizeEssentialGraph`` (monocular): 20 iterations of LM; g2opy does
    not expose ``setUserLambdaInit`` (ORB-SLAM: 1e-16), so g2o's default λ₀ is used."""
    opt = _levenberg(g2o.BlockSolverSim3(g2o.LinearSolverEigenSim3()))
    vs = []
    for k in range(len(S)):
        v = g2o.VertexSim3Expmap()
        v.set_estimate(_sim3(S[k]))
        v.set_id(k)
        v.set_fixed(k == loop_kf)
        v.set_marginalized(False)
        opt.add_vertex(v)
        vs.append(v)
    info = np.eye(7)
    edges = []
    for k in range(len(ij)):
        e = g2o.EdgeSim3()
        e.set_vertex(0, vs[ij[k, 0]])
        e.set_vertex(1, vs[ij[k, 1]])
        e.set_measurement(_sim3(S_ji[k]))
        e.set_information(info)
        opt.add_edge(e)
        edges.append(e)
    stamp()
    opt.initialize_optimization()
    opt.optimize(20)
    out = np.stack([_sim3_mat(v.estimate()) for v in vs])
    return out, lambda: _active_chi2(edges, [True] * len(edges))
