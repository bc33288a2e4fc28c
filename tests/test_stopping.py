"""The stopping tests: each fires where its definition says, and names itself."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import ALGOS, build_pose_graph

from graphopt import StoppingConfig, StopReason

OFF = {"function_tolerance": 0.0, "gradient_tolerance": 0.0, "parameter_tolerance": 0.0}


def _max_gradient(opt) -> float:
    asm, _ = opt.problem.linearize()
    return opt.problem.max_abs(opt.problem.gradient(asm))


@pytest.mark.parametrize("algorithm", ALGOS)
def test_defaults_stop_at_convergence_by_function_tolerance(algorithm: str) -> None:
    opt, _, _ = build_pose_graph(algorithm)
    res = opt.optimize(100)
    assert res.stop_reason == StopReason.FUNCTION_TOLERANCE and res.stop_reason.converged
    assert res.iterations < 30
    chi = [res.initial_chi2, *res.chi2_history]
    changes = [abs(a - b) / a for a, b in zip(chi, chi[1:], strict=False)]
    # Every iteration before the last changed chi2 by more than the tolerance; the last did
    # not (or was a rejected trial whose change was that small: chi2 unchanged).
    assert all(c > 1e-6 for c in changes[:-1]) and changes[-1] <= 1e-6
    ref, _, _ = build_pose_graph("gn")
    ref.stopping = StoppingConfig.iterations_only()
    best = ref.optimize(50).final_chi2
    assert res.final_chi2 == pytest.approx(best, rel=1e-6)


def test_gradient_tolerance_stops_when_the_gradient_is_small() -> None:
    opt, _, _ = build_pose_graph("lm")
    tol = 1e-3
    opt.stopping = StoppingConfig(**OFF | {"gradient_tolerance": tol})
    res = opt.optimize(100)
    assert res.stop_reason == StopReason.GRADIENT_TOLERANCE
    assert _max_gradient(opt) <= tol
    # The stop came at the first linearisation below the tolerance, which is not an iteration:
    # the state after the last iteration is the one whose gradient was measured.
    assert res.final_chi2 == res.chi2_history[-1] == pytest.approx(opt.active_robust_chi2())
    again, _, _ = build_pose_graph("lm")
    again.stopping = StoppingConfig.iterations_only(res.iterations - 1)
    again.optimize()
    assert _max_gradient(again) > tol


def test_parameter_tolerance_stops_before_applying_a_negligible_step() -> None:
    opt, _, _ = build_pose_graph("gn")
    opt.stopping = StoppingConfig(**OFF | {"parameter_tolerance": 1e-6})
    res = opt.optimize(100)
    assert res.stop_reason == StopReason.PARAMETER_TOLERANCE
    last = res.info[-1]
    assert last.failed and last.chi2 == res.chi2_history[-2] == res.final_chi2  # not applied
    assert res.iterations < 100


def test_the_cap_and_optimize_without_a_count() -> None:
    opt, _, _ = build_pose_graph("lm")
    opt.stopping = StoppingConfig.iterations_only(3)
    res = opt.optimize()
    assert res.iterations == 3 and res.stop_reason == StopReason.ITERATIONS
    opt2, _, _ = build_pose_graph("lm")
    opt2.stopping = StoppingConfig.iterations_only(50)
    assert opt2.optimize(2).iterations == 2  # an explicit count overrides max_iterations


def test_gain_threshold_is_g2os_relative_decrease() -> None:
    cfg = StoppingConfig(gain_threshold=1e-3)
    assert cfg.gain_reached(100.0, 99.95) and not cfg.gain_reached(100.0, 99.0)
    assert not cfg.gain_reached(100.0, 100.5)  # an increase (GN) is not a small gain
    assert not StoppingConfig().gain_reached(100.0, 100.0)  # off by default


def test_the_tests_definitions() -> None:
    cfg = StoppingConfig()
    assert (cfg.max_iterations, cfg.function_tolerance, cfg.gradient_tolerance,
            cfg.parameter_tolerance) == (50, 1e-6, 1e-10, 1e-8)  # Ceres' defaults
    assert cfg.function_converged(1000.0, 1000.0 - 1e-3) and not cfg.function_converged(
        1000.0, 1000.0 - 2e-3)
    assert cfg.function_converged(1000.0, 1000.0 + 1e-3)  # a rejected step counts too
    assert cfg.parameters_converged(1e-8 * (2.0 + 1e-8), 2.0)
    assert not cfg.parameters_converged(1.01e-8 * 2.0, 2.0)
    assert cfg.gradient_converged(1e-10) and not cfg.gradient_converged(1.1e-10)


@pytest.mark.parametrize("bad", [{"max_iterations": -1}, {"max_iterations": 2.5},
                                 {"function_tolerance": -1.0}, {"gradient_tolerance": np.nan},
                                 {"gain_threshold": -0.1}])
def test_invalid_configs_are_refused(bad: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        StoppingConfig(**bad)
