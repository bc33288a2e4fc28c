"""One free vertex and nothing to eliminate: the dense single-block assembly equals the general
assembler's, term by term (unary edges, the free vertex at either position of a binary edge,
inactive edges, two groups)."""

from __future__ import annotations

import numpy as np
import pytest

from graphopt import RobustKernelHuber, SparseOptimizer
from graphopt.lie import se3_exp
from graphopt.linear.assembly import Assembler
from graphopt.linear.single_block import SingleBlockAssembler
from graphopt.types import (
    CameraParameters,
    EdgeSE3Expmap,
    EdgeSE3ProjectXYZOnlyPose,
    VertexSE3Expmap,
)

CAM = CameraParameters(500.0, 510.0, 320.0, 240.0)


def _pose(rng: np.random.Generator, scale: float = 0.2) -> np.ndarray:
    return se3_exp(rng.normal(0.0, scale, (1, 6)))[0]


def one_free_pose(levels: bool) -> SparseOptimizer:
    """Pose 0 free with 40 projections (kernels on half) and relative-pose edges to three
    fixed poses in both directions (the free pose first in some, second in others)."""
    rng = np.random.default_rng(5)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE3Expmap, [0, 1, 2, 3], np.stack([_pose(rng) for _ in range(4)]),
                     fixed=[False, True, True, True])
    Xw = rng.uniform(-1, 1, (40, 3)) + [0, 0, 5]
    z = rng.uniform(100, 500, (40, 2))
    proj = opt.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((40, 1), dtype=int), z,
                         information=rng.uniform(0.5, 2.0, 40)[:, None, None] * np.eye(2),
                         params=CAM, data={"Xw": Xw})
    proj[np.arange(40) % 2 == 0].set_robust_kernel(RobustKernelHuber(2.0))
    rel = opt.add_edges(EdgeSE3Expmap, np.array([[0, 1], [2, 0], [0, 3], [3, 0]]),
                        np.stack([_pose(rng, 0.05) for _ in range(4)]))
    if levels:
        proj.set_level((np.arange(40) % 5 == 0).astype(int))
        rel.set_level([0, 1, 0, 0])
    return opt


@pytest.mark.parametrize("levels", [False, True])
def test_single_block_assembly_equals_the_general_one(levels: bool) -> None:
    opt = one_free_pose(levels)
    opt.initialize_optimization(0)
    system = opt.linear_system
    assert isinstance(system.assembler, SingleBlockAssembler)
    assert any(sel is not None for hterms, _ in system.assembler.terms for *_, sel in hterms)
    lin, _ = opt.problem.linearizer.linearize()
    args = (lin.jacobians, lin.weighted, lin.weighted_errors)
    fast = system.assembler.assemble(*args)
    general = Assembler(system.index, system.config.cost).assemble(*args)
    scale = np.abs(general.h_data).max()
    np.testing.assert_allclose(fast.h_data, general.h_data, rtol=1e-12, atol=1e-14 * scale)
    np.testing.assert_allclose(fast.bu, general.bu, rtol=1e-12,
                               atol=1e-14 * np.abs(general.bu).max())
    assert fast.v == [] and fast.bv == [] and fast.wt == []


def test_a_second_free_vertex_takes_the_general_assembler() -> None:
    opt = one_free_pose(False)
    opt.vertex(1).set_fixed(False)
    opt.initialize_optimization()
    assert isinstance(opt.linear_system.assembler, Assembler)
    res = opt.optimize(5)  # and it runs
    assert res.final_chi2 < res.initial_chi2
