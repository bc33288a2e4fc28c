"""Seconds per LM iteration of direct BA on the task's data (analytic vs numeric Jacobians).

Run::

    .venv/bin/python -P benchmarks/bench_direct_ba.py [--data DIR] [--repeats 5] [--iterations 10]

Each repeat builds the problem afresh, runs one warm-up iteration, then times ``--iterations``
LM iterations; the median of the per-repeat seconds-per-iteration is reported, with the
breakdown of an iteration (edge work, assembly, Schur complement, solve) and ratios to the
issue's target (0.04 s) and reference numbers (vectorised numpy ≈ 0.1 s, g2o driven from Python
≈ 3 s, the task's C++ g2o ≈ 0.18 s).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from graphopt.apps.direct_ba_problem import build_problem
from graphopt.io.directba import load_directba

TARGET = 0.04
REFERENCES = {"numpy (vectorised)": 0.1, "g2o from Python": 3.0, "g2o C++ (task)": 0.18}
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "directba"


def _edge_times(problem, repeats: int = 15) -> tuple[float, float]:
    """Median seconds of one batched ``linearize`` and one ``error`` over all edge groups."""
    opt = problem.optimizer
    opt.initialize_optimization()
    lz = opt.problem.linearizer
    lin, err = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for gi, g in enumerate(lz.groups):
            g.etype.linearize(lz.gather(gi), g.measurements, lz.context(gi))
        t1 = time.perf_counter()
        for gi, g in enumerate(lz.groups):
            g.etype.error(lz.gather(gi), g.measurements, lz.context(gi))
        t2 = time.perf_counter()
        lin.append(t1 - t0)
        err.append(t2 - t1)
    return statistics.median(lin), statistics.median(err)


def bench(data, parametrization: str, numeric: bool, repeats: int, iterations: int) -> dict:
    """Time LM iterations of one configuration.

    Args:
        data: The loaded problem.
        parametrization: ``"xyz"`` or ``"inverse-depth"``.
        numeric: Numeric instead of analytic Jacobians.
        repeats: Fresh problems to time.
        iterations: Timed iterations per repeat.
    """
    per_it, parts = [], []
    edge = (float("nan"), float("nan"))
    for r in range(repeats):
        problem = build_problem(data, parametrization, "huber", 0.5, "cholmod", "lm",
                                numeric=numeric)
        opt = problem.optimizer
        opt.optimize(1)  # warm-up: caches, first allocations
        if r == 0:
            edge = _edge_times(problem, 5 if numeric else 15)
        res = opt.optimize(iterations)
        if res.iterations:
            per_it.append(res.seconds / res.iterations)
            parts.append((np.mean(res.linearize_seconds), np.mean(res.schur_seconds),
                          np.mean(res.solve_seconds), np.mean(res.trials)))
    med = statistics.median(per_it)
    p = np.median(np.array(parts), axis=0)
    return {"parametrization": parametrization, "jacobians": "numeric" if numeric else "analytic",
            "seconds_per_iteration": med, "edge_linearize_s": edge[0], "edge_error_s": edge[1],
            "optimizer_linearize_s": float(p[0]), "schur_s": float(p[1]), "solve_s": float(p[2]),
            "trials_per_iteration": float(p[3]), "repeats": len(per_it)}


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print a table.

    Args:
        argv: Command-line arguments.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--numeric-iterations", type=int, default=3)
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args(argv)
    if not Path(args.data).is_dir():
        print(f"bench_direct_ba: data folder not found: {args.data}", file=sys.stderr)
        return 1
    data = load_directba(args.data)
    rows = [
        bench(data, "xyz", False, args.repeats, args.iterations),
        bench(data, "inverse-depth", False, args.repeats, args.iterations),
        bench(data, "xyz", True, max(1, args.repeats // 2), args.numeric_iterations),
    ]
    print(f"direct BA, {args.data}: 28826 edges, Huber 0.5, LM, CHOLMOD; median of repeats")
    print(f"{'configuration':<28}{'s/iter':>9}{'edge lin':>10}{'edge err':>10}{'opt lin':>9}"
          f"{'schur':>8}{'solve':>8}{'trials':>7}{'/target':>9}")
    for r in rows:
        name = f"{r['parametrization']} {r['jacobians']}"
        print(f"{name:<28}{r['seconds_per_iteration']:>9.4f}{r['edge_linearize_s']:>10.4f}"
              f"{r['edge_error_s']:>10.4f}{r['optimizer_linearize_s']:>9.4f}{r['schur_s']:>8.4f}"
              f"{r['solve_s']:>8.4f}{r['trials_per_iteration']:>7.2f}"
              f"{r['seconds_per_iteration'] / TARGET:>9.2f}")
    best = rows[0]["seconds_per_iteration"]
    print(f"analytic xyz: {best / TARGET:.2f}x the {TARGET} s target; "
          + ", ".join(f"{best / v:.3f}x {k} ({v} s)" for k, v in REFERENCES.items()))
    print(f"numeric / analytic Jacobians: "
          f"{rows[2]['seconds_per_iteration'] / best:.1f}x per iteration, "
          f"{rows[2]['edge_linearize_s'] / rows[0]['edge_linearize_s']:.1f}x per linearisation")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "target": TARGET,
                                               "references": REFERENCES}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
