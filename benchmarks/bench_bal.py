"""Benchmark: graphopt vs Ceres (pycolmap + pyceres) vs scipy on BAL problems.

Measures, on each problem and for each solver, in the same run and on one thread:

* seconds per iteration (median over the iterations of a run), and the same median over the
  working iterations only — those up to the first that reaches the target below, without the
  converged tail, whose iterations differ in kind between solvers (Ceres' unsuccessful steps skip
  the Jacobian; a g2o-style iteration repeats rejected trials);
* seconds to reach a cost within 1e-4 (relative) of the best final cost that any solver reached
  in this run, from the start of the solver's own setup (symbolic analysis / preprocessing
  included, problem construction excluded).

All costs are BAL's ``½ Σ ‖r‖²`` evaluated by graphopt's model on each solver's state, so that
the three solvers are compared on the same objective (pycolmap's cost differs from BAL's model on
observations behind their camera; see ``docs/benchmarks.md``).

Method: one warm-up run per solver (a few iterations, discarded), then ``--repeats`` timed runs;
the medians are reported. Ceres runs twice per repeat: once timed (a callback only records
Ceres' own iteration timings) and once instrumented (the callback reads the state after every
iteration to evaluate BAL's cost); Ceres is deterministic, so both runs follow one trajectory.

Usage (from outside the repository root, or with ``python -P``)::

    python -P benchmarks/bench_bal.py [FILE ...] [--repeats 3] [--iterations 50]
        [--scipy-iterations 30] [--skip-ceres] [--skip-scipy] [--json out.json]

Ceres and scipy come from the optional ``bench`` extra (``pip install graphopt[bench]``); a peer
that is not installed is skipped with a message.
"""

from __future__ import annotations

import os

# One thread everywhere, set before numpy/scipy/CHOLMOD load their BLAS.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from graphopt.io.bal import BALProblem, read_bal  # noqa: E402
from graphopt.types.bal import bal_project  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bal"
DEFAULT_FILES = ["problem-16-22106-pre.txt.bz2", "problem-49-7776-pre.txt.bz2"]
REL_TOL = 1e-4


@dataclass
class Trace:
    """One solver run.

    Args:
        solver: Solver name.
        costs: BAL cost at the start (index 0) and after each iteration.
        times: Seconds from the start of the solver's setup at which ``costs[k]`` was reached.
        iter_seconds: Duration of each iteration.
        setup_seconds: Symbolic analysis / preprocessing before the first iteration.
    """

    solver: str
    costs: list[float] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    iter_seconds: list[float] = field(default_factory=list)
    setup_seconds: float = 0.0
    total_seconds: float = 0.0
    stop: str = ""

    @property
    def final_cost(self) -> float:
        """Cost after the last iteration."""
        return self.costs[-1]

    def working_iterations(self, target: float) -> list[float]:
        """Durations of the iterations up to the first that reaches ``target`` (all if none
        does): the iterations that do the work, without the converged tail.

        Args:
            target: Cost threshold.
        """
        for k, c in enumerate(self.costs[1:], start=1):
            if c <= target:
                return self.iter_seconds[:k]
        return self.iter_seconds

    def time_to(self, target: float) -> float:
        """Seconds until the cost first reached ``target`` (inf if never).

        Args:
            target: Cost threshold.
        """
        for c, t in zip(self.costs, self.times, strict=True):
            if c <= target:
                return t
        return float("inf")


def bal_cost(problem: BALProblem, cameras: np.ndarray, points: np.ndarray) -> float:
    """BAL's ``½ Σ ‖r‖²`` at the given state.

    Args:
        problem: Observations and indices.
        cameras: ``(c, 9)`` cameras.
        points: ``(n, 3)`` points.
    """
    uv, _ = bal_project(cameras[problem.camera_index], points[problem.point_index])
    r = uv - problem.observations
    return 0.5 * float(np.einsum("ij,ij->", r, r))


# --- graphopt ---------------------------------------------------------------------------------


def bal_optimizer(problem: BALProblem, algorithm: Any, solver: str = "auto") -> Any:
    """A ``SparseOptimizer`` with the problem's cameras, marginalised points and projection
    edges, as ``graphopt-bal`` builds it.

    Args:
        problem: The BAL problem.
        algorithm: Algorithm name or config.
        solver: Linear solver name.
    """
    from graphopt import SparseOptimizer
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    nc = problem.num_cameras
    opt = SparseOptimizer(algorithm=algorithm, solver=solver)
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(problem.num_points), problem.points,
                     marginalized=True)
    opt.add_edges(EdgeBALProjection,
                  np.column_stack([problem.camera_index, nc + problem.point_index]),
                  problem.observations)
    return opt


