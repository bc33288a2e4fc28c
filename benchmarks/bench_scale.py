"""Benchmark at scale: graphopt against Ceres on city-scale synthetic BAL problems.

Sizes are Final-13682's counts scaled to 1M, 3M, 10M and 29M observations
(``graphopt-bal-city --preset``; 29M is Final-13682's exact counts: 13,682 cameras, 4,456,117
points, 28,987,644 observations), cameras along streets with local co-visibility. Every side
runs in its own subprocess, on one thread, for a fixed number of iterations:

* ``graphopt:cholmod`` — ``graphopt-bal``'s optimizer (LM, Marquardt damping, points
  marginalised, the explicit reduced camera system factorised by CHOLMOD);
* ``graphopt:iterative-schur`` — the same with the implicit-Schur PCG solver, when graphopt has
  a linear solver of that name;
* ``ceres:sparse-schur`` and ``ceres:iterative-schur`` (Schur-Jacobi preconditioner) — Ceres
  through pycolmap + pyceres on the same problem (COLMAP's RADIAL camera is BAL's camera, see
  ``bench_bal.py``), skipped when its estimated memory does not fit.

Measured per side: set-up seconds (graphopt: ``initialize_optimization``, the structure, Schur
plan and symbolic factorisation; Ceres: its preprocessor), seconds per iteration (median),
the cost ``½Σ‖r‖²`` before and after the iterations, and the process's peak RSS (total, in
bytes per observation; for Ceres also the RSS before its solve, which holds pycolmap's
reconstruction). Reading the file is timed apart and not part of set-up. Ratios are printed
against the best Ceres side. Problems are generated into ``--data`` when missing (text files;
29M takes about 1.4 GB of disk).

Usage (one thread; from outside the repository root, or with ``python -P``)::

    python -P benchmarks/bench_scale.py [--sizes 1M,3M] [--iterations 5]
        [--sides graphopt:cholmod,ceres:sparse-schur,...] [--data DIR] [--max-rss-gb G]
        [--json out.json]

``--max-rss-gb`` kills a side whose RSS passes the limit (reported as such): on a shared
machine, keep the whole run inside its memory.
"""

from __future__ import annotations

import os

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
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_bal, also under python -P
DATA = ROOT / "out" / "scale"
DEFAULT_SIZES = "1M,3M"
ALL_SIDES = ("graphopt:cholmod", "graphopt:iterative-schur", "ceres:sparse-schur",
             "ceres:iterative-schur")
#: Peak RSS of a Ceres side per observation (1.0-1.1 kB measured at 1M and 3M, see
#: docs/scale.md, and a margin), to skip a size where Ceres would not fit.
CERES_BYTES_PER_OBS = 1300


