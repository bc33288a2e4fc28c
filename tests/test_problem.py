"""The numeric problem: linearisation, robust weights, reduced linearisations, caches and steps
(graphopt.linearizer, graphopt.problem)."""

from __future__ import annotations

import numpy as np
import pytest
from custom_types import (
    EdgeCurve,
    EdgeCurveNumeric,
    EdgeSE2,
    VertexCurve,
    VertexSE2,
    pose_graph,
)
from graphs import TRUE_ABC, build_pose_graph, curve_data, fit_curve

import graphopt.linearizer
from graphopt import (
    BaseEdge,
    EdgeContext,
    GraphError,
    LevenbergConfig,
    Linearization,
    RobustKernelHuber,
    SparseOptimizer,
    StoppingConfig,
    VertexVector,
    numeric_jacobians,
)
from graphopt.solvers import LinearSolverDense


def test_numeric_and_analytic_fits_agree() -> None:
    meas = curve_data()
    a, _ = fit_curve(meas, edge=EdgeCurve)
    b, _ = fit_curve(meas, edge=EdgeCurveNumeric)
    np.testing.assert_allclose(a, b, atol=1e-7)


def test_curve_jacobian_matches_numeric() -> None:
    meas = curve_data(n=30)
    x = (np.tile([0.3, -0.2, 0.5], (30, 1)),)
    ctx = EdgeContext()
    (ja,) = EdgeCurve.jacobians(x, meas, ctx)
    (jn,) = numeric_jacobians(EdgeCurve, x, meas, ctx)
    np.testing.assert_allclose(ja, jn, rtol=1e-6, atol=1e-8)


def test_se2_jacobians_match_numeric() -> None:
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(50, 3))
    xj = rng.normal(size=(50, 3))
    z = rng.normal(size=(50, 3)) * 0.3
    ja = EdgeSE2.jacobians((xi, xj), z, EdgeContext())
    jn = numeric_jacobians(EdgeSE2, (xi, xj), z, EdgeContext())
    for a, n in zip(ja, jn, strict=True):
        np.testing.assert_allclose(a, n, rtol=1e-6, atol=1e-7)


def test_structure_is_built_once() -> None:
    class CountingDense(LinearSolverDense):
        analyses = 0

        def analyze(self, pattern, block_sizes):
            CountingDense.analyses += 1
            super().analyze(pattern, block_sizes)

    truth, init, edges, meas = pose_graph(20)
    opt = SparseOptimizer("lm", CountingDense())
    opt.add_vertices(VertexSE2, np.arange(20), init, fixed=np.arange(20) == 0)
    opt.add_edges(EdgeSE2, edges, meas)
    opt.optimize(5)
    problem = opt.problem
    opt.optimize(5)
    assert CountingDense.analyses == 1 and opt.problem is problem
    opt.vertex(3).set_fixed(True)  # a structural change triggers one new analysis
    opt.optimize(1)
    assert CountingDense.analyses == 2


def test_per_edge_kernels_mix_in_one_group() -> None:
    meas = curve_data(n=20, outliers=0.2, seed=5)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexCurve, [0], [[1.0, 2.0, 1.0]])
    huber = RobustKernelHuber(0.3)
    for i, z in enumerate(meas):
        opt.add_edge(EdgeCurve([0], z, robust_kernel=huber if i % 2 else None))
    opt.compute_active_errors()
    e = EdgeCurve.error((np.tile([1.0, 2.0, 1.0], (20, 1)),), meas, EdgeContext())[:, 0]
    s = e**2
    rho = np.where(np.arange(20) % 2 == 1, huber.robustify(s)[0], s)
    assert opt.chi2() == pytest.approx(s.sum())
    assert opt.active_robust_chi2() == pytest.approx(rho.sum())
    assert opt.edges()[1].robust_kernel is huber and opt.edges()[0].robust_kernel is None
    opt.edges()[0].set_robust_kernel(huber)  # changing a kernel after adding
    opt.compute_active_errors()
    assert opt.active_robust_chi2() == pytest.approx(
        rho.sum() - s[0] + huber.robustify(s[:1])[0][0])


