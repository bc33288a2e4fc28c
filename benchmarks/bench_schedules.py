"""Benchmark: the LM damping schedules (g2o's, Ceres', GTSAM's) and Gauss–Newton per problem family.

For every problem, each configuration runs from the same start to the library's default stopping
tests (:class:`graphopt.StoppingConfig`, at most ``--iterations``) and reports the iterations,
the seconds (``optimize``'s wall time; set-up excluded, it is the same for all), the stop reason,
the final chi2, and the iterations and seconds until chi2 first came within ``--rel`` of the
best final chi2 of all configurations (``-`` if never). One thread, one warm-up, medians of
``--repeats`` runs. The defaults ``graphopt-bal``, ``graphopt-g2o`` and ``graphopt-direct-ba``
use are chosen from this table (see ``docs/benchmarks.md``).

Usage (from the repository root)::

    .venv/bin/python -P benchmarks/bench_schedules.py [--family bal|posegraph|directba ...]
        [--repeats 3] [--iterations 100] [--initial-lambdas 1e-5 3e-6 1e-6 ...]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from graphopt import (  # noqa: E402
    GaussNewtonConfig,
    LevenbergConfig,
    SparseOptimizer,
    StoppingConfig,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_bal, also under python -P
Builder = Callable[[Any], SparseOptimizer]


def _bal_builder(problem: Any) -> Builder:
    from bench_bal import bal_optimizer

    return lambda algorithm: bal_optimizer(problem, algorithm)


def bal_problems() -> dict[str, tuple[Builder, dict[str, Any]]]:
    """BAL files (observations behind their camera dropped, as bench_bal does) and a
    synthetic street scene; LM with Marquardt's diagonal damping, as graphopt-bal runs it."""
    from bench_bal import drop_behind_camera

    from graphopt.apps.bal_scene import synthetic_scene
    from graphopt.io.bal import read_bal

    out: dict[str, tuple[Builder, dict[str, Any]]] = {}
    for name in ("problem-16-22106-pre.txt.bz2", "problem-49-7776-pre.txt.bz2"):
        path = SHARED / "bal" / name
        if path.exists():
            out[name] = (_bal_builder(drop_behind_camera(read_bal(path))[0]),
                         {"diagonal_damping": True})
    out["synthetic street (16 cameras)"] = (_bal_builder(synthetic_scene().problem),
                                            {"diagonal_damping": True})
    return out


def posegraph_problems() -> dict[str, tuple[Builder, dict[str, Any]]]:
    """The pose graphs of ../shared/data/posegraph (``--guess`` where the file needs it) and
    the generated Manhattan world; identity damping, as graphopt-g2o runs it."""
    from graphopt.apps.slam_scene import manhattan_world
    from graphopt.io.g2o import read_graph
    from graphopt.types.slam_graph import build_graph

    def builder(graph: Any, guess: bool) -> Builder:
        def build(algorithm: Any) -> SparseOptimizer:
            opt = SparseOptimizer(algorithm=algorithm)
            build_graph(graph, opt, guess=guess)
            return opt
        return build

    out: dict[str, tuple[Builder, dict[str, Any]]] = {}
    for name, guess in (("w10000.graph", False), ("sphere_smallnoise.graph", True),
                        ("victoriaPark_reduced_1k.g2o", True), ("w100.graph", False)):
        path = SHARED / "posegraph" / name
        if path.exists():
            out[name] = (builder(read_graph(path), guess), {})
    out["manhattan world (3000 poses)"] = (builder(manhattan_world(3000, 0)[0], False), {})
    # Noisier worlds, where the schedules end in different minima (σ_xy, σ_θ as named).
    for poses, seed, sxy, sth in ((5000, 1, 0.1, 0.05), (3000, 3, 0.2, 0.1),
                                  (2000, 4, 0.05, 0.1)):
        graph = manhattan_world(poses, seed, sigma_xy=sxy, sigma_theta=sth)[0]
        out[f"manhattan world ({poses} poses, seed {seed}, σ {sxy}/{sth})"] = (
            builder(graph, False), {})
    return out


