"""Cost of editing a graph between two runs against a fresh ``initialize_optimization`` on the
same graph (issue 22's rule: an edit of levels, kernels or estimates costs at most 10 % of it).

Workloads: a local-BA window (10 free + 10 fixed ``VertexSE3Expmap`` keyframes, 1,000
marginalised ``VertexPointXYZ``, 5,000 ``EdgeSE3ProjectXYZ`` with Huber kernels, 10 % outliers;
``tests/ba_scene.py``) and Olson's w10000 pose graph (``../shared/data``, skipped if absent).

For each, in one run and interleaved (medians of ``--repeats``): a fresh initialisation
(slots, block pattern, Schur plan, symbolic factorisation) and three edits, each timed up to
the point where the next ``optimize`` starts iterating on the reused structure:

* levels: ``EdgeSet.set_level`` (10 % of the edges to level 1, alternating between two
  masks), ``initialize_optimization(0)`` and the idle-vertex update the next linearisation
  does (``problem.anchors``);
* kernels: ``EdgeSet.set_robust_kernel`` (Huber ↔ none), ``initialize_optimization(0)`` and
  the next linearisation's share (dropping unused kernels);
* estimates: ``set_estimates_of`` for every vertex type and ``initialize_optimization(0)``.

Also one LM iteration with every edge active against one with 10 % inactive (the zeroed rows'
cost per iteration). One thread (OMP/OpenBLAS set to 1 before numpy loads).

Usage::

    .venv/bin/python -P benchmarks/bench_editing.py [--repeats 15]
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

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the synthetic local-BA scene

from ba_scene import build, local_ba_scene  # noqa: E402

from graphopt import RobustKernelHuber, SparseOptimizer  # noqa: E402
from graphopt.edge_set import EdgeSet  # noqa: E402

W10000 = ROOT.parent / "shared" / "data" / "posegraph" / "w10000.graph"


def local_ba() -> tuple[SparseOptimizer, EdgeSet]:
    """The 5,000-observation window."""
    scene = local_ba_scene(free=10, fixed=10, points=1000, per_point=5, outliers=0.1, seed=0)
    return build(scene)


def w10000() -> tuple[SparseOptimizer, EdgeSet] | None:
    """Olson's w10000 (one edge group), or ``None`` without the data."""
    if not W10000.exists():
        return None
    from graphopt.io.g2o import read_graph
    from graphopt.types.slam_graph import build_graph

    opt = build_graph(read_graph(W10000)).optimizer
    return opt, opt.edge_sets()[0]


def fresh_init(opt: SparseOptimizer) -> None:
    """A new structure for the same graph (what a rebuild costs)."""
    opt.set_solver(opt._solver_spec)  # drops the problem
    opt.initialize_optimization(0)


def run(name: str, opt: SparseOptimizer, es: EdgeSet, repeats: int) -> None:
    rng = np.random.default_rng(1)
    m = len(es)
    masks = [(rng.random(m) < 0.1).astype(np.int64) for _ in range(2)]
    kernel = RobustKernelHuber(np.sqrt(5.991))
    types = [g.vtype for g in opt.graph.stores.values()]
    saved = [opt.estimates_of(t) for t in types]
    opt.optimize(1)
    state = {"i": 0}

    def levels() -> None:
        state["i"] ^= 1
        es.set_level(masks[state["i"]])
        opt.initialize_optimization(0)
        opt.problem.anchors._update()  # the next linearisation's share

    def kernels() -> None:
        state["i"] ^= 1
        es.set_robust_kernel(kernel if state["i"] else None)
        opt.initialize_optimization(0)
        es.group.kernel_index  # noqa: B018 - the next linearisation's share (unused kernels)

    def estimates() -> None:
        for t, est in zip(types, saved, strict=True):
            opt.set_estimates_of(t, est)
        opt.initialize_optimization(0)

    def iteration(active: bool) -> Callable[[], None]:
        def go() -> None:
            es.set_level(0 if active else masks[0])
            opt.initialize_optimization(0)
            t0 = time.perf_counter()
            opt.optimize(1)
            times["iter active" if active else "iter 10% inactive"].append(
                time.perf_counter() - t0)
        return go

    jobs: dict[str, Callable[[], None]] = {
        "fresh init": lambda: fresh_init(opt), "levels": levels, "kernels": kernels,
        "estimates": estimates}
    times: dict[str, list[float]] = {k: [] for k in jobs}
    times["iter active"], times["iter 10% inactive"] = [], []
    for _ in range(repeats):  # interleaved
        for key, fn in jobs.items():
            t0 = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t0)
        iteration(True)()
        iteration(False)()
        es.set_level(0)
        es.set_robust_kernel(kernel)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    base = med["fresh init"]
    print(f"\n{name}: {m} edges; fresh initialize_optimization {base:.2f} ms")
    for key in ("levels", "kernels", "estimates"):
        print(f"  edit {key:<10} {med[key]:8.3f} ms   {med[key] / base:6.1%} of a fresh init"
              f"   (target <= 10%)")
    print(f"  one LM iteration: all active {med['iter active']:.2f} ms, 10% inactive "
          f"{med['iter 10% inactive']:.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    run("local BA 10+10 keyframes, 1,000 points", *local_ba(), args.repeats)
    w = w10000()
    if w is None:
        print(f"\nw10000: skipped ({W10000} not found)")
    else:
        run("w10000", *w, args.repeats)


if __name__ == "__main__":
    main()
