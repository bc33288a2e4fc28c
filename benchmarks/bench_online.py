"""Benchmark: online SLAM — graphopt's incremental optimizer against GTSAM's ISAM2, pose by pose.

Protocol (:mod:`graphopt.types.slam_online`, the same for every side): poses in id order; step
``k`` adds pose ``k`` — started by composing its odometry onto the *current* estimate of pose
``k − 1`` (without odometry: the file's estimate, or the spanning-tree guess for files without
vertex lines) — the landmarks first seen at this step (from their first observation) and every
edge whose larger pose endpoint is ``k``, then one update. The first pose is fixed (GTSAM: a
prior with σ = 1e-6). A step's time covers everything a user's loop does: making the new
values and factors, the update, and reading the estimate of the newest pose (GTSAM:
``calculateEstimate`` of that pose; graphopt keeps every estimate current).

Graphs: a generated 3,500-pose Manhattan world (``manhattan_world(3500, 0, max_closures=1,
closure_radius=0, side=43)``: 5,451 edges, the size of Olson's M3500), ``w10000.graph``,
``sphere_smallnoise.graph`` and ``victoriaPark_reduced_1k.g2o`` (landmarks). Reported per side:
total seconds, median / p95 / max step, final chi2 (g2o's ``Σ e'Ωe`` of the final estimate,
evaluated by graphopt for every side) against the batch optimum (graphopt's LM from the file's
start, run to convergence). GTSAM's factors: ``BetweenFactorPose2/3`` with the file's
information (3-D: reordered to GTSAM's rotation-first tangent, the rotation rows scaled from
g2o's half-angle quaternion error to angles); Victoria Park's point observations ``(x, y)`` in
the pose frame become ``BearingRangeFactor2D`` (bearing ``atan2(y, x)``, range ``|z|``, σ_range
= σ, σ_bearing = σ / range for the file's isotropic σ): GTSAM has no such Pose2–Point2 factor.

One thread on every side (set before numpy loads; GTSAM's wheel has no TBB). ``--repeats``
rounds run the sides interleaved; the table shows medians of the totals, and the step
statistics of the median run. Steps are timed in wall time and in the thread's CPU time (columns
``CPU``): on a machine shared with other jobs the wall time of either side swings by several
times between runs, the CPU time much less.

Usage::

    python -P benchmarks/bench_online.py [--graphs manhattan,w10000,sphere,victoria]
                                         [--repeats 1] [--skip-gtsam] [--defaults-only]
                                         [--json FILE]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from graphopt.apps.slam_scene import manhattan_world  # noqa: E402
from graphopt.io.g2o import read_graph  # noqa: E402
from graphopt.io.g2o_records import GraphFile  # noqa: E402
from graphopt.types.isometry3 import matrix_to_quat  # noqa: E402
from graphopt.types.slam_graph import SlamGraph, build_graph  # noqa: E402
from graphopt.types.slam_online import (  # noqa: E402
    ReplaySchedule,
    replay,
    replay_schedule,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph"
#: name → (file or None for the generated world, build with the spanning-tree guess)
GRAPHS = {"manhattan": (None, False), "w10000": ("w10000.graph", False),
          "sphere": ("sphere_smallnoise.graph", True),
          "victoria": ("victoriaPark_reduced_1k.g2o", True)}


def load(name: str) -> tuple[GraphFile, bool]:
    """The graph's records and whether it needs the guess."""
    path, guess = GRAPHS[name]
    if path is None:
        return manhattan_world(3500, 0, max_closures=1, closure_radius=0.0, side=43)[0], False
    return read_graph(DATA / path), guess


def batch_optimum(graph: GraphFile, guess: bool) -> tuple[SlamGraph, float]:
    """The graph built from the file's start and its converged chi2 (graphopt's LM)."""
    slam = build_graph(graph, guess=guess)
    slam.optimizer.optimize(100)
    slam.optimizer.compute_active_errors()
    return slam, float(slam.optimizer.chi2())


