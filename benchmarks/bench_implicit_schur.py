"""Benchmark: implicit-Schur PCG (``iterative-schur``) against the explicit reduced system
(``cholmod``) on synthetic BAL problems with local co-visibility.

The scene (private to this benchmark, :func:`path_scene`): cameras along a straight path, one
unit apart, looking at points about 10 units away; every point is seen by 2–7 consecutive
cameras (BAL-like tracks), so that a camera shares points only with its few neighbours and the
reduced camera system is banded. Observations get 0.5 px of noise and the initial estimate is the
truth perturbed (``apps.bal_preprocess.perturb``), as in ``graphopt-bal``'s synthetic scene.

Every (size, solver) runs in its own process, so that its peak RSS is its own: set-up seconds
(``initialize_optimization``: structure, Schur plans, symbolic factorisation), seconds per LM
iteration (diagonal damping, as ``graphopt-bal``; the median and the total of the run), CG
iterations per solve, peak RSS and its
growth over the process after the scene was built, and the cost ``½Σ‖r‖²`` after 10 iterations.

Usage (from the repository root)::

    .venv/bin/python -P benchmarks/bench_implicit_schur.py [--sizes 100000 1000000]
        [--solvers cholmod iterative-schur] [--iterations 10] [--json out.json]
"""

from __future__ import annotations

import os

# One thread everywhere, set before numpy/scipy/CHOLMOD load their BLAS.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from graphopt.io.bal import BALProblem  # noqa: E402

OBS_PER_CAMERA = 1000


