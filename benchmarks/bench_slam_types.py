"""Microseconds per edge of the SLAM types' batched ``error`` and ``linearize`` (and per vertex
of ``oplus``) on random states: 64,000 edges by default, the size of Olson's w10000 graph.

CPU time (``time.process_time``), the best of ``--repeats`` runs of ``--number`` calls each:
the shared machine's other load shows in wall-clock time, much less in CPU time.

Usage::

    .venv/bin/python -P benchmarks/bench_slam_types.py [--edges 64000] [--repeats 9]
"""

from __future__ import annotations

import argparse
import time
import timeit
from collections.abc import Callable

import numpy as np

from graphopt.edge import EdgeContext
from graphopt.lie import so3_exp
from graphopt.types import (
    EdgeSE2,
    EdgeSE2PointXY,
    EdgeSE3,
    EdgeSE3PointXYZ,
    ParameterSE3Offset,
    VertexSE2,
    VertexSE3,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edges", type=int, default=64_000)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--number", type=int, default=5)
    args = ap.parse_args()
    m = args.edges
    rng = np.random.default_rng(0)

    def se2() -> np.ndarray:
        x = rng.normal(0.0, 3.0, (m, 3))
        x[:, 2] = rng.uniform(-np.pi, np.pi, m)
        return x

    def se3() -> np.ndarray:
        T = np.empty((m, 3, 4))
        T[:, :, :3] = so3_exp(rng.normal(0.0, 1.5, (m, 3)))
        T[:, :, 3] = rng.normal(0.0, 3.0, (m, 3))
        return T

    def us(fn: Callable[[], object]) -> float:
        best = min(timeit.repeat(fn, number=args.number, repeat=args.repeats,
                                 timer=time.process_time))
        return best / args.number / m * 1e6

    ctx = EdgeContext()
    offset = EdgeContext(ParameterSE3Offset(se3()[0]))
    xi, xj, z, p2 = se2(), se2(), se2(), rng.normal(0.0, 3.0, (m, 2))
    Xi, Xj, Z, p3 = se3(), se3(), se3(), rng.normal(0.0, 3.0, (m, 3))
    cases = [
        ("EdgeSE2", EdgeSE2, (xi, xj), z, ctx),
        ("EdgeSE2PointXY", EdgeSE2PointXY, (xi, p2), p2, ctx),
        ("EdgeSE3", EdgeSE3, (Xi, Xj), Z, ctx),
        ("EdgeSE3PointXYZ (offset)", EdgeSE3PointXYZ, (Xi, p3), p3, offset),
    ]
    print(f"{m} edges, µs per edge (CPU time, best of {args.repeats})")
    for name, et, x, meas, c in cases:
        err = us(lambda et=et, x=x, meas=meas, c=c: et.error(x, meas, c))
        lin = us(lambda et=et, x=x, meas=meas, c=c: et.linearize(x, meas, c))
        print(f"  {name:26s} error {err:6.3f}   linearize {lin:6.3f}")
    d2, d6 = rng.normal(0.0, 0.01, (m, 3)), rng.normal(0.0, 0.01, (m, 6))
    print(f"  {'VertexSE2.oplus':26s} {us(lambda: VertexSE2.oplus(xi, d2)):6.3f} µs per vertex")
    print(f"  {'VertexSE3.oplus':26s} {us(lambda: VertexSE3.oplus(Xi, d6)):6.3f} µs per vertex")


if __name__ == "__main__":
    main()
