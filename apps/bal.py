"""``graphopt-bal``: bundle adjustment of a BAL problem (or a synthetic one) with graphopt.

Usage::

    graphopt-bal [INPUT] [--iterations N] [--algorithm lm|gn|dogleg]
                 [--solver auto|cholmod|dense|pcg] [--robust KERNEL --robust-delta D]
                 [--normalize] [--perturb R T P] [--seed S]
                 [--ply-before FILE] [--ply-after FILE] [--rrd FILE] [--json FILE] [--quiet]
                 [--lm-damping diagonal|identity]

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
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

PROG = "graphopt-bal"


class AppError(Exception):
    """An error reported to the user as one line (no traceback)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit status 2) instead of usage + error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser.

    Returns:
        The parser.
    """
    p = _Parser(
        prog=PROG,
        description="Bundle adjustment of a BAL file (or a synthetic scene) with graphopt.",
    )
    p.add_argument("input", nargs="?", metavar="INPUT",
                   help="BAL file (.txt, .txt.gz, .txt.bz2); omit for a synthetic scene")
    p.add_argument("--iterations", type=int, default=20, metavar="N",
                   help="maximum iterations (default 20)")
    p.add_argument("--algorithm", choices=("lm", "gn", "dogleg"), default="lm")
    p.add_argument("--lm-damping", choices=("diagonal", "identity"), default="diagonal",
                   help="LM damping: lambda*diag(H) (Marquardt, as Ceres; default) or "
                        "lambda*I (g2o)")
    p.add_argument("--solver", choices=("auto", "cholmod", "dense", "pcg"), default="auto",
                   help="linear solver for the reduced camera system (default auto: dense "
                        "Cholesky for a small dense system, else CHOLMOD)")
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
    p.add_argument("--rrd", metavar="FILE", help="rerun recording (.rrd) of the optimisation")
    p.add_argument("--json", metavar="FILE", help="write the summary as one JSON object")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def _check_options(args: argparse.Namespace) -> None:
    if args.iterations < 0:
        raise AppError(f"--iterations must be >= 0, got {args.iterations}")
    if not math.isfinite(args.robust_delta) or args.robust_delta <= 0:
        raise AppError(f"--robust-delta must be positive, got {args.robust_delta}")
    if args.perturb is not None and any(not math.isfinite(s) or s < 0 for s in args.perturb):
        raise AppError(f"--perturb sigmas must be finite and >= 0, got {args.perturb}")
    outputs = [args.ply_before, args.ply_after, args.rrd, args.json]
    for out in outputs:
        if out is None:
            continue
        folder = Path(out).parent
        if not folder.is_dir():
            raise AppError(f"{out}: folder {folder} does not exist")
        if Path(out).is_dir():
            raise AppError(f"{out}: is a directory")
        if args.input is not None and Path(out).resolve() == Path(args.input).resolve():
            raise AppError(f"{out}: refusing to overwrite the input file")
    named = [o for o in outputs if o is not None]
    if len({str(Path(o).resolve()) for o in named}) != len(named):
        raise AppError("two outputs name the same file")


def _cameras_to_poses(cams: np.ndarray) -> np.ndarray:
    from graphopt.lie import make_transform, so3_exp

    return make_transform(so3_exp(cams[:, :3]), cams[:, 3:6])


def _residual_stats(problem: Any, cams: np.ndarray, pts: np.ndarray) -> tuple[float, float, int]:
    """Cost ½Σ‖r‖², RMS pixel error and observations behind their camera."""
    from graphopt.types.bal import bal_project

    uv, pz = bal_project(cams[problem.camera_index], pts[problem.point_index])
    r = uv - problem.observations
    sq = np.einsum("ij,ij->i", r, r)
    return 0.5 * float(sq.sum()), float(np.sqrt(sq.mean())), int(np.count_nonzero(pz >= 0))


class _RecorderHook:
    """Logs points, frusta and cost to a rerun recording; keeps its own time out of ``seconds``."""

    def __init__(self, path: str, problem: Any, scene_scale: float) -> None:
        from graphopt.recording import Recorder

        self.rec = Recorder(path, application_id=PROG, camera_xyz="RUB")
        self.problem = problem
        # Image size is not in BAL files: use the extent of each camera's observations.
        ext = np.zeros((problem.num_cameras, 2))
        np.maximum.at(ext, problem.camera_index, np.abs(problem.observations))
        self.resolution = np.maximum(2.0 * ext, 2.0)
        self.plane = 0.05 * scene_scale
        self.seconds = 0.0

    def log(self, iteration: int, cams: np.ndarray, pts: np.ndarray, cost: float) -> None:
        t0 = time.perf_counter()
        self.rec.set_iteration(iteration)
        self.rec.log_points(pts)
        self.rec.log_cameras(
            _cameras_to_poses(cams),
            focal=np.abs(cams[:, 6]),
            resolution=self.resolution,
            principal_point=self.resolution / 2.0,
            image_plane_distance=self.plane,
        )
        self.rec.log_scalar("cost", cost)
        self.seconds += time.perf_counter() - t0


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run bundle adjustment as configured by parsed options.

    Args:
        args: Options from :func:`build_parser`.

    Returns:
        The summary dictionary (also written by ``--json``).
    """
    from graphopt import GraphError, LevenbergConfig, SparseOptimizer, make_kernel
    from graphopt.apps.bal_preprocess import normalize, perturb
    from graphopt.apps.bal_scene import ground_truth_errors, synthetic_scene
    from graphopt.io.bal import read_bal
    from graphopt.io.ply import write_scene_ply
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    _check_options(args)
    kernel = None
    if args.robust is not None:
        try:
            kernel = make_kernel(args.robust, args.robust_delta)
        except ValueError as exc:
            raise AppError(str(exc)) from None

    truth = None
    if args.input is None:
        scene = synthetic_scene(seed=args.seed)
        problem, truth = scene.problem, scene.truth
        source = f"synthetic scene (seed {args.seed})"
    else:
        problem = read_bal(args.input)  # BALFormatError is reported by main()
        source = args.input
    if args.normalize:
        problem = normalize(problem)
    if args.perturb is not None:
        problem = perturb(problem, *args.perturb, seed=args.seed)

    nc, npt, nobs = problem.num_cameras, problem.num_points, problem.num_observations
    initial_cost, initial_rms, behind0 = _residual_stats(problem, problem.cameras, problem.points)
    if not math.isfinite(initial_cost):
        raise AppError(f"{source}: the initial reprojection error is not finite "
                       "(a point at depth 0 in its camera?)")

    if args.ply_before:
        write_scene_ply(args.ply_before, problem.points, problem.camera_centers())

    verbose = not args.quiet
    algorithm: Any = args.algorithm
    if args.algorithm == "lm":
        # BAL mixes parameters of very different scales (focal lengths ~1e3 px next to k2 as
        # small as 1e-7): λ·diag(H) damps each in its own units, λ·I starves the small ones.
        algorithm = LevenbergConfig(diagonal_damping=args.lm_damping == "diagonal")
    opt = SparseOptimizer(algorithm=algorithm, solver=args.solver, verbose=verbose,
                          stream=sys.stderr)
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), problem.points, marginalized=True)
    opt.add_edges(
        EdgeBALProjection,
        np.column_stack([problem.camera_index, nc + problem.point_index]),
        problem.observations,
        robust_kernel=kernel,
    )
    try:
        opt.initialize_optimization()
    except GraphError as exc:
        raise AppError(f"{source}: {exc}") from None

    hook = None
    if args.rrd:
        centers = problem.camera_centers()
        scale = float(np.median(np.linalg.norm(centers - np.median(problem.points, 0), axis=1)))
        hook = _RecorderHook(args.rrd, problem, scale if scale > 0 else 1.0)
        hook.log(0, problem.cameras, problem.points, initial_cost)

        def on_iteration(o: SparseOptimizer, info: Any) -> None:
            t0 = time.perf_counter()
            cams = o.estimates_of(VertexCameraBAL)
            pts = o.estimates_of(VertexPointXYZ)
            cost = _residual_stats(problem, cams, pts)[0]
            extra = time.perf_counter() - t0
            hook.log(info.iteration + 1, cams, pts, cost)
            hook.seconds += extra  # keep the recording's work out of the reported seconds

        opt.add_callback("post_iteration", on_iteration)

    try:
        res = opt.optimize(args.iterations)
    except BaseException:
        if hook is not None:
            hook.rec.abort()
        raise
    cams = opt.estimates_of(VertexCameraBAL)
    pts = opt.estimates_of(VertexPointXYZ)
    final_cost, final_rms, behind1 = _residual_stats(problem, cams, pts)
    if not (math.isfinite(final_cost) and np.isfinite(cams).all() and np.isfinite(pts).all()):
        if hook is not None:
            hook.rec.abort()
        raise AppError("the optimisation produced non-finite estimates")
    seconds = res.seconds - (hook.seconds if hook is not None else 0.0)

    summary: dict[str, Any] = {
        "input": source,
        "cameras": nc,
        "points": npt,
        "observations": nobs,
        "algorithm": args.algorithm,
        "lm_damping": args.lm_damping if args.algorithm == "lm" else None,
        "solver": args.solver,
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
    }
    if truth is not None:
        from graphopt.io.bal import BALProblem

        est = BALProblem(cams, pts, problem.camera_index, problem.point_index,
                         problem.observations)
        summary["ground_truth_initial"] = ground_truth_errors(problem, truth)
        summary["ground_truth"] = ground_truth_errors(est, truth)

    if hook is not None:
        hook.rec.close()
    if args.ply_after:
        from graphopt.io.bal import BALProblem

        est = BALProblem(cams, pts, problem.camera_index, problem.point_index,
                         problem.observations)
        write_scene_ply(args.ply_after, pts, est.camera_centers())
    if args.json:
        from graphopt.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump(summary, f, indent=2, allow_nan=False)
            f.write("\n")
    if not args.quiet:
        print(format_summary(summary))
        if res.stop_reason == "failed":
            print(f"{PROG}: warning: no step was possible because the normal equations are "
                  "singular (bundle adjustment has a 7-dimensional gauge freedom); use "
                  "--algorithm lm or dogleg, which damp it", file=sys.stderr)
    return summary


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
        + f", solver {s['solver']}, robust kernel "
        f"{s['robust_kernel'] or 'none'}, points marginalised (Schur complement)",
        f"  initial cost {s['initial_cost']:.6e}   final cost {s['final_cost']:.6e}"
        "   (1/2 sum |r|^2, no kernel)",
        f"  initial chi2 {s['initial_chi2']:.6e}   final chi2 {s['final_chi2']:.6e}",
        f"  RMS reprojection error {s['initial_rms_px']:.4f} px -> {s['rms_px']:.4f} px",
        f"  iterations {s['iterations']} ({s['stop_reason']}), {s['seconds']:.3f} s, "
        f"{s['seconds_per_iteration']:.4f} s/iteration",
        f"  observations behind their camera: {s['behind_camera_initial']} initially, "
        f"{s['behind_camera_final']} at the end (kept, BAL's model)",
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
    from graphopt.io.bal import BALFormatError

    args = build_parser().parse_args(argv)
    try:
        run(args)
    except (AppError, BALFormatError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the user gets one line, not a traceback
        if os.environ.get("GRAPHOPT_DEBUG"):
            raise
        msg = str(exc).splitlines()[0] if str(exc) else ""
        print(f"{PROG}: error: {type(exc).__name__}: {msg}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