def _rss() -> int:
    """Current RSS of this process (bytes)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_rss() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# --- the sides, each in its own process -----------------------------------------------------


def side_graphopt(path: str, solver: str, iterations: int) -> dict[str, Any]:
    """graphopt as ``graphopt-bal`` runs it.

    Args:
        path: BAL file.
        solver: graphopt linear solver.
        iterations: LM iterations.
    """
    import numpy as np

    from graphopt import LevenbergConfig, SparseOptimizer
    from graphopt.io.bal import read_bal
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    t0 = time.perf_counter()
    problem = read_bal(path)
    t_read = time.perf_counter() - t0
    rss_read = _rss()
    nc, npt = problem.num_cameras, problem.num_points
    opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True), solver=solver)
    t0 = time.perf_counter()
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), problem.points, marginalized=True)
    opt.add_edges(EdgeBALProjection,
                  np.column_stack([problem.camera_index, nc + problem.point_index]),
                  problem.observations)
    t_add = time.perf_counter() - t0
    t0 = time.perf_counter()
    opt.initialize_optimization()
    t_setup = time.perf_counter() - t0
    rss_setup = _rss()
    stamps: list[float] = []
    opt.add_callback("post_iteration", lambda o, info: stamps.append(time.perf_counter()))
    t0 = time.perf_counter()
    res = opt.optimize(iterations)
    steps = [b - a for a, b in zip([t0, *stamps[:-1]], stamps, strict=True)]
    chosen = getattr(opt.solver, "chosen", None) or opt.solver
    return {"read_seconds": t_read, "add_seconds": t_add, "setup_seconds": t_setup,
            "iteration_seconds": steps, "iterations": int(res.iterations),
            "initial_cost": 0.5 * float(res.initial_chi2),
            "final_cost": 0.5 * float(res.final_chi2), "stop_reason": str(res.stop_reason),
            "solver": str(getattr(chosen, "name", solver)),
            "rss_after_read": rss_read, "rss_after_setup": rss_setup}


def side_ceres(path: str, linear_solver: str, iterations: int) -> dict[str, Any]:
    """Ceres (pycolmap's BAL-equivalent RADIAL cost, pyceres), one thread.

    Args:
        path: BAL file.
        linear_solver: ``sparse-schur`` or ``iterative-schur`` (Schur-Jacobi).
        iterations: LM iterations (``max_num_iterations``, tolerances off).
    """
    import pyceres
    import pycolmap
    from bench_bal import _colmap_reconstruction

    from graphopt.io.bal import read_bal

    t0 = time.perf_counter()
    problem = read_bal(path)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    rec, _ = _colmap_reconstruction(problem)
    m = problem.num_observations
    del problem
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_principal_point = False
    opts.refine_focal_length = True
    opts.refine_extra_params = True
    cfg = pycolmap.BundleAdjustmentConfig()
    for i in range(rec.num_images()):
        cfg.add_image(i + 1)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)
    t_build = time.perf_counter() - t0
    so = pyceres.SolverOptions()
    if linear_solver == "sparse-schur":
        so.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    else:
        so.linear_solver_type = pyceres.LinearSolverType.ITERATIVE_SCHUR
        so.preconditioner_type = pyceres.PreconditionerType.SCHUR_JACOBI
    so.minimizer_type = pyceres.MinimizerType.TRUST_REGION
    so.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    so.num_threads = 1
    so.max_num_iterations = iterations
    so.function_tolerance = so.gradient_tolerance = so.parameter_tolerance = 0.0
    so.minimizer_progress_to_stdout = False
    so.logging_type = pyceres.LoggingType.SILENT
    times: list[float] = []

    class _Cb(pyceres.IterationCallback):
        def __call__(self, s: Any) -> Any:
            times.append(s.iteration_time_in_seconds)
            return pyceres.CallbackReturnType.SOLVER_CONTINUE

    cb = _Cb()
    so.callbacks = [cb]
    rss_before = _rss()
    summary = pyceres.SolverSummary()
    pyceres.solve(so, ba.problem, summary)
    return {"read_seconds": t_read, "build_seconds": t_build,
            "setup_seconds": summary.preprocessor_time_in_seconds,
            "iteration_seconds": times[1:],  # record 0 is the initial evaluation
            "iterations": len(times) - 1, "initial_cost": summary.initial_cost,
            "final_cost": summary.final_cost, "stop_reason": str(summary.termination_type),
            "solver": linear_solver, "rss_before_solve": rss_before, "observations": m}


def worker(side: str, path: str, iterations: int) -> None:
    """Run one side and print its result as the last line of stdout (JSON).

    Args:
        side: ``graphopt:SOLVER`` or ``ceres:sparse-schur|iterative-schur``.
        path: BAL file.
        iterations: Iterations.
    """
    kind, _, name = side.partition(":")
    out = (side_graphopt(path, name, iterations) if kind == "graphopt"
           else side_ceres(path, name, iterations))
    out["peak_rss"] = _peak_rss()
    print(json.dumps(out), flush=True)


# --- the driver -----------------------------------------------------------------------------


def _run_side(side: str, path: Path, iterations: int, max_rss: float | None,
              timeout: float | None) -> dict[str, Any]:
    """One side in a subprocess, killed past ``max_rss`` bytes or ``timeout`` seconds."""
    cmd = [sys.executable, "-P", str(Path(__file__).resolve()), "--worker", side, str(path),
           "--iterations", str(iterations)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    peak, killed = 0, ""
    while proc.poll() is None:
        try:
            with open(f"/proc/{proc.pid}/statm") as f:
                rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            rss = 0
        peak = max(peak, rss)
        if max_rss is not None and rss > max_rss:
            killed = f"killed at RSS {rss / 2**30:.2f} GiB (--max-rss-gb)"
        elif timeout is not None and time.perf_counter() - t0 > timeout:
            killed = f"killed after {timeout:.0f} s (--timeout)"
        if killed:
            proc.kill()
            break
        time.sleep(0.05)
    stdout, _ = proc.communicate()
    if killed or proc.returncode:
        return {"error": killed or f"exit status {proc.returncode}", "peak_rss": peak}
    return json.loads(stdout.strip().splitlines()[-1])


def _ensure_problem(size: str, data: Path) -> tuple[Path, int]:
    """The city problem of a size (generated when missing) and its observations."""
    from graphopt.apps.bal_city import preset, write_city

    cfg = preset(size)
    path = data / f"city-{size}-seed{cfg.seed}.txt"
    if not path.exists():
        data.mkdir(parents=True, exist_ok=True)
        print(f"generating {path} ...", flush=True)
        stats = write_city(str(path), cfg)
        print(f"  {stats.seconds:.1f} s; observations per camera {stats.per_camera}, "
              f"co-visible cameras {stats.co_visible}", flush=True)
    return path, cfg.observations


def _available_memory() -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    return 0


def bench_size(size: str, args: argparse.Namespace, sides: list[str]) -> dict[str, Any]:
    """Every side on one size.

    Args:
        size: ``1M``, ``3M``, ``10M`` or ``29M``.
        args: Command-line options.
        sides: The sides to run.
    """
    path, m = _ensure_problem(size, Path(args.data))
    print(f"\n== {size}: {path.name}, {m:,} observations", flush=True)
    out: dict[str, Any] = {"size": size, "file": str(path), "observations": m, "sides": {}}
    max_rss = args.max_rss_gb * 2**30 if args.max_rss_gb else None
    for side in sides:
        if side.startswith("ceres"):
            need = CERES_BYTES_PER_OBS * m
            limit = min(_available_memory(), max_rss or float("inf"))
            if need > limit:
                out["sides"][side] = {"error": f"skipped: needs about {need / 2**30:.1f} GiB, "
                                      f"{limit / 2**30:.1f} GiB available"}
                print(f"   {side:<26} {out['sides'][side]['error']}", flush=True)
                continue
        r = _run_side(side, path, args.iterations, max_rss, args.timeout)
        out["sides"][side] = r
        if "error" in r:
            print(f"   {side:<26} {r['error']}", flush=True)
            continue
        r["seconds_per_iteration"] = (statistics.median(r["iteration_seconds"])
                                      if r["iteration_seconds"] else float("nan"))
        r["bytes_per_observation"] = r["peak_rss"] / m
        print(f"   {side:<26} set-up {r['setup_seconds']:8.2f} s  "
              f"{r['seconds_per_iteration']:8.3f} s/it ({r['iterations']} it)  cost "
              f"{r['initial_cost']:.6e} -> {r['final_cost']:.6e}  peak RSS "
              f"{r['peak_rss'] / 2**30:6.2f} GiB ({r['bytes_per_observation']:.0f} B/obs)  "
              f"read {r['read_seconds']:.1f} s", flush=True)
    _ratios(out)
    return out


def _ratios(out: dict[str, Any]) -> None:
    """graphopt against the best Ceres side: s/iter, set-up, memory (printed and stored)."""
    ok = {k: v for k, v in out["sides"].items() if "error" not in v}
    ceres = [v for k, v in ok.items() if k.startswith("ceres")]
    if not ceres:
        return
    best_it = min(v["seconds_per_iteration"] for v in ceres)
    best_setup = min(v["setup_seconds"] for v in ceres)
    best_rss = min(v["peak_rss"] for v in ceres)
    for k, v in ok.items():
        if k.startswith("graphopt"):
            v["ratios"] = {"s_per_iter_over_ceres_best": v["seconds_per_iteration"] / best_it,
                           "setup_over_ceres_best": v["setup_seconds"] / best_setup,
                           "peak_rss_over_ceres_best": v["peak_rss"] / best_rss}
            q = v["ratios"]
            print(f"   {k}: s/iter x{q['s_per_iter_over_ceres_best']:.2f} of Ceres' best "
                  f"({'met' if q['s_per_iter_over_ceres_best'] <= 1 else 'missed'}), set-up "
                  f"x{q['setup_over_ceres_best']:.2f} of Ceres' preprocessing "
                  f"({'met' if q['setup_over_ceres_best'] <= 1 else 'missed'}), peak RSS "
                  f"x{q['peak_rss_over_ceres_best']:.2f}", flush=True)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments (``sys.argv[1:]`` if None).
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default=DEFAULT_SIZES,
                    help=f"comma-separated: 1M, 3M, 10M, 29M (default {DEFAULT_SIZES})")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--sides", default=",".join(ALL_SIDES),
                    help="comma-separated sides (default: all; graphopt:iterative-schur only "
                         "if graphopt has that solver)")
    ap.add_argument("--data", default=str(DATA), help=f"problem folder (default {DATA})")
    ap.add_argument("--max-rss-gb", type=float, default=None)
    ap.add_argument("--timeout", type=float, default=None, help="seconds per side")
    ap.add_argument("--json")
    ap.add_argument("--worker", nargs=2, metavar=("SIDE", "FILE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker[0], args.worker[1], args.iterations)
        return 0
    from graphopt.solvers import SOLVERS

    sides = [s for s in args.sides.split(",") if s]
    for s in sides:
        if s not in ALL_SIDES and not s.startswith("graphopt:"):
            ap.error(f"unknown side {s!r}; choose among {', '.join(ALL_SIDES)}")
    if "graphopt:iterative-schur" in sides and "iterative-schur" not in SOLVERS:
        print("graphopt:iterative-schur: skipped (graphopt has no linear solver of that name)")
        sides.remove("graphopt:iterative-schur")
    if any(s.startswith("ceres") for s in sides):
        try:
            import pyceres  # noqa: F401
            import pycolmap  # noqa: F401
        except ImportError:
            print("ceres: skipped (pip install pycolmap==4.2.1 pyceres==2.6)")
            sides = [s for s in sides if not s.startswith("ceres")]
    results = [bench_size(size, args, sides) for size in args.sizes.split(",") if size]
    if args.json:
        from graphopt.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
