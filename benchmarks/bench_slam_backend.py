"""ORB-SLAM's four back-end optimisations, graphopt against g2opy in the same run.

Workloads (``benchmarks/slam_backend_scenes.py``: synthetic, known truth, 10 % outliers):
motion-only BA (``PoseOptimization``) at 100, 500 and 2,000 matches, mono and stereo; local BA
(``LocalBundleAdjustment``) with 10 free + 10 fixed keyframes, 1,000 points, 5,000
observations and 20 + 30, 5,000, 25,000; ``OptimizeSim3`` with 100 matches; the essential
graph (``OptimizeEssentialGraph``) of 200 and 1,000 keyframes.

* **graphopt** runs the code of ``docs/slam_backend.md`` as written (its Python blocks are
  executed here): Levenberg–Marquardt, dense Cholesky for the pose and Sim3 problems, the
  Schur complement with ``auto`` (dense for these windows) for local BA, CHOLMOD for the
  essential graph; graphopt's default stopping tests (which may end a run before its
  iteration cap).
* **g2opy** 2.3.0 runs the same procedures the way ORB-SLAM2 writes them: one Python object
  per vertex and edge, per-edge loops for the outlier checks, ORB-SLAM's block and linear
  solvers. Where the bindings lack something, the closest equal computation is used and
  listed in the output: the stereo only-pose edge (its ``Xw``/``bf`` are not exposed) is
  ``EdgeStereoSE3ProjectXYZ`` on a fixed point; ``setRobustKernel(0)`` is a Huber kernel of
  δ = 1e12 (the identity below chi2 1e24); the Sim3 vertex's intrinsics are not exposed (the
  projections get normalised measurements and ``f²``-scaled information, the same chi2);
  ``setUserLambdaInit(1e-16)`` is not exposed (g2o's default λ₀ on the essential graph).

Timing: ``build`` from the optimiser's creation to its first ``initialize_optimization``,
``optimise`` from there to the end of the procedure (every round, the outlier checks and
edits in between); one thread each side (``OMP_NUM_THREADS=1`` etc. before numpy loads);
graphopt and g2opy runs interleaved, medians of ``--runs`` after ``--warmup`` untimed runs of
each side (a SLAM system calls these every frame; Python's first calls of a procedure also pay
its interpreter's specialisation). The quality columns come from the last run: the final
active chi2 (the edges of the last ``optimize``, at the final estimate, no kernel), inliers,
the inlier sets' disagreement, and the error against the truth, computed after the clock stops
on both sides (graphopt's procedures return the chi2, which costs it a masked sum per round).

Usage::

    .venv/bin/python -P benchmarks/bench_slam_backend.py [--runs 5] [--warmup 1] [--cpu]
        [--only motion,...] [--floor]

``--floor`` adds, under each mono motion-only row, ``motion_only_floor.py``'s framework-free
numpy loop timed in the same turns (build + optimise in one figure; its ratio to g2opy).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import motion_only_floor as floor_side  # noqa: E402
import slam_backend_g2o as g2o_side  # noqa: E402
import slam_backend_scenes as scenes  # noqa: E402

import graphopt  # noqa: E402

DOC = HERE.parent / "docs" / "slam_backend.md"


def graphopt_procedures(stamp: Callable[[], None]) -> dict[str, Any]:
    """The doc's procedure blocks, executed with a ``SparseOptimizer`` whose first
    ``initialize_optimization`` calls ``stamp`` (the end of the build).

    Raises:
        SystemExit: graphopt has no editing API yet (``add_edges`` returns no ``EdgeSet``).
    """
    if not hasattr(graphopt.SparseOptimizer, "remove_vertices"):
        raise SystemExit("bench_slam_backend: this graphopt has no editing API (EdgeSet, edge "
                         "levels; issue 22's edit22 branch): only g2opy could run. Merge it "
                         "first, or run with --g2o-only.")
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    ns: dict[str, Any] = {"__name__": "slam_backend_doc"}
    for i, block in enumerate(b for b in blocks if "slam_backend_scenes" not in b):
        exec(compile(block, f"{DOC.name}[procedure block {i + 1}]", "exec"), ns)  # noqa: S102

    class TimedOptimizer(graphopt.SparseOptimizer):
        def initialize_optimization(self, *args: Any, **kwargs: Any) -> bool:
            stamp()
            return super().initialize_optimization(*args, **kwargs)

    ns["SparseOptimizer"] = TimedOptimizer
    return ns


class Clock:
    """Build and optimise times of one call: ``stamp`` marks the end of the build (the first
    call counts).

    Args:
        cpu: Measure process CPU time (``time.process_time``) instead of wall time: on a
            shared machine the other load shows much less in it; with one thread a side it is
            the wall time of an idle machine.
    """

    def __init__(self, cpu: bool = False) -> None:
        self.now = time.process_time if cpu else time.perf_counter
        self.t0 = self.t_build = 0.0

    def start(self) -> None:
        self.t0, self.t_build = self.now(), 0.0

    def stamp(self) -> None:
        if not self.t_build:
            self.t_build = self.now()

    def stop(self) -> tuple[float, float]:
        t = self.now()
        return self.t_build - self.t0, t - self.t_build


def _workloads(only: set[str]) -> list[tuple[str, str, Callable[[], Any]]]:
    out: list[tuple[str, str, Callable[[], Any]]] = []
    if "motion" in only:
        for stereo in (False, True):
            for m in (100, 500, 2000):
                out.append(("motion", f"motion-only BA, {'stereo' if stereo else 'mono'}, "
                            f"{m} matches", lambda m=m, s=stereo: scenes.motion_only(m, s)))
    if "local" in only:
        out.append(("local", "local BA 10+10 kf, 1,000 pts, 5,000 obs.",
                    lambda: scenes.local_ba(10, 10, 1000, 5000)))
        out.append(("local", "local BA 20+30 kf, 5,000 pts, 25,000 obs.",
                    lambda: scenes.local_ba(20, 30, 5000, 25000)))
    if "sim3" in only:
        out.append(("sim3", "OptimizeSim3, 100 matches", lambda: scenes.sim3(100)))
    if "essential" in only:
        for n in (200, 1000):
            out.append(("essential", f"essential graph, {n} keyframes",
                        lambda n=n: scenes.essential_graph(n)))
    return out


def _run_graphopt(kind: str, s: Any, ns: dict[str, Any]) -> tuple[Any, ...]:
    """One graphopt run of the doc's procedure: its outputs (the report is made from them after
    the clock stops, as g2opy's in :func:`_run_g2o`)."""
    if kind == "motion":
        cam = scenes.STEREO if s.z.shape[1] == 3 else scenes.CAM
        return ns["pose_optimization"](s.T_init, s.Xw, s.z, s.inv_sigma2, cam)
    if kind == "local":
        return ns["local_bundle_adjustment"](s.T_init, s.fixed, s.X_init, s.kf, s.pt, s.z,
                                             s.inv_sigma2, scenes.CAM)
    if kind == "sim3":
        return ns["optimize_sim3"](s.S12_init, s.P1c, s.P2c, s.z1, s.z2, s.inv_sigma2_1,
                                   s.inv_sigma2_2, scenes.CAM, scenes.CAM)
    return ns["optimize_essential_graph"](s.S_init, s.ij, s.S_ji, s.loop_kf)