class VertexP3(VertexVector):
    dimension = 3


class EdgeFactored(BaseEdge):
    """A 4-row error whose Jacobian factors as −G·P with a 2-row P (like a patch whose rows share
    one projection): e = z − G·tanh(P x), G = data["g"] (4x2)."""

    dimension = 4
    vertex_types = (VertexP3,)
    P = np.array([[1.0, 0.5, -0.3], [0.2, -1.0, 0.7]])

    @classmethod
    def error(cls, x, z, ctx):
        return z - np.einsum("mkj,mj->mk", ctx.data["g"], np.tanh(x[0] @ cls.P.T))

    @classmethod
    def jacobians(cls, x, z, ctx):
        d = 1.0 - np.tanh(x[0] @ cls.P.T) ** 2  # (m, 2)
        return (-np.einsum("mkj,mj,ji->mki", ctx.data["g"], d, cls.P),)


class EdgeFactoredReduced(EdgeFactored):
    linearization_rows = 2

    @classmethod
    def linearize(cls, x, z, ctx):
        e = cls.error(x, z, ctx)
        g = ctx.data["g"]
        d = 1.0 - np.tanh(x[0] @ cls.P.T) ** 2
        gtg = np.einsum("mki,mkj->mij", g, g)
        R = np.swapaxes(np.linalg.cholesky(gtg), 1, 2)  # upper, RᵀR = GᵀG
        j_red = -R @ (d[:, :, None] * cls.P)
        e_lin = np.linalg.solve(np.swapaxes(R, 1, 2), np.einsum("mki,mk->mi", g, e)[:, :, None])
        return Linearization(e, (j_red,), e_lin[:, :, 0])


@pytest.mark.parametrize("kernel", [None, RobustKernelHuber(0.5)])
def test_reduced_linearisation_gives_the_same_steps(kernel) -> None:
    rng = np.random.default_rng(3)
    m = 60
    g = rng.normal(size=(m, 4, 2))
    ids = rng.integers(0, 5, size=(m, 1))
    truth = rng.normal(size=(5, 3)) * 0.5
    z = EdgeFactored.error((truth[ids[:, 0]],), np.zeros((m, 4)), EdgeContext(data={"g": g}))
    z = -z + rng.normal(0, 0.05, z.shape)
    results = []
    for et in (EdgeFactored, EdgeFactoredReduced):
        opt = SparseOptimizer("lm", "dense")
        opt.add_vertices(VertexP3, np.arange(5), np.zeros((5, 3)))
        opt.add_edges(et, ids, z, robust_kernel=kernel, data={"g": g})
        opt.initialize_optimization()
        asm, chi = opt.problem.linearize()
        step = opt.problem.solve(asm, 1e-3)[0]
        res = opt.optimize(15)
        results.append((chi, step, res.chi2_history))
    (c1, s1, h1), (c2, s2, h2) = results
    assert c1 == pytest.approx(c2, rel=1e-12)
    np.testing.assert_allclose(s2, s1, rtol=1e-9, atol=1e-12)
    n = min(len(h1), len(h2))  # the last, converged iterations may differ by rounding only
    np.testing.assert_allclose(h2[:n], h1[:n], rtol=1e-9)
    assert n >= 4


def test_reduced_linearisation_checks_its_output() -> None:
    class Broken(EdgeFactoredReduced):
        @classmethod
        def linearize(cls, x, z, ctx):
            e, j, _, _ = EdgeFactoredReduced.linearize(x, z, ctx)
            return Linearization(e, j)

    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexP3, [0], np.zeros((1, 3)))
    opt.add_edges(Broken, np.zeros((3, 1), int), np.ones((3, 4)),
                  data={"g": np.ones((3, 4, 2)) + np.eye(4, 2)})
    with pytest.raises(GraphError, match="reduced_error"):
        opt.optimize(1)

    class WrongRows(EdgeFactoredReduced):
        @classmethod
        def linearize(cls, x, z, ctx):
            e, j, e_lin, _ = EdgeFactoredReduced.linearize(x, z, ctx)
            return Linearization(e, j, e_lin[:, :1])

    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexP3, [0], np.zeros((1, 3)))
    opt.add_edges(WrongRows, np.zeros((3, 1), int), np.ones((3, 4)),
                  data={"g": np.ones((3, 4, 2)) + np.eye(4, 2)})
    with pytest.raises(GraphError, match=r"needs e_lin \(3, 2\), got shape \(3, 1\)"):
        opt.optimize(1)


