"""The implicit Schur path's W products from the per-edge Jacobians (no W blocks), against
the dense Schur complement: robust kernels, per-edge information matrices, repeated
camera–point pairs (in one edge type and across two), fixed cameras and points; and the
linearisation in chunks of edges, against one call per group."""

from __future__ import annotations

import numpy as np
import pytest

import graphopt.linearizer as linearizer_module
import graphopt.problem as problem_module
from graphopt import (
    BaseEdge,
    LevenbergConfig,
    RobustKernelCauchy,
    RobustKernelHuber,
    SparseOptimizer,
)
from graphopt.apps.bal_scene import synthetic_scene
from graphopt.linear.implicit import SchurOperator
from graphopt.linear.pattern import with_data
from graphopt.problem import trial_linearization_allowed
from graphopt.solvers import ImplicitSchurConfig, LinearSolverImplicitSchur
from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL
from graphopt.types.vertices import VertexPointXYZ


class EdgeCameraPoint(BaseEdge):
    """A second camera–point edge type (numeric Jacobians): the point in the camera frame's
    translation, ``X − t``, against a 3-D measurement."""

    dimension = 3
    vertex_types = (VertexCameraBAL, VertexPointXYZ)

    @classmethod
    def error(cls, x, z, ctx):
        cam, X = x
        return X - 0.5 * cam[:, 3:6] * (1.0 + 0.1 * cam[:, 0:1]) - z


def awkward_ba(solver, seed: int = 5) -> SparseOptimizer:
    """8 cameras (the first fixed), 150 points (three fixed), projection edges with per-edge
    information, Huber on half of them, 40 observations repeated; 60 camera–point edges of a
    second type (Cauchy), half of them on pairs the projections already link."""
    rng = np.random.default_rng(seed)
    sc = synthetic_scene(8, 150, seed=seed).problem
    nc, npt = sc.num_cameras, sc.num_points
    opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True), solver=solver)
    opt.add_vertices(VertexCameraBAL, np.arange(nc), sc.cameras, fixed=np.arange(nc) < 1)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), sc.points, marginalized=True,
                     fixed=np.isin(np.arange(npt), [3, 50, 90]))
    ids = np.column_stack([sc.camera_index, nc + sc.point_index])
    z = sc.observations
    rep = rng.choice(len(ids), 40, replace=False)
    ids = np.concatenate([ids, ids[rep]])
    z = np.concatenate([z, z[rep] + rng.normal(scale=2.0, size=(40, 2))])
    a = rng.normal(size=(len(ids), 2, 2)) * 0.3
    info = np.eye(2) + np.einsum("mij,mkj->mik", a, a)
    half = len(ids) // 2
    opt.add_edges(EdgeBALProjection, ids[:half], z[:half], information=info[:half],
                  robust_kernel=RobustKernelHuber(1.0))
    opt.add_edges(EdgeBALProjection, ids[half:], z[half:], information=info[half:])
    pairs = np.concatenate([ids[rng.choice(len(ids), 30, replace=False)],
                            np.column_stack([rng.integers(0, nc, 30),
                                             nc + rng.integers(0, npt, 30)])])
    opt.add_edges(EdgeCameraPoint, pairs, rng.normal(scale=0.3, size=(60, 3)),
                  information=np.diag([2.0, 1.0, 0.5]), robust_kernel=RobustKernelCauchy(0.5))
    opt.initialize_optimization()
    return opt


def dense_and_operator(lam: float = 1e-3) -> tuple[np.ndarray, np.ndarray, SchurOperator,
                                                   SparseOptimizer, SparseOptimizer]:
    opt_e, opt_i = awkward_ba("dense"), awkward_ba("iterative-schur")
    ae, _ = opt_e.problem.linearize()
    ai, _ = opt_i.problem.linearize()
    s, rhs, _ = opt_e.linear_system.reduce(ae, lam, opt_e.problem.damping(ae, True))
    op, _, _ = opt_i.linear_system.reduce(ai, lam, opt_i.problem.damping(ai, True))
    assert isinstance(op, SchurOperator) and ai.wt is None and ai.wjac is not None
    return with_data(opt_e.linear_system.pattern, s).toarray(), rhs, op, opt_e, opt_i


