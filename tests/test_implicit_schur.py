"""Implicit-Schur PCG (``iterative-schur``): the matrix-free products against the explicit
reduction, PCG against direct solves, LM runs against CHOLMOD/dense, its failure modes, the
structure it skips, its names and the automatic choice."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import build_pose_graph
from schur_toys import multi_toy

from graphopt import SparseOptimizer
from graphopt.algorithms import LevenbergConfig
from graphopt.apps.bal import build_parser
from graphopt.apps.bal_scene import synthetic_scene
from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.implicit import SchurOperator
from graphopt.linear.pattern import with_data
from graphopt.solvers import (
    SOLVERS,
    ImplicitSchurConfig,
    LinearSolverAuto,
    LinearSolverImplicitSchur,
    ReducedCostModel,
    make_solver,
)
from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
from graphopt.types.vertices import VertexPointXYZ


def bal_optimizer(solver, cameras: int = 8, points: int = 400, seed: int = 3,
                  algorithm=None, fixed: int = 0) -> SparseOptimizer:
    """A small synthetic BAL problem (cameras along a street, points marginalised; the first
    ``fixed`` cameras fixed)."""
    sc = synthetic_scene(cameras, points, seed=seed).problem
    alg = algorithm if algorithm is not None else LevenbergConfig(diagonal_damping=True)
    opt = SparseOptimizer(algorithm=alg, solver=solver)
    nc = sc.num_cameras
    opt.add_vertices(VertexCameraBAL, np.arange(nc), sc.cameras, fixed=np.arange(nc) < fixed)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(sc.num_points), sc.points, marginalized=True)
    opt.add_edges(EdgeBALProjection, np.column_stack([sc.camera_index, nc + sc.point_index]),
                  sc.observations)
    opt.initialize_optimization()
    return opt


def explicit_and_implicit(opt_e: SparseOptimizer, opt_i: SparseOptimizer, lam: float,
                          diagonal: bool) -> tuple[np.ndarray, np.ndarray, SchurOperator]:
    """Dense S and its rhs from the explicit reduction, and the implicit operator, at one
    linearisation of the same state."""
    ae, _ = opt_e.problem.linearize()
    ai, _ = opt_i.problem.linearize()
    de, di = opt_e.problem.damping(ae, diagonal), opt_i.problem.damping(ai, diagonal)
    s, rhs, _ = opt_e.linear_system.reduce(ae, lam, de)
    op, rhs_i, _ = opt_i.linear_system.reduce(ai, lam, di)
    assert isinstance(op, SchurOperator) and rhs_i is op.rhs
    return with_data(opt_e.linear_system.pattern, s).toarray(), rhs, op


@pytest.mark.parametrize(("lam", "diagonal"), [(0.0, False), (1e-2, False), (1e-3, True)])
def test_implicit_product_equals_explicit_schur_complement(lam: float, diagonal: bool) -> None:
    S, rhs, op = explicit_and_implicit(bal_optimizer("dense"), bal_optimizer("iterative-schur"),
                                       lam, diagonal)
    assert S.shape == (72, 72) and op.n == 72
    x = np.random.default_rng(0).normal(size=(op.n, 3))
    for j in range(3):
        np.testing.assert_allclose(op.matvec(x[:, j]), S @ x[:, j], rtol=1e-10,
                                   atol=1e-10 * np.abs(S).max())
    np.testing.assert_allclose(op.rhs, rhs, rtol=1e-10, atol=1e-10 * np.abs(rhs).max())
    assert op.products == 3
    # Preconditioner blocks: S's diagonal blocks (Schur-Jacobi), U_λ's (Jacobi).
    blocks = np.stack([S[9 * k:9 * k + 9, 9 * k:9 * k + 9] for k in range(8)])
    (sj,) = op.diagonal_blocks(schur=True)
    np.testing.assert_allclose(sj, blocks, rtol=1e-10, atol=1e-10 * np.abs(blocks).max())
    (uj,) = op.diagonal_blocks(schur=False)
    assert np.all(np.einsum("nii->n", uj) > np.einsum("nii->n", sj))  # W V⁻¹ Wᵀ is PSD


def test_several_w_classes_u_couplings_and_kernels() -> None:
    """multi_toy: cameras and intrinsics (U blocks of 4 and 2) see landmarks, cameras see lines
    (two V classes, three W classes), a chain prior couples cameras, Huber weights."""
    opt_e, opt_i = multi_toy(True), multi_toy(True)
    opt_i.set_solver("iterative-schur")
    opt_e.initialize_optimization()
    opt_i.initialize_optimization()
    assert len(opt_i.linear_system.index.wclasses) == 3
    S, rhs, op = explicit_and_implicit(opt_e, opt_i, 0.5, True)
    x = np.random.default_rng(1).normal(size=op.n)
    np.testing.assert_allclose(op.matvec(x), S @ x, rtol=1e-10, atol=1e-10 * np.abs(S).max())
    np.testing.assert_allclose(op.rhs, rhs, rtol=1e-10, atol=1e-10 * np.abs(rhs).max())
    for group, blocks in zip(op.structure.groups, op.diagonal_blocks(schur=True), strict=True):
        ref = np.stack([S[np.ix_(i, i)] for i in group.idx])
        np.testing.assert_allclose(blocks, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
    # A step through the whole problem: the same as the dense solver's.
    cfg = ImplicitSchurConfig(eta=1e-14, criterion="residual")
    opt_i.set_solver(LinearSolverImplicitSchur(cfg))
    opt_i.initialize_optimization()
    for p in (opt_e.problem, opt_i.problem):
        p.asm = p.linearize()[0]
    se = opt_e.problem.solve(opt_e.problem.asm, 0.5)
    si = opt_i.problem.solve(opt_i.problem.asm, 0.5)
    np.testing.assert_allclose(si[0], se[0], rtol=1e-8, atol=1e-10)
    # V blocks are numbered per system (co-visibility, or first reached by the edges when
    # matrix-free): compare them by store slot.
    for c, (a, b) in enumerate(zip(si[1], se[1], strict=True)):
        ai = np.argsort(opt_i.linear_system.index.vclasses[c].slots)
        be = np.argsort(opt_e.linear_system.index.vclasses[c].slots)
        np.testing.assert_allclose(a[ai], b[be], rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("preconditioner", ["jacobi", "schur-jacobi"])
def test_pcg_with_tiny_eta_matches_the_direct_solve(preconditioner: str) -> None:
    S, rhs, op = explicit_and_implicit(bal_optimizer("dense"), bal_optimizer("iterative-schur"),
                                       1e-4, True)
    solver = LinearSolverImplicitSchur(ImplicitSchurConfig(
        eta=1e-13, criterion="residual", preconditioner=preconditioner))
    x = solver.solve(op, op.rhs)
    ref = np.linalg.solve(S, rhs)
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    assert 10 < solver.last_iterations <= 2 * 72 and solver.iterations == [solver.last_iterations]
    assert np.linalg.norm(S @ x - rhs) <= 1e-12 * np.linalg.norm(rhs)


def test_loose_eta_stops_early_and_the_default_test_is_ceres_quadratic() -> None:
    _, _, op = explicit_and_implicit(bal_optimizer("dense"), bal_optimizer("iterative-schur"),
                                     1e-4, True)
    tight = LinearSolverImplicitSchur(ImplicitSchurConfig(eta=1e-13, criterion="residual"))
    loose = LinearSolverImplicitSchur()
    assert loose.config == ImplicitSchurConfig(0.1, "quadratic", 500, 0, "jacobi", 1e-10)
    tight.solve(op, op.rhs)
    loose.solve(op, op.rhs)
    assert 1 <= loose.last_iterations < tight.last_iterations / 2
    capped = LinearSolverImplicitSchur(ImplicitSchurConfig(eta=0.0, max_iterations=3))
    capped.solve(op, op.rhs)
    assert capped.last_iterations == 3


def test_lm_reaches_the_explicit_final_chi2() -> None:
    chi = {}
    for solver in ("cholmod", "dense", "iterative-schur"):
        try:
            opt = bal_optimizer(solver)
        except ImportError:  # pragma: no cover - without CHOLMOD
            continue
        res = opt.optimize(30)
        chi[solver] = res.final_chi2
        assert res.final_chi2 < 0.01 * res.initial_chi2
    assert chi["iterative-schur"] == pytest.approx(chi["dense"], rel=1e-6)
    if "cholmod" in chi:
        assert chi["iterative-schur"] == pytest.approx(chi["cholmod"], rel=1e-6)


def test_inexact_step_keeps_lm_predicted_decrease_exact() -> None:
    """LM predicts Δᵀ(λDΔ + b); for a truncated CG step (from zero, with the exact V part) it
    is still the quadratic model's decrease 2bᵀΔ − ΔᵀHΔ."""
    opt = bal_optimizer(LinearSolverImplicitSchur(ImplicitSchurConfig(eta=0.5)))
    p = opt.problem
    asm, _ = p.linearize()
    b, damp, lam = p.gradient(asm), p.damping(asm, True), 1e-4
    step = p.solve(asm, lam, damp)
    assert opt.solver.last_iterations < 10  # truncated, far from the exact solution

    def dot(a, c):
        return float(a[0] @ c[0] + sum(np.vdot(x, y) for x, y in zip(a[1], c[1], strict=True)))

    lm = dot(step, ((lam * damp[0] * step[0]), [lam * d * x for d, x in
                                                 zip(damp[1], step[1], strict=True)])) \
        + dot(step, b)
    model = 2 * dot(b, step) - dot(step, p.hessian_product(asm, step))
    assert model > 0
    assert lm == pytest.approx(model, rel=1e-9)


