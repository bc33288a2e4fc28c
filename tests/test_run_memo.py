"""Runs answered from memory (graphopt.run_memo): a run with the inputs of a kept one ends where
that run ended, with its records; any changed input — an estimate, a level, a kernel or its
width, the algorithm, the stopping tests, the cap — computes afresh; levels set to what they are
change nothing."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import graphopt.run_memo as rm
from graphopt import RobustKernelHuber, SparseOptimizer, StoppingConfig
from graphopt.algorithms import LevenbergConfig
from graphopt.types import EdgeSE3ProjectXYZOnlyPose, VertexSE3Expmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import slam_backend_scenes as scenes  # noqa: E402

CHI2 = 5.991


def _problem(m: int = 60) -> tuple[SparseOptimizer, object, object]:
    s = scenes.motion_only(m, False)
    opt = SparseOptimizer(algorithm="lm", solver="dense")
    opt.add_vertices(VertexSE3Expmap, [0], s.T_init[None])
    edges = opt.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((m, 1), dtype=int), s.z,
                          information=s.inv_sigma2[:, None, None] * np.eye(2),
                          robust_kernel=RobustKernelHuber(np.sqrt(CHI2)), params=scenes.CAM,
                          data={"Xw": s.Xw})
    return opt, edges, s


def _run(opt: SparseOptimizer, T: np.ndarray, iterations: int = 10):
    opt.vertex(0).set_estimate(T)
    opt.initialize_optimization(0)
    return opt.optimize(iterations)


def test_the_same_inputs_replay_the_run_and_its_end_state() -> None:
    opt, edges, s = _problem()
    first = _run(opt, s.T_init)
    T_end = opt.vertex(0).estimate.copy()
    chi2_end = edges.chi2()
    assert not first.replayed and first.iterations >= 3
    again = _run(opt, s.T_init)
    assert again.replayed
    assert np.array_equal(opt.vertex(0).estimate, T_end)  # bit for bit
    assert np.array_equal(edges.chi2(), chi2_end)
    assert opt.active_robust_chi2() == first.final_chi2
    assert (again.initial_chi2, again.final_chi2, again.stop_reason) == (
        first.initial_chi2, first.final_chi2, first.stop_reason)
    assert again.chi2_history == first.chi2_history and again.trials == first.trials
    # A fresh optimizer with the same inputs computes the same numbers.
    ref, ref_edges, _ = _problem()
    assert not _run(ref, s.T_init).replayed
    assert np.array_equal(ref.vertex(0).estimate, T_end)
    assert np.array_equal(ref_edges.chi2(), chi2_end)


def test_a_replay_calls_no_edge_type(monkeypatch: pytest.MonkeyPatch, numpy_path: None
                                     ) -> None:
    """The end state's evaluation that a replay makes comes from the evaluation memo (the run's
    last trial's outputs, kept when the run was): the type is not called; a run that is not
    replayed calls it (the numpy path: a compiled loop has no memo)."""
    opt, edges, s = _problem()
    _run(opt, s.T_init)
    calls = []
    for method in ("evaluate", "linearize"):
        real = getattr(EdgeSE3ProjectXYZOnlyPose, method)
        monkeypatch.setattr(EdgeSE3ProjectXYZOnlyPose, method, classmethod(
            lambda cls, *a, _real=real, _m=method: calls.append(_m) or _real(*a)))
    assert _run(opt, s.T_init).replayed and calls == []
    chi2 = opt.active_robust_chi2()
    assert not _run(opt, s.T_init, iterations=9).replayed and calls
    assert _run(opt, s.T_init).replayed and opt.active_robust_chi2() == chi2


def test_every_changed_input_computes_afresh() -> None:
    opt, edges, s = _problem()
    _run(opt, s.T_init)
    assert _run(opt, s.T_init).replayed
    moved = s.T_init.copy()
    moved[0, 3] += 1e-9
    assert not _run(opt, moved).replayed                     # an estimate
    chi2 = edges.chi2()
    edges.set_level((chi2 > CHI2).astype(int))
    assert not _run(opt, s.T_init).replayed                  # levels
    assert _run(opt, s.T_init).replayed
    edges.set_level((chi2 > CHI2).astype(int))                # the same levels again
    assert _run(opt, s.T_init).replayed
    kernel = RobustKernelHuber(2.0)
    edges.set_robust_kernel(kernel)
    assert not _run(opt, s.T_init).replayed                  # another kernel object...
    assert _run(opt, s.T_init).replayed
    kernel.set_delta(1.5)
    assert not _run(opt, s.T_init).replayed                  # ...and its width
    assert not _run(opt, s.T_init, 9).replayed               # the cap
    opt.stopping = StoppingConfig(function_tolerance=1e-7)
    assert not _run(opt, s.T_init, 9).replayed               # the stopping tests
    opt.set_algorithm(LevenbergConfig(tau=1e-4))
    assert not _run(opt, s.T_init, 9).replayed               # the algorithm
    assert _run(opt, s.T_init, 9).replayed


def test_verbose_callbacks_and_stopped_runs_are_not_replayed(capsys: pytest.CaptureFixture
                                                             ) -> None:
    opt, _, s = _problem()
    _run(opt, s.T_init)
    seen: list[int] = []
    opt.add_callback("post_iteration", lambda o, info: seen.append(info.iteration))
    assert not _run(opt, s.T_init).replayed and seen  # callbacks see every iteration
    opt2, _, _ = _problem()
    opt2.verbose = True
    _run(opt2, s.T_init)
    assert not _run(opt2, s.T_init).replayed
    assert capsys.readouterr().err.count("iteration= ") >= 6
    for stop, reason in (("force_stop", "stopped"), ("stop", "interrupted")):
        opt3, _, _ = _problem()
        opt3.add_callback("post_iteration", lambda o, info, stop=stop: getattr(o, stop)())
        assert _run(opt3, s.T_init).stop_reason == reason
        opt3._callbacks["post_iteration"] = []
        assert not _run(opt3, s.T_init).replayed  # the stopped run was not kept


def test_kept_state_is_not_shared_with_the_caller() -> None:
    opt, _, s = _problem()
    first = _run(opt, s.T_init)
    T_end = opt.vertex(0).estimate.copy()
    first.info.clear()  # the caller's records are its own
    opt.vertex(0).set_estimate(s.T_init)  # writes into the live array
    again = _run(opt, s.T_init)
    assert again.replayed and again.iterations > 0
    assert np.array_equal(opt.vertex(0).estimate, T_end)
    opt.vertex(0).set_estimate(np.eye(4))
    assert np.array_equal(opt._problem.runs[next(iter(opt._problem.runs))][0][0][0], T_end)


def test_at_most_memo_runs_are_kept(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rm, "MEMO_RUNS", 2)
    opt, _, s = _problem()
    starts = []
    for k in range(3):
        T = s.T_init.copy()
        T[0, 3] += 1e-6 * k
        starts.append(T)
        _run(opt, T)
    assert len(opt._problem.runs) == 2
    assert not _run(opt, starts[0]).replayed  # the oldest went
    assert _run(opt, starts[2]).replayed


def test_levels_set_to_what_they_are_keep_the_activity_version() -> None:
    opt, edges, _ = _problem(10)
    opt.initialize_optimization(0)
    g = opt._problem.groups[0]
    v = g.activity_version
    edges.set_level(np.zeros(10, dtype=int))
    assert g.activity_version == v
    edges.set_level(np.r_[np.zeros(9, dtype=int), 1])
    assert g.activity_version != v
    v = g.activity_version
    edges[[9, 9]].set_level(1)
    assert g.activity_version == v
    edges[[2]].set_level(1)
    assert g.activity_version != v and list(edges.levels()) == [0, 0, 1] + [0] * 6 + [1]