def directba_problems() -> dict[str, tuple[Builder, dict[str, Any]]]:
    """The direct photometric BA data (as graphopt-direct-ba runs it)."""
    from graphopt.apps.direct_ba_problem import build_problem
    from graphopt.io.directba import load_directba

    path = SHARED / "directba"
    if not path.exists():
        return {}
    data = load_directba(path)

    def build(algorithm: Any) -> SparseOptimizer:
        opt = build_problem(data).optimizer
        opt.set_algorithm(algorithm)
        return opt
    return {"directba (7 images)": (build, {})}


CONFIGS: dict[str, Callable[[dict[str, Any]], Any]] = {
    "lm g2o": lambda kw: LevenbergConfig(schedule="g2o", **kw),
    "lm ceres": lambda kw: LevenbergConfig(schedule="ceres", **kw),
    "lm gtsam": lambda kw: LevenbergConfig(schedule="gtsam", **kw),  # GTSAM's λ₀ = 1e-5
    "gn": lambda kw: GaussNewtonConfig(),
}


def run(build: Builder, algorithm: Any, iterations: int) -> dict[str, Any]:
    """One run to the default stopping tests."""
    opt = build(algorithm)
    opt.stopping = StoppingConfig(max_iterations=iterations)
    opt.initialize_optimization()
    t0 = time.perf_counter()
    res = opt.optimize()
    total = time.perf_counter() - t0
    return {"seconds": total, "iterations": res.iterations, "stop": str(res.stop_reason),
            "final": res.final_chi2, "chi2": res.chi2_history,
            "times": list(np.cumsum(res.iteration_seconds))}


def configs(lambdas: list[float]) -> dict[str, Callable[[dict[str, Any]], Any]]:
    """:data:`CONFIGS`, plus GTSAM's schedule from each initial λ in ``lambdas``."""
    out = dict(CONFIGS)
    for lam in lambdas:
        out[f"gtsam {lam:g}"] = (
            lambda kw, lam=lam: LevenbergConfig(schedule="gtsam", initial_lambda=lam, **kw))
    return out


def bench(name: str, build: Builder, kw: dict[str, Any], args: argparse.Namespace) -> None:
    """Run every configuration on one problem and print its rows."""
    rows: dict[str, list[dict[str, Any]]] = {}
    for label, make in configs(args.initial_lambdas).items():
        run(build, make(kw), 2)  # warm-up
        rows[label] = [run(build, make(kw), args.iterations) for _ in range(args.repeats)]
    finals = [r["final"] for rs in rows.values() for r in rs if np.isfinite(r["final"])]
    best = min(finals)
    target = best * (1 + args.rel) if best > 0 else args.rel
    print(f"\n== {name} (best final chi2 {best:.10g}; target within {args.rel:g})")
    print(f"{'config':<12} {'iters':>5} {'seconds':>8} {'stop':<20} {'final chi2':>16} "
          f"{'it to target':>12} {'s to target':>11}")
    for label, rs in rows.items():
        r = rs[0]
        hit = next((k for k, c in enumerate(r["chi2"]) if c <= target), None)
        secs = [x["times"][hit] for x in rs] if hit is not None else []
        print(f"{label:<12} {r['iterations']:5d} "
              f"{statistics.median(x['seconds'] for x in rs):8.3f} {r['stop']:<20} "
              f"{r['final']:16.10g} {('-' if hit is None else str(hit + 1)):>12} "
              f"{('-' if not secs else f'{statistics.median(secs):.3f}'):>11}", flush=True)


def main() -> None:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--family", nargs="*", default=["bal", "posegraph", "directba"],
                    choices=["bal", "posegraph", "directba"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--initial-lambdas", type=float, nargs="*", default=[],
                    help="also run GTSAM's schedule from each of these initial λ (the pose "
                         "graphs' default, 3e-6, was chosen from 1e-5 3e-6 1e-6 3e-7 1e-7 1e-8 "
                         "1e-9)")
    ap.add_argument("--rel", type=float, default=None,
                    help="relative distance to the best final chi2 counted as reached "
                         "(default: 1e-4 for BAL and direct BA, 1e-6 for pose graphs)")
    args = ap.parse_args()
    makers = {"bal": bal_problems, "posegraph": posegraph_problems,
              "directba": directba_problems}
    for family in args.family:
        rel = args.rel
        args.rel = rel if rel is not None else (1e-6 if family == "posegraph" else 1e-4)
        for name, (build, kw) in makers[family]().items():
            bench(name, build, kw, args)
        args.rel = rel


if __name__ == "__main__":
    main()