def test_never_non_finite() -> None:
    opt = bal_optimizer("iterative-schur")
    asm, _ = opt.problem.linearize()
    op, rhs, _ = opt.linear_system.reduce(asm, 1e-4)
    solver = LinearSolverImplicitSchur()
    assert not np.any(solver.solve(op, np.zeros(op.n)))  # zero rhs: zero step, no division
    assert solver.last_iterations == 0
    with pytest.raises(NotPositiveDefiniteError, match="not finite"):
        solver.solve(op, np.full(op.n, np.nan))
    op.matvec = lambda x: -x  # an indefinite S: non-positive curvature at the first step
    with pytest.raises(NotPositiveDefiniteError, match="curvature"):
        solver.solve(op, rhs)
    with pytest.raises(NotPositiveDefiniteError):  # damping that makes V blocks indefinite
        opt.linear_system.reduce(asm, -1e9)
    # λ = 0 on BAL's gauge-free system: a finite step or a failed solve, never NaN.
    try:
        du, dv = opt.problem.solve(asm, 0.0)
        assert np.all(np.isfinite(du)) and all(np.all(np.isfinite(v)) for v in dv)
    except NotPositiveDefiniteError:
        pass
    res = opt.optimize(15)
    assert np.all(np.isfinite(res.chi2_history))
    assert np.all(np.isfinite(opt.estimates_of(VertexCameraBAL)))


