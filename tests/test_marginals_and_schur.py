"""Schur complement against the full system, and marginal covariances against H⁻¹."""

from __future__ import annotations

import numpy as np
import pytest
from custom_types import EdgeSE2, VertexSE2, pose_graph
from schur_toys import EdgeDifference, VertexCam, VertexLandmark, ba_toy

from graphopt import GraphError, SparseOptimizer
from graphopt.linear import SchurConfig, SchurCostModel
from graphopt.solvers import CHOLMOD_AVAILABLE

SOLVERS = ["dense", "pcg", "scipy"] + (["cholmod"] if CHOLMOD_AVAILABLE else [])


#: W V⁻¹ Wᵀ formed by the sparse contractions, by the dense syrk or by the gathered Gram
#: products. Dense: only the per-panel cost counts, so runs of points merge into panels of at
#: most 10 points (30 rows). Gram: the sparse contractions are made so dear that the U blocks
#: take Gram products too.
SCHUR = {
    "sparse": SchurConfig("sparse", SchurCostModel(gram_enabled=False)),
    "dense": SchurConfig("dense", SchurCostModel(
        blas_mac=0.0, dense_element=0.0, place=0.0, area=0.0, panel=1.0, panel_rows=30,
        gram_enabled=False)),
    "gram": SchurConfig("gram", SchurCostModel(sparse_mac=1e9)),
}


@pytest.fixture(params=sorted(SCHUR))
def schur_path(request):
    """The name of a Schur strategy (a key of ``SCHUR``)."""
    return request.param


@pytest.mark.parametrize("per_point", [3, 6])  # 6: every point in every camera (dense W)
@pytest.mark.parametrize("solver", SOLVERS)
def test_schur_step_equals_full_step(solver: str, schur_path: str, per_point: int) -> None:
    full = ba_toy(False, "dense", per_point=per_point)
    full.initialize_optimization()
    asm, _ = full.problem.linearize()
    ref = full.problem.solve(asm, 1e-3)[0]
    schur = ba_toy(True, solver, per_point=per_point, schur=SCHUR[schur_path])
    schur.initialize_optimization()
    system = schur.linear_system
    assert system is not None
    if schur_path == "dense":
        panels = system.reduction.strategies[0].panels
        # Panels cover the W blocks in order, each once; 40 points, at most 10 per panel.
        nw = len(system.index.wclasses[0].ublock)
        assert [p.w0 for p in panels] == [0] + [p.w1 for p in panels[:-1]]
        assert panels[-1].w1 == nw and 4 <= len(panels) <= 8
        assert all(p.rows <= 10 for p in panels)
        # Each W block enters its panel's Z = L⁻¹Wᵀ through the 6 entries of a 3x3 L⁻¹.
        assert sum(p.d1 - p.d0 for p in panels) == 6 * nw
        # Every point sees all cameras (6, one fixed): every panel is 5 U blocks wide.
        if per_point == 6:
            assert all(p.cols == system.index.n_ublocks == 5 for p in panels)
    assert system.schur and not full.linear_system.schur
    # One W class (cameras x points), formed by the forced strategy.
    assert [t.name for t in system.reduction.strategies] == [schur_path]
    assert system.reduction.couplings == []
    asm, _ = schur.problem.linearize()
    du, dv = schur.problem.solve(asm, 1e-3)
    by_slot = np.zeros_like(dv[0])
    by_slot[system.index.vclasses[0].slots] = dv[0]  # V blocks are numbered internally
    np.testing.assert_allclose(np.concatenate([du, by_slot.ravel()]), ref, rtol=1e-7,
                               atol=1e-10)


def test_schur_and_full_converge_to_the_same_optimum(schur_path: str) -> None:
    a, b = ba_toy(False), ba_toy(True, schur=SCHUR[schur_path])
    ra, rb = a.optimize(30), b.optimize(30)
    assert rb.final_chi2 == pytest.approx(ra.final_chi2, rel=1e-9)
    np.testing.assert_allclose(a.estimates_of(VertexLandmark), b.estimates_of(VertexLandmark),
                               atol=1e-8)


def numeric_hessian(opt: SparseOptimizer, vtypes, free_masks, h=1e-6):
    """H = Jᵀ Ω J from central differences of the public error over every free tangent dim."""
    groups = opt.edge_groups()

    def residuals():
        out = []
        for g in groups:
            x = tuple(opt.estimates_of(vt)[np.searchsorted(opt.ids_of(vt), g.vertex_ids[:, k])]
                      for k, vt in enumerate(g.etype.vertex_types))
            e = g.etype.error(x, g.measurements, g.context())
            L = np.linalg.cholesky(g.information)  # Ω = L Lᵀ → whitened r = Lᵀ e
            out.append((e @ L).ravel())
        return np.concatenate(out)

    cols = []
    for vt, mask in zip(vtypes, free_masks, strict=True):
        base = opt.estimates_of(vt)
        for slot in np.flatnonzero(mask):
            for d in range(vt.dimension):
                delta = np.zeros((1, vt.dimension))
                delta[0, d] = h
                plus, minus = base.copy(), base.copy()
                plus[slot] = vt.oplus(base[slot:slot + 1], delta)[0]
                minus[slot] = vt.oplus(base[slot:slot + 1], -delta)[0]
                opt.set_estimates_of(vt, plus)
                rp = residuals()
                opt.set_estimates_of(vt, minus)
                rm = residuals()
                opt.set_estimates_of(vt, base)
                cols.append((rp - rm) / (2 * h))
    J = np.stack(cols, 1)
    return J.T @ J


