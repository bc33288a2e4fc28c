"""Gauss–Newton, Levenberg–Marquardt and Dogleg on custom types (graphopt.algorithms)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from custom_types import (
    EdgeCurve,
    EdgeSE2,
    VertexCurve,
    VertexSE2,
    pose_graph,
    relative,
)
from graphs import ALGOS, TRUE_ABC, build_pose_graph, curve_data, fit_curve

from graphopt import (
    DoglegConfig,
    GaussNewtonConfig,
    LevenbergConfig,
    NotPositiveDefiniteError,
    PCGConfig,
    RobustKernelCauchy,
    RobustKernelHuber,
    SparseOptimizer,
    StoppingConfig,
)
from graphopt.algorithms import Dogleg, LevenbergMarquardt, make_algorithm
from graphopt.solvers import CHOLMOD_AVAILABLE, LinearSolverDense


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


@pytest.mark.parametrize("solver", [
    "dense",
    pytest.param("cholmod", marks=pytest.mark.skipif(
        not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed: 'cholmod' "
        "would fall back to 'scipy'")),
    "scipy",
])
def test_gauss_newton_on_singular_system_reports_failure_without_nan(solver: str) -> None:
    truth, init, edges, meas = pose_graph(10)
    opt = SparseOptimizer("gn", solver)
    opt.add_vertices(VertexSE2, np.arange(10), init)  # no vertex fixed: gauge freedom
    opt.add_edges(EdgeSE2, edges, meas)
    res = opt.optimize(5)
    assert res.stop_reason == "singular"
    assert len(res.info) == 1 and res.info[0].singular == 1 and res.not_positive_definite == 1
    assert res.final_chi2 == res.initial_chi2 == pytest.approx(0.024341, rel=1e-4)
    np.testing.assert_array_equal(opt.estimates_of(VertexSE2), init)  # no step applied, no NaN


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


def test_lm_diagonal_damping_converges_to_the_same_optimum() -> None:
    a, _, _ = build_pose_graph(LevenbergConfig(diagonal_damping=True))
    b, _, _ = build_pose_graph("lm")
    ra, rb = a.optimize(40), b.optimize(40)
    assert ra.final_chi2 == pytest.approx(rb.final_chi2, rel=1e-6)
    assert ra.lambda_history[0] == pytest.approx(1e-4)


def test_algorithms_are_dispatched_by_config_type() -> None:
    @dataclass(frozen=True)
    class MyLevenberg(LevenbergConfig):
        note: str = "mine"

    assert isinstance(make_algorithm(MyLevenberg()), LevenbergMarquardt)
    assert isinstance(make_algorithm("DogLeg"), Dogleg)
    with pytest.raises(TypeError, match="not an algorithm configuration"):
        make_algorithm(PCGConfig())  # type: ignore[arg-type]


def test_dogleg_reports_the_trials_it_made() -> None:
    """A Dogleg iteration that gives up early reports the trials made, not its cap."""
    opt, _, _ = build_pose_graph(DoglegConfig(max_trials=100))
    opt.stopping = StoppingConfig.iterations_only()
    res = opt.optimize(200)
    assert res.stop_reason == "converged" and res.info[-1].failed
    assert 1 <= res.info[-1].trials < 100


def test_gtsam_schedule_divides_and_multiplies_lambda_by_its_factor() -> None:
    opt, _, _ = build_pose_graph(LevenbergConfig(schedule="gtsam", factor=10.0))
    res = opt.optimize(30)
    lams, trials = res.lambda_history, res.trials
    assert lams[0] == 1e-5  # GTSAM's initial λ, absolute
    for a, b, t in zip(lams, lams[1:], trials[1:], strict=False):
        # after an accepted step λ/10, then ×10 for every rejected trial before the next one
        assert b == pytest.approx(a / 10.0 * 10.0 ** (t - 1), rel=1e-12)
    assert res.final_chi2 == pytest.approx(build_pose_graph("gn")[0].optimize(30).final_chi2,
                                           rel=1e-9)
    with pytest.raises(ValueError, match="unknown LM schedule"):
        LevenbergConfig(schedule="nielsen")
    with pytest.raises(ValueError, match="factor must be > 1"):
        LevenbergConfig(schedule="gtsam", factor=1.0)


@pytest.mark.parametrize("free_poses", [1, 2])
def test_a_trial_predicted_to_end_the_run_does_not_linearise(
        monkeypatch: pytest.MonkeyPatch, free_poses: int) -> None:
    """LM's trial whose predicted decrease is under half the function tolerance evaluates
    errors only: the same iterations as when every trial linearises, fewer Jacobians (the
    single-vertex and the general problem)."""
    from test_single_block import one_free_pose

    from graphopt.types import EdgeSE3ProjectXYZOnlyPose

    calls = {"n": 0}
    orig = EdgeSE3ProjectXYZOnlyPose.linearize.__func__

    def counted(cls: type, *args: object) -> object:
        calls["n"] += 1
        return orig(cls, *args)

    monkeypatch.setattr(EdgeSE3ProjectXYZOnlyPose, "linearize", classmethod(counted))
    runs = []
    for predict in (True, False):
        if not predict:
            monkeypatch.setattr(StoppingConfig, "predicts_function", lambda self, chi, d: False)
        opt = one_free_pose(False)
        if free_poses == 2:
            opt.vertex(1).set_fixed(False)
        calls["n"] = 0
        res = opt.optimize(20)
        assert res.stop_reason is not None and res.stop_reason.value == "function_tolerance"
        runs.append(([i.chi2 for i in res.info], calls["n"], opt.vertex(0).estimate))
    (chi_a, n_a, x_a), (chi_b, n_b, x_b) = runs
    assert chi_a == chi_b
    np.testing.assert_array_equal(x_a, x_b)
    assert n_a == n_b - 1  # the last trial's Jacobians