def test_linearize_on_trial_reuses_the_accepted_linearisation(monkeypatch) -> None:
    # Small groups of analytic types linearise on trial anyway: not the baseline wanted here.
    monkeypatch.setattr(graphopt.linearizer, "TRIAL_LINEARIZE_EDGES", 0)
    calls = {"lin": 0, "err": 0}

    class Counting(EdgeCurve):
        @classmethod
        def error(cls, x, measurement, ctx):
            calls["err"] += 1
            return EdgeCurve.error(x, measurement, ctx)

        @classmethod
        def linearize(cls, x, measurement, ctx):
            calls["lin"] += 1
            return Linearization(EdgeCurve.error(x, measurement, ctx),
                                 EdgeCurve.jacobians(x, measurement, ctx))

    class OnTrial(Counting):
        linearize_on_trial = True

    meas = curve_data()
    histories = {}
    for et in (Counting, OnTrial):
        calls.update(lin=0, err=0)
        abc, res = fit_curve(meas, LevenbergConfig(tau=1.0), edge=et, iters=8)
        histories[et.__name__] = (res.chi2_history, abc, dict(calls), res)
    h1, a1, c1, _ = histories["Counting"]
    h2, a2, c2, res = histories["OnTrial"]
    assert h1 == h2 and np.array_equal(a1, a2)
    assert c1["lin"] == res.iterations
    # A trial after an accepted one linearises (the next iteration reuses it); a trial after a
    # rejected one evaluates the errors alone. An iteration linearises again only when its
    # accepted trial came after a rejection (the first iteration reuses the initial evaluation).
    trials = res.trials
    assert sum(trials) > len(trials)  # the case under test: some trials were rejected
    after_rejection = sum(t - 1 for t in trials) + (1 if res.info[-1].failed else 0)
    relinearised = sum(1 for t, r in zip(trials[:-1], res.info[:-1], strict=True)
                       if t > 1 and not r.failed)
    # The last iteration a run allows does not linearise on trial (nothing would read it):
    # its first trial, which would have, evaluates the errors alone.
    final = int(len(trials) == 8 and (len(trials) == 1 or not res.info[-2].failed))
    assert final == 1  # the case under test
    assert c2["err"] == after_rejection + final
    assert c2["lin"] == 1 + (sum(trials) - after_rejection) + relinearised - final
    assert c2["lin"] + c2["err"] < c1["lin"] + c1["err"]


def test_derived_vertex_values_reach_the_edges_and_follow_the_state() -> None:
    """``derived`` is computed per state, gathered per edge, and withheld from perturbed calls."""
    seen: list[bool] = []

    class VertexExp(VertexCurve):
        @classmethod
        def derived(cls, estimates):
            return np.exp(estimates[:, 2:3])  # exp(c), shared by all edges of the vertex

    class EdgeExp(EdgeCurveNumeric):  # numeric Jacobians: perturbed calls get no derived values
        vertex_types = (VertexExp,)
        uses_derived = True

        @classmethod
        def error(cls, x, measurement, ctx):
            p = x[0]
            xs, ys = measurement[:, 0], measurement[:, 1]
            ec = np.exp(p[:, 2]) if ctx.derived is None else ctx.derived[0][:, 0]
            seen.append(ctx.derived is not None)
            # A stale or mismatched cache would break the fit below.
            np.testing.assert_allclose(ec, np.exp(p[:, 2]), rtol=1e-15)
            return (ys - np.exp(p[:, 0] * xs**2 + p[:, 1] * xs) * ec)[:, None]

    meas = curve_data(sigma=0.0)
    ref = SparseOptimizer("lm", "dense")
    ref.add_vertices(VertexCurve, [0], [[0.5, 1.5, 0.5]])
    ref.add_edges(EdgeCurve, np.zeros((len(meas), 1), int), meas)
    ref.optimize(30)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexExp, [0], [[0.5, 1.5, 0.5]])
    opt.add_edges(EdgeExp, np.zeros((len(meas), 1), int), meas)
    opt.optimize(30)
    np.testing.assert_allclose(opt.vertex(0).estimate, TRUE_ABC, atol=1e-8)
    np.testing.assert_allclose(opt.vertex(0).estimate, ref.vertex(0).estimate, atol=1e-10)
    assert any(seen) and not all(seen)  # the optimizer's calls had them, the perturbed ones not


