"""Per-iteration time of small SLAM problems: graphopt against g2o (g2opy 2.3.0), same run.

Workloads (synthetic, known truth, 1 px noise, 10 % outliers, Huber kernels of width
``sqrt(5.991)`` as ORB-SLAM sets them, LM on both sides):

* ``motion-M``: motion-only BA, one free ``VertexSE3Expmap`` and ``M`` matches to fixed world
  points. graphopt uses ``EdgeSE3ProjectXYZOnlyPose`` when ``graphopt.types`` has it, else
  ``EdgeSE3ProjectXYZ`` to fixed ``VertexPointXYZ`` (the same normal equations); g2o uses its
  ``EdgeSE3ProjectXYZOnlyPose`` with ``LinearSolverDense`` (ORB-SLAM's ``PoseOptimization``).
* ``local-5k``: 10 free + 10 fixed keyframes, 1,000 marginalised points, 5,000 observations
  (``EdgeSE3ProjectXYZ``); g2o with ``LinearSolverEigen`` (ORB-SLAM's local BA).
* ``local-25k``: 20 free + 30 fixed keyframes, 5,000 points, 25,000 observations.

Method: each side builds its graph once. A *round* resets the estimates to the perturbed
start (moved by ``k`` nm in round ``k`` on both sides: no round starts where another did, so
graphopt's evaluation memo does not apply) and calls ``initialize_optimization`` (as
ORB-SLAM does before every ``optimize``; LM's λ restarts on both sides), not timed, then
times ``optimize(n)`` for ``n`` = 1 and
``n`` = ``--iterations``: the **per-iteration** time is ``(t(n) − t(1)) / (n − 1)``, so that
what ``optimize`` does once per call (the initial chi2, bookkeeping) cancels on both sides.
``first`` is ``t(1)``, one whole ``optimize(1)`` call. Rounds interleave the two sides;
medians of ``--repeats`` rounds. One thread everywhere (set before numpy loads). The clock is
the process's CPU time by default (both sides run in this process on one thread, so it is what
each spends, without the shared machine's other load); ``--clock wall`` for wall-clock time.
The start is close enough that every iteration accepts its first trial on both sides
(``trials`` shows graphopt's count per iteration; g2o's comes from its batch statistics in a
separate, untimed run).

Usage::

    .venv/bin/python -P benchmarks/bench_small_iteration.py [--repeats 15] [--iterations 5]
        [--only motion-100,local-5k]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import itertools  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from graphopt import SparseOptimizer  # noqa: E402
from graphopt.algorithms import LevenbergConfig  # noqa: E402
from graphopt.lie import se3_exp  # noqa: E402
from graphopt.robust_kernel import RobustKernelHuber  # noqa: E402
from graphopt.stopping import StoppingConfig  # noqa: E402
from graphopt.types import (  # noqa: E402
    CameraParameters,
    EdgeSE3ProjectXYZ,
    VertexPointXYZ,
    VertexSE3Expmap,
)

try:  # types22's unary edge, when it has landed
    from graphopt.types import EdgeSE3ProjectXYZOnlyPose  # type: ignore[attr-defined]
except (ImportError, AttributeError):
    EdgeSE3ProjectXYZOnlyPose = None

CAM = CameraParameters(458.0, 457.0, 367.0, 248.0)
DELTA = float(np.sqrt(5.991))


@dataclass
class Scene:
    """Poses ``T_cw`` (truth and start), points (truth and start), observations.

    Args:
        poses: ``(k, 4, 4)`` start poses.
        fixed: ``(k,)`` fixed flags.
        points: ``(n, 3)`` start points.
        free_points: Whether the points are free (marginalised) or fixed.
        obs: ``(m, 2)`` ``(pose, point)`` indices.
        uv: ``(m, 2)`` pixels.
    """

    poses: np.ndarray
    fixed: np.ndarray
    points: np.ndarray
    free_points: bool
    obs: np.ndarray
    uv: np.ndarray


def _project(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    P = np.einsum("mij,mj->mi", T[:, :3, :3], X) + T[:, :3, 3]
    return np.stack([CAM.fx * P[:, 0] / P[:, 2] + CAM.cx, CAM.fy * P[:, 1] / P[:, 2] + CAM.cy], 1)


def _observe(rng: np.random.Generator, T: np.ndarray, X: np.ndarray) -> np.ndarray:
    uv = _project(T, X) + rng.normal(0.0, 1.0, (len(X), 2))
    out = rng.random(len(X)) < 0.1
    uv[out] += rng.uniform(-40.0, 40.0, (int(out.sum()), 2))
    return uv


def motion_scene(m: int, seed: int = 0) -> Scene:
    """One pose seeing ``m`` fixed points 2–10 m ahead; the start is 0.02 rad / 5 cm off."""
    rng = np.random.default_rng(seed)
    T = se3_exp(np.array([[0.1, -0.2, 0.05, 0.3, -0.1, 0.2]]))
    Pc = np.column_stack([rng.uniform(-3, 3, m), rng.uniform(-2, 2, m), rng.uniform(2, 10, m)])
    R, t = T[0, :3, :3], T[0, :3, 3]
    X = (Pc - t) @ R
    uv = _observe(rng, np.repeat(T, m, 0), X)
    start = se3_exp(np.array([[0.02, -0.01, 0.015, 0.05, 0.03, -0.04]])) @ T
    return Scene(start, np.array([False]), X, False, np.column_stack([np.zeros(m, int),
                                                                       np.arange(m)]), uv)


def local_scene(free: int, fixed: int, n: int, per_point: int = 5, seed: int = 1) -> Scene:
    """Keyframes 20 cm apart along x; ``n`` points seen by ``per_point`` keyframes each (one
    free at least); free poses start 0.005 rad / 2 cm off, points 5 cm off."""
    rng = np.random.default_rng(seed)
    k = free + fixed
    xi = np.zeros((k, 6))
    xi[:, 3] = -0.2 * np.arange(k)
    xi[:, :3] = rng.normal(0.0, 0.02, (k, 3))
    T = se3_exp(xi)
    X = np.column_stack([rng.uniform(-3, 0.2 * k + 3, n), rng.uniform(-2, 2, n),
                         rng.uniform(4, 12, n)])
    cams = np.array([rng.choice(k, per_point, replace=False) for _ in range(n)])
    cams[:, 0] = rng.integers(fixed, k, n)  # one free keyframe at least
    cams.sort(axis=1)
    cams = np.array([np.unique(c) for c in cams], dtype=object)
    obs = np.array([(c, p) for p, cs in enumerate(cams) for c in cs])
    uv = _observe(rng, T[obs[:, 0]], X[obs[:, 1]])
    fixed_flags = np.arange(k) < fixed
    start = T.copy()
    pert = np.column_stack([rng.normal(0.0, 0.005, (k, 3)), rng.normal(0.0, 0.02, (k, 3))])
    start[~fixed_flags] = se3_exp(pert[~fixed_flags]) @ T[~fixed_flags]
    Xs = X + rng.normal(0.0, 0.05, X.shape)
    return Scene(start, fixed_flags, Xs, True, obs, uv)


def _starts(sc: Scene) -> Iterator[np.ndarray]:
    """The poses of round 0, 1, 2, …: the scene's start moved by ``k`` nm along x in round
    ``k`` (the same on both sides), so that no round starts where an earlier one did and
    graphopt's evaluation memo (``graphopt/evaluation_memo.py``) plays no part."""
    for k in itertools.count():
        T = sc.poses.copy()
        T[:, 0, 3] += 1e-9 * k
        yield T