def path_scene(n_obs: int, seed: int = 0) -> BALProblem:
    """A BAL problem of about ``n_obs`` observations: cameras on a path, local tracks.

    Args:
        n_obs: Observations wanted (the scene has about as many).
        seed: Random seed.
    """
    from graphopt.apps.bal_preprocess import perturb
    from graphopt.lie import angle_axis_rotate
    from graphopt.types.bal import bal_project

    rng = np.random.default_rng(seed)
    n_cams = max(8, n_obs // OBS_PER_CAMERA)
    tracks = rng.integers(2, 8, size=int(n_obs / 4.5))  # 2..7 cameras per point
    n_pts = len(tracks)
    first = rng.integers(0, n_cams - tracks + 1)
    centers = np.column_stack([np.arange(n_cams, dtype=float) + rng.normal(0, 0.05, n_cams),
                               rng.normal(0, 0.1, n_cams), rng.normal(0, 0.1, n_cams)])
    cams = np.zeros((n_cams, 9))
    cams[:, :3] = rng.normal(0, 0.02, (n_cams, 3))  # R_cw close to I: looking down −z
    cams[:, 3:6] = -angle_axis_rotate(cams[:, :3], centers)
    cams[:, 6] = 500.0 * rng.uniform(0.9, 1.1, n_cams)
    cams[:, 7] = rng.normal(0.0, 0.05, n_cams)
    cams[:, 8] = rng.normal(0.0, 0.005, n_cams)
    mid = first + (tracks - 1) / 2.0
    pts = np.column_stack([mid + rng.uniform(-1.0, 1.0, n_pts), rng.uniform(-3.0, 3.0, n_pts),
                           -10.0 + rng.uniform(-1.0, 1.0, n_pts)])
    pi = np.repeat(np.arange(n_pts), tracks)
    ci = first[pi] + (np.arange(len(pi)) - np.repeat(np.cumsum(tracks) - tracks, tracks))
    uv, _ = bal_project(cams[ci], pts[pi])
    obs = uv + rng.normal(0.0, 0.5, uv.shape)
    truth = BALProblem(cams, pts, ci.astype(np.int64), pi.astype(np.int64), obs)
    return perturb(truth, 0.005, 0.05, 0.05, seed=seed + 1)


def _rss_mb() -> float:
    """Current resident set size (MB)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def run_one(n_obs: int, solver: str, iterations: int) -> dict[str, Any]:
    """One measurement in this process (see the module docstring).

    Args:
        n_obs: Observations of the scene.
        solver: ``cholmod``, ``iterative-schur`` or ``auto``.
        iterations: LM iterations.
    """
    from graphopt import SparseOptimizer
    from graphopt.algorithms import LevenbergConfig
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    problem = path_scene(n_obs)
    base = _rss_mb()
    opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True), solver=solver)
    nc = problem.num_cameras
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(problem.num_points), problem.points,
                     marginalized=True)
    opt.add_edges(EdgeBALProjection, np.column_stack([problem.camera_index,
                                                      nc + problem.point_index]),
                  problem.observations)
    t0 = time.perf_counter()
    opt.initialize_optimization()
    setup = time.perf_counter() - t0
    after_setup = _rss_mb()
    initial = opt.chi2() / 2.0
    res = opt.optimize(iterations)
    chosen = getattr(opt.solver, "chosen", None) or opt.solver
    cg = list(getattr(chosen, "iterations", []))
    per_it = [i.seconds for i in res.info]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    return {
        "observations": len(problem.observations), "cameras": nc,
        "points": problem.num_points, "solver": solver, "ran": chosen.name,
        "setup_s": setup, "s_per_iteration": statistics.median(per_it) if per_it else 0.0,
        "solve_s_per_iteration": statistics.median(
            [i.schur_seconds + i.solve_seconds for i in res.info]) if per_it else 0.0,
        "linearize_s_per_iteration": statistics.median(
            [i.linearize_seconds for i in res.info]) if per_it else 0.0,
        "iterations": len(res.info), "cg_iterations": cg, "total_s": sum(per_it),
        "initial_cost": initial, "final_cost": res.final_chi2 / 2.0,
        "peak_rss_mb": peak, "rss_after_scene_mb": base, "rss_after_setup_mb": after_setup,
        "bytes_per_observation": (peak - base) * 1e6 / len(problem.observations),
        "s_pattern_nnz": int(opt.linear_system.pattern.nnz),
    }


def main(argv: list[str] | None = None) -> int:
    """Run every (size, solver) in a child process and print a table with ratios.

    Args:
        argv: Command-line arguments.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--solvers", nargs="+", default=["cholmod", "iterative-schur"])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--json", help="write the measurements here")
    ap.add_argument("--child", nargs=2, metavar=("N_OBS", "SOLVER"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(run_one(int(args.child[0]), args.child[1], args.iterations)))
        return 0
    rows = []
    for n in args.sizes:
        for solver in args.solvers:
            out = subprocess.run([sys.executable, "-P", __file__, "--child", str(n), solver,
                                  "--iterations", str(args.iterations)],
                                 capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            cg = row["cg_iterations"]
            print(f"{row['observations']:>9} obs {row['cameras']:>5} cams  {solver:<16} "
                  f"({row['ran']}) setup {row['setup_s']:6.2f} s  "
                  f"{row['s_per_iteration']:6.3f} s/it median (solve "
                  f"{row['solve_s_per_iteration']:.3f}), {row['total_s']:6.2f} s in "
                  f"{row['iterations']}"
                  f"  peak {row['peak_rss_mb']:7.0f} MB ({row['bytes_per_observation']:5.0f} B/obs)"
                  f"  cost {row['final_cost']:.6e}"
                  + (f"  CG {np.mean(cg):.1f}/solve ({sum(cg)} in {len(cg)})" if cg else ""),
                  flush=True)
    by = {(r["observations"], r["solver"]): r for r in rows}
    if "cholmod" in args.solvers:
        for r in rows:
            ref = by[(r["observations"], "cholmod")]
            if r is ref:
                continue
            print(f"{r['observations']:>9} obs  {r['solver']} / cholmod: "
                  f"s/it {r['s_per_iteration'] / ref['s_per_iteration']:.2f}x  "
                  f"total {r['total_s'] / ref['total_s']:.2f}x  "
                  f"setup {r['setup_s'] / ref['setup_s']:.2f}x  "
                  f"peak RSS {r['peak_rss_mb'] / ref['peak_rss_mb']:.2f}x  "
                  f"final cost {r['final_cost'] / ref['final_cost']:.6f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