def test_pose_graph_is_plain_pcg_on_h() -> None:
    ref, _, _ = build_pose_graph("lm", "dense")
    opt, _, _ = build_pose_graph("lm", "iterative-schur")
    opt.initialize_optimization()
    assert opt.linear_system.matrix_free and not opt.linear_system.schur
    asm, _ = opt.problem.linearize()
    op, _, _ = opt.linear_system.reduce(asm, 1e-2)
    H = with_data(opt.linear_system.pattern, asm.h_data).toarray() + 1e-2 * np.eye(op.n)
    x = np.random.default_rng(2).normal(size=op.n)
    np.testing.assert_allclose(op.matvec(x), H @ x, rtol=1e-12, atol=1e-9)
    assert opt.optimize(40).final_chi2 == pytest.approx(ref.optimize(40).final_chi2, rel=1e-6)


def test_no_schur_structure_is_built(monkeypatch) -> None:
    import graphopt.linear.system as system

    def fail(*args, **kwargs):
        raise AssertionError("the Schur strategies must not be built")

    monkeypatch.setattr(system, "SchurComplement", fail)
    opt = bal_optimizer("iterative-schur")
    ls = opt.linear_system
    assert ls.matrix_free and ls.reduction is None and ls.implicit is not None
    assert ls.pattern.nnz == 8 * 81  # the camera blocks only: no fill
    monkeypatch.undo()
    explicit = bal_optimizer(LinearSolverAuto()).linear_system  # small: explicit
    assert not explicit.matrix_free and explicit.pattern.nnz == 4860


