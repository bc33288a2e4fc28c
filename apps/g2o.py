"""``graphopt-g2o``: optimise a g2o, TORO or GTSAM pose graph, as g2o's ``g2o_cli`` does.

Usage::

    graphopt-g2o [INPUT] [-o OUTPUT.g2o] [-i/--iterations N] [--algorithm gn|lm|dogleg]
                 [--solver auto|cholmod|dense|pcg|scipy] [--robust-kernel NAME]
                 [--robust-delta D] [--guess] [--marginals] [--skip-unknown]
                 [--json FILE] [--rrd FILE] [--png FILE] [--quiet] [--poses N] [--seed S]

INPUT is read by :func:`graphopt.io.g2o.read_graph` (every tag converted to its canonical g2o
tag) and built by :func:`graphopt.types.slam_graph.build_graph` (gauge, ``EQUIV``, landmark ids,
initial guess). Without INPUT a Manhattan-world 2D graph with known ground truth is generated
(:func:`graphopt.apps.slam_scene.manhattan_world`) and the trajectory's error against the truth
is reported before and after.

chi2 is g2o's (``optimizer.chi2()``: ``Σ e'Ωe`` without the robust kernel); the iteration lines
(stderr) print the robustified chi2 as g2o does. Errors in the input or options end the program
with one line on stderr naming the file and line, exit status 1 (2 for bad options).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from graphopt import (
    GraphError,
    NotPositiveDefiniteError,
    SparseOptimizer,
    make_kernel,
)
from graphopt.apps import _cli, g2o_online
from graphopt.apps.g2o_report import (
    GraphView,
    SlamRecording,
    graph_view,
    recording_markdown,
    write_png,
)
from graphopt.apps.slam_scene import manhattan_world, trajectory_error
from graphopt.io.g2o import GraphFormatError, read_graph, write_g2o
from graphopt.io.g2o_records import GraphFile
from graphopt.robust_kernel import RobustKernel
from graphopt.types.slam_graph import SlamGraph, build_graph, graph_file, pose_graph_levenberg

PROG = "graphopt-g2o"
#: Marginals of every free pose up to this many, else of an evenly spaced sample of this many.
MARGINALS_MAX = 500


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser.

    Returns:
        The parser.
    """
    p = _cli.OneLineParser(
        prog=PROG,
        description="Optimise a g2o/TORO/GTSAM graph file (or a generated Manhattan world) "
                    "with graphopt, as g2o_cli does.",
    )
    p.add_argument("input", nargs="?", metavar="INPUT",
                   help="graph file (.g2o, .graph, .txt; .gz/.bz2); omit for a generated "
                        "Manhattan world with known ground truth")
    p.add_argument("-o", "--output", metavar="OUTPUT", help="write the optimised graph (g2o)")
    _cli.add_stopping_options(p)
    p.add_argument("--algorithm", choices=("gn", "lm", "dogleg"), default="lm",
                   help="Gauss-Newton, Levenberg-Marquardt (default) or Powell's dogleg")
    p.add_argument("--lm-schedule", choices=("gtsam", "g2o", "ceres"), default="gtsam",
                   help="LM damping schedule: GTSAM's lambda/10 after a success, x10 after a "
                        "failure (default: converges in 8 iterations on w10000 where g2o's "
                        "rule needs over 100), g2o's or Ceres'")
    _cli.add_solver_option(p)
    p.add_argument("--robust-kernel", metavar="NAME", default=None,
                   help="robust kernel on every edge (huber, cauchy, pseudohuber, tukey, ...)")
    p.add_argument("--robust-delta", type=float, default=1.0, metavar="D",
                   help="kernel width (default 1)")
    p.add_argument("--guess", action="store_true",
                   help="initial estimate by composing edges along a spanning tree from the "
                        "fixed poses (needed for files without vertex lines)")
    p.add_argument("--marginals", action="store_true",
                   help=f"marginal covariances of the poses (all up to {MARGINALS_MAX}, else "
                        "a sample), summarised")
    p.add_argument("--skip-unknown", action="store_true",
                   help="skip lines with unknown tags (counted per tag) instead of failing")
    p.add_argument("--json", metavar="FILE", help="write the summary as one JSON object")
    p.add_argument("--rrd", metavar="FILE", help="rerun recording (.rrd) of the optimisation")
    p.add_argument("--png", metavar="FILE", help="top-down before/after picture (.png)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.add_argument("--poses", type=int, default=1000, metavar="N",
                   help="poses of the generated graph (no INPUT; default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the generated graph (default 0)")
    g2o_online.add_options(p)
    return p


