"""The g2o facade and the iteration loop (graphopt.optimizer, graphopt.result)."""

from __future__ import annotations

import io
import json
import re

import numpy as np
import pytest
from custom_types import VertexSE2
from graphs import build_pose_graph

from graphopt import SparseOptimizer, StoppingConfig, StopReason


def test_per_object_api_equals_bulk() -> None:
    a, _, _ = build_pose_graph(per_object=False)
    b, _, _ = build_pose_graph(per_object=True)
    ra, rb = a.optimize(10), b.optimize(10)
    assert ra.chi2_history == pytest.approx(rb.chi2_history, rel=1e-12)
    np.testing.assert_allclose(a.estimates_of(VertexSE2), b.estimates_of(VertexSE2), atol=1e-12)
    assert len(b.edges()) == b.num_edges() == a.num_edges()
    assert b.edges()[0].chi2() >= 0.0
    assert b.vertex(0).fixed() and not b.vertex(1).fixed()


def test_fixed_vertices_stay_put() -> None:
    opt, _, init = build_pose_graph("lm")
    fixed = [0, 7, 21]
    for i in fixed:
        opt.vertex(i).set_fixed(True)
    opt.optimize(10)
    est = opt.estimates_of(VertexSE2)
    np.testing.assert_array_equal(est[fixed], init[fixed])
    assert np.abs(est[1:7] - init[1:7]).max() > 1e-4


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
    opt.stopping = StoppingConfig(100, 0.0, 0.0, 0.0, gain_threshold=1e-3)
    res = opt.optimize()
    assert res.stop_reason == "gain" and res.iterations < 100
    gains = np.diff(res.chi2_history) / np.array(res.chi2_history[1:])
    assert -gains[-1] < 1e-3


def test_result_times_and_history() -> None:
    opt, _, _ = build_pose_graph("lm")
    opt.stopping = StoppingConfig.iterations_only()
    res = opt.optimize(5)
    assert res.iterations == len(res.chi2_history) == len(res.linearize_seconds) == 5
    assert all(t > 0 for t in res.linearize_seconds + res.solve_seconds)
    assert res.seconds >= sum(res.linearize_seconds)
    assert res.final_chi2 == res.chi2_history[-1] == pytest.approx(opt.active_robust_chi2())


@pytest.mark.parametrize(("algorithm", "fields"), [
    ("gn", r"$"),
    ("dogleg", r"\t delta= \d+\.\d{6}\t lambda= [0-9.e+-]+$"),
])
def test_each_algorithm_prints_its_own_line_fields(algorithm: str, fields: str) -> None:
    out = io.StringIO()
    opt, _, _ = build_pose_graph(algorithm)
    opt.stream = out
    opt.set_verbose(True)
    opt.optimize(2)
    lines = out.getvalue().strip().splitlines()
    assert len(lines) == 2
    for line in lines:
        assert re.search(r"\t schur= 0" + fields, line), line


def test_stop_reason_is_an_enum_equal_to_its_word() -> None:
    opt, _, _ = build_pose_graph("lm")
    res = opt.optimize(3)
    assert res.stop_reason is StopReason.ITERATIONS and res.stop_reason == "iterations"
    assert f"{res.stop_reason}" == "iterations"
    assert json.loads(json.dumps({"s": res.stop_reason})) == {"s": "iterations"}


def test_histories_are_views_of_the_iteration_records() -> None:
    """A last iteration without an acceptable step is an iteration like the others."""
    opt, _, _ = build_pose_graph("lm")
    opt.stopping = StoppingConfig.iterations_only()
    res = opt.optimize(200)
    assert res.stop_reason == StopReason.CONVERGED
    assert res.info[-1].failed and not any(r.failed for r in res.info[:-1])
    assert res.iterations == len(res.info) == len(res.chi2_history) == res.accepted_iterations + 1
    assert res.chi2_history == [r.chi2 for r in res.info]
    assert res.chi2_history[-1] == res.chi2_history[-2] == res.final_chi2  # nothing changed
    assert res.trials == [r.trials for r in res.info] and res.trials[-1] == 10
    assert res.iteration_seconds == [r.seconds for r in res.info]
    assert res.seconds_per_iteration == pytest.approx(res.seconds / res.iterations)
    assert all(r.seconds >= r.linearize_seconds + r.solve_seconds for r in res.info)


def test_problem_exists_after_initialisation_only() -> None:
    opt, _, _ = build_pose_graph("lm", solver="auto")
    assert opt.problem is None and opt.linear_system is None and opt.solver is None
    opt.initialize_optimization()
    assert opt.linear_system is opt.problem.system and opt.linear_system.n == 39 * 3
    assert opt.solver is opt.problem.solver and opt.solver.name == "auto"
    assert SparseOptimizer().optimize(0).iterations == 0  # library default solver: auto


@pytest.mark.parametrize("algorithm", ["lm", "dogleg"])
def test_stop_between_trials_restores_the_estimate(algorithm: str) -> None:
    """A stop request during an iteration ends it after the rejected trial, state restored."""
    opt, _, _ = build_pose_graph(algorithm)
    opt.optimize(1)
    start = opt.estimates_of(VertexSE2)
    chi = opt.active_robust_chi2()
    p = opt.problem
    trial_chi2 = p.robust_chi2
    calls = []

    def rejecting(linearize: bool = True) -> float:  # the user presses Ctrl-C mid-iteration
        calls.append(trial_chi2(linearize))
        opt.stop()
        return float("inf")

    p.robust_chi2 = rejecting
    res = opt.optimize(10)
    assert res.stop_reason is StopReason.INTERRUPTED and len(calls) == 1
    assert res.iterations == 1 and res.info[0].failed and res.info[0].trials == 1
    np.testing.assert_array_equal(opt.estimates_of(VertexSE2), start)
    assert res.final_chi2 == chi == opt.active_robust_chi2()


def test_stop_ends_the_run_at_the_next_safe_point_as_interrupted() -> None:
    import threading

    opt, _, _ = build_pose_graph("lm")
    ref = build_pose_graph("lm")[0].optimize(2)
    opt.add_callback("post_iteration", lambda o, info: info.iteration == 1 and o.stop())
    res = opt.optimize(50)
    assert res.stop_reason is StopReason.INTERRUPTED and res.iterations == 2
    assert res.final_chi2 == ref.final_chi2 == opt.active_robust_chi2()
    # A request from another thread (here before the run) is cleared when a run starts.
    other, _, _ = build_pose_graph("lm")
    timer = threading.Timer(0.0, other.stop)
    timer.start()
    timer.join()
    res = other.optimize(3)
    assert res.stop_reason == "iterations" and res.iterations == 3


@pytest.mark.parametrize("algorithm", ["gn", "lm", "dogleg"])
def test_optimizer_is_freed_without_the_garbage_collector(algorithm: str) -> None:
    """No reference cycle keeps a finished optimizer (and its problem's arrays) alive until
    the collector runs: the next problem built would pay for fresh memory."""
    import gc
    import weakref

    opt, _, _ = build_pose_graph(algorithm)
    opt.optimize(3)
    problem = weakref.ref(opt._problem)
    gone = weakref.ref(opt)
    gc.disable()
    try:
        del opt
        assert gone() is None and problem() is None
    finally:
        gc.enable()
