"""``graphopt-bal``: bundle adjustment of a BAL problem (or a synthetic one) with graphopt.

Usage::

    graphopt-bal [INPUT] [-i/--iterations N] [--algorithm lm|gn|dogleg]
                 [--solver auto|cholmod|dense|pcg|scipy|iterative-schur]
                 [--robust KERNEL --robust-delta D]
                 [--normalize] [--perturb R T P] [--seed S]
                 [--ply-before FILE] [--ply-after FILE] [--ply-drop-far] [--rrd FILE] [--json FILE]
                 [--quiet] [--lm-damping diagonal|identity] [--lm-schedule g2o|ceres|gtsam]
                 [--function-tolerance T] [--gradient-tolerance T] [--parameter-tolerance T]
                 [--gain G]

Cameras are :class:`~graphopt.types.bal.VertexCameraBAL`, points
:class:`~graphopt.types.vertices.VertexPointXYZ` (marginalised: the Schur complement eliminates
them), observations :class:`~graphopt.types.bal.EdgeBALProjection`. Without INPUT a synthetic
BAL-like scene with known ground truth is generated and the error against it is reported.

Costs follow Ceres' convention ``½ Σ ‖r‖²`` without robust kernel; chi2 is what g2o prints
(``Σ ρ(e'e)``, with the kernel if one is set). Errors in the input or options end the program
with a one-line message on stderr and exit status 1 (2 for bad options).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from graphopt import GraphError, LevenbergConfig, SparseOptimizer, make_kernel
from graphopt.apps import _cli
from graphopt.apps.bal_preprocess import normalize, perturb
from graphopt.apps.bal_report import BALRecording, recording_markdown
from graphopt.apps.bal_scene import ground_truth_errors, synthetic_scene
from graphopt.io.bal import BALFormatError, BALProblem, read_bal
from graphopt.io.ply import write_scene_ply
from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL, reprojection_errors
from graphopt.types.vertices import VertexPointXYZ

PROG = "graphopt-bal"


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser.

    Returns:
        The parser.
    """
    p = _cli.OneLineParser(
        prog=PROG,
        description="Bundle adjustment of a BAL file (or a synthetic scene) with graphopt.",
    )
    p.add_argument("input", nargs="?", metavar="INPUT",
                   help="BAL file (.txt, .txt.gz, .txt.bz2); omit for a synthetic scene")
    _cli.add_stopping_options(p)
    p.add_argument("--algorithm", choices=("lm", "gn", "dogleg"), default="lm")
    p.add_argument("--lm-damping", choices=("diagonal", "identity"), default="diagonal",
                   help="LM damping: lambda*diag(H) (Marquardt, as Ceres; default) or "
                        "lambda*I (g2o)")
    p.add_argument("--lm-schedule", choices=("g2o", "ceres", "gtsam"), default="g2o",
                   help="LM damping schedule: g2o's Nielsen rule (default: fewest iterations on "
                        "the BAL files, benchmarks/bench_schedules.py), Ceres' or GTSAM's")
    _cli.add_solver_option(p)
    p.add_argument("--robust", metavar="KERNEL", default=None,
                   help="robust kernel (huber, cauchy, pseudohuber, tukey, ...)")
    p.add_argument("--robust-delta", type=float, default=1.0, metavar="D",
                   help="kernel width in pixels (default 1)")
    p.add_argument("--normalize", action="store_true",
                   help="centre and scale the scene as Ceres' bundle_adjuster does")
    p.add_argument("--perturb", type=float, nargs=3, metavar=("R", "T", "P"), default=None,
                   help="add Gaussian noise: rotation (rad), translation and point sigmas")
    p.add_argument("--seed", type=int, default=0, help="seed for --perturb and the synthetic scene")
    p.add_argument("--ply-before", metavar="FILE", help="PLY of the initial reconstruction")
    p.add_argument("--ply-after", metavar="FILE", help="PLY of the optimised reconstruction")
    p.add_argument("--ply-drop-far", action="store_true",
                   help=f"leave out of the PLY files the points farther than {FAR_FACTOR:g}x the "
                        "median distance from the median point (see the summary's count)")
    p.add_argument("--rrd", metavar="FILE", help="rerun recording (.rrd) of the optimisation")
    p.add_argument("--json", metavar="FILE", help="write the summary as one JSON object")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def _check_options(args: argparse.Namespace) -> None:
    """Check what argparse cannot: value ranges, and that the outputs can be written."""
    _cli.check_run_options(args, args.robust_delta)
    if args.perturb is not None and any(not math.isfinite(s) or s < 0 for s in args.perturb):
        raise _cli.AppError(f"--perturb sigmas must be finite and >= 0, got {args.perturb}")
    _cli.check_outputs({"--ply-before": args.ply_before, "--ply-after": args.ply_after,
                        "--rrd": args.rrd, "--json": args.json}, inputs=[args.input])