def _check_options(args: argparse.Namespace) -> RobustKernel | None:
    """Value ranges and output paths (before any work); the robust kernel, if one is named."""
    _cli.check_run_options(args, args.robust_delta)
    if args.input is None and args.poses < 2:
        raise _cli.AppError(f"--poses must be >= 2, got {args.poses}")
    _cli.check_outputs({"-o": args.output, "--json": args.json, "--rrd": args.rrd,
                        "--png": args.png}, inputs=[args.input])
    if args.robust_kernel is None:
        return None
    try:
        return make_kernel(args.robust_kernel, args.robust_delta)
    except ValueError as exc:
        raise _cli.AppError(str(exc)) from None


def _load(args: argparse.Namespace) -> tuple[GraphFile, np.ndarray | None, str]:
    """The graph's records, the true poses (generated graph only) and a name for its source."""
    if args.input is None:
        graph, truth = manhattan_world(args.poses, args.seed)
        return graph, truth, f"generated Manhattan world ({args.poses} poses, seed {args.seed})"
    return read_graph(args.input, skip_unknown=args.skip_unknown), None, args.input


def _build(args: argparse.Namespace, graph: GraphFile, kernel: RobustKernel | None
           ) -> SlamGraph:
    """The optimizer with the graph's vertices and edges (one-line errors naming the line)."""
    algorithm: Any = args.algorithm
    if algorithm == "lm":
        algorithm = pose_graph_levenberg(args.lm_schedule)
    options: dict[str, Any] = {"algorithm": algorithm, "solver": args.solver,
                               "verbose": not args.quiet, "stream": sys.stderr,
                               "stopping": _cli.stopping_config(args)}
    opt = SparseOptimizer(**options)
    try:
        slam = build_graph(graph, opt, guess=args.guess)
    except GraphError as exc:
        raise _cli.AppError(str(exc).replace("build with guess=True", "use --guess")) from None
    if kernel is not None:
        for group in opt.edge_groups():  # every edge the builder added
            group.set_kernel(slice(None), kernel)
    return slam


def _marginals(slam: SlamGraph, view: GraphView) -> dict[str, Any]:
    """Marginal covariances of the free poses (or a sample of them), summarised."""
    t0 = time.perf_counter()
    free = view.pose_ids[~np.isin(view.pose_ids, list(slam.fixed))]
    pick = free
    if len(free) > MARGINALS_MAX:
        pick = free[np.unique(np.linspace(0, len(free) - 1, MARGINALS_MAX).round().astype(int))]
    try:
        covs = slam.optimizer.compute_marginals(pick.tolist())
    except NotPositiveDefiniteError as exc:
        raise _cli.AppError(f"--marginals: {exc}") from None
    cov = np.stack([covs[int(v)] for v in pick]) if len(pick) else np.zeros((0, 3, 3))
    k = 3 if view.dimension == 3 else 2
    position = np.sqrt(np.linalg.eigvalsh(cov[:, :k, :k])[:, -1].clip(0))
    if view.dimension == 3:  # δq is the quaternion's vector part: half the rotation angle
        rotation = 2.0 * np.sqrt(np.linalg.eigvalsh(cov[:, 3:, 3:])[:, -1].clip(0))
    else:
        rotation = np.sqrt(cov[:, 2, 2].clip(0))
    worst = int(np.argmax(position)) if len(pick) else 0
    return {
        "poses": len(pick),
        "free_poses": len(free),
        "sampled": len(pick) < len(free),
        "max_position_sigma": float(position.max()) if len(pick) else None,
        "max_position_sigma_vertex": int(pick[worst]) if len(pick) else None,
        "median_position_sigma": float(np.median(position)) if len(pick) else None,
        "max_rotation_sigma_rad": float(rotation.max()) if len(pick) else None,
        "seconds": time.perf_counter() - t0,
    }


def _truth_errors(view: GraphView, truth: np.ndarray) -> dict[str, Any]:
    """Trajectory error against the truth (first pose aligned, as ``FIX 0`` sets it)."""
    est = np.column_stack([view.poses()[:, :2], view.headings()])
    return trajectory_error(est, truth, align="first")


def _start_recording(path: str, opt: SparseOptimizer, view: GraphView, chi2: float,
                     truth: np.ndarray | None) -> SlamRecording:
    """Open the recording, log the start and (timed, see ``_cli.RunRecording``) every
    iteration."""
    recording = SlamRecording(path, PROG, view)
    xyz = None if truth is None else np.column_stack([truth[:, :2], np.zeros(len(truth))])
    with recording.timed():
        recording.log_state(0, chi2, truth=xyz)

    def on_iteration(o: SparseOptimizer, info: Any) -> None:
        with recording.timed():  # the recording's work is kept out of the reported seconds
            recording.log_state(info.iteration + 1, info.chi2, seconds=info.seconds)

    opt.add_callback("post_iteration", on_iteration)
    return recording


