"""The same g2opy program run with the g2opy wheel and with ``graphopt.g2o``, in one process.

Workloads (the SLAM back-end's, written once in g2opy's API; synthetic scenes with known truth,
10 % outlier observations, one pixel of noise):

* ``motion-only BA`` (ORB-SLAM's ``PoseOptimization``): one ``VertexSE3Expmap``, N
  ``EdgeSE3ProjectXYZOnlyPose``; 4 rounds of 10 iterations, the pose reset each round, edges with
  ``chi2 > 5.991`` to level 1, kernels dropped after round 2;
* ``local BA`` (``LocalBundleAdjustment``): free and fixed keyframes, marginalised points,
  ``EdgeSE3ProjectXYZ`` with Huber kernels; 5 iterations, outliers (``chi2 > 5.991`` or depth
  ≤ 0) to level 1, kernels dropped, 10 iterations;
* ``ba_demo`` (g2o's example, ``EdgeProjectXYZ2UV``), 10 iterations;
* ``object building``: microseconds per ``add_vertex`` / ``add_edge`` call alone, and per
  ``estimate()`` of a point and of a pose after ``initialize_optimization``.

Each workload reports *build* (creating the objects and adding them) and *optimise* (every
``initialize_optimization``/``optimize``/outlier pass) seconds and their total — each the median
of ``--repeats`` runs, the two sides interleaved —, the final active chi2 of each side and the
inlier counts. A side that cannot run a workload (``graphopt.g2o`` before graphopt has the
pose-only edge) prints why. One thread each side (set before numpy loads).

Usage::

    .venv/bin/python -P benchmarks/bench_g2o_api.py [--repeats 5] [--quick] [--clock cpu]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import g2o_programs  # noqa: E402
from g2o_programs import CX, CY, local_ba, motion_only, scene  # noqa: E402


def ba_demo(g2o: Any, _: Any, n: int) -> tuple[float, float, float, int]:
    """g2o's ``ba_demo`` (tests/g2o_programs.py), timed as a whole (build + optimise)."""
    t0 = g2o_programs.clock()
    out = g2o_programs.ba_demo(g2o, n_points=n)
    return 0.0, g2o_programs.clock() - t0, out["chi2"], out["edges"]


def building(g2o: Any, sc: dict[str, Any], n: int) -> tuple[float, ...]:
    """Microseconds per add_vertex and per add_edge call (objects made beforehand), and per
    estimate() of a point and of the pose after initialize_optimization."""
    opt = g2o.SparseOptimizer()
    point_cls = getattr(g2o, "VertexPointXYZ", None) or g2o.VertexSBAPointXYZ
    kf = g2o.VertexSE3Expmap()
    kf.set_id(0)
    kf.set_estimate(g2o.SE3Quat(np.identity(3), np.zeros(3)))
    opt.add_vertex(kf)
    pts = []
    for j in range(n):
        v = point_cls()
        v.set_id(j + 1)
        v.set_estimate(np.array([0.0, 0.0, 5.0 + j * 1e-3]))
        pts.append(v)
    edges = []
    for v in pts:
        e = g2o.EdgeSE3ProjectXYZ()
        e.set_vertex(0, v)
        e.set_vertex(1, kf)
        e.set_measurement(np.array([CX, CY]))
        e.set_information(np.identity(2))
        edges.append(e)
    t0 = g2o_programs.clock()
    for v in pts:
        opt.add_vertex(v)
    t1 = g2o_programs.clock()
    for e in edges:
        opt.add_edge(e)
    t2 = g2o_programs.clock()
    opt.initialize_optimization()
    t3 = g2o_programs.clock()
    for v in pts:  # reading estimates back (after the records became arrays)
        v.estimate()
    t4 = g2o_programs.clock()
    for _ in range(n):  # a pose (an SE3Quat)
        kf.estimate()
    t5 = g2o_programs.clock()
    return (t1 - t0) / n * 1e6, (t2 - t1) / n * 1e6, (t4 - t3) / n * 1e6, n, (t5 - t4) / n * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="wall: perf_counter; cpu: this process's CPU time (one thread each "
                         "side, so the same work, without the waits for a CPU that other "
                         "processes on a loaded machine add)")
    args = ap.parse_args()
    if args.clock == "cpu":
        g2o_programs.clock = time.process_time
    import graphopt.g2o as ours

    sides: dict[str, Any] = {"graphopt.g2o": ours}
    try:
        import g2opy

        sides["g2opy"] = g2opy
    except ImportError:
        print("g2opy is not installed (pip install g2opy==2.3.0): graphopt.g2o only")
    big = not args.quick
    small_scene = scene(20, 1000, 5, seed=1)
    work: list[tuple[str, Callable, Any, int]] = [
        ("object building, 5,000 points (us per call)", building, None, 5000),
        ("motion-only BA, 100 matches", motion_only, small_scene, 100),
        ("motion-only BA, 500 matches", motion_only, scene(2, 2000, 2, seed=2), 500),
        ("local BA 10+10 KF, 1,000 points, 5,000 obs.", local_ba, small_scene, 10),
        ("ba_demo, 500 points", ba_demo, None, 500),
    ]
    if big:
        work.insert(3, ("motion-only BA, 2,000 matches", motion_only, scene(2, 4000, 2, 3), 2000))
        work.append(("local BA 20+30 KF, 5,000 points, 25,000 obs.", local_ba,
                     scene(50, 5000, 5, seed=4), 20))
    for title, fn, sc, n in work:
        runs: dict[str, list[tuple[float, float, float, int]]] = {s: [] for s in sides}
        skipped: dict[str, str] = {}
        for _ in range(args.repeats):
            for name, mod in sides.items():
                if name in skipped:
                    continue
                try:
                    runs[name].append(fn(mod, sc, n))
                except NotImplementedError as exc:
                    skipped[name] = str(exc)
        print(f"\n{title}")
        for name in sides:
            if name in skipped:
                print(f"  {name:13s} not run: {skipped[name]}")
                continue
            b = statistics.median(r[0] for r in runs[name])
            o = statistics.median(r[1] for r in runs[name])
            tot = statistics.median(r[0] + r[1] for r in runs[name])
            chi2, inl = runs[name][-1][2], runs[name][-1][3]
            if fn is building:
                est = statistics.median(r[2] for r in runs[name])
                pose = statistics.median(r[4] for r in runs[name])
                print(f"  {name:13s} add_vertex {b:6.2f} us   add_edge {o:6.2f} us   "
                      f"estimate() {est:6.2f} us (point) {pose:6.2f} us (pose)")
            else:
                print(f"  {name:13s} build {b * 1e3:8.1f} ms  optimise {o * 1e3:8.1f} ms  "
                      f"total {tot * 1e3:8.1f} ms  chi2 {chi2:.6g}  inliers {inl}")
        if len(runs) == 2 and all(runs.values()) and not skipped and fn is not building:
            med = {s: statistics.median(r[0] + r[1] for r in runs[s]) for s in sides}
            print(f"  ratio graphopt.g2o / g2opy (medians of build + optimise): "
                  f"{med['graphopt.g2o'] / med['g2opy']:.2f}")


if __name__ == "__main__":
    main()