def test_names_and_app_option() -> None:
    assert "iterative-schur" in SOLVERS
    for name in ("iterative-schur", "implicit-schur", "Implicit-Schur"):
        solver = make_solver(name)
        assert isinstance(solver, LinearSolverImplicitSchur) and solver.matrix_free
        assert solver.name == "iterative-schur"
    assert build_parser().parse_args(["--solver", "iterative-schur"]).solver == "iterative-schur"
    with pytest.raises(ValueError, match="preconditioner"):
        ImplicitSchurConfig(preconditioner="ilu")
    with pytest.raises(ValueError, match="criterion"):
        ImplicitSchurConfig(criterion="energy")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="eta"):
        ImplicitSchurConfig(eta=float("nan"))


def test_marginals_through_the_implicit_solver() -> None:
    ids = [3, 8, 20]  # two cameras fixed: no gauge freedom left
    opts = [bal_optimizer(s, fixed=2) for s in ("dense", "iterative-schur")]  # one state
    m_e, m_i = (opt.compute_marginals(ids) for opt in opts)
    for i in ids:
        np.testing.assert_allclose(m_i[i], m_e[i], rtol=1e-7, atol=1e-9 * np.abs(m_e[i]).max())


def test_dogleg_runs_on_the_implicit_system() -> None:
    res = bal_optimizer("iterative-schur", algorithm="dogleg").optimize(10)
    assert res.final_chi2 < 0.01 * res.initial_chi2


def test_auto_chooses_by_the_measured_model() -> None:
    small = LinearSolverAuto()
    opt = bal_optimizer(small)
    assert small.chosen.name == "dense" and small.decision["reason"] == "small"
    # A budget below the explicit path's modelled bytes: implicit, without S's pattern.
    tight = LinearSolverAuto(model=ReducedCostModel(memory_budget=1e5, min_w_blocks=0))
    opt = bal_optimizer(tight)
    d = tight.decision
    assert tight.chosen.name == "iterative-schur" and d["reason"] == "memory"
    assert opt.linear_system.matrix_free and d["explicit_bytes"] > 1e5
    assert d["nnz_s"] == 4860  # the explicit pattern's entries (measured above), predicted
    assert d["pairs"] == pytest.approx(
        float(sum(n * (n + 1) / 2 for n in np.bincount(
            opt.linear_system.index.wclasses[0].vblock))))
    # Free products: implicit modelled faster.
    fast = LinearSolverAuto(model=ReducedCostModel(min_w_blocks=0, operator_seconds=0.0,
                                                   product_seconds=0.0))
    bal_optimizer(fast)
    assert fast.chosen.name == "iterative-schur" and fast.decision["reason"] == "time"
    # Default constants on a banded problem: explicit is modelled faster and fits.
    fits = LinearSolverAuto(model=ReducedCostModel(min_w_blocks=0))
    bal_optimizer(fits)
    assert fits.chosen.name == "dense" and fits.decision["reason"].startswith("explicit")
    assert 0 < fits.decision["explicit_seconds"] < fits.decision["implicit_seconds"]
    pose = LinearSolverAuto(model=ReducedCostModel(min_w_blocks=0))
    build_pose_graph("lm", pose)[0].initialize_optimization()
    assert pose.decision["reason"] == "no marginalised vertices"