def run_graphopt(
    problem: BALProblem, iterations: int, solver: str = "auto", diagonal: bool = True,
    default: bool = False,
) -> Trace:
    """LM with points marginalised, as ``graphopt-bal`` runs it.

    Args:
        problem: The BAL problem.
        iterations: Maximum iterations.
        solver: Linear solver name.
        diagonal: Marquardt damping ``λ·diag(H)`` (the app's default) or g2o's ``λ·I``.
        default: Stop at convergence with the library's default tests (a user's default run);
            otherwise run ``iterations`` iterations unless no step is found.
    """
    from graphopt import LevenbergConfig, StoppingConfig

    opt = bal_optimizer(problem, LevenbergConfig(diagonal_damping=diagonal), solver)
    opt.stopping = StoppingConfig() if default else StoppingConfig.iterations_only()
    tr = Trace("graphopt" if diagonal else "graphopt-g2o")
    stamps: list[float] = []
    costs: list[float] = []
    opt.add_callback("post_iteration",
                     lambda o, info: (stamps.append(time.perf_counter()), costs.append(info.chi2)))
    t0 = time.perf_counter()
    opt.initialize_optimization()
    t1 = time.perf_counter()
    res = opt.optimize(iterations)
    tr.total_seconds = time.perf_counter() - t0
    tr.stop = str(res.stop_reason)
    tr.setup_seconds = t1 - t0
    tr.costs = [0.5 * res.initial_chi2]
    tr.times = [tr.setup_seconds]
    # A failed last iteration (no acceptable step) is reported but leaves the state unchanged.
    prev = t1
    for s, c in zip(stamps, costs, strict=True):
        tr.iter_seconds.append(s - prev)
        prev = s
        tr.costs.append(0.5 * c)
        tr.times.append(s - t0)
    return tr


# --- Ceres through pycolmap + pyceres ---------------------------------------------------------


def _colmap_reconstruction(problem: BALProblem) -> tuple[Any, list[int]]:
    """A pycolmap Reconstruction equivalent to the BAL problem, and its point ids.

    BAL's camera looks down −z with y up; COLMAP's looks down +z with y down. Rotating the camera
    frame by π about x (``P' = diag(1, −1, −1) P``) and negating observed y makes COLMAP's RADIAL
    model ``f (1 + k1 r² + k2 r⁴) P'_xy / P'_z + c`` with ``c = 0`` equal to BAL's projection.
    Observations are grouped per image and per point by sorting (linear in the observations;
    ``bench_scale.py`` builds its 10M-observation problems with it too).
    """
    import pycolmap

    from graphopt.lie import so3_exp

    flip = np.diag([1.0, -1.0, -1.0])
    R = flip @ so3_exp(problem.cameras[:, :3])
    t = problem.cameras[:, 3:6] @ flip
    obs = problem.observations * np.array([1.0, -1.0])
    ci, pi = problem.camera_index, problem.point_index
    m, nc = problem.num_observations, problem.num_cameras
    order = np.argsort(ci, kind="stable")
    cstart = np.searchsorted(ci[order], np.arange(nc + 1))
    kp = np.empty(m, np.int64)  # keypoint of every observation within its image
    kp[order] = np.arange(m) - np.repeat(cstart[:-1], np.diff(cstart))
    rec = pycolmap.Reconstruction()
    for i in range(nc):
        sel = order[cstart[i]:cstart[i + 1]]
        size = int(2 * np.abs(problem.observations[sel]).max()) + 2 if len(sel) else 2
        c = problem.cameras[i]
        cam = pycolmap.Camera(model="RADIAL", width=size, height=size,
                              params=[c[6], 0.0, 0.0, c[7], c[8]], camera_id=i + 1)
        rec.add_camera_with_trivial_rig(cam)
        img = pycolmap.Image(name=str(i), keypoints=obs[sel], camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R[i]), t[i]))
    po = np.argsort(pi, kind="stable")
    pstart = np.searchsorted(pi[po], np.arange(problem.num_points + 1)).tolist()
    img_ids, kps = (ci[po] + 1).tolist(), kp[po].tolist()
    element = pycolmap.TrackElement
    point_ids = []
    for j, xyz in enumerate(problem.points):
        a, b = pstart[j], pstart[j + 1]
        track = pycolmap.Track([element(img_ids[k], kps[k]) for k in range(a, b)])
        point_ids.append(rec.add_point3D(xyz, track))
    return rec, point_ids