@pytest.mark.parametrize("solver", ["dense"] + (["cholmod"] if CHOLMOD_AVAILABLE else []))
def test_marginals_equal_inverse_hessian_blocks_pose_graph(solver: str) -> None:
    """Also with CHOLMOD, which has the U blocks numbered in its own order."""
    truth, init, edges, meas = pose_graph(15)
    info = np.diag([4.0, 4.0, 9.0])
    opt = SparseOptimizer("lm", solver)
    opt.add_vertices(VertexSE2, np.arange(15), init, fixed=np.arange(15) == 0)
    opt.add_edges(EdgeSE2, edges, meas, information=info)
    opt.optimize(10)
    H = numeric_hessian(opt, [VertexSE2], [np.arange(15) > 0])
    cov = np.linalg.inv(H)
    marg = opt.compute_marginals([1, 7, opt.vertex(14)])
    for vid in (1, 7, 14):
        k = (vid - 1) * 3
        np.testing.assert_allclose(marg[vid], cov[k:k + 3, k:k + 3], rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("solver", ["dense", "pcg"] + (["cholmod"] if CHOLMOD_AVAILABLE else []))
def test_marginals_with_schur_equal_inverse_hessian_blocks(solver: str, schur_path: str) -> None:
    opt = ba_toy(True, solver, schur=SCHUR[schur_path])
    opt.optimize(20)
    H = numeric_hessian(opt, [VertexCam, VertexLandmark], [np.arange(6) > 0, np.ones(40, bool)])
    cov = np.linalg.inv(H)
    marg = opt.compute_marginals([2, 100, 117])
    np.testing.assert_allclose(marg[2], cov[4:8, 4:8], rtol=1e-4, atol=1e-9)
    for vid in (100, 117):
        k = 20 + (vid - 100) * 3
        np.testing.assert_allclose(marg[vid], cov[k:k + 3, k:k + 3], rtol=1e-4, atol=1e-9)


def test_marginals_reject_fixed_and_unknown() -> None:
    opt = ba_toy(True)
    with pytest.raises(GraphError, match="vertex 0 is fixed"):
        opt.compute_marginals([0])
    with pytest.raises(GraphError, match="vertex 999 does not exist"):
        opt.compute_marginals([999])


def test_edge_between_two_marginalised_vertices_is_rejected() -> None:
    class EdgeLL(EdgeDifference):
        dimension = 3
        vertex_types = (VertexLandmark, VertexLandmark)

    opt = ba_toy(True)
    opt.add_edges(EdgeLL, np.array([[100, 101]]), np.zeros((1, 3)))
    with pytest.raises(GraphError, match="two different marginalised vertices"):
        opt.initialize_optimization()


@pytest.mark.parametrize("algorithm", ["dogleg", "gn"])
def test_other_algorithms_with_schur_reach_the_lm_optimum(algorithm: str, schur_path: str) -> None:
    ref = ba_toy(True)
    ref.optimize(40)
    opt = ba_toy(True, schur=SCHUR[schur_path])
    opt.set_algorithm(algorithm)
    res = opt.optimize(40)
    assert res.final_chi2 == pytest.approx(ref.active_robust_chi2(), rel=1e-6)
    np.testing.assert_allclose(opt.estimates_of(VertexLandmark), ref.estimates_of(VertexLandmark),
                               atol=1e-6)


def test_hessian_product_matches_the_full_hessian(schur_path: str) -> None:
    rng = np.random.default_rng(7)
    full, schur = ba_toy(False), ba_toy(True, schur=SCHUR[schur_path])
    for o in (full, schur):
        o.initialize_optimization()
    system = schur.linear_system
    xu = rng.normal(size=system.n)
    xv = [rng.normal(size=(40, 3))]
    slots = system.index.vclasses[0].slots  # V block b is the landmark in slot slots[b]
    asm_f, _ = full.problem.linearize()
    by_slot = np.zeros_like(xv[0])
    by_slot[slots] = xv[0]
    ref = full.problem.hessian_product(asm_f, (np.concatenate([xu, by_slot.ravel()]), []))[0]
    asm_s, _ = schur.problem.linearize()
    hu, hv = schur.problem.hessian_product(asm_s, (xu, xv))
    hv_slot = np.zeros_like(hv[0])
    hv_slot[slots] = hv[0]
    np.testing.assert_allclose(np.concatenate([hu, hv_slot.ravel()]), ref, rtol=1e-10,
                               atol=1e-10)


@pytest.mark.parametrize("kernel", [None, "huber"])
def test_gram_products_equal_the_sparse_contractions(kernel) -> None:
    """The gathered Gram products (camera blocks of U, and every block of W V⁻¹ Wᵀ) give the
    sparse contractions' numbers: with and without a robust kernel (then ρ'ΩJ is not J)."""
    from graphopt import RobustKernelHuber

    def reduced(gram: bool):
        opt = ba_toy(True, per_point=4, schur=SCHUR["gram" if gram else "sparse"])
        if kernel:
            for g in opt.edge_groups():
                g.set_kernel(slice(None), RobustKernelHuber(0.02))
        opt.initialize_optimization()
        system = opt.linear_system
        assert [t.name for t in system.reduction.strategies] == ["gram" if gram else "sparse"]
        assert (system.assembler.u_gram_terms > 0) == gram
        asm, _ = opt.problem.linearize()
        s, rhs, _ = system.reduce(asm, 1e-3, system.damping(asm, True))
        return asm.h_data, s, rhs

    for ref, got in zip(reduced(False), reduced(True), strict=True):
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
