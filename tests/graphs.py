"""Small test problems built through the public API: a curve fit and a 2D pose graph."""

from __future__ import annotations

import numpy as np
from custom_types import (
    EdgeCurve,
    EdgeSE2,
    VertexCurve,
    VertexSE2,
    pose_graph,
)

from graphopt import (
    SparseOptimizer,
    StoppingConfig,
)
from graphopt.solvers import CHOLMOD_AVAILABLE

TRUE_ABC = np.array([1.0, 2.0, 1.0])


def curve_data(n=200, sigma=0.1, outliers=0.0, seed=1):
    rng = np.random.default_rng(seed)
    xs = rng.uniform(0, 1, n)
    ys = np.exp(TRUE_ABC[0] * xs**2 + TRUE_ABC[1] * xs + TRUE_ABC[2]) + rng.normal(0, sigma, n)
    k = int(outliers * n)
    if k:
        idx = rng.choice(n, k, replace=False)
        ys[idx] += rng.uniform(5, 15, k)
    return np.stack([xs, ys], 1)


def fit_curve(meas, algorithm="lm", kernel=None, solver="dense", edge=EdgeCurve, iters=100):
    # References: run until no step improves (g2o's rule), tighter than any tolerance.
    opt = SparseOptimizer(algorithm, solver, stopping=StoppingConfig.iterations_only())
    opt.add_vertices(VertexCurve, [0], [[0.0, 0.0, 0.0]])
    opt.add_edges(edge, np.zeros((len(meas), 1), int), meas, robust_kernel=kernel)
    res = opt.optimize(iters)
    return opt.vertex(0).estimate, res


ALGOS = ["gn", "lm", "dogleg"]


SOLVERS = ["dense", "pcg", "scipy", "auto"] + (["cholmod"] if CHOLMOD_AVAILABLE else [])


def build_pose_graph(algorithm="lm", solver="dense", n=40, seed=0, per_object=False):
    truth, init, edges, meas = pose_graph(n, seed)
    info = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.01**2])
    opt = SparseOptimizer(algorithm, solver)
    if per_object:
        for i in range(n):
            v = VertexSE2(i, init[i])
            v.set_fixed(i == 0)
            opt.add_vertex(v)
        for (i, j), z in zip(edges, meas, strict=True):
            e = EdgeSE2()
            e.set_vertex(0, opt.vertex(int(i)))
            e.set_vertex(1, int(j))
            e.set_measurement(z)
            e.set_information(info)
            opt.add_edge(e)
    else:
        opt.add_vertices(VertexSE2, np.arange(n), init, fixed=np.arange(n) == 0)
        opt.add_edges(EdgeSE2, edges, meas, information=info)
    return opt, truth, init


def step_in_graph_order(problem, du: np.ndarray) -> np.ndarray:
    """The U part of a step ordered by store, then slot (a solver may have the U blocks
    numbered in another order: :meth:`LinearSolver.block_order`)."""
    index = problem.system.index
    rows = []
    for si, ub in enumerate(index.ublock):
        ub = ub[ub >= 0]
        d = index.stores[si].vtype.dimension
        rows.append((index.uoffset[ub][:, None] + np.arange(d)).ravel())
    return du[np.concatenate(rows)] if rows else du