#: Observations projected per pass when computing costs (bounds the temporary arrays).
STATS_CHUNK = 1 << 20


def _residual_stats(
    problem: BALProblem, cams: np.ndarray, pts: np.ndarray
) -> tuple[float, float, int]:
    """Cost ½Σ‖r‖², RMS pixel error and observations behind their camera."""
    total, behind = 0.0, 0
    for lo in range(0, problem.num_observations, STATS_CHUNK):
        part = BALProblem(cams, pts, problem.camera_index[lo:lo + STATS_CHUNK],
                          problem.point_index[lo:lo + STATS_CHUNK],
                          problem.observations[lo:lo + STATS_CHUNK])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # the caller reports
            r, pz = reprojection_errors(part)
            total += float(np.einsum("ij,ij->", r, r))
        behind += int(np.count_nonzero(pz >= 0))
    m = max(problem.num_observations, 1)
    return 0.5 * total, float(np.sqrt(total / m)), behind


#: Seconds after which a loading or set-up step says what it is doing (and then how long it
#: took): small problems print nothing.
PROGRESS_DELAY = 3.0


class _Progress:
    """One line on stderr per slow step: ``graphopt-bal: STEP ... 12.3 s``.

    The step's name appears once it has run for :data:`PROGRESS_DELAY` seconds (from a timer
    thread), its seconds when it ends; a step that ends sooner prints nothing.

    Args:
        quiet: Print nothing.
    """

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet

    @contextlib.contextmanager
    def step(self, what: str) -> Iterator[None]:
        """Time one step.

        Args:
            what: What the step does (``reading FILE``).
        """
        if self.quiet:
            yield
            return
        lock = threading.Lock()
        state = {"shown": False, "done": False}

        def show() -> None:
            with lock:
                if not state["done"]:
                    print(f"{PROG}: {what} ...", end="", file=sys.stderr, flush=True)
                    state["shown"] = True

        t0 = time.perf_counter()
        timer = threading.Timer(PROGRESS_DELAY, show)
        timer.daemon = True
        timer.start()
        try:
            yield
        finally:
            with lock:
                state["done"] = True
                timer.cancel()
                if state["shown"]:
                    print(f" {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)


def _first_bad_observation(problem: BALProblem, source: str) -> str:
    """Where the first observation with a non-finite reprojection error is (file:line)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        r, _ = reprojection_errors(problem)
    bad = np.flatnonzero(~np.isfinite(r).all(axis=1))
    if not len(bad):
        return source
    i = int(bad[0])
    # Observations are lines 2.. of a BAL file (line 1 is the header).
    where = f"{source}:{i + 2}" if problem.path else source
    return (f"{where}: observation {i} (camera {int(problem.camera_index[i])}, point "
            f"{int(problem.point_index[i])})")


def _load(args: argparse.Namespace, progress: _Progress
          ) -> tuple[BALProblem, BALProblem | None, str]:
    """The problem to solve (read or synthetic, then normalised/perturbed), its ground truth
    (synthetic scene only) and a description of its source."""
    truth = None
    if args.input is None:
        scene = synthetic_scene(seed=args.seed)
        problem, truth = scene.problem, scene.truth
        source = f"synthetic scene (seed {args.seed})"
    else:
        with progress.step(f"reading {args.input}"):
            problem = read_bal(args.input)  # BALFormatError is reported by main()
        source = args.input
    if args.normalize:
        problem = normalize(problem)
    if args.perturb is not None:
        problem = perturb(problem, *args.perturb, seed=args.seed)
    return problem, truth, source


def _build_optimizer(
    args: argparse.Namespace, problem: BALProblem, kernel: Any, source: str,
    progress: _Progress,
) -> tuple[SparseOptimizer, str, str]:
    """Cameras, marginalised points and one projection edge per observation, initialised
    (structure, Schur plan, symbolic factorisation); with the solver's name and description."""
    algorithm: Any = args.algorithm
    if args.algorithm == "lm":
        # BAL mixes parameters of very different scales (focal lengths ~1e3 px next to k2 as
        # small as 1e-7): λ·diag(H) damps each in its own units, λ·I starves the small ones.
        algorithm = LevenbergConfig(diagonal_damping=args.lm_damping == "diagonal",
                                    schedule=args.lm_schedule)
    opt = SparseOptimizer(algorithm=algorithm, solver=args.solver, verbose=not args.quiet,
                          stream=sys.stderr, stopping=_cli.stopping_config(args))
    nc, npt = problem.num_cameras, problem.num_points
    with progress.step(f"building the graph ({problem.num_observations:,} observations)"):
        opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
        opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), problem.points, marginalized=True)
        opt.add_edges(
            EdgeBALProjection,
            np.column_stack([problem.camera_index, nc + problem.point_index]),
            problem.observations,
            robust_kernel=kernel,
        )
    try:
        with progress.step("set-up (structure, Schur complement plan, symbolic factorisation)"):
            solver, solver_text, _ = _cli.initialize(opt, args.solver)
    except GraphError as exc:
        raise _cli.AppError(f"{source}: {exc}") from None
    return opt, solver, solver_text


