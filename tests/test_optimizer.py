"""The core optimizer on custom types written only against the public API."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
from custom_types import (
    EdgeCurve,
    EdgeCurveNumeric,
    EdgeSE2,
    VertexCurve,
    VertexSE2,
    pose_graph,
    relative,
)

from graphopt import (
    BaseEdge,
    DoglegConfig,
    EdgeContext,
    GaussNewtonConfig,
    GraphError,
    LevenbergConfig,
    Linearization,
    NotPositiveDefiniteError,
    RobustKernelCauchy,
    RobustKernelHuber,
    SparseOptimizer,
    VertexVector,
    numeric_jacobians,
)
from graphopt.solvers import CHOLMOD_AVAILABLE, LinearSolverDense

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
    opt = SparseOptimizer(algorithm, solver)
    opt.add_vertices(VertexCurve, [0], [[0.0, 0.0, 0.0]])
    opt.add_edges(edge, np.zeros((len(meas), 1), int), meas, robust_kernel=kernel)
    res = opt.optimize(iters)
    return opt.vertex(0).estimate, res


ALGOS = ["gn", "lm", "dogleg"]
SOLVERS = ["dense", "pcg", "scipy", "auto"] + (["cholmod"] if CHOLMOD_AVAILABLE else [])


@pytest.mark.parametrize("algorithm", ["lm", "dogleg"])
def test_curve_fit_converges(algorithm: str) -> None:
    meas = curve_data(sigma=0.1)
    abc, res = fit_curve(meas, algorithm)
    np.testing.assert_allclose(abc, TRUE_ABC, atol=0.05)
    # At the optimum chi2 ≈ N σ² (200 · 0.01 = 2) within sampling spread.
    assert 1.4 < res.final_chi2 < 2.6
    assert res.final_chi2 < res.initial_chi2 / 1e3
    assert all(b <= a + 1e-9 for a, b in zip([res.initial_chi2] + res.chi2_history,
                                             res.chi2_history, strict=False))


def test_gauss_newton_curve_fit_from_a_close_start() -> None:
    meas = curve_data(sigma=0.1)
    opt = SparseOptimizer("gn", "dense")
    opt.add_vertices(VertexCurve, [0], [[0.8, 2.2, 0.9]])
    opt.add_edges(EdgeCurve, np.zeros((len(meas), 1), int), meas)
    opt.optimize(20)
    ref, _ = fit_curve(meas, "lm")
    np.testing.assert_allclose(opt.vertex(0).estimate, ref, atol=1e-8)


@pytest.mark.parametrize("algorithm", ALGOS)
@pytest.mark.parametrize("kernel", [RobustKernelCauchy(1.0), RobustKernelHuber(0.5)])
def test_robust_kernel_rejects_outliers(algorithm: str, kernel) -> None:
    meas = curve_data(sigma=0.1, outliers=0.15, seed=3)
    start_close = algorithm == "gn"
    plain, _ = fit_curve(meas, "lm")
    opt = SparseOptimizer(algorithm, "dense")
    opt.add_vertices(VertexCurve, [0], [plain if start_close else [0.0, 0.0, 0.0]])
    opt.add_edges(EdgeCurve, np.zeros((len(meas), 1), int), meas, robust_kernel=kernel)
    res = opt.optimize(100)
    robust = opt.vertex(0).estimate
    err_plain = np.abs(plain - TRUE_ABC).max()
    err_robust = np.abs(robust - TRUE_ABC).max()
    assert err_plain > 0.2, err_plain  # the outliers do bias least squares
    assert err_robust < 0.1, err_robust
    assert np.isfinite(res.final_chi2) and res.final_chi2 < res.initial_chi2


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


@pytest.mark.parametrize("algorithm", ALGOS)
def test_pose_graph_converges(algorithm: str) -> None:
    opt, truth, init = build_pose_graph(algorithm)
    res = opt.optimize(30)
    est = opt.estimates_of(VertexSE2)
    assert res.final_chi2 < res.initial_chi2 / 10
    # 52 edges of 3 dof, 39 free poses: chi2 ≈ 3·52 − 3·39 = 39 at the optimum, give or take.
    assert res.final_chi2 < 120
    err = relative(truth, est)
    assert np.abs(err[:, :2]).max() < 0.3 and np.abs(err[:, 2]).max() < 0.05
    np.testing.assert_array_equal(est[0], init[0])  # the fixed vertex stays put


def test_algorithms_agree_on_pose_graph() -> None:
    finals = {}
    for algorithm in ALGOS:
        opt, _, _ = build_pose_graph(algorithm)
        finals[algorithm] = (opt.optimize(40).final_chi2, opt.estimates_of(VertexSE2))
    ref_chi, ref_est = finals["lm"]
    for chi, est in finals.values():
        assert abs(chi - ref_chi) < 1e-6 * ref_chi
        np.testing.assert_allclose(est, ref_est, atol=1e-6)


def test_per_object_api_equals_bulk() -> None:
    a, _, _ = build_pose_graph(per_object=False)
    b, _, _ = build_pose_graph(per_object=True)
    ra, rb = a.optimize(10), b.optimize(10)
    assert ra.chi2_history == pytest.approx(rb.chi2_history, rel=1e-12)
    np.testing.assert_allclose(a.estimates_of(VertexSE2), b.estimates_of(VertexSE2), atol=1e-12)
    assert len(b.edges()) == b.num_edges() == a.num_edges()
    assert b.edges()[0].chi2() >= 0.0
    assert b.vertex(0).fixed() and not b.vertex(1).fixed()


@pytest.mark.parametrize("solver", SOLVERS)
def test_solvers_give_the_same_step(solver: str) -> None:
    steps = {}
    for name in ("dense", solver):
        opt, _, _ = build_pose_graph("lm", name)
        opt.initialize_optimization()
        asm, _ = opt.linearize()
        steps[name] = opt.solve(asm, 1e-2)[0]
    np.testing.assert_allclose(steps[solver], steps["dense"], rtol=1e-7, atol=1e-9)
    assert np.abs(steps["dense"]).max() > 1e-3  # a real step, not zeros


def test_fixed_vertices_stay_put() -> None:
    opt, _, init = build_pose_graph("lm")
    fixed = [0, 7, 21]
    for i in fixed:
        opt.vertex(i).set_fixed(True)
    opt.optimize(10)
    est = opt.estimates_of(VertexSE2)
    np.testing.assert_array_equal(est[fixed], init[fixed])
    assert np.abs(est[1:7] - init[1:7]).max() > 1e-4


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
    system = opt._system
    opt.optimize(5)
    assert CountingDense.analyses == 1 and opt._system is system
    opt.vertex(3).set_fixed(True)  # a structural change triggers one new analysis
    opt.optimize(1)
    assert CountingDense.analyses == 2


def test_verbose_prints_g2o_lines() -> None:
    out = io.StringIO()
    opt, _, _ = build_pose_graph("lm")
    opt.stream = out
    opt.set_verbose(True)
    res = opt.optimize(3)
    lines = out.getvalue().strip().splitlines()
    assert len(lines) == 3
    pat = (r"^iteration= (\d+)\t chi2= (\d+\.\d{6})\t time= \S+\t cumTime= \S+\t "
           r"edges= (\d+)\t schur= 0\t lambda= [0-9.e+-]+\t levenbergIter= \d+$")
    for i, line in enumerate(lines):
        m = re.match(pat, line)
        assert m, line
        assert int(m.group(1)) == i and int(m.group(3)) == opt.num_edges()
        assert float(m.group(2)) == pytest.approx(res.chi2_history[i], rel=1e-6)


def test_callbacks_and_force_stop() -> None:
    opt, _, _ = build_pose_graph("lm")
    seen = []

    def post(o, info):
        seen.append(info.chi2)
        if info.iteration == 1:
            o.force_stop()

    opt.add_callback("pre_iteration", lambda o, info: seen.append(("pre", info.iteration)))
    opt.add_callback("post_iteration", post)
    res = opt.optimize(10)
    assert res.iterations == 2 and res.stop_reason == "stopped"
    assert seen[0] == ("pre", 0) and seen[2] == ("pre", 1) and seen[3] == res.final_chi2


def test_gain_threshold_stops_early() -> None:
    opt, _, _ = build_pose_graph("lm")
    opt.gain_threshold = 1e-3
    res = opt.optimize(100)
    assert res.stop_reason == "gain" and res.iterations < 100
    gains = np.diff(res.chi2_history) / np.array(res.chi2_history[1:])
    assert -gains[-1] < 1e-3


def test_result_times_and_history() -> None:
    opt, _, _ = build_pose_graph("lm")
    res = opt.optimize(5)
    assert res.iterations == len(res.chi2_history) == len(res.linearize_seconds) == 5
    assert all(t > 0 for t in res.linearize_seconds + res.solve_seconds)
    assert res.seconds >= sum(res.linearize_seconds)
    assert res.final_chi2 == res.chi2_history[-1] == pytest.approx(opt.active_robust_chi2())


def test_lm_retries_when_not_positive_definite() -> None:
    class FlakyDense(LinearSolverDense):
        failures = 2

        def solve(self, data, rhs):
            if FlakyDense.failures > 0:
                FlakyDense.failures -= 1
                raise NotPositiveDefiniteError("simulated")
            return super().solve(data, rhs)

    opt, _, _ = build_pose_graph("lm", FlakyDense())
    ref, _, _ = build_pose_graph("lm")
    res = opt.optimize(30)
    assert res.not_positive_definite == 2
    assert res.info[0].trials >= 3 and res.info[0].not_pd == 2
    assert res.lambda_history[0] > 2 * ref.optimize(1).lambda_history[0]
    assert np.all(np.isfinite(opt.estimates_of(VertexSE2)))
    assert res.final_chi2 < res.initial_chi2 / 10


def test_gauss_newton_on_singular_system_reports_failure_without_nan() -> None:
    truth, init, edges, meas = pose_graph(10)
    opt = SparseOptimizer("gn", "dense")
    opt.add_vertices(VertexSE2, np.arange(10), init)  # no vertex fixed: gauge freedom
    opt.add_edges(EdgeSE2, edges, meas)
    res = opt.optimize(5)
    assert res.stop_reason == "failed" and res.not_positive_definite >= 1
    np.testing.assert_array_equal(opt.estimates_of(VertexSE2), init)


def test_lm_handles_gauge_freedom() -> None:
    truth, init, edges, meas = pose_graph(10)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, np.arange(10), init)
    opt.add_edges(EdgeSE2, edges, meas)
    res = opt.optimize(20)
    assert np.all(np.isfinite(opt.estimates_of(VertexSE2)))
    assert res.final_chi2 < res.initial_chi2


def test_algorithm_configs() -> None:
    opt, _, _ = build_pose_graph(LevenbergConfig(tau=1e-3, max_trials=5))
    r1 = opt.optimize(1)
    opt2, _, _ = build_pose_graph(LevenbergConfig())
    r2 = opt2.optimize(1)
    assert r1.lambda_history[0] == pytest.approx(100 * r2.lambda_history[0])
    for cfg in (GaussNewtonConfig(), DoglegConfig(initial_radius=10.0)):
        o, _, _ = build_pose_graph(cfg)
        assert o.optimize(20).final_chi2 < 120
    with pytest.raises(ValueError, match="unknown algorithm"):
        SparseOptimizer("newton")
    with pytest.raises(ValueError, match="unknown linear solver"):
        SparseOptimizer("lm", "qr").optimize(1)


def test_cholmod_fallback_warns_once(monkeypatch) -> None:
    import graphopt.solvers as solvers

    monkeypatch.setattr(solvers, "CHOLMOD_AVAILABLE", False)
    monkeypatch.setattr(solvers, "_warned", False)
    with pytest.warns(RuntimeWarning, match="CHOLMOD .* not available.*'scipy'"):
        first = solvers.make_solver("cholmod")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = solvers.make_solver("cholmod")  # no second warning
    assert first.name == second.name == "scipy"
    opt, _, _ = build_pose_graph("lm", "cholmod")
    assert opt.optimize(10).final_chi2 < 120


def test_pcg_tolerance_and_iteration_cap() -> None:
    from graphopt import LinearSolverPCG, PCGConfig

    opt, _, _ = build_pose_graph("lm", "dense")
    opt.initialize_optimization()
    asm, _ = opt.linearize()
    ref = opt.solve(asm, 1e-2)[0]
    s, rhs, _ = opt._system.reduce(asm, 1e-2)
    for cfg, close in ((PCGConfig(tolerance=1e-12), True), (PCGConfig(max_iterations=2), False)):
        pcg = LinearSolverPCG(cfg)
        pcg.analyze(opt._system.pattern, opt._system.udims)
        x = pcg.solve(s, rhs)
        assert np.allclose(x, ref, rtol=1e-7, atol=1e-9) == close
        if not close:
            assert pcg.last_iterations == 2


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


def test_lm_diagonal_damping_converges_to_the_same_optimum() -> None:
    a, _, _ = build_pose_graph(LevenbergConfig(diagonal_damping=True))
    b, _, _ = build_pose_graph("lm")
    ra, rb = a.optimize(40), b.optimize(40)
    assert ra.final_chi2 == pytest.approx(rb.final_chi2, rel=1e-6)
    assert ra.lambda_history[0] == pytest.approx(1e-4)


def test_auto_solver_chooses_by_size_and_fill() -> None:
    from graphopt.solvers import LinearSolverAuto

    opt, _, _ = build_pose_graph("lm", LinearSolverAuto())
    opt.initialize_optimization()
    assert opt.solver.chosen.name == "dense"  # 117 unknowns
    opt2, _, _ = build_pose_graph("lm", LinearSolverAuto(dense_max_size=50))
    opt2.initialize_optimization()
    assert opt2.solver.chosen.name in ("cholmod", "scipy")
    assert opt.optimize(20).final_chi2 == pytest.approx(opt2.optimize(20).final_chi2, rel=1e-9)


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
        asm, chi = opt.linearize()
        step = opt.solve(asm, 1e-3)[0]
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


def test_linearize_on_trial_reuses_the_accepted_linearisation() -> None:
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
        abc, res = fit_curve(meas, "lm", edge=et, iters=8)
        histories[et.__name__] = (res.chi2_history, abc, dict(calls), sum(res.trials))
    h1, a1, c1, t1 = histories["Counting"]
    h2, a2, c2, t2 = histories["OnTrial"]
    assert h1 == h2 and np.array_equal(a1, a2)
    assert c1["lin"] == 8 and c2["err"] == 0
    # One linearisation per trial plus the first: accepted trials are not linearised again.
    assert c2["lin"] == t2 + 1
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