def _colmap_state(rec: Any, point_ids: list[int], nc: int) -> tuple[np.ndarray, np.ndarray]:
    """BAL cameras and points from a pycolmap Reconstruction (inverse of the conversion)."""
    from graphopt.lie import so3_log

    flip = np.diag([1.0, -1.0, -1.0])
    cams = np.zeros((nc, 9))
    Rs = np.zeros((nc, 3, 3))
    for i in range(nc):
        pose = rec.image(i + 1).cam_from_world()
        m = np.asarray(pose.matrix())
        Rs[i] = flip @ m[:, :3]
        cams[i, 3:6] = flip @ m[:, 3]
        p = np.asarray(rec.camera(i + 1).params)
        cams[i, 6], cams[i, 7], cams[i, 8] = p[0], p[3], p[4]
    cams[:, :3] = so3_log(Rs)
    pts = np.array([rec.point3D(pid).xyz for pid in point_ids])
    return cams, pts


def run_ceres(problem: BALProblem, iterations: int, instrument: bool,
              default: bool = False) -> Trace:
    """pycolmap's reprojection cost (RADIAL camera, principal point fixed) with pyceres.

    Args:
        problem: The BAL problem.
        iterations: Maximum iterations (``max_num_iterations``).
        instrument: Evaluate BAL's cost on the state after every iteration (slow; for the
            cost trajectory, not for timing).
        default: Keep Ceres' default stopping tolerances (a user's default run); otherwise
            they are disabled and Ceres runs ``iterations`` iterations.
    """
    import pyceres
    import pycolmap

    rec, point_ids = _colmap_reconstruction(problem)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_principal_point = False
    opts.refine_focal_length = True
    opts.refine_extra_params = True
    cfg = pycolmap.BundleAdjustmentConfig()
    for i in range(problem.num_cameras):
        cfg.add_image(i + 1)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)  # BAL fixes no gauge either
    ba = pycolmap.create_default_ceres_bundle_adjuster(opts, cfg, rec)

    so = pyceres.SolverOptions()
    so.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    so.minimizer_type = pyceres.MinimizerType.TRUST_REGION
    so.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    so.num_threads = 1
    so.max_num_iterations = iterations
    if not default:
        so.function_tolerance = 0.0
        so.gradient_tolerance = 0.0
        so.parameter_tolerance = 0.0
    so.minimizer_progress_to_stdout = False
    so.logging_type = pyceres.LoggingType.SILENT
    so.update_state_every_iteration = instrument

    records: list[tuple[float, float, float]] = []
    states: list[float] = []
    nc = problem.num_cameras

    class _Cb(pyceres.IterationCallback):
        def __call__(self, s: Any) -> Any:
            records.append((s.cost, s.cumulative_time_in_seconds, s.iteration_time_in_seconds))
            if instrument:
                cams, pts = _colmap_state(rec, point_ids, nc)
                states.append(bal_cost(problem, cams, pts))
            return pyceres.CallbackReturnType.SOLVER_CONTINUE

    cb = _Cb()
    so.callbacks = [cb]
    summary = pyceres.SolverSummary()
    pyceres.solve(so, ba.problem, summary)
    tr = Trace("ceres")
    tr.setup_seconds = summary.preprocessor_time_in_seconds
    tr.total_seconds = summary.total_time_in_seconds
    tr.stop = str(summary.termination_type).rsplit(".", 1)[-1].lower()
    # Record 0 is Ceres' evaluation at the start; the others are iterations.
    tr.times = [r[1] for r in records]
    tr.iter_seconds = [r[2] for r in records[1:]]
    tr.costs = states if instrument else [r[0] for r in records]
    cams, pts = _colmap_state(rec, point_ids, nc)
    if instrument or default:
        tr.costs[-1] = bal_cost(problem, cams, pts)
    return tr


# --- scipy ------------------------------------------------------------------------------------