def _start_recording(path: str, opt: SparseOptimizer, problem: BALProblem) -> BALRecording:
    """Open the recording, log the start and every iteration (timed, see ``_cli.RunRecording``)."""
    centers = problem.camera_centers()
    scale = float(np.median(np.linalg.norm(centers - np.median(problem.points, 0), axis=1)))
    recording = BALRecording(path, PROG, problem, scale if scale > 0 else 1.0)
    with recording.timed():
        opt.compute_active_errors()
        recording.log_start(problem.cameras, problem.points, opt.active_robust_chi2())

    def on_iteration(o: SparseOptimizer, info: Any) -> None:
        with recording.timed():  # the recording's work is kept out of the reported seconds
            recording.log_state(info.iteration + 1, o.estimates_of(VertexCameraBAL),
                                o.estimates_of(VertexPointXYZ), info.chi2, info.seconds)

    opt.add_callback("post_iteration", on_iteration)
    return recording


#: A point is *far* when its distance from the median point exceeds this many times the median
#: distance (Ladybug-49 ends with 19 points beyond 1,000 units in a scene whose input spans 633).
FAR_FACTOR = 100.0


def far_points(points: np.ndarray, factor: float = FAR_FACTOR) -> np.ndarray:
    """Mask of points far outside the scene: farther from the median point than ``factor``
    times the median distance (robust to the outliers it looks for).

    Args:
        points: ``(n, 3)`` points.
        factor: The multiple of the median distance.

    Returns:
        ``(n,)`` boolean mask.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    dist = np.linalg.norm(pts - np.median(pts, axis=0), axis=1)
    return dist > factor * np.median(dist)


def _write_ply(path: str, problem: BALProblem, drop_far: bool) -> None:
    keep = ~far_points(problem.points) if drop_far else slice(None)
    write_scene_ply(path, problem.points[keep], problem.camera_centers())


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run bundle adjustment as configured by parsed options.

    Args:
        args: Options from :func:`build_parser`.

    Returns:
        The summary dictionary (also written by ``--json``).
    """
    _check_options(args)
    kernel = None
    if args.robust is not None:
        try:
            kernel = make_kernel(args.robust, args.robust_delta)
        except ValueError as exc:
            raise _cli.AppError(str(exc)) from None

    progress = _Progress(args.quiet)
    problem, truth, source = _load(args, progress)
    with progress.step("initial cost"):
        initial_cost, initial_rms, behind0 = _residual_stats(problem, problem.cameras,
                                                             problem.points)
    if not math.isfinite(initial_cost):
        raise _cli.AppError(f"{_first_bad_observation(problem, source)}: the initial "
                            "reprojection error is not finite (a point at depth 0 in its camera?)")
    if args.ply_before:
        _write_ply(args.ply_before, problem, args.ply_drop_far)

    opt, solver, solver_text = _build_optimizer(args, problem, kernel, source, progress)
    # The graph has its own indices; the app's copies need not be 8 bytes each.
    if problem.num_cameras < 2**31 and problem.num_points < 2**31:
        problem.camera_index = problem.camera_index.astype(np.int32)
        problem.point_index = problem.point_index.astype(np.int32)
    recording = _start_recording(args.rrd, opt, problem) if args.rrd else None
    res = _cli.optimize_recorded(opt, args.iterations, recording)
    est = BALProblem(opt.estimates_of(VertexCameraBAL), opt.estimates_of(VertexPointXYZ),
                     problem.camera_index, problem.point_index, problem.observations)
    final_cost, final_rms, behind1 = _residual_stats(problem, est.cameras, est.points)
    if not (math.isfinite(final_cost) and np.isfinite(est.cameras).all()
            and np.isfinite(est.points).all()):
        if recording is not None:
            recording.abort()
        raise _cli.AppError("the optimisation produced non-finite estimates")
    seconds = res.seconds - (recording.seconds if recording is not None else 0.0)

    summary: dict[str, Any] = {
        "input": source,
        "cameras": problem.num_cameras,
        "points": problem.num_points,
        "observations": problem.num_observations,
        "algorithm": args.algorithm,
        "lm_damping": args.lm_damping if args.algorithm == "lm" else None,
        "lm_schedule": args.lm_schedule if args.algorithm == "lm" else None,
        "solver": solver,
        "solver_requested": args.solver,
        "solver_text": solver_text,
        "robust_kernel": None if kernel is None else f"{args.robust}:{args.robust_delta:g}",
        "initial_cost": initial_cost,
        "final_cost": final_cost,
        "initial_chi2": float(res.initial_chi2),
        "final_chi2": float(res.final_chi2),
        "initial_rms_px": initial_rms,
        "rms_px": final_rms,
        "iterations": int(res.iterations),
        "seconds": float(seconds),
        "seconds_per_iteration": float(seconds / res.iterations) if res.iterations else 0.0,
        "stop_reason": res.stop_reason,
        "behind_camera_initial": behind0,
        "behind_camera_final": behind1,
        "far_points_initial": int(far_points(problem.points).sum()),
        "far_points_final": int(far_points(est.points).sum()),
        "far_points_dropped_from_ply": bool(args.ply_drop_far),
    }
    if truth is not None:
        summary["ground_truth_initial"] = ground_truth_errors(problem, truth)
        summary["ground_truth"] = ground_truth_errors(est, truth)

    if recording is not None:
        with recording.timed():
            recording.finish(opt, est.points)
            recording.log_summary(recording_markdown(PROG, summary, recording))
        recording.close()
    if args.ply_after:
        _write_ply(args.ply_after, est, args.ply_drop_far)
    if args.json:
        _cli.write_json(args.json, summary)
    if not args.quiet:
        print(format_summary(summary))
        warning = stop_warning(args.algorithm, str(res.stop_reason), int(res.iterations),
                               args.lm_damping)
        if warning:
            print(f"{PROG}: warning: {warning}", file=sys.stderr)
    return summary