# --- graphopt ------------------------------------------------------------------------------


def graphopt_build(sc: Scene) -> tuple[SparseOptimizer, Callable[[], None]]:
    """The optimizer and a function resetting its estimates to the scene's start."""
    opt = SparseOptimizer(LevenbergConfig(), "auto",
                          stopping=StoppingConfig.iterations_only(100))
    k, n = len(sc.poses), len(sc.points)
    opt.add_vertices(VertexSE3Expmap, np.arange(k), sc.poses, fixed=sc.fixed)
    kern = RobustKernelHuber(DELTA)
    if not sc.free_points and EdgeSE3ProjectXYZOnlyPose is not None:
        opt.add_edges(EdgeSE3ProjectXYZOnlyPose, sc.obs[:, :1], sc.uv, robust_kernel=kern,
                      params=CAM, data={"Xw": sc.points[sc.obs[:, 1]]})
    else:
        opt.add_vertices(VertexPointXYZ, k + np.arange(n), sc.points, fixed=not sc.free_points,
                         marginalized=sc.free_points)
        opt.add_edges(EdgeSE3ProjectXYZ, np.column_stack([sc.obs[:, 0], k + sc.obs[:, 1]]),
                      sc.uv, robust_kernel=kern, params=CAM)
    opt.initialize_optimization()

    starts = _starts(sc)

    def reset() -> None:
        opt.set_estimates_of(VertexSE3Expmap, next(starts))
        if sc.free_points:
            opt.set_estimates_of(VertexPointXYZ, sc.points)
        opt.initialize_optimization()  # as ORB-SLAM does before every optimize (λ restarts)

    return opt, reset


# --- g2o -----------------------------------------------------------------------------------