def chi2_of(slam: SlamGraph, schedule: ReplaySchedule, poses: np.ndarray,
            landmarks: np.ndarray | None) -> float:
    """g2o's chi2 of the graph at the given estimates (poses in step order)."""
    opt = slam.optimizer
    store = opt.graph.stores[schedule.pose_type]
    order = np.argsort(store.ids)
    est = store.estimates.copy()
    est[order] = poses
    store.estimates = est
    if landmarks is not None and schedule.landmark_type is not None:
        lst = opt.graph.stores[schedule.landmark_type]
        pos = np.searchsorted(lst.ids, schedule.landmark_ids, sorter=np.argsort(lst.ids))
        lest = lst.estimates.copy()
        lest[np.argsort(lst.ids)[pos]] = landmarks
        lst.estimates = lest
    opt.compute_active_errors()
    return float(opt.chi2())


# --- GTSAM ------------------------------------------------------------------------------------

def _gtsam_pose(gtsam: Any, three_d: bool, x: np.ndarray) -> Any:
    if not three_d:
        return gtsam.Pose2(float(x[0]), float(x[1]), float(x[2]))
    q = matrix_to_quat(x[None, :, :3])[0]
    return gtsam.Pose3(gtsam.Rot3.Quaternion(q[3], q[0], q[1], q[2]), x[:, 3].copy())


def _gtsam_info(info: np.ndarray) -> np.ndarray:
    """g2o's SE3 information (translation, half-angle quaternion vector) to GTSAM's Pose3
    tangent order (rotation angle, translation)."""
    perm = np.r_[3:6, 0:3]
    out = info[np.ix_(perm, perm)].copy()
    out[:3, :] *= 0.5
    out[:, :3] *= 0.5
    return out


def gtsam_run(schedule: ReplaySchedule, relinearize_skip: int) -> dict[str, Any]:
    """Replay with GTSAM's ISAM2 (default parameters but ``relinearizeSkip``)."""
    import gtsam

    three_d = schedule.pose_type.__name__ == "VertexSE3"
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = relinearize_skip
    isam = gtsam.ISAM2(params)
    n = schedule.steps
    pid = schedule.pose_ids
    lm_key = 1 << 40  # landmark keys apart from pose keys
    models: dict[bytes, Any] = {}

    def model(info: np.ndarray) -> Any:
        key = info.tobytes()
        if key not in models:
            models[key] = gtsam.noiseModel.Gaussian.Information(info)
        return models[key]

    edges = [(e, e.tag == "EDGE_SE2_XY") for e in schedule.edges]
    between = gtsam.BetweenFactorPose3 if three_d else gtsam.BetweenFactorPose2
    bmeas = [[_gtsam_pose(gtsam, three_d, z) for z in e.measurements] if not obs else None
             for e, obs in edges]
    binfo = [[_gtsam_info(w) if three_d else w for w in e.information] if not obs else None
             for e, obs in edges]
    steps = np.zeros(n)
    cpu = np.zeros(n)
    current = None
    for k in range(n):
        t0, c0 = time.perf_counter(), time.thread_time()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if k == 0:
            x0 = _gtsam_pose(gtsam, three_d, schedule.estimates[0])
            prior = gtsam.PriorFactorPose3 if three_d else gtsam.PriorFactorPose2
            graph.add(prior(int(pid[0]), x0, gtsam.noiseModel.Isotropic.Sigma(
                6 if three_d else 3, 1e-6)))
            current = x0
        elif schedule.has_odometry[k]:
            current = current.compose(_gtsam_pose(gtsam, three_d, schedule.odometry[k]))
        else:
            current = _gtsam_pose(gtsam, three_d, schedule.estimates[k])
        values.insert(int(pid[k]), current)
        a, b = schedule.landmark_bounds[k], schedule.landmark_bounds[k + 1]
        for ei, (e, obs) in enumerate(edges):
            lo, hi = int(e.bounds[k]), int(e.bounds[k + 1])
            for r in range(lo, hi):
                i, j = int(e.ids[r, 0]), int(e.ids[r, 1])
                if not obs:
                    graph.add(between(i, j, bmeas[ei][r], model(binfo[ei][r])))
                    continue
                z = e.measurements[r]
                rng = float(np.hypot(z[0], z[1]))
                sigma = 1.0 / np.sqrt(e.information[r][0, 0])
                graph.add(gtsam.BearingRangeFactor2D(
                    i, lm_key + j, gtsam.Rot2(float(np.arctan2(z[1], z[0]))), rng,
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma / rng, sigma]))))
            if obs:
                for lm, row in zip(schedule.landmark_ids[a:b].tolist(),
                                   schedule.landmark_first[a:b].tolist(), strict=True):
                    z = e.measurements[row]
                    values.insert(lm_key + lm, current.transformFrom(
                        gtsam.Point2(float(z[0]), float(z[1]))))
        isam.update(graph, values)
        current = (isam.calculateEstimatePose3 if three_d
                   else isam.calculateEstimatePose2)(int(pid[k]))
        steps[k] = time.perf_counter() - t0
        cpu[k] = time.thread_time() - c0
    est = isam.calculateEstimate()
    if three_d:
        poses = np.stack([est.atPose3(int(i)).matrix()[:3] for i in pid])
    else:
        poses = np.stack([[p.x(), p.y(), p.theta()] for p in
                          (est.atPose2(int(i)) for i in pid)])
    lms = None
    if len(schedule.landmark_ids):
        lms = np.stack([est.atPoint2(lm_key + int(j)) for j in schedule.landmark_ids])
    return {"steps": steps, "cpu": cpu, "poses": poses, "landmarks": lms}