def _graphopt_report(kind: str, s: Any, out: tuple[Any, ...]) -> dict[str, Any]:
    """The report's numbers of a graphopt run's outputs ``out``."""
    if kind == "motion":
        T, inl, chi2 = out
        return {"inliers": inl, "chi2": chi2, "error": _pose_err(T, s.T_true)}
    if kind == "local":
        T, X, inl, chi2 = out
        return {"inliers": inl, "chi2": chi2, "error": _window_err(T, X, s)}
    if kind == "sim3":
        S, inl, chi2 = out
        return {"inliers": inl, "chi2": chi2, "error": _sim3_err(S, s.S12_true)}
    S, chi2 = out
    return {"inliers": None, "chi2": chi2, "error": _centre_err(S, s.S_true)}


def _run_g2o(kind: str, s: Any, clock: Clock) -> tuple[tuple[float, float], dict[str, Any]]:
    """One timed g2opy run; the report's numbers are computed after the clock stops."""
    clock.start()
    if kind == "motion":
        T, inl, report = g2o_side.pose_optimization(s.T_init, s.Xw, s.z, s.inv_sigma2,
                                                    clock.stamp)
        times = clock.stop()
        return times, {"inliers": inl, "chi2": report(), "error": _pose_err(T, s.T_true)}
    if kind == "local":
        T, X, _, report = g2o_side.local_bundle_adjustment(
            s.T_init, s.fixed, s.X_init, s.kf, s.pt, s.z, s.inv_sigma2, clock.stamp)
        times = clock.stop()
        chi2, inl = report()
        return times, {"inliers": inl, "chi2": chi2, "error": _window_err(T, X, s)}
    if kind == "sim3":
        S, inl, report = g2o_side.optimize_sim3(s.S12_init, s.P1c, s.P2c, s.z1, s.z2,
                                                s.inv_sigma2_1, s.inv_sigma2_2, clock.stamp)
        times = clock.stop()
        return times, {"inliers": inl, "chi2": report(), "error": _sim3_err(S, s.S12_true)}
    S, report = g2o_side.optimize_essential_graph(s.S_init, s.ij, s.S_ji, s.loop_kf,
                                                  clock.stamp)
    times = clock.stop()
    return times, {"inliers": None, "chi2": report(), "error": _centre_err(S, s.S_true)}


def _pose_err(T: np.ndarray, T_true: np.ndarray) -> str:
    rot, pos = scenes.pose_error(T, T_true)
    return f"{rot:.3f}° {100 * pos:.2f} cm"