def run_scipy(problem: BALProblem, iterations: int, default: bool = False) -> Trace:
    """``scipy.optimize.least_squares`` (trf) with finite differences over ``jac_sparsity``.

    Args:
        problem: The BAL problem.
        iterations: Maximum iterations (``max_nfev``; scipy's trf iterates once per evaluation).
        default: Keep SciPy's default tolerances (``ftol = xtol = gtol = 1e-8``: a user's default
            run); otherwise they are 1e-15 and SciPy runs ``iterations`` evaluations.
    """
    import scipy.sparse as sp
    from scipy.optimize import least_squares

    nc, npt, m = problem.num_cameras, problem.num_points, problem.num_observations
    rows = np.arange(2 * m).reshape(m, 2)
    cam_cols = (9 * problem.camera_index)[:, None] + np.arange(9)
    pt_cols = (9 * nc + 3 * problem.point_index)[:, None] + np.arange(3)
    r_idx = np.concatenate([np.repeat(rows, 9, axis=1).reshape(-1), np.repeat(rows, 3, axis=1)
                            .reshape(-1)])
    c_idx = np.concatenate([np.tile(cam_cols, (1, 2)).reshape(-1),
                            np.tile(pt_cols, (1, 2)).reshape(-1)])
    sparsity = sp.csr_matrix((np.ones(len(r_idx), np.int8), (r_idx, c_idx)),
                             shape=(2 * m, 9 * nc + 3 * npt))

    def fun(x: np.ndarray) -> np.ndarray:
        cams = x[: 9 * nc].reshape(nc, 9)
        pts = x[9 * nc :].reshape(npt, 3)
        uv, _ = bal_project(cams[problem.camera_index], pts[problem.point_index])
        return (uv - problem.observations).ravel()

    x0 = np.concatenate([problem.cameras.ravel(), problem.points.ravel()])
    tr = Trace("scipy")
    stamps: list[tuple[float, float]] = []

    def callback(intermediate_result: Any) -> None:
        stamps.append((time.perf_counter(), float(intermediate_result.cost)))

    tol = 1e-8 if default else 1e-15
    t0 = time.perf_counter()
    out = least_squares(fun, x0, jac_sparsity=sparsity, method="trf", x_scale="jac",
                        max_nfev=iterations, ftol=tol, xtol=tol, gtol=tol, callback=callback)
    tr.total_seconds = time.perf_counter() - t0
    tr.stop = {-1: "failed", 0: "iterations", 1: "gradient_tolerance",
               2: "function_tolerance", 3: "parameter_tolerance",
               4: "function+parameter"}.get(int(out.status), str(out.status))
    tr.costs = [0.5 * float(np.sum(fun(x0) ** 2))]
    tr.times = [0.0]
    prev = t0
    for s, c in stamps:
        tr.iter_seconds.append(s - prev)
        prev = s
        tr.costs.append(c)
        tr.times.append(s - t0)
    return tr


def drop_behind_camera(problem: BALProblem) -> tuple[BALProblem, int]:
    """Remove observations whose point starts behind its camera.

    pycolmap's cost function treats such observations differently from BAL's model (it does not
    project points behind the camera), so with them the solvers would minimise different
    functions. Removing them (31 of 31843 on Ladybug-49, none on Dubrovnik-16) makes the three
    objectives identical.

    Args:
        problem: The problem.

    Returns:
        ``(problem without those observations, how many were removed)``.
    """
    _, pz = bal_project(problem.cameras[problem.camera_index], problem.points[problem.point_index])
    keep = pz < 0
    if keep.all():
        return problem, 0
    out = problem.copy()
    out.camera_index = problem.camera_index[keep]
    out.point_index = problem.point_index[keep]
    out.observations = problem.observations[keep]
    return out, int(np.count_nonzero(~keep))


# --- driver -----------------------------------------------------------------------------------