def test_push_apply_pop_restores_the_state_exactly() -> None:
    opt, _, init = build_pose_graph("lm")
    opt.initialize_optimization()
    p = opt.problem
    asm, chi = p.linearize()
    step = p.solve(asm, 1e-3)
    p.push()
    p.apply(step)
    moved = opt.estimates_of(VertexSE2)
    assert p.robust_chi2() < chi
    np.testing.assert_array_equal(moved[0], init[0])  # fixed: no column, no update
    np.testing.assert_allclose(moved[1:, :2] - init[1:, :2], step[0].reshape(-1, 3)[:, :2],
                               rtol=1e-12)  # VertexSE2.oplus adds x, y (θ is wrapped)
    p.pop()
    np.testing.assert_array_equal(opt.estimates_of(VertexSE2), init)
    assert p.robust_chi2() == chi


def test_lm_computes_the_damping_once_per_linearisation() -> None:
    """Rejected trials reuse the damping diagonal: one ``damping`` call per iteration."""
    opt, _, _ = build_pose_graph(LevenbergConfig(diagonal_damping=True))
    opt.initialize_optimization()
    system = opt.linear_system
    calls = []
    original = system.damping

    def counting(asm, diagonal):
        calls.append(diagonal)
        return original(asm, diagonal)

    system.damping = counting
    opt.stopping = StoppingConfig.iterations_only()
    res = opt.optimize(30)
    assert sum(r.trials for r in res.info) > len(res.info)  # trials were rejected
    assert calls == [True] * len(res.info)


def test_solve_with_diagonal_damping_matches_a_dense_reference() -> None:
    opt, _, _ = build_pose_graph("lm")
    opt.initialize_optimization()
    p = opt.problem
    asm, _ = p.linearize()
    h = p.system.pattern.copy()
    h.data = asm.h_data.copy()
    hd = h.toarray()
    d = p.damping(asm, True)
    np.testing.assert_array_equal(d[0], np.clip(np.diag(hd), 1e-6, 1e32))
    step = p.solve(asm, 0.3, d)[0]
    np.testing.assert_allclose(step, np.linalg.solve(hd + 0.3 * np.diag(d[0]), asm.bu),
                               rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("kernel", [None, RobustKernelHuber(0.05)])
def test_trial_linearisation_of_small_groups_changes_no_number(monkeypatch, kernel) -> None:
    # Small analytic groups linearise on trial and the next linearize reuses the trial's
    # Jacobians, Ωe, e'Ωe, ρ and ρ' (linearizer.TRIAL_LINEARIZE_EDGES): the same iterations,
    # to the bit, as evaluating errors at the trial and linearising again.
    meas = curve_data()
    assert EdgeCurve.has_analytic_jacobians() and len(meas) <= 32768  # the policy applies
    runs = []
    for limit in (0, graphopt.linearizer.TRIAL_LINEARIZE_EDGES):
        monkeypatch.setattr(graphopt.linearizer, "TRIAL_LINEARIZE_EDGES", limit)
        abc, res = fit_curve(meas, LevenbergConfig(tau=1.0), kernel=kernel, iters=12)
        runs.append((res.chi2_history, res.trials, abc))
    assert sum(runs[0][1]) > len(runs[0][1])  # rejected trials: both paths are exercised
    assert runs[0][0] == runs[1][0] and runs[0][1] == runs[1][1]
    assert np.array_equal(runs[0][2], runs[1][2])
