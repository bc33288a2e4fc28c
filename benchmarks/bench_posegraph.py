"""Benchmark: graphopt vs g2o (g2opy) vs GTSAM on pose graphs — seconds to converge.

For each graph, all solvers start from the same estimate: graphopt reads the file
(``graphopt.io.g2o.read_graph``) and builds it (``graphopt.types.slam_graph.build_graph``, with
the spanning-tree guess where asked), and that start is written as a g2o file
(``write_g2o``) which g2o and GTSAM load. Per solver and configuration it records every
iteration's chi2 (g2o's definition, ``Σ e'Ωe``) and wall time, then reports

* **s to converge**: time from the loaded graph until the first iteration whose chi2 is within
  1e-6 (relative) of the best final chi2 any solver reached on that graph — the answer a user
  waits for; ``-`` when never reached. It includes each solver's set-up (column **set-up**):
  graphopt's ``initialize_optimization`` (structure, scatter maps, symbolic factorisation) and
  the work ``optimize`` does before its first iteration; g2o's ``initialize_optimization``
  (its structure and symbolic analysis run inside its first iteration, whose time counts
  anyway); GTSAM's optimizer constructor. Loading the file is not counted on either side;
* **s / iteration**: the median iteration time.

g2o runs with its sparse Cholesky (``LinearSolverEigen``, the best it ships for these sizes)
under Gauss–Newton and Levenberg–Marquardt; its per-iteration times and chi2 come from its own
iteration lines (``set_verbose``), read from the C++ standard error. GTSAM runs
``LevenbergMarquardtOptimizer`` and ``GaussNewtonOptimizer`` one ``iterate()`` at a time, on
the 2-D pose-only graphs: its ``readG2o`` drops ``EDGE_SE2_XY`` landmarks, its ``EDGE_SE3:QUAT``
information applies to full angles (not g2o's half-angles), and its ``Pose2`` error is the
SE(2) logarithm rather than g2o's ``(x, y, θ)``, so its minimum differs slightly: GTSAM's rows
are timed to *its own* converged chi2 (marked ``own``), not the common target. One thread
everywhere (set before numpy loads); every configuration runs once as a warm-up, then
``--repeats`` rounds run every configuration once each (interleaved, so that a slow minute of
the machine hits every solver alike); the table shows medians.

Usage::

    python -P benchmarks/bench_posegraph.py [--repeats 3] [--iterations 30] [--skip-gtsam]

Peers come from the ``bench`` extra (``g2opy==2.3.0``, ``gtsam==4.3.0``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from graphopt import SparseOptimizer  # noqa: E402
from graphopt.io.g2o import read_graph, write_g2o  # noqa: E402
from graphopt.types.slam_graph import build_graph, graph_file, pose_graph_levenberg  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph"
#: (file, build with the spanning-tree guess)
GRAPHS = [("w10000.graph", False), ("sphere_smallnoise.graph", True),
          ("victoriaPark_reduced_1k.g2o", True), ("pose2example.txt", False),
          ("pose3example.txt", False)]
REL = 1e-6
Trace = list[tuple[float, float]]  # (seconds since the start, chi2), set-up then each iteration


def graphopt_run(path: Path, guess: bool, algorithm: object, iterations: int) -> Trace:
    """One graphopt run; its trace (the first entry is the set-up, chi2 ``inf``)."""
    opt = SparseOptimizer(algorithm, "auto")
    build_graph(read_graph(path), opt, guess=guess)
    t0 = time.perf_counter()
    opt.initialize_optimization()
    setup = time.perf_counter() - t0
    res = opt.optimize(iterations)
    # What optimize() spends outside its iterations (the initial chi2, bookkeeping) counts as
    # set-up: an upper bound on what precedes the first iteration.
    setup += res.seconds - sum(r.seconds for r in res.info)
    out, cum = [(setup, float("inf"))], setup
    for r in res.info:
        cum += r.seconds
        if not r.failed:
            out.append((cum, r.chi2))
    return out


def write_start(path: Path, guess: bool, folder: Path) -> Path:
    """The graph with graphopt's start estimate, as a g2o file g2o and GTSAM can read."""
    opt = SparseOptimizer()
    slam = build_graph(read_graph(path), opt, guess=guess)
    dst = folder / (path.name + ".start.g2o")
    write_g2o(dst, graph_file(slam), drop_equiv=True)
    return dst


_LINE = re.compile(rb"iteration= *(\d+)\s+chi2= *(\S+)\s+time= *(\S+)")