def stop_warning(algorithm: str, stop_reason: str, iterations: int,
                 lm_damping: str = "diagonal") -> str | None:
    """What to tell the user when the run ended because no step could be computed.

    Only ``failed`` and ``singular`` runs get a warning, and its advice fits the algorithm
    that ran: Gauss–Newton is told to use a damped algorithm; Levenberg–Marquardt with
    ``lambda*diag(H)`` damping to damp every parameter (a parameter no observation constrains
    has a zero diagonal, which that damping leaves at zero); the others to check the input.

    Args:
        algorithm: ``"gn"``, ``"lm"`` or ``"dogleg"``.
        stop_reason: The run's stop reason.
        iterations: Iterations done (the failed one included).
        lm_damping: LM's damping (``"diagonal"`` or ``"identity"``).

    Returns:
        The warning (without the program's prefix), or None.
    """
    if stop_reason not in ("failed", "singular"):
        return None
    when = ("no step was possible" if iterations <= 1
            else f"the run stopped at iteration {iterations} without a step")
    if algorithm == "gn":
        cause = ("the normal equations are singular (bundle adjustment has a 7-dimensional "
                 "gauge freedom)" if stop_reason == "singular" else
                 "the normal equations were not positive definite or the step made the cost "
                 "non-finite")
        return f"{when}: {cause}; use --algorithm lm or dogleg, which damp the system"
    name = {"lm": "Levenberg-Marquardt", "dogleg": "dogleg"}.get(algorithm, algorithm)
    text = (f"{when}: every damped solve of {name} met normal equations that are not positive "
            "definite")
    if algorithm == "lm" and lm_damping == "diagonal":
        return (text + "; a parameter that no observation constrains keeps a zero diagonal "
                "under lambda*diag(H): try --lm-damping identity, or check the input")
    return text + "; check the input for non-finite or extreme values"


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable summary lines.

    Args:
        s: The summary dictionary from :func:`run`.
    """
    lines = [
        f"{PROG}: {s['input']}",
        f"  cameras {s['cameras']}, points {s['points']}, observations {s['observations']}",
        f"  algorithm {s['algorithm']}"
        + (f" ({s['lm_damping']} damping)" if s.get("lm_damping") else "")
        + f", linear solver {s['solver_text']}, robust kernel "
        f"{s['robust_kernel'] or 'none'}, points marginalised (Schur complement)",
        f"  initial cost {s['initial_cost']:.6e}   final cost {s['final_cost']:.6e}"
        "   (1/2 sum |r|^2, no kernel)",
        f"  initial chi2 {s['initial_chi2']:.6e}   final chi2 {s['final_chi2']:.6e}",
        f"  RMS reprojection error {s['initial_rms_px']:.4f} px -> {s['rms_px']:.4f} px",
        f"  iterations {s['iterations']} ({s['stop_reason']}), {s['seconds']:.3f} s, "
        f"{s['seconds_per_iteration']:.4f} s/iteration",
        f"  observations behind their camera: {s['behind_camera_initial']} initially, "
        f"{s['behind_camera_final']} at the end (kept, BAL's model)",
        f"  points far outside the scene (> {FAR_FACTOR:g}x the median distance from the median "
        f"point): {s['far_points_initial']} initially, {s['far_points_final']} at the end"
        + (" (left out of the PLY files)" if s["far_points_dropped_from_ply"] else ""),
    ]
    if "ground_truth" in s:
        g0, g = s["ground_truth_initial"], s["ground_truth"]
        lines.append(
            f"  vs ground truth (after similarity alignment): point RMS {g0['point_rms']:.4g} -> "
            f"{g['point_rms']:.4g}, camera centre RMS {g0['camera_center_rms']:.4g} -> "
            f"{g['camera_center_rms']:.4g}, rotation {g0['rotation_deg_rms']:.4g} -> "
            f"{g['rotation_deg_rms']:.4g} deg, focal {g0['focal_rel_rms']:.3g} -> "
            f"{g['focal_rel_rms']:.3g} (relative)"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``graphopt-bal``.

    Args:
        argv: Arguments (``sys.argv[1:]`` if None).

    Returns:
        Exit status: 0 on success, 1 on an input/processing error, 2 on bad options.
    """
    return _cli.run_main(PROG, build_parser(), run, argv, user_errors=(BALFormatError,))


if __name__ == "__main__":
    sys.exit(main())
