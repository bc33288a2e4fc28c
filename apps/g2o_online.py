"""``graphopt-g2o --online``: replay a graph file pose by pose with the incremental optimizer.

The protocol is :mod:`graphopt.types.slam_online`'s (poses in id order, each started from its
odometry on the current estimate, the first pose fixed); every step is one
:meth:`IncrementalOptimizer.update <graphopt.online.IncrementalOptimizer.update>`. The final
estimate is the one after the last step (``--online-final-batch`` polishes it with the batch
optimiser). ``--rrd`` records the trajectory growing on a ``step`` timeline (every step's time
as ``metrics/step_seconds``, the trajectory at up to :data:`TRAJECTORY_FRAMES` steps).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from graphopt import GraphError, SparseOptimizer
from graphopt.apps import _cli
from graphopt.apps.g2o_report import GraphView, SlamRecording
from graphopt.robust_kernel import RobustKernel
from graphopt.types.slam_graph import SlamGraph
from graphopt.types.slam_online import replay, replay_schedule

#: The trajectory is logged at most this many times (every step's time is logged).
TRAJECTORY_FRAMES = 200


def add_options(p: argparse.ArgumentParser) -> None:
    """Add ``--online`` and ``--online-final-batch``.

    Args:
        p: The app's parser.
    """
    p.add_argument("--online", action="store_true",
                   help="replay the graph pose by pose (poses in id order, each from its "
                        "odometry on the current estimate) with the incremental optimizer")
    p.add_argument("--online-final-batch", action="store_true",
                   help="with --online: polish the last step's estimate with the batch "
                        "optimiser (-i iterations)")


@dataclass
class OnlineResult:
    """What the app reports of an online run, in the fields of an optimisation result.

    Args:
        initial_chi2: Robust chi2 of the file's estimate.
        final_chi2: Robust chi2 at the end.
        iterations: Iterations of the final batch polish (0 without).
        seconds: Seconds of all steps (and of the polish).
        stop_reason: ``"online"``, or the polish's stop reason.
        online: The ``online`` JSON object.
    """

    initial_chi2: float
    final_chi2: float
    iterations: int = 0
    seconds: float = 0.0
    stop_reason: str = "online"
    online: dict[str, Any] = field(default_factory=dict)


def _copy_estimates(src: SparseOptimizer, dst: SparseOptimizer) -> None:
    """Copy every vertex estimate of ``src`` into the vertex of the same id in ``dst``."""
    for vtype, store in src.graph.stores.items():
        target = dst.graph.stores[vtype]
        order = np.argsort(target.ids)
        rows = order[np.searchsorted(target.ids, store.ids, sorter=order)]
        est = target.estimates.copy()
        est[rows] = store.estimates
        target.estimates = est


def _step_recorder(path: str, prog: str, view: GraphView, n: int) -> tuple[Any, Any]:
    """A recording and the callback that logs a step into it (on the ``step`` timeline)."""
    recording = SlamRecording(path, prog, view, timeline="step")
    every = max(1, n // TRAJECTORY_FRAMES)

    def log(k: int, seconds: float, poses: np.ndarray) -> None:
        with recording.timed() as rec:
            rec.set_step(k)
            rec.log_scalar("step_seconds", seconds)
            if k % every == 0 or k == n - 1:
                xyz = poses[:, :3, 3] if poses.ndim == 3 else np.column_stack(
                    [poses[:, :2], np.zeros(len(poses))])
                rec.log_trajectory(xyz, entity="world/trajectory")

    return recording, log


def run_online(args: argparse.Namespace, slam: SlamGraph, view: GraphView, prog: str,
               kernel: RobustKernel | None, initial_chi2: float) -> OnlineResult:
    """Replay the graph online; leave the final estimates in ``slam.optimizer``.

    Args:
        args: The app's options (``quiet``, ``rrd``, ``online_final_batch``, ``iterations``).
        slam: The built graph (its estimates: the fallback starts; then the final ones).
        view: The graph's view (for the recording).
        prog: The app's name.
        kernel: The robust kernel of every edge, or ``None``.
        initial_chi2: Robust chi2 of the file's estimate.

    Returns:
        The :class:`OnlineResult`.
    """
    try:
        schedule = replay_schedule(slam)
    except GraphError as exc:
        raise _cli.AppError(str(exc)) from None
    n = schedule.steps
    recording, log = (_step_recorder(args.rrd, prog, view, n) if args.rrd else (None, None))
    every = max(1, n // 20)
    t0 = time.perf_counter()
    store: list[Any] = []

    def on_step(k: int, report: Any, seconds: float, opt: SparseOptimizer) -> None:
        if log is not None:
            if not store:
                store.append(opt.graph.stores[schedule.pose_type])
            log(k, seconds, store[0].estimates)
        if not args.quiet and ((k + 1) % every == 0 or k == n - 1):
            print(f"{prog}: online step {k + 1}/{n}  {time.perf_counter() - t0:.1f} s  "
                  f"last step {seconds * 1e3:.2f} ms ({report.factor})", file=sys.stderr,
                  flush=True)

    try:
        out = replay(schedule, on_step=on_step, kernel=kernel)
    except BaseException:
        if recording is not None:
            recording.abort()
        raise
    if recording is not None:
        recording.close()
    _copy_estimates(out.optimizer, slam.optimizer)
    reports = out.incremental.reports
    steps = out.steps
    result = OnlineResult(initial_chi2, 0.0, seconds=float(steps.sum()), online={
        "steps": int(n),
        "total_seconds": float(steps.sum()),
        "median_step_seconds": float(np.median(steps)),
        "p95_step_seconds": float(np.percentile(steps, 95)),
        "max_step_seconds": float(steps.max()),
        "solves": int(sum(r.solved for r in reports)),
        "batch_steps": int(sum(r.factor == "rebuilt" for r in reports)),
        "fallbacks": int(sum(r.fallback for r in reports)),
        "final_batch": bool(args.online_final_batch),
    })
    if args.online_final_batch:
        res = _cli.optimize_recorded(slam.optimizer, args.iterations, None)
        result.iterations, result.stop_reason = int(res.iterations), str(res.stop_reason)
        result.seconds += float(res.seconds)
    result.final_chi2 = float(slam.optimizer.active_robust_chi2()
                              if args.online_final_batch else _robust_chi2(slam.optimizer))
    return result


def _robust_chi2(opt: SparseOptimizer) -> float:
    opt.compute_active_errors()
    return float(opt.active_robust_chi2())