def g2o_build(sc: Scene) -> tuple[object, Callable[[], None]]:
    """g2o's optimizer (ORB-SLAM's set-up) and a function resetting its estimates."""
    import g2opy as g2o

    opt = g2o.SparseOptimizer()
    if sc.free_points:
        solver = g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())
    else:
        solver = g2o.BlockSolverSE3(g2o.LinearSolverDenseSE3())
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(solver))
    k = len(sc.poses)
    poses = []
    for i, T in enumerate(sc.poses):
        v = g2o.VertexSE3Expmap()
        v.set_id(i)
        v.set_estimate(g2o.SE3Quat(T[:3, :3], T[:3, 3]))
        v.set_fixed(bool(sc.fixed[i]))
        opt.add_vertex(v)
        poses.append(v)
    points = []
    if sc.free_points:
        for j, X in enumerate(sc.points):
            p = g2o.VertexPointXYZ()
            p.set_id(k + j)
            p.set_estimate(X)
            p.set_marginalized(True)
            opt.add_vertex(p)
            points.append(p)
    for (c, j), z in zip(sc.obs, sc.uv, strict=True):
        if sc.free_points:
            e = g2o.EdgeSE3ProjectXYZ()
            e.set_vertex(0, points[j])
            e.set_vertex(1, poses[c])
        else:
            e = g2o.EdgeSE3ProjectXYZOnlyPose()
            e.set_vertex(0, poses[c])
            e.Xw = sc.points[j]
        e.set_measurement(z)
        e.set_information(np.eye(2))
        e.set_robust_kernel(g2o.RobustKernelHuber(DELTA))
        e.fx, e.fy, e.cx, e.cy = CAM.fx, CAM.fy, CAM.cx, CAM.cy
        opt.add_edge(e)
    opt.initialize_optimization()

    starts = _starts(sc)

    def reset() -> None:
        for v, T in zip(poses, next(starts), strict=True):
            v.set_estimate(g2o.SE3Quat(T[:3, :3], T[:3, 3]))
        for p, X in zip(points, sc.points if points else [], strict=True):
            p.set_estimate(X)
        opt.initialize_optimization()

    return opt, reset


def g2o_trials(opt: object, reset: Callable[[], None], n: int) -> list[int]:
    """g2o's LM trials per iteration (its batch statistics, an untimed run)."""
    reset()
    opt.set_compute_batch_statistics(True)
    opt.optimize(n)
    out = [int(s.levenberg_iterations) for s in opt.batch_statistics()]
    opt.set_compute_batch_statistics(False)
    return out


# --- timing --------------------------------------------------------------------------------

WORKLOADS: dict[str, Callable[[], Scene]] = {
    "motion-100": lambda: motion_scene(100),
    "motion-500": lambda: motion_scene(500),
    "motion-2000": lambda: motion_scene(2000),
    "local-5k": lambda: local_scene(10, 10, 1000),
    "local-25k": lambda: local_scene(20, 30, 5000),
}


#: The clock of every timing (``--clock``).
CLOCK: Callable[[], float] = time.process_time


def _timed(reset: Callable[[], None], run: Callable[[int], object], n: int) -> float:
    reset()
    t0 = CLOCK()
    run(n)
    return CLOCK() - t0


def bench(name: str, repeats: int, iterations: int) -> None:
    """Time one workload on both sides and print its row."""
    sc = WORKLOADS[name]()
    go, go_reset = graphopt_build(sc)
    g2, g2_reset = g2o_build(sc)
    sides = {"graphopt": (go_reset, go.optimize), "g2o": (g2_reset, g2.optimize)}
    for reset, run in sides.values():  # warm-up
        _timed(reset, run, iterations)
    times: dict[str, dict[int, list[float]]] = {s: {1: [], iterations: []} for s in sides}
    for _ in range(repeats):
        for s, (reset, run) in sides.items():
            for n in (1, iterations):
                times[s][n].append(_timed(reset, run, n))
    go_reset()
    res = go.optimize(iterations)
    trials = [i.trials for i in res.info]
    g2_tr = g2o_trials(g2, g2_reset, iterations)
    g2.compute_active_errors()
    med = {s: {n: statistics.median(v) for n, v in t.items()} for s, t in times.items()}
    per = {s: (m[iterations] - m[1]) / (iterations - 1) for s, m in med.items()}
    print(f"{name:12s} {len(sc.uv):6d}  {per['graphopt'] * 1e6:9.1f} {per['g2o'] * 1e6:9.1f} "
          f"{per['graphopt'] / per['g2o']:6.2f}   {med['graphopt'][1] * 1e6:9.1f} "
          f"{med['g2o'][1] * 1e6:9.1f}   {res.final_chi2:11.4f} {g2.active_robust_chi2():11.4f}"
          f"   {''.join(map(str, trials))}/{''.join(map(str, g2_tr))}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--only", default=",".join(WORKLOADS))
    ap.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                    help="CPU time of the process (default: both sides run in it, on one "
                         "thread; robust to a shared machine's load) or wall-clock time")
    args = ap.parse_args()
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    edge = "OnlyPose" if EdgeSE3ProjectXYZOnlyPose is not None else "fixed VertexPointXYZ"
    print(f"motion-only graphopt edges: {edge}; LM, {args.iterations} iterations, medians of "
          f"{args.repeats}; µs of {args.clock} time")
    print(f"{'workload':12s} {'edges':>6s}  {'graphopt':>9s} {'g2o':>9s} {'ratio':>6s}   "
          f"{'first go':>9s} {'first g2o':>9s}   {'chi2 go':>11s} {'chi2 g2o':>11s}   trials",
          flush=True)
    for name in args.only.split(","):
        bench(name.strip(), args.repeats, args.iterations)


if __name__ == "__main__":
    main()