def g2o_run(start: Path, algorithm: str, iterations: int) -> Trace:
    """One g2o run (GN or LM, Eigen's sparse Cholesky), from its own iteration lines."""
    import g2opy as g2o

    opt = g2o.SparseOptimizer()
    solver = g2o.BlockSolverX(g2o.LinearSolverEigenX())
    algo = (g2o.OptimizationAlgorithmLevenberg if algorithm == "lm"
            else g2o.OptimizationAlgorithmGaussNewton)(solver)
    opt.set_algorithm(algo)
    if not opt.load(str(start)):
        raise SystemExit(f"g2o could not load {start}")
    opt.vertex(min(v for v in opt.vertices())).set_fixed(True)
    t0 = time.perf_counter()
    opt.initialize_optimization()
    setup = time.perf_counter() - t0
    opt.set_verbose(True)
    with tempfile.TemporaryFile() as err:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(err.fileno(), 2)
        try:
            opt.optimize(iterations)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        err.seek(0)
        lines = err.read()
    out, cum = [(setup, float("inf"))], setup
    for _, chi2, dt in _LINE.findall(lines):
        cum += float(dt)
        out.append((cum, float(chi2)))
    return out


def gtsam_run(start: Path, algorithm: str, iterations: int) -> Trace:
    """One GTSAM run, one ``iterate()`` at a time (2-D only; chi2 = 2 × GTSAM's error)."""
    import gtsam

    graph, initial = gtsam.readG2o(str(start), False)
    key = min(initial.keys())
    graph.add(gtsam.PriorFactorPose2(key, initial.atPose2(key),
                                     gtsam.noiseModel.Constrained.All(3)))
    t0 = time.perf_counter()
    if algorithm == "lm":
        params = gtsam.LevenbergMarquardtParams()
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    else:
        opt = gtsam.GaussNewtonOptimizer(graph, initial, gtsam.GaussNewtonParams())
    cum = time.perf_counter() - t0
    out = [(cum, float("inf"))]
    for _ in range(iterations):
        t0 = time.perf_counter()
        opt.iterate()
        cum += time.perf_counter() - t0
        out.append((cum, 2.0 * graph.error(opt.values())))
    return out


def summarise(trace: Trace, target: float) -> tuple[float | None, float, float, int]:
    """(seconds to reach the target, set-up seconds, median s/iteration, iterations to the
    target)."""
    setup = trace[0][0]
    steps = [b[0] - a[0] for a, b in zip(trace, trace[1:], strict=False)]
    per = statistics.median(steps) if steps else float("nan")
    for i, (t, c) in enumerate(trace[1:]):
        if c <= target:
            return t, setup, per, i + 1
    return None, setup, per, len(steps)


def main() -> None:
    """Run the benchmark and print a table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--skip-gtsam", action="store_true")
    ap.add_argument("--graphs", nargs="*", help="file names in the data folder (default: all)")
    args = ap.parse_args()
    folder = Path(tempfile.mkdtemp())
    configs = {
        "graphopt lm-gtsam": lambda p, g, s, n: graphopt_run(p, g, pose_graph_levenberg(), n),
        "graphopt gn": lambda p, g, s, n: graphopt_run(p, g, "gn", n),
        "graphopt lm-g2o": lambda p, g, s, n: graphopt_run(p, g, "lm", n),
        "g2o gn": lambda p, g, s, n: g2o_run(s, "gn", n),
        "g2o lm": lambda p, g, s, n: g2o_run(s, "lm", n),
    }
    if not args.skip_gtsam:
        configs["gtsam lm"] = lambda p, g, s, n: gtsam_run(s, "lm", n)
        configs["gtsam gn"] = lambda p, g, s, n: gtsam_run(s, "gn", n)
    print(f"{'graph':30s} {'solver':18s} {'s to conv':>9s} {'set-up':>7s} {'iters':>5s} "
          f"{'s/iter':>8s} {'final chi2':>14s}")
    for name, guess in GRAPHS:
        if args.graphs and name not in args.graphs:
            continue
        path = DATA / name
        start = write_start(path, guess, folder)
        runners = {label: run for label, run in configs.items()
                   if not label.startswith("gtsam") or name in ("w10000.graph",
                                                                 "pose2example.txt")}
        for run in runners.values():
            run(path, guess, start, 2)  # warm-up
        traces: dict[str, list[Trace]] = {label: [] for label in runners}
        for _ in range(args.repeats):  # rounds: every configuration once, in the same minutes
            for label, run in runners.items():
                traces[label].append(run(path, guess, start, args.iterations))
        best = min(c for label, runs in traces.items() for t in runs for _, c in t
                   if not label.startswith("gtsam"))
        target = best * (1 + REL)
        for label, runs in traces.items():
            own = label.startswith("gtsam")
            goal = min(c for t in runs for _, c in t) * (1 + REL) if own else target
            rows = [summarise(t, goal) for t in runs]
            reached = [r[0] for r in rows if r[0] is not None]
            done = len(reached) == len(rows)
            conv = f"{statistics.median(reached):9.3f}" if done else f"{'-':>9s}"
            setup = statistics.median(r[1] for r in rows)
            per = statistics.median(r[2] for r in rows)
            its = rows[0][3]
            final = runs[0][-1][1] if len(runs[0]) > 1 else float("nan")
            print(f"{name:30s} {label:18s} {conv} {setup:7.3f} {its:5d} {per:8.4f} "
                  f"{final:14.8g}" + (" own" if own else ""))
        print(f"{'':30s} target chi2 {target:.10g} (best final + 1e-6)")


if __name__ == "__main__":
    main()