def graphopt_run(schedule: ReplaySchedule) -> dict[str, Any]:
    """Replay with graphopt's :class:`~graphopt.online.IncrementalOptimizer` (defaults)."""
    out = replay(schedule)
    reps = out.incremental.reports
    return {"steps": out.steps, "cpu": out.cpu_steps, "poses": out.poses,
            "landmarks": out.landmarks, "batch_steps": sum(r.factor == "rebuilt" for r in reps),
            "solves": sum(r.solved for r in reps)}


def summary(steps: np.ndarray) -> dict[str, float]:
    """Total, median, p95 and max of per-step seconds."""
    return {"total": float(steps.sum()), "median": float(np.median(steps)),
            "p95": float(np.percentile(steps, 95)), "max": float(steps.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--graphs", default="manhattan,w10000,sphere,victoria")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--skip-gtsam", action="store_true")
    ap.add_argument("--defaults-only", action="store_true",
                    help="run iSAM2 with its defaults only (not relinearizeSkip=1)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    sides: list[tuple[str, Any]] = []
    if not args.skip_gtsam:
        sides.append(("isam2", lambda s: gtsam_run(s, 10)))
        if not args.defaults_only:
            sides.append(("isam2 skip=1", lambda s: gtsam_run(s, 1)))
    sides.insert(0, ("graphopt", graphopt_run))
    results: dict[str, Any] = {}
    for name in args.graphs.split(","):
        graph, guess = load(name)
        slam, best = batch_optimum(graph, guess)
        schedule = replay_schedule(build_graph(graph, guess=guess))
        runs: dict[str, list[dict[str, Any]]] = {s: [] for s, _ in sides}
        for _ in range(args.repeats):
            for side, fn in sides:
                out = fn(schedule)
                chi2 = chi2_of(slam, schedule, out["poses"], out["landmarks"])
                cpu = summary(out["cpu"])
                runs[side].append({**summary(out["steps"]), "chi2": chi2,
                                   **{f"cpu_{k}": v for k, v in cpu.items()}})
        print(f"\n{name}: {schedule.steps} steps, batch optimum chi2 {best:.6g}")
        print(f"  {'side':<14}{'total s':>9}{'median ms':>11}{'p95 ms':>9}{'max ms':>9}"
              f"{'chi2':>14}{'vs batch':>10}{'CPU s':>8}{'CPU p95':>9}")
        results[name] = {"batch_chi2": best, "steps": schedule.steps}
        for side, rs in runs.items():
            mid = sorted(rs, key=lambda r: r["total"])[len(rs) // 2]
            results[name][side] = {**mid, "totals": [r["total"] for r in rs]}
            print(f"  {side:<14}{statistics.median(r['total'] for r in rs):>9.2f}"
                  f"{mid['median'] * 1e3:>11.2f}{mid['p95'] * 1e3:>9.2f}{mid['max'] * 1e3:>9.1f}"
                  f"{mid['chi2']:>14.6g}{(mid['chi2'] / best - 1) * 100:>9.3f}%"
                  f"{mid['cpu_total']:>8.2f}{mid['cpu_p95'] * 1e3:>9.2f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