def _available(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def _default_runs(problem: BALProblem, args: argparse.Namespace,
                  ceres: bool) -> dict[str, Any]:
    """What a user waits for: each solver's default run, to its own stopping tests.

    graphopt with :class:`~graphopt.StoppingConfig`'s defaults, Ceres with its own (the same
    tolerances), SciPy's ``least_squares`` with its own (1e-8), all capped at
    ``--default-iterations``; whole-run seconds (graphopt: its initialisation and ``optimize``;
    Ceres: ``total_time_in_seconds``; SciPy: the call), one warm-up (not for SciPy), medians of
    ``--repeats`` runs (``--scipy-repeats`` for SciPy).
    """
    runners: dict[str, Any] = {
        "graphopt": lambda: run_graphopt(problem, args.default_iterations, default=True)}
    if ceres:
        runners["ceres"] = lambda: run_ceres(problem, args.default_iterations, instrument=False,
                                             default=True)
    if not args.skip_scipy:
        runners["scipy"] = lambda: run_scipy(problem, args.default_iterations, default=True)
    result: dict[str, Any] = {}
    for name, run in runners.items():
        if name != "scipy":
            run()  # warm-up (SciPy's runs take tens of seconds: no warm-up, --scipy-repeats)
        repeats = args.scipy_repeats if name == "scipy" else args.repeats
        trs = [run() for _ in range(repeats)]
        result[name] = {
            "seconds": statistics.median(t.total_seconds for t in trs),
            "iterations": len(trs[0].iter_seconds),
            "final_cost": trs[0].final_cost,
            "stop": trs[0].stop,
            "seconds_per_iteration": statistics.median(
                statistics.median(t.iter_seconds) for t in trs),
        }
        r = result[name]
        print(f"   default run, {name}: {r['seconds']:.3f} s, {r['iterations']} iterations "
              f"({r['stop']}), final cost {r['final_cost']:.6e}", flush=True)
    if "scipy" in result:
        result["graphopt_over_scipy_seconds"] = (result["graphopt"]["seconds"]
                                                 / result["scipy"]["seconds"])
    if "ceres" in result:
        g, c = result["graphopt"], result["ceres"]
        result["graphopt_over_ceres_seconds"] = g["seconds"] / c["seconds"]
        result["cost_difference"] = (g["final_cost"] - c["final_cost"]) / c["final_cost"]
        print(f"   default run: graphopt / ceres time x{result['graphopt_over_ceres_seconds']:.2f}"
              f" (<1: graphopt faster), final costs differ by "
              f"{result['cost_difference']:+.1e} (relative)", flush=True)
    return result


def bench_file(path: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Run all solvers on one file.

    Args:
        path: BAL file.
        args: Command-line options.

    Returns:
        A JSON-serialisable result.
    """
    problem = read_bal(path)
    dropped = 0
    if not args.keep_behind:
        problem, dropped = drop_behind_camera(problem)
    print(f"\n== {path.name}: {problem.num_cameras} cameras, {problem.num_points} points, "
          f"{problem.num_observations} observations"
          + (f" ({dropped} behind their camera dropped)" if dropped else ""), flush=True)
    runners: dict[str, Any] = {"graphopt": lambda n: run_graphopt(problem, n)}
    if args.g2o_damping:
        runners["graphopt-g2o"] = lambda n: run_graphopt(problem, n, diagonal=False)
    if not args.skip_ceres:
        if _available("pycolmap") and _available("pyceres"):
            runners["ceres"] = lambda n: run_ceres(problem, n, instrument=False)
        else:
            print("   ceres: skipped (pip install 'graphopt[bench]' for pycolmap and pyceres)")
    if not args.skip_scipy:
        runners["scipy"] = lambda n: run_scipy(problem, n)

    out: dict[str, Any] = {"file": path.name, "dropped_behind_camera": dropped, "solvers": {}}
    out["default_runs"] = _default_runs(problem, args, "ceres" in runners)
    if args.default_only:
        return out
    runs: dict[str, list[Trace]] = {}
    for name, run in runners.items():
        iters = args.scipy_iterations if name == "scipy" else args.iterations
        repeats = args.scipy_repeats if name == "scipy" else args.repeats
        run(min(3, iters))  # warm-up (imports, caches, allocator), discarded
        runs[name] = []
        for rep in range(repeats):
            tr = run(iters)
            if name == "ceres":
                costs = run_ceres(problem, iters, instrument=True).costs
                if len(costs) == len(tr.costs):
                    tr.costs = costs
                else:
                    print("   ceres: instrumented run diverged from the timed one; using "
                          "Ceres' own costs")
            runs[name].append(tr)
            print(f"   {name} run {rep + 1}/{repeats}: final cost {tr.final_cost:.6e}, "
                  f"{len(tr.iter_seconds)} iterations, "
                  f"{statistics.median(tr.iter_seconds):.4f} s/iteration", flush=True)

    best = min(tr.final_cost for trs in runs.values() for tr in trs)
    target = best * (1.0 + REL_TOL)
    out.update(best_cost=best, target=target)
    for name, trs in runs.items():
        out["solvers"][name] = {
            "seconds_per_iteration": statistics.median(
                statistics.median(t.iter_seconds) for t in trs),
            "seconds_per_working_iteration": statistics.median(
                statistics.median(t.working_iterations(target)) for t in trs),
            "seconds_to_target": statistics.median(t.time_to(target) for t in trs),
            "final_cost": statistics.median(t.final_cost for t in trs),
            "iterations": len(trs[0].iter_seconds),
            "setup_seconds": statistics.median(t.setup_seconds for t in trs),
            "repeats": len(trs),
            "trace": asdict(trs[0]),
        }
    g = out["solvers"]["graphopt"]
    for peer in ("ceres", "scipy"):
        if peer in out["solvers"]:
            p = out["solvers"][peer]
            a, b = p["seconds_to_target"], g["seconds_to_target"]
            out[f"ratio_{peer}_over_graphopt"] = {
                "seconds_per_iteration": p["seconds_per_iteration"] / g["seconds_per_iteration"],
                "seconds_per_working_iteration": (p["seconds_per_working_iteration"]
                                                  / g["seconds_per_working_iteration"]),
                # inf: only graphopt reached the target; 0: only the peer; None: neither.
                "seconds_to_target": None if a == b == float("inf") else (
                    float("inf") if b == 0 else a / b),
            }
    return out


def print_table(results: list[dict[str, Any]]) -> None:
    """Print a summary table.

    Args:
        results: Outputs of :func:`bench_file`.
    """
    print(f"\nDefault runs (each solver to its own stopping tests):\n{'file':<32} {'solver':<9} "
          f"{'seconds':>8} {'iters':>5} {'stop':<20} {'final cost':>13}  graphopt/ceres")
    for r in results:
        d = r["default_runs"]
        for name in ("graphopt", "ceres", "scipy"):
            if name in d:
                x = d[name]
                ratio = (f"x{d['graphopt_over_ceres_seconds']:.2f}"
                         if name == "graphopt" and "ceres" in d else "")
                print(f"{r['file']:<32} {name:<9} {x['seconds']:8.3f} {x['iterations']:5d} "
                      f"{x['stop']:<20} {x['final_cost']:13.6e}  {ratio}")
    if not any(r["solvers"] for r in results):
        return
    print(f"\n{'file':<32} {'solver':<12} {'s/iter':>8} {'s/work it':>9} {'s to 1e-4':>10} "
          f"{'final cost':>13} {'iters':>5}")
    for r in results:
        for name, s in r["solvers"].items():
            print(f"{r['file']:<32} {name:<12} {s['seconds_per_iteration']:8.4f} "
                  f"{s['seconds_per_working_iteration']:9.4f} "
                  f"{s['seconds_to_target']:10.3f} {s['final_cost']:13.6e} {s['iterations']:5d}")
        for peer in ("ceres", "scipy"):
            key = f"ratio_{peer}_over_graphopt"
            if key in r:
                q = r[key]
                tt = q["seconds_to_target"]
                tt_s = "n/a (neither reached it)" if tt is None else f"x{tt:.2f}"
                print(f"{'':<32} {peer}/graphopt: s/iter x{q['seconds_per_iteration']:.2f}, "
                      f"s/working iter x{q['seconds_per_working_iteration']:.2f}, "
                      f"time to target {tt_s} (>1: graphopt faster)")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments (``sys.argv[1:]`` if None).
    """
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", help=f"BAL files (default: {DEFAULT_FILES} in {DATA})")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--scipy-iterations", type=int, default=30)
    ap.add_argument("--scipy-repeats", type=int, default=1)
    ap.add_argument("--skip-ceres", action="store_true")
    ap.add_argument("--skip-scipy", action="store_true")
    ap.add_argument("--g2o-damping", action="store_true",
                    help="also run graphopt with g2o's identity damping (lambda*I)")
    ap.add_argument("--keep-behind", action="store_true",
                    help="keep observations behind their camera (pycolmap's cost then differs "
                         "from BAL's model on them)")
    ap.add_argument("--default-iterations", type=int, default=100,
                    help="cap of the default runs (stopping at convergence; default 100)")
    ap.add_argument("--default-only", action="store_true",
                    help="only the default runs (whole runs to each solver's stopping tests)")
    ap.add_argument("--json", help="write all results (with traces) to this file")
    args = ap.parse_args(argv)
    files = [Path(f) for f in args.files] or [DATA / f for f in DEFAULT_FILES]
    missing = [str(f) for f in files if not f.exists()]
    if missing:
        print(f"bench_bal: missing input {missing[0]}", file=sys.stderr)
        return 1
    results = [bench_file(f, args) for f in files]
    print_table(results)
    if args.json:
        from graphopt.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump(results, f, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