def test_the_awkward_graph_has_what_it_should() -> None:
    _, _, op, _, opt_i = dense_and_operator()
    jw = opt_i.linear_system.assembler.jw
    assert len(opt_i.linear_system.index.wclasses) == 1 and len(jw.terms) == 2
    # Fixed cameras leave the projections' W term a subset of its edges; repeated pairs in
    # one term and across the two.
    assert jw.terms[0].sel is not None and len(jw.terms[0].sel) < opt_i.graph.groups[
        next(iter(opt_i.graph.groups))].size
    rep = jw._repeated[0]
    assert rep is not None and len(rep.start) >= 40 and set(rep.term.tolist()) == {0, 1}


def test_products_from_jacobians_equal_the_dense_schur_complement() -> None:
    S, rhs, op, _, _ = dense_and_operator()
    x = np.random.default_rng(0).normal(size=(op.n, 4))
    for j in range(4):
        ref = S @ x[:, j]
        assert np.linalg.norm(op.matvec(x[:, j]) - ref) <= 1e-12 * np.linalg.norm(ref)
    assert np.linalg.norm(op.rhs - rhs) <= 1e-12 * np.linalg.norm(rhs)
    for group, blocks in zip(op.structure.groups, op.diagonal_blocks(schur=True), strict=True):
        ref = np.stack([S[np.ix_(i, i)] for i in group.idx])
        assert np.abs(blocks - ref).max() <= 1e-12 * np.abs(ref).max()


def test_hessian_product_back_substitution_and_w_blocks_agree() -> None:
    _, _, _, opt_e, opt_i = dense_and_operator()
    pe, pi = opt_e.problem, opt_i.problem
    ae, ai = pe.linearize()[0], pi.linearize()[0]
    ixe, ixi = opt_e.linear_system.index, opt_i.linear_system.index
    rng = np.random.default_rng(2)
    xu = rng.normal(size=ixe.n)
    by_slot = rng.normal(size=(len(ixe.vclasses[0].slots), 3))  # indexed by store slot order
    se, si = np.argsort(ixe.vclasses[0].slots), np.argsort(ixi.vclasses[0].slots)
    xve, xvi = np.empty_like(by_slot), np.empty_like(by_slot)
    xve[se], xvi[si] = by_slot, by_slot
    he, hi = pe.hessian_product(ae, (xu, [xve])), pi.hessian_product(ai, (xu, [xvi]))
    assert np.linalg.norm(hi[0] - he[0]) <= 1e-12 * np.linalg.norm(he[0])
    assert np.linalg.norm(hi[1][0][si] - he[1][0][se]) <= 1e-12 * np.linalg.norm(he[1][0])
    # The W blocks formed on demand (marginal covariances) equal the assembled ones.
    we, wi = ae.wt[0], ai.wjac.class_wt(0)
    ke, ki = ixe.wclasses[0], ixi.wclasses[0]
    slot_e = ixe.vclasses[0].slots[ke.vblock] * ixe.n_ublocks + ke.ublock
    slot_i = ixi.vclasses[0].slots[ki.vblock] * ixi.n_ublocks + ki.ublock
    oe, oi = np.argsort(slot_e), np.argsort(slot_i)
    assert np.array_equal(slot_e[oe], slot_i[oi])
    assert np.abs(wi[oi] - we[oe]).max() <= 1e-12 * np.abs(we).max()


@pytest.mark.parametrize("preconditioner", ["jacobi", "schur-jacobi"])
def test_iterative_schur_step_equals_the_direct_ones(preconditioner: str) -> None:
    steps = {}
    for solver in ("dense", "cholmod"):
        opt = awkward_ba(solver)
        asm = opt.problem.linearize()[0]
        steps[solver] = (opt.problem.solve(asm, 1e-3, opt.problem.damping(asm, True)),
                         opt.linear_system.index.vclasses[0].slots)
    opt = awkward_ba(LinearSolverImplicitSchur(ImplicitSchurConfig(
        eta=1e-14, criterion="residual", preconditioner=preconditioner)))
    asm = opt.problem.linearize()[0]
    (du, (dv,)), slots = (opt.problem.solve(asm, 1e-3, opt.problem.damping(asm, True)),
                          opt.linear_system.index.vclasses[0].slots)
    for (due, (dve,)), slots_e in steps.values():
        assert np.linalg.norm(du - due) <= 1e-9 * np.linalg.norm(due)
        a, b = dv[np.argsort(slots)], dve[np.argsort(slots_e)]
        assert np.linalg.norm(a - b) <= 1e-9 * np.linalg.norm(b)