def _window_err(T: np.ndarray, X: np.ndarray, s: Any) -> str:
    free = ~s.fixed
    c = np.linalg.norm(scenes.centres(T[free]) - scenes.centres(s.T_true[free]), axis=1)
    p = np.linalg.norm(X - s.X_true, axis=1)
    return f"kf {100 * np.sqrt((c**2).mean()):.2f} cm, pts {100 * np.median(p):.1f} cm"


def _sim3_err(S: np.ndarray, S_true: np.ndarray) -> str:
    from graphopt.types.sim3_lie import sim3_parts

    R, t, s = sim3_parts(S[None])
    Rt, tt, st = sim3_parts(S_true[None])
    rot = np.degrees(np.linalg.norm(graphopt.lie.so3_log(R @ np.swapaxes(Rt, 1, 2))))
    return f"{rot:.3f}° {100 * np.linalg.norm(t - tt):.2f} cm, s {100 * (s[0] / st[0] - 1):+.2f} %"


def _centre_err(S: np.ndarray, S_true: np.ndarray) -> str:
    d = scenes.centres(S) - scenes.centres(S_true)
    return f"centres {100 * np.sqrt((d**2).sum(1).mean()):.1f} cm RMS"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1,
                    help="untimed runs of each side per workload first (a SLAM system runs "
                         "these every frame: the steady state, not a process's first call)")
    ap.add_argument("--only", default="motion,local,sim3,essential")
    ap.add_argument("--g2o-only", action="store_true", help="time g2opy alone")
    ap.add_argument("--cpu", action="store_true", help="CPU time instead of wall time")
    ap.add_argument("--floor", action="store_true",
                    help="also time motion_only_floor.py's bare numpy loop (mono motion-only)")
    args = ap.parse_args()
    clock = Clock(cpu=args.cpu)
    ns = None if args.g2o_only else graphopt_procedures(clock.stamp)
    print(f"graphopt {graphopt.__version__} vs g2opy 2.3.0; one thread; medians of {args.runs} "
          f"interleaved runs; {'CPU' if args.cpu else 'wall'} times in ms")
    print("| workload | g2opy build + optimise | graphopt build + optimise | ratio | "
          "final active chi2 g2opy / graphopt | inliers g2opy / graphopt (true) [differ] | "
          "error g2opy / graphopt |")
    print("|---|---|---|---|---|---|---|")
    for kind, name, make in _workloads(set(args.only.split(","))):
        s = make()
        times: dict[str, list[tuple[float, float]]] = {"g2o": [], "go": []}
        res: dict[str, dict[str, Any]] = {}
        floor = args.floor and kind == "motion" and s.z.shape[1] == 2
        for _ in range(args.warmup):  # both sides alike, nothing recorded
            _run_g2o(kind, s, clock)
            if ns is not None:
                _run_graphopt(kind, s, ns)
        for _ in range(args.runs):
            t, res["g2o"] = _run_g2o(kind, s, clock)
            times["g2o"].append(t)
            if floor:  # the framework-free numpy loop, timed the same way, same turn
                clock.start()
                clock.stamp()
                floor_side.bare(s.T_init, s.Xw, s.z, s.inv_sigma2, scenes.CAM, [0])
                times.setdefault("bare", []).append(clock.stop())
            if ns is not None:
                clock.start()
                out = _run_graphopt(kind, s, ns)
                times["go"].append(clock.stop())
                res["go"] = _graphopt_report(kind, s, out)
        print(_row(name, s, times, res))
        if floor:
            bare, g2o = _ms(times["bare"])[2], _ms(times["g2o"])[2]
            print(f"|   bare numpy (motion_only_floor.py), the floor | | {bare:.2f} | "
                  f"{bare / g2o:.2f} | | | |")
        sys.stdout.flush()


def _ms(ts: list[tuple[float, float]]) -> tuple[float, float, float]:
    a = np.array(ts) * 1e3
    return float(np.median(a[:, 0])), float(np.median(a[:, 1])), float(np.median(a.sum(1)))


def _row(name: str, s: Any, times: dict[str, list], res: dict[str, dict[str, Any]]) -> str:
    gb, go_, gt = _ms(times["g2o"])
    cols = [name, f"{gb:.2f} + {go_:.2f}"]
    rg = res["g2o"]
    if "go" not in res:
        return "| " + " | ".join(cols + ["—", "—", f"{rg['chi2']:.6g}", "—", rg["error"]]) + " |"
    pb, po, pt = _ms(times["go"])
    rp = res["go"]
    cols += [f"{pb:.2f} + {po:.2f}", f"{pt / gt:.2f}", f"{rg['chi2']:.6g} / {rp['chi2']:.6g}"]
    if rg["inliers"] is not None:
        true = int((~s.outlier).sum())
        differ = int((rg["inliers"] != rp["inliers"]).sum())
        cols.append(f"{rg['inliers'].sum()} / {rp['inliers'].sum()} ({true}) [{differ}]")
    else:
        cols.append("—")
    cols.append(f"{rg['error']} / {rp['error']}")
    return "| " + " | ".join(cols) + " |"


if __name__ == "__main__":
    main()