def _g2o_chi2(opt: SparseOptimizer) -> float:
    """g2o's ``chi2()`` at the current estimates: ``Σ e'Ωe`` without kernels."""
    opt.compute_active_errors()
    return float(opt.chi2())


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text, flush=True)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Load, build, optimise and report, as configured by parsed options.

    Args:
        args: Options from :func:`build_parser`.

    Returns:
        The summary dictionary (also written by ``--json``).
    """
    kernel = _check_options(args)
    t0 = time.perf_counter()
    graph, truth, source = _load(args)  # GraphFormatError is reported by main()
    t1 = time.perf_counter()
    slam = _build(args, graph, kernel)
    opt, view = slam.optimizer, graph_view(slam)
    t2 = time.perf_counter()
    solver, solver_text, setup_notes = _cli.initialize(opt, args.solver)
    t3 = time.perf_counter()
    notes = list(dict.fromkeys([*graph.notes, *slam.notes, *setup_notes]))
    for note in notes:
        if not note.startswith("skipped lines with unknown tags"):  # the summary counts them
            _say(args, f"{PROG}: note: {note}")
    initial_chi2 = _g2o_chi2(opt)
    before = (view.poses(), view.landmarks())
    truth0 = _truth_errors(view, truth) if truth is not None else None

    recording = None
    if args.rrd and not args.online:
        recording = _start_recording(args.rrd, opt, view, opt.active_robust_chi2(), truth)
    try:
        res = (g2o_online.run_online(args, slam, view, PROG, kernel, opt.active_robust_chi2())
               if args.online else _cli.optimize_recorded(opt, args.iterations, recording))
    except FloatingPointError as exc:
        raise _cli.AppError(f"{source}: {exc}") from None
    if not all(np.isfinite(a).all() for a in (view.poses(), view.landmarks())):
        if recording is not None:
            recording.abort()
        raise _cli.AppError("the optimisation produced non-finite estimates")
    seconds = res.seconds - (recording.seconds if recording is not None else 0.0)
    final_chi2 = _g2o_chi2(opt)

    summary: dict[str, Any] = {
        "input": source,
        "vertices": int(sum(slam.vertex_counts.values())),
        "edges": int(sum(slam.edge_counts.values())),
        "vertex_types": dict(slam.vertex_counts),
        "edge_types": dict(slam.edge_counts),
        "loop_closures": len(view.closures),
        "fixed": {str(v): why for v, why in slam.fixed.items()},
        "guessed": len(slam.guessed),
        "skipped": dict(graph.skipped),
        "notes": notes,
        "algorithm": args.algorithm,
        "lm_schedule": args.lm_schedule if args.algorithm == "lm" else None,
        "solver": solver,
        "solver_requested": args.solver,
        "robust_kernel": None if kernel is None else f"{args.robust_kernel}:{args.robust_delta:g}",
        "initial_chi2": initial_chi2,
        "final_chi2": final_chi2,
        "initial_robust_chi2": float(res.initial_chi2),
        "final_robust_chi2": float(res.final_chi2),
        "iterations": int(res.iterations),
        "seconds": float(seconds),
        "seconds_per_iteration": float(seconds / res.iterations) if res.iterations else 0.0,
        "read_seconds": t1 - t0,
        "build_seconds": t2 - t1,
        "setup_seconds": t3 - t2,
        "stop_reason": str(res.stop_reason),
        "ground_truth": None if truth is None else {
            "initial": truth0, "final": _truth_errors(view, truth)},
        "marginals": _marginals(slam, view) if args.marginals else None,
        "output": args.output,
        "equiv": len(slam.equiv),
        "online": getattr(res, "online", None),
    }
    if args.output:
        write_g2o(args.output, graph_file(slam), drop_equiv=True)
    if args.png:
        units = "grid units" if truth is not None else "file units"
        tail = f"{res.iterations} iterations" if res.iterations != 1 else "1 iteration"
        xyz = None if truth is None else np.column_stack([truth[:, :2], np.zeros(len(truth))])
        write_png(args.png, view, before, (view.poses(), view.landmarks()), truth=xyz,
                  units=units, titles=(f"before: chi2 {initial_chi2:.6g}",
                                       f"after {tail}: chi2 {final_chi2:.6g}"))
    if recording is not None:
        recording.finish()  # after _g2o_chi2: the last evaluation is at the final estimate
        recording.log_summary(recording_markdown(PROG, summary, recording, solver_text))
        recording.close()
    if args.json:
        _cli.write_json(args.json, summary)
    _say(args, format_summary(summary, solver_text))
    return summary


def format_summary(s: dict[str, Any], solver_text: str | None = None) -> str:
    """Human-readable summary lines.

    Args:
        s: The summary dictionary from :func:`run`.
        solver_text: How to name the linear solver (``s["solver"]`` if None).
    """
    def counts(d: dict[str, int]) -> str:
        return ", ".join(f"{t} {n}" for t, n in d.items())

    fixed = ", ".join(f"{v} ({why})" for v, why in s["fixed"].items()) or "none"
    lines = [
        f"{PROG}: {s['input']}",
        f"  vertices {s['vertices']}: {counts(s['vertex_types'])}; fixed: {fixed}"
        + (f"; {s['guessed']} estimated by --guess" if s["guessed"] else ""),
        f"  edges {s['edges']}: {counts(s['edge_types'])}; {s['loop_closures']} loop closures",
    ]
    if s["skipped"]:
        lines.append(f"  skipped lines with unknown tags: {counts(s['skipped'])}")
    lines += [
        f"  algorithm {s['algorithm']}, linear solver {solver_text or s['solver']}, "
        f"robust kernel {s['robust_kernel'] or 'none'}",
        f"  initial chi2 {s['initial_chi2']:.6f}   final chi2 {s['final_chi2']:.6f}"
        "   (g2o's chi2: sum e'Omega e"
        + (f"; with the kernel {s['initial_robust_chi2']:.6f} -> {s['final_robust_chi2']:.6f})"
           if s["robust_kernel"] else ")"),
        # An online run without a final batch runs no iteration: no per-iteration figure.
        (f"  iterations {s['iterations']}, stop: {s['stop_reason']}; {s['seconds']:.3f} s, "
         f"{s['seconds_per_iteration']:.4f} s/iteration; " if s["iterations"] else
         f"  no batch iteration, stop: {s['stop_reason']}; {s['seconds']:.3f} s; ")
        + f"read {s['read_seconds']:.3f} s, build {s['build_seconds']:.3f} s, "
        f"setup {s['setup_seconds']:.3f} s",
    ]
    if s["online"]:
        o = s["online"]
        lines.append(f"  online: {o['steps']} steps, {o['total_seconds']:.3f} s; step median "
                     f"{o['median_step_seconds'] * 1e3:.3f} ms, p95 "
                     f"{o['p95_step_seconds'] * 1e3:.3f} ms, max {o['max_step_seconds'] * 1e3:.1f}"
                     f" ms; {o['batch_steps']} batch steps, {o['fallbacks']} fallbacks")
    if s["ground_truth"] is not None:
        g0, g = s["ground_truth"]["initial"], s["ground_truth"]["final"]
        lines.append(
            f"  vs ground truth (first pose aligned): position RMS {g0['rms_position']:.4g} -> "
            f"{g['rms_position']:.4g} (max {g0['max_position']:.4g} -> {g['max_position']:.4g}),"
            f" heading RMS {g0['rms_heading']:.4g} -> {g['rms_heading']:.4g} rad")
    m = s["marginals"]
    if m is not None and m["poses"]:
        lines.append(
            f"  marginals of {m['poses']} of {m['free_poses']} free poses"
            + (" (evenly spaced sample)" if m["sampled"] else "")
            + f": largest position sigma {m['max_position_sigma']:.4g} (vertex "
            f"{m['max_position_sigma_vertex']}), median {m['median_position_sigma']:.4g}, "
            f"largest rotation sigma {m['max_rotation_sigma_rad']:.4g} rad; "
            f"{m['seconds']:.3f} s")
    if s["output"]:
        lines.append(f"  wrote {s['output']}" + (
            f" (without the {s['equiv']} EQUIV pairs: g2o has no such line)" if s["equiv"]
            else ""))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``graphopt-g2o`` and ``python -m graphopt.apps.g2o``.

    Args:
        argv: Command-line arguments; None reads ``sys.argv[1:]``.

    Returns:
        0, or 1 after a one-line error (file and line for a bad input), 2 for a bad option.
    """
    return _cli.run_main(PROG, build_parser(), run, argv, user_errors=(GraphFormatError,))


if __name__ == "__main__":
    sys.exit(main())
