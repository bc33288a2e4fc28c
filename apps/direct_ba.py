"""graphopt-direct-ba: direct (photometric) bundle adjustment, real data or a synthetic scene.

Usage::

    graphopt-direct-ba [DATA_DIR] [--iterations N] [--robust KERNEL --robust-delta D]
                       [--parametrization xyz|inverse-depth] [--patch 4] [--solver ...]
                       [--rrd FILE] [--png FILE] [--json FILE] [--quiet]

With ``DATA_DIR`` (poses.txt, points.txt, 0.png…) every (point, image) pair is a photometric
patch edge, as in the task's skeleton; without it a synthetic textured room is rendered from known
poses, perturbed and recovered, and the errors against the truth are reported.

Conventions: see :mod:`graphopt.apps.direct_ba_problem` (problem building);
:mod:`graphopt.apps.direct_ba_report` writes the PNG, the rerun recording and the errors against
the truth. ``chi2`` is g2o's robust chi2 ``Σ ρ(e'e)`` over active edges.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from typing import Any

from graphopt import GraphError, NotPositiveDefiniteError
from graphopt.apps import _cli
from graphopt.apps.direct_ba_problem import PARAMETRIZATIONS, build_problem
from graphopt.apps.direct_ba_report import (
    DirectBARecording,
    recording_markdown,
    truth_report,
    write_png,
)
from graphopt.apps.direct_ba_scene import synthetic_scene
from graphopt.io.directba import DirectBAFormatError, load_directba

PROG = "graphopt-direct-ba"
PATCHES = (2, 4, 6, 8)

#: Synthetic scene used without DATA_DIR (7 frames like the task's data).
SYNTHETIC = {"n_frames": 7, "n_points": 2000, "seed": 0}


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser.

    Returns:
        The parser.
    """
    ap = _cli.OneLineParser(
        prog=PROG,
        description="Direct (photometric) bundle adjustment of the task's data (DATA_DIR with "
        "poses.txt, points.txt, 0.png...) or, without DATA_DIR, of a synthetic textured scene.",
    )
    ap.add_argument("data_dir", nargs="?", metavar="DATA_DIR", help="data folder")
    _cli.add_stopping_options(ap)
    ap.add_argument("--robust", default="huber", metavar="KERNEL",
                    help="robust kernel: huber (default), cauchy, tukey, ... or none")
    ap.add_argument("--robust-delta", type=float, default=0.5, metavar="D",
                    help="kernel width on sqrt(e'e) (default 0.5, the task's)")
    ap.add_argument("--parametrization", choices=PARAMETRIZATIONS, default="xyz",
                    help="point parametrisation (default xyz)")
    ap.add_argument("--patch", type=int, choices=PATCHES, default=4,
                    help="patch side (default 4; other sizes need the synthetic scene)")
    _cli.add_solver_option(ap)
    ap.add_argument("--rrd", metavar="FILE", help="write a rerun recording")
    ap.add_argument("--png", metavar="FILE", help="write a top-down before/after picture")
    ap.add_argument("--json", metavar="FILE", help="write a JSON summary")
    ap.add_argument("--quiet", action="store_true", help="no iteration lines or summary")
    return ap


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the app with parsed arguments; returns the JSON summary.

    Args:
        args: Parsed command line (see :func:`build_parser`).

    Raises:
        _cli.AppError: Bad input or output location (one-line message).
    """
    _cli.check_run_options(args, args.robust_delta)
    _cli.check_outputs({"--rrd": args.rrd, "--png": args.png, "--json": args.json},
                       inputs=[args.data_dir])
    out = sys.stdout
    say = (lambda *a: print(*a, file=out)) if not args.quiet else (lambda *a: None)

    t0 = time.perf_counter()
    try:
        if args.data_dir is not None:
            if args.patch != 4:
                raise _cli.AppError(
                    f"--patch {args.patch}: the data's points.txt holds 4x4 patches; other "
                    "sizes work with the synthetic scene (no DATA_DIR)")
            data = load_directba(args.data_dir)
        else:
            data = synthetic_scene(patch=args.patch, **SYNTHETIC)
    except DirectBAFormatError as exc:
        raise _cli.AppError(str(exc)) from None
    load_s = time.perf_counter() - t0
    try:
        problem = build_problem(data, args.parametrization, args.robust, args.robust_delta,
                                args.solver, verbose=not args.quiet, stream=out)
    except (ValueError, GraphError) as exc:
        raise _cli.AppError(str(exc)) from None
    opt = problem.optimizer
    opt.stopping = _cli.stopping_config(args)
    solver, solver_text, _ = _cli.initialize(opt, args.solver)
    before = (problem.poses(), problem.points())
    opt.compute_active_errors()
    active0 = opt.active_edge_count()
    say(f"# {PROG}: {data.source}: {len(data.poses)} poses, {len(problem.point_index)} points "
        f"({problem.parametrization}), {problem.n_edges} edges, {active0} active, patch "
        f"{data.patch}x{data.patch}, robust {args.robust} {args.robust_delta:g}, "
        f"linear solver {solver_text}; load {load_s:.2f} s")
    if problem.dropped_points:
        say(f"# {problem.dropped_points} points behind every camera were left out")

    recording = None
    if args.rrd:
        recording = DirectBARecording(args.rrd, problem, PROG)
        with recording.timed():
            recording.log_state(0, opt.active_robust_chi2(), first=True)

        def on_iteration(o: Any, info: Any) -> None:
            with recording.timed():  # kept out of the reported seconds
                recording.log_state(info.iteration + 1, info.chi2, seconds=info.seconds)

        opt.add_callback("post_iteration", on_iteration)
    try:
        res = _cli.optimize_recorded(opt, args.iterations, recording)
    except (NotPositiveDefiniteError, FloatingPointError) as exc:
        raise _cli.AppError(f"optimisation failed: {exc}") from None
    seconds = res.seconds - (recording.seconds if recording is not None else 0.0)
    per_iteration = seconds / res.iterations if res.iterations else 0.0
    opt.compute_active_errors()
    summary: dict[str, Any] = {
        "input": data.source,
        "algorithm": "lm",
        "solver": solver,
        "solver_requested": args.solver,
        "robust_kernel": (None if args.robust in (None, "none", "")
                          else f"{args.robust}:{args.robust_delta:g}"),
        "parametrization": problem.parametrization,
        "patch": data.patch,
        "poses": len(data.poses),
        "points": len(problem.point_index),
        "edges": problem.n_edges,
        "active_edges": active0,
        "active_edges_final": opt.active_edge_count(),
        "initial_chi2": res.initial_chi2,
        "final_chi2": res.final_chi2,
        "iterations": res.iterations,
        "stop_reason": res.stop_reason,
        "seconds": seconds,
        "seconds_per_iteration": per_iteration,
        "chi2_history": res.chi2_history,
    }
    if data.true_poses is not None:
        summary.update(truth_report(problem))
    if recording is not None:
        recording.finish()  # the last evaluation (compute_active_errors above) is the final one
        recording.log_summary(recording_markdown(PROG, summary, recording, solver_text))
        recording.close()
    if args.png:
        write_png(args.png, problem, before, (problem.poses(), problem.points()))
    if args.json:
        _cli.write_json(args.json, summary)
    say(f"# chi2 {res.initial_chi2:.6g} -> {res.final_chi2:.6g} in {res.iterations} iterations "
        f"({res.stop_reason}), {seconds:.3f} s, {per_iteration:.4f} s/iteration; "
        f"active edges {active0} -> {summary['active_edges_final']} of {problem.n_edges}")
    if data.true_poses is not None:
        s = summary
        say(f"# vs truth: rotation {s['initial_rotation_error_deg_mean']:.3f} -> "
            f"{s['final_rotation_error_deg_mean']:.4f} deg (mean), translation "
            f"{s['initial_translation_error_m_mean'] * 100:.2f} -> "
            f"{s['final_translation_error_m_mean'] * 100:.3f} cm (mean; "
            f"{s['final_translation_error_scale_aligned_m_mean'] * 100:.3f} cm after scale "
            f"{s['final_scale']:.4f}), points "
            f"{s['initial_point_error_m_median'] * 100:.2f} -> "
            f"{s['final_point_error_m_median'] * 100:.3f} cm (median)")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments (``sys.argv[1:]`` by default).

    Returns:
        Exit status: 0 on success, 1 on a runtime error, 2 on a usage error.
    """
    return _cli.run_main(PROG, build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
