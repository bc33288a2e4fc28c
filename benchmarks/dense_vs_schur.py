"""Why "bundle adjustment is slow" is wrong: dense normal equations vs Schur + sparse Cholesky.

Takes the first N points of a BAL problem (with all their observations), and times LM
iterations of graphopt on the same problem in three ways:

* ``dense``: no vertex marginalised, the full normal equations ``H`` factorised densely
  (``O((9c + 3n)³)``, what a naive implementation does);
* ``sparse``: no vertex marginalised, ``H`` factorised by CHOLMOD (sparse, fill-reducing order);
* ``schur``: points marginalised (the reduced camera system ``S = U − W V⁻¹ Wᵀ``), ``S``
  factorised by CHOLMOD — what ``graphopt-bal`` does.

Usage::

    python -P benchmarks/dense_vs_schur.py [FILE] [--points 500 1000 2000 4000] [--iterations 3]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from graphopt.io.bal import BALProblem, read_bal  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bal"


def subset(problem: BALProblem, n_points: int) -> BALProblem:
    """The first ``n_points`` points with their observations (all cameras kept).

    Args:
        problem: Full problem.
        n_points: Points to keep.
    """
    keep = problem.point_index < n_points
    return BALProblem(problem.cameras.copy(), problem.points[:n_points].copy(),
                      problem.camera_index[keep], problem.point_index[keep],
                      problem.observations[keep])


def time_iterations(problem: BALProblem, mode: str, iterations: int) -> tuple[float, float]:
    """Median seconds per LM iteration and final cost.

    Args:
        problem: The problem.
        mode: ``dense``, ``sparse`` or ``schur``.
        iterations: LM iterations.
    """
    from graphopt import SparseOptimizer
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
    from graphopt.types.vertices import VertexPointXYZ

    nc = problem.num_cameras
    opt = SparseOptimizer(algorithm="lm", solver="dense" if mode == "dense" else "cholmod")
    opt.add_vertices(VertexCameraBAL, np.arange(nc), problem.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(problem.num_points), problem.points,
                     marginalized=(mode == "schur"))
    opt.add_edges(EdgeBALProjection,
                  np.column_stack([problem.camera_index, nc + problem.point_index]),
                  problem.observations)
    opt.initialize_optimization()
    res = opt.optimize(iterations)
    per = [a + b + c for a, b, c in zip(res.linearize_seconds, res.schur_seconds,
                                        res.solve_seconds, strict=True)]
    return statistics.median(per), 0.5 * res.final_chi2


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments.
    """
    ap = argparse.ArgumentParser(description="dense normal equations vs Schur complement")
    ap.add_argument("file", nargs="?", default=str(DATA / "problem-16-22106-pre.txt.bz2"))
    ap.add_argument("--points", type=int, nargs="+", default=[500, 1000, 2000, 4000])
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--dense-max", type=int, default=6000,
                    help="skip the dense solve above this many unknowns")
    args = ap.parse_args(argv)
    full = read_bal(args.file)
    sizes = sorted({min(n, full.num_points) for n in args.points} | {full.num_points})
    print(f"{Path(args.file).name}: LM iteration time (median of {args.iterations}), one thread")
    print(f"{'points':>7} {'obs':>7} {'unknowns':>9} {'dense H':>10} {'sparse H':>10} "
          f"{'Schur+CHOLMOD':>14} {'dense/Schur':>12}")
    last_dense: tuple[int, float] | None = None
    t_schur = float("nan")
    for n in sizes:
        p = subset(full, n)
        unknowns = 9 * p.num_cameras + 3 * p.num_points
        t_schur, c_schur = time_iterations(p, "schur", args.iterations)
        t_sparse, _ = time_iterations(p, "sparse", args.iterations)
        if unknowns <= args.dense_max:
            t_dense, c_dense = time_iterations(p, "dense", args.iterations)
            assert abs(c_dense - c_schur) <= 1e-6 * c_schur + 1e-9, (c_dense, c_schur)
            dense = f"{t_dense:10.4f}"
            last_dense = (unknowns, t_dense)
            ratio = f"{t_dense / t_schur:12.0f}"
        else:
            # Dense Cholesky is O(N³): extrapolate from the largest measured size.
            dense, ratio = f"{'(skipped)':>10}", f"{'':>12}"
        print(f"{n:7d} {p.num_observations:7d} {unknowns:9d} {dense} {t_sparse:10.4f} "
              f"{t_schur:14.4f} {ratio}", flush=True)
    if last_dense is not None:
        n_full = 9 * full.num_cameras + 3 * full.num_points
        t_full = last_dense[1] * (n_full / last_dense[0]) ** 3
        print(f"dense H on the full problem, extrapolated as N³ from {last_dense[0]} unknowns: "
              f"{t_full:.0f} s per iteration ({t_full / t_schur:.0f}x the Schur complement), "
              f"and {8 * n_full**2 / 1e9:.1f} GB for the matrix")
    return 0


if __name__ == "__main__":
    sys.exit(main())