def test_lm_runs_agree_with_cholmod() -> None:
    """Solved tightly, PCG follows CHOLMOD's LM path (robust kernels make loose solves
    wander off it)."""
    tight = LinearSolverImplicitSchur(ImplicitSchurConfig(eta=1e-13, criterion="residual"))
    runs = {s: awkward_ba(s).optimize(6) for s in ("cholmod", tight)}
    (ref, got) = runs.values()
    assert got.final_chi2 == pytest.approx(ref.final_chi2, rel=1e-9)
    assert got.final_chi2 < 0.05 * ref.initial_chi2


class EdgeSometimesInactive(EdgeBALProjection):
    """Calls of 7 edges report an active mask (their first 3), other calls none."""

    @classmethod
    def linearize(cls, x, measurement, ctx):
        out = super().linearize(x, measurement, ctx)
        m = len(measurement)
        return out._replace(active=np.arange(m) < 3) if m == 7 else out


@pytest.mark.parametrize("etype", [EdgeBALProjection, EdgeSometimesInactive])
def test_linearisation_in_chunks_equals_one_call(monkeypatch, etype) -> None:
    sc = synthetic_scene(6, 120, seed=1).problem
    opt = SparseOptimizer(algorithm=LevenbergConfig(), solver="dense")
    nc = sc.num_cameras
    opt.add_vertices(VertexCameraBAL, np.arange(nc), sc.cameras)
    opt.add_vertices(VertexPointXYZ, nc + np.arange(sc.num_points), sc.points,
                     marginalized=True)
    opt.add_edges(etype, np.column_stack([sc.camera_index, nc + sc.point_index]),
                  sc.observations)
    opt.initialize_optimization()
    lin = opt.problem.linearizer
    group = opt.edge_groups()[0]

    def run() -> tuple:
        w, ev = lin.linearize()
        chi_lin, active_lin = group.last_chi2.copy(), group.active_count
        ev_e = lin.evaluate(linearize_trial=False)
        return w, ev, chi_lin, active_lin, ev_e, group.last_chi2.copy(), group.active_count

    one = run()
    monkeypatch.setattr(linearizer_module, "CHUNK_EDGES", 7)  # the last chunk is shorter
    assert group.size % 7
    many = run()
    for a, b in zip(one[0].jacobians[0] + one[0].weighted[0],
                    many[0].jacobians[0] + many[0].weighted[0], strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(one[0].weighted_errors[0], many[0].weighted_errors[0])
    assert np.array_equal(one[2], many[2]) and np.array_equal(one[5], many[5])
    assert one[1].robust_chi2 == many[1].robust_chi2 == one[4].robust_chi2
    assert one[3] == one[6] == group.size  # one call: no mask (7 edges are not a call's size)
    if etype is EdgeSometimesInactive:  # the last, shorter chunk reports none: all active
        m = group.size
        expect = np.arange(m) % 7 < 3
        expect[m - m % 7:] = True
        assert many[3] == int(expect.sum())  # linearize reports the masks
        assert many[6] == group.size  # its evaluate (the base class's) reports none
    else:
        assert many[3] == many[6] == group.size


def test_trial_linearisation_rule() -> None:
    opt = awkward_ba("dense")
    opt.initialize_optimization()
    groups = opt.edge_groups()
    # 8 bytes x rows x (camera 9 + point 3) per projection; the second type does not
    # linearise on trial.
    proj = sum(g.size for g in groups if g.etype is EdgeBALProjection)
    jac = 8 * proj * 2 * 12
    assert trial_linearization_allowed(groups, False, 1.0)
    assert trial_linearization_allowed(groups, True, 8 * jac)
    assert not trial_linearization_allowed(groups, True, 8 * jac - 8)


def test_errors_only_trials_under_memory_pressure_give_the_same_run(monkeypatch) -> None:
    """With too little memory for a second set of Jacobians, an implicit-Schur run's trials
    evaluate errors only; an accepted step is linearised again at the same state, so every
    iteration is the same to the last bit."""
    def run() -> tuple[bool, list[float]]:
        opt = awkward_ba("iterative-schur")
        opt.initialize_optimization()
        res = opt.optimize(5)
        return opt.problem.trial_linearization, [r.chi2 for r in res.info]

    allowed, ref = run()
    monkeypatch.setattr(problem_module, "available_memory", lambda: 1.0)
    refused, got = run()
    assert allowed and not refused
    assert got == ref and ref[-1] < 0.5 * ref[0]
