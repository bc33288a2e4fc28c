"""Automatic differentiation against analytic Jacobians and central differences, same run.

1. One linearisation of 100,000 ``EdgeBALProjection`` edges (100 cameras, 20,000 points) and
   of 100,000 ``EdgeSE3ProjectXYZ`` edges (100 poses, a point per edge): the type's analytic
   ``linearize``, the same type with ``differentiation = "autodiff"``, and central differences
   (``"numeric"``), each given what the optimizer gives (gathered estimates, derived values).
   Medians of ``--repeats`` interleaved runs (after :data:`WARMUP` untimed ones: a block
   program is traced and checked once per signature), wall clock, one thread.
2. Dubrovnik-16 (``../shared/data/bal``), Levenberg–Marquardt as ``graphopt-bal`` runs it, for
   ``--iterations`` iterations: seconds per iteration (and per trial step) and final chi2 of
   the analytic and the autodiff type (interleaved runs, the median of each).
3. The tangent layout: the product rule ``t_a·v_b + t_b·v_a`` of a 12-direction jet over a
   block of 8,192 edges with the tangent axis first ``(k, m)`` (graphopt's) and last ``(m, k)``.

Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python -P benchmarks/bench_autodiff.py

``--cpu`` times with the process's CPU time instead of the wall clock: on a shared machine it
is disturbed less by other processes (one thread each side, so the two agree when idle).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from graphopt import EdgeContext, LevenbergConfig, SparseOptimizer, StoppingConfig
from graphopt.autodiff import tape
from graphopt.autodiff.jacobians import distinct_vertices
from graphopt.lie import se3_exp
from graphopt.numeric import numeric_jacobians
from graphopt.types import (
    CameraParameters,
    EdgeBALProjection,
    EdgeSE3ProjectXYZ,
    VertexCameraBAL,
    VertexPointXYZ,
)

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "bal"

class EdgeBALAutodiff(EdgeBALProjection):
    differentiation = "autodiff"

class EdgeSE3ProjectXYZAutodiff(EdgeSE3ProjectXYZ):
    differentiation = "autodiff"

#: The clock: wall (``perf_counter``) or, with ``--cpu``, this process's CPU time, which a
#: loaded machine disturbs less (one thread: the two agree on an idle machine).
CLOCK: list[Callable[[], float]] = [time.perf_counter]


def _forward(f: Callable[[], Any]) -> Callable[[], Any]:
    """``f`` with forward jets throughout (no recording for reverse accumulation)."""
    def run() -> Any:
        tape.ENABLED = False
        try:
            return f()
        finally:
            tape.ENABLED = True
    return run


#: Untimed calls of each variant first: autodiff traces a block program at the second
#: linearisation of a signature (``graphopt.autodiff.programs.TRACE_AFTER``) and checks it at
#: the third; what is timed is every linearisation after those (an LM run's).
WARMUP = 3


def _interleaved(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, float]:
    """Median seconds of each function, the runs interleaved (after :data:`WARMUP` each)."""
    for f in fns.values():
        for _ in range(WARMUP):
            f()
    times: dict[str, list[float]] = {k: [] for k in fns}
    clock = CLOCK[0]
    for _ in range(repeats):
        for k, f in fns.items():
            t = clock()
            f()
            times[k].append(clock() - t)
    return {k: float(np.median(v)) for k, v in times.items()}

def _compare(name: str, analytic: type, autodiff: type, x: tuple[np.ndarray, ...],
             z: np.ndarray, ctx: EdgeContext, repeats: int) -> None:
    """Time one linearisation by ``analytic`` (the type's own Jacobians), by ``autodiff`` (its
    autodiff subclass: reverse, and forward jets only) and by central differences; print.

    Args:
        name: What the line reports (``"100,000 EdgeBALProjection edges"``).
        analytic: The edge type.
        autodiff: Its subclass with ``differentiation = "autodiff"``.
        x: The gathered estimates ``(m, ...)`` per vertex position.
        z: ``(m, d)`` measurements.
        ctx: What the optimizer passes (derived values, params).
        repeats: Interleaved runs per variant (medians).
    """
    t = _interleaved({
        "analytic": lambda: analytic.linearize(x, z, ctx),
        "autodiff": lambda: autodiff.linearize(x, z, ctx),
        "forward": _forward(lambda: autodiff.linearize(x, z, ctx)),
        "numeric": lambda: (analytic.evaluate(x, z, ctx),
                            numeric_jacobians(analytic, x, z, ctx)),
    }, repeats)
    a, d, n, f = t["analytic"], t["autodiff"], t["numeric"], t["forward"]
    print(f"{name}: analytic {a * 1e3:.1f} ms, autodiff {d * 1e3:.1f} ms (forward jets only "
          f"{f * 1e3:.1f} ms), central differences {n * 1e3:.1f} ms; autodiff/analytic "
          f"{d / a:.2f}x (target <= 1.5; forward only {f / a:.2f}x), autodiff/numeric "
          f"{d / n:.3f}x (target <= 0.3)")

def bench_bal(m: int, repeats: int, rng: np.random.Generator) -> None:
    nc, npt = 100, 20_000
    cams = np.c_[rng.normal(0, 0.3, (nc, 3)), rng.normal(0, 1, (nc, 3)),
                 rng.uniform(400, 1500, nc), rng.normal(0, 0.1, nc), rng.normal(0, 0.01, nc)]
    ci, pi = rng.integers(0, nc, m), rng.integers(0, npt, m)
    pts = rng.normal(0, 1, (npt, 3)) + [0, 0, -10]
    cam, X = np.asfortranarray(cams[ci]), np.asfortranarray(pts[pi])  # as the optimizer gathers
    z = rng.normal(0, 200, (m, 2))
    # What the optimizer passes: derived values and, for an automatically differentiated
    # type, which edges share a vertex (structure, found once per group).
    ctx = EdgeContext(derived=(np.asfortranarray(VertexCameraBAL.derived(cams)[ci]), None),
                      vertices=(distinct_vertices(ci), distinct_vertices(pi)))
    _compare(f"{m:,} EdgeBALProjection edges", EdgeBALProjection, EdgeBALAutodiff, (cam, X), z,
             ctx, repeats)

def bench_se3(m: int, repeats: int, rng: np.random.Generator) -> None:
    nc = 100
    T = se3_exp(rng.normal(0, 0.3, (nc, 6)))
    ci = rng.integers(0, nc, m)
    Tm = T[ci]
    pc = np.c_[rng.normal(0, 0.5, (m, 2)), rng.uniform(4, 8, m)]
    X = np.asfortranarray(np.einsum("mji,mj->mi", Tm[:, :3, :3], pc - Tm[:, :3, 3]))
    z = rng.normal(300, 50, (m, 2))
    ctx = EdgeContext(CameraParameters(500, 510, 320, 240),
                      vertices=(distinct_vertices(ci), distinct_vertices(np.arange(m))))
    _compare(f"{m:,} EdgeSE3ProjectXYZ edges", EdgeSE3ProjectXYZ, EdgeSE3ProjectXYZAutodiff,
             (Tm, X), z, ctx, repeats)

def bench_dubrovnik(iterations: int, runs: int) -> None:
    path = DATA / "problem-16-22106-pre.txt.bz2"
    if not path.exists():
        print(f"Dubrovnik-16: skipped ({path} not found)")
        return
    from graphopt.io.bal import read_bal

    problem = read_bal(str(path))
    nc = problem.num_cameras

    def run(edge: type) -> tuple[float, float]:
        opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True))
        opt.stopping = StoppingConfig.iterations_only()
        opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
        opt.add_vertices(VertexPointXYZ, nc + np.arange(problem.num_points), problem.points,
                         marginalized=True)
        opt.add_edges(edge, np.column_stack([problem.camera_index, nc + problem.point_index]),
                      problem.observations)
        opt.initialize_optimization()
        t = CLOCK[0]()
        res = opt.optimize(iterations)
        sec = CLOCK[0]() - t
        trials = sum(i.trials for i in res.info)
        return sec / max(res.iterations, 1), res.final_chi2, sec / max(trials, 1), trials

    out: dict[str, list[tuple[float, float, float, int]]] = {"analytic": [], "autodiff": []}
    for _ in range(runs):
        out["analytic"].append(run(EdgeBALProjection))
        out["autodiff"].append(run(EdgeBALAutodiff))
    a, d = (float(np.median([r[0] for r in out[k]])) for k in ("analytic", "autodiff"))
    ta, td = (float(np.median([r[2] for r in out[k]])) for k in ("analytic", "autodiff"))
    ca, cd = out["analytic"][0][1], out["autodiff"][0][1]
    na, nd = out["analytic"][0][3], out["autodiff"][0][3]
    print(f"Dubrovnik-16 LM, {iterations} iterations: analytic {a * 1e3:.0f} ms/iteration, "
          f"autodiff {d * 1e3:.0f} ms/iteration ({d / a:.2f}x, target <= 1.3); per trial step "
          f"(a linearisation and a solve; {na} vs {nd} trials) {ta * 1e3:.0f} vs {td * 1e3:.0f} ms "
          f"({td / ta:.2f}x); final chi2 {ca:.12e} vs {cd:.12e} (relative "
          f"{abs(ca - cd) / ca:.1e}, target 1e-10)")

def bench_layout(repeats: int, rng: np.random.Generator) -> None:
    k, m = 12, 8192
    va, vb = rng.normal(size=m), rng.normal(size=m)
    first = (rng.normal(size=(k, m)), rng.normal(size=(k, m)))
    last = (np.ascontiguousarray(first[0].T), np.ascontiguousarray(first[1].T))
    t = _interleaved({
        "first": lambda: first[0] * vb + first[1] * va,
        "last": lambda: last[0] * vb[:, None] + last[1] * va[:, None],
    }, repeats * 20)
    print(f"product rule, {k} directions x {m} edges: tangent axis first {t['first'] * 1e6:.0f} "
          f"us, last {t['last'] * 1e6:.0f} us ({t['last'] / t['first']:.2f}x)")

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edges", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=7)
    # 8: from the 9th iteration on the cost is at its floor (steps change it by ~1e-12
    # relative) and whether a step is accepted is decided by rounding; a run that rejects one
    # makes up to 10 trials in that iteration, in either mode (the per-trial time is printed).
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--cpu", action="store_true", help="time with process CPU time")
    ap.add_argument("--skip-lm", action="store_true", help="only the linearisations")
    args = ap.parse_args()
    if args.cpu:
        CLOCK[0] = time.process_time
    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: set OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 for one thread per side")
    rng = np.random.default_rng(0)
    bench_bal(args.edges, args.repeats, rng)
    bench_se3(args.edges, args.repeats, rng)
    bench_layout(args.repeats, rng)
    if not args.skip_lm:
        bench_dubrovnik(args.iterations, args.runs)

if __name__ == "__main__":
    main()
