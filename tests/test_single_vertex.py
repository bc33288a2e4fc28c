"""One free vertex: :class:`SingleVertexProblem` runs the same iterations as the general
:class:`Problem` (every algorithm, levels, kernels, edits between runs, an idle vertex), gives
the same marginals, and is chosen only where it applies."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from custom_types import EdgeCurve, EdgeCurveAutodiff, VertexCurve
from graphs import curve_data
from test_single_block import CAM, one_free_pose

from graphopt import RobustKernelHuber, SparseOptimizer
from graphopt.problem import Problem
from graphopt.single_vertex import SingleVertexProblem
from graphopt.solvers import LinearSolverDense
from graphopt.solvers.cholmod import LinearSolverCholmod
from graphopt.stopping import StoppingConfig
from graphopt.types import EdgeSE3ProjectXYZOnlyPose, VertexSE3Expmap


@pytest.fixture
def general(monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """Call to make the optimizers initialised afterwards use the general problem."""
    def use() -> None:
        monkeypatch.setattr(SingleVertexProblem, "of", classmethod(lambda cls, *a, **k: None))
    return use


def _run(opt: SparseOptimizer, rounds: int = 1) -> list[tuple[float, float, int, bool]]:
    """ORB-SLAM's rounds: optimise, move the projections with the largest chi2 (above its 70th
    percentile) to level 1, drop their kernels after the first round, start again from the
    first estimate."""
    start = opt.vertex(0).estimate.copy()
    proj = opt.edge_groups()[0]
    out = []
    for r in range(rounds):
        opt.vertex(0).set_estimate(start)
        opt.initialize_optimization(0)
        res = opt.optimize(10)
        out += [(i.chi2, i.lam, i.trials, i.failed) for i in res.info]
        if rounds > 1:
            levels = (proj.last_chi2 > np.quantile(proj.last_chi2, 0.7)).astype(int)
            proj.set_levels(np.arange(proj.size), levels)
            if r == 0:
                proj.set_kernel(np.arange(proj.size), None)
    return out


def _compare(fast: SparseOptimizer, slow: SparseOptimizer, a: list, b: list) -> None:
    assert isinstance(fast.problem, SingleVertexProblem)
    assert type(slow.problem) is Problem
    assert len(a) == len(b) > 1
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x[:2], y[:2], rtol=1e-9)
        assert x[2:] == y[2:]
    np.testing.assert_allclose(fast.vertex(0).estimate, slow.vertex(0).estimate, atol=1e-10)


@pytest.mark.parametrize("algorithm", ["lm", "gn", "dogleg"])
@pytest.mark.parametrize("levels", [False, True])
def test_the_same_iterations_as_the_general_problem(general: Callable[[], None],
                                                    algorithm: str, levels: bool) -> None:
    fast = one_free_pose(levels)
    fast.set_algorithm(algorithm)
    a = _run(fast)
    general()
    slow = one_free_pose(levels)
    slow.set_algorithm(algorithm)
    _compare(fast, slow, a, _run(slow))


def test_rounds_with_levels_and_kernels_edited_between_them(general: Callable[[], None]
                                                            ) -> None:
    fast = one_free_pose(False)
    a = _run(fast, rounds=3)
    general()
    slow = one_free_pose(False)
    _compare(fast, slow, a, _run(slow, rounds=3))
    g_fast, g_slow = fast.edge_groups()[0], slow.edge_groups()[0]
    assert 0 < int(g_fast.levels.sum()) < g_fast.size  # some edges did move
    np.testing.assert_array_equal(g_fast.levels, g_slow.levels)


def test_an_idle_vertex_keeps_its_estimate(general: Callable[[], None]) -> None:
    """Every edge on the free vertex at level 1: Gauss–Newton, without a gradient test, takes
    zero steps on both paths (the identity anchors the vertex; without it H is singular)."""
    results = []
    for use_general in (False, True):
        if use_general:
            general()
        opt = one_free_pose(False)
        opt.set_algorithm("gn")
        opt.stopping = StoppingConfig.iterations_only()
        before = opt.vertex(0).estimate.copy()
        for g in opt.edge_groups():
            g.set_levels(np.arange(g.size), np.ones(g.size, dtype=int))
        opt.initialize_optimization(0)
        res = opt.optimize(3)
        np.testing.assert_array_equal(opt.vertex(0).estimate, before)
        assert res.info and not any(i.failed or i.not_pd for i in res.info)
        results.append((res.initial_chi2, res.final_chi2, len(res.info)))
    assert results[0] == results[1]


def test_marginals_are_the_general_problems(general: Callable[[], None]) -> None:
    fast = one_free_pose(True)
    fast.optimize(5)
    cov = fast.compute_marginals([0])[0]
    general()
    slow = one_free_pose(True)
    slow.optimize(5)
    np.testing.assert_allclose(cov, slow.compute_marginals([0])[0], rtol=1e-7)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_chosen_only_where_it_applies() -> None:
    opt = one_free_pose(False)
    opt.initialize_optimization()
    assert isinstance(opt.problem, SingleVertexProblem)
    assert opt.linear_system is not None and not opt.linear_system.schur  # built on use
    opt = one_free_pose(False)
    opt.vertex(1).set_fixed(False)  # two free vertices
    opt.initialize_optimization()
    assert type(opt.problem) is Problem
    for solver in (LinearSolverCholmod(), type("Mine", (LinearSolverDense,), {})()):
        opt = one_free_pose(False)  # a solver the user chose (not the dense one by name)
        opt.set_solver(solver)
        opt.initialize_optimization()
        assert type(opt.problem) is Problem
        assert opt.problem.solver is solver


def _with_a_point_at_the_camera_centre() -> tuple[SparseOptimizer, object]:
    opt = one_free_pose(False)
    T = opt.vertex(0).estimate
    centre = -T[:3, :3].T @ T[:3, 3]  # projects to 0/0: a non-finite error and Jacobian
    bad = opt.add_edges(EdgeSE3ProjectXYZOnlyPose, [[0]], [[320.0, 240.0]], params=CAM,
                        data={"Xw": centre[None]})
    bad.set_level(1)
    return opt, bad


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_an_inactive_edges_non_finite_rows_do_not_reach_the_system(general: Callable[[], None]
                                                                  ) -> None:
    """The fast path weighs inactive rows zero instead of zeroing them; where one is not
    finite it evaluates again with the rows zeroed, as the general path does."""
    fast, bad = _with_a_point_at_the_camera_centre()
    fast.initialize_optimization(0)
    assert not np.isfinite(bad.chi2()).all()
    a = _run(fast)
    general()
    slow, _ = _with_a_point_at_the_camera_centre()
    _compare(fast, slow, a, _run(slow))


def _one_kernel_for_all() -> SparseOptimizer:
    """One free pose, 40 projections sharing one Huber kernel, a fifth of them at level 1."""
    opt = one_free_pose(False)
    proj = opt.edge_groups()[0]
    proj.set_kernel(np.arange(proj.size), RobustKernelHuber(2.0))
    proj.set_levels(np.arange(proj.size), (np.arange(proj.size) % 5 == 0).astype(int))
    return opt


def test_one_kernel_for_all_takes_the_fused_weighing(general: Callable[[], None],
                                                     numpy_path: None) -> None:
    """A unary group with one kernel (then none) and levels: the fused terms
    (:mod:`graphopt.unary_terms`) give the general path's iterations (the numpy path's; the
    compiled loop's are tested against it in test_compiled.py)."""
    fast = _one_kernel_for_all()
    a = _run(fast, rounds=3)
    assert fast.problem._weighing[0][1] is not None  # the projections' group was fused
    general()
    slow = _one_kernel_for_all()
    _compare(fast, slow, a, _run(slow, rounds=3))


def test_edge_chi2_after_a_run_is_its_errors_chi2() -> None:
    """After a run with a fifth of the edges at level 1, the edge set's per-edge ``e'Ωe`` —
    every edge's, kept from the run's last evaluation — is bit for bit what the group's
    information makes of the kept errors, inactive edges included, and close to a fresh
    optimizer's at the same estimate (which gathers the pose instead of broadcasting it)."""
    from graphopt.edge_set import _chi2, group_errors

    fast = _one_kernel_for_all()
    _run(fast)
    g = fast.edge_groups()[0]
    assert g.raw_eval is not None and g.raw_eval[2] is not None  # kept by the fused weighing
    got = group_errors(fast.graph, g)[1]
    assert np.array_equal(got, _chi2(g, g.raw_eval[1].copy())[1]) and not got.flags.writeable
    assert np.all(got[np.arange(g.size) % 5 == 0] > 0)  # the inactive edges' own e'Ωe
    fresh = _one_kernel_for_all()
    fresh.vertex(0).set_estimate(fast.vertex(0).estimate)
    np.testing.assert_allclose(got, group_errors(fresh.graph, fresh.edge_groups()[0])[1],
                               rtol=1e-9)


def test_a_repeated_estimate_reuses_the_types_evaluation(monkeypatch: pytest.MonkeyPatch,
                                                         numpy_path: None) -> None:
    """ORB-SLAM's rounds restart from the same pose: a round with the levels of the last one
    retraces it without calling the edge type again, and ends where it did (the numpy path's
    memo; a compiled loop costs less than the lookup)."""
    calls = []
    linearize = EdgeSE3ProjectXYZOnlyPose.linearize.__func__  # type: ignore[attr-defined]

    def counted(cls: type, *args: object) -> object:
        calls.append(1)
        return linearize(cls, *args)

    monkeypatch.setattr(EdgeSE3ProjectXYZOnlyPose, "linearize", classmethod(counted))
    opt = _one_kernel_for_all()
    start = opt.vertex(0).estimate.copy()
    ends = []
    for _ in range(2):
        opt.vertex(0).set_estimate(start)
        opt.initialize_optimization(0)
        calls.clear()
        res = opt.optimize(10)
        ends.append((res.final_chi2, opt.vertex(0).estimate.copy(), len(calls)))
    assert ends[0][2] > 1 and ends[1][2] == 0
    assert ends[0][0] == ends[1][0]
    np.testing.assert_array_equal(ends[0][1], ends[1][1])
    # Another estimate is evaluated afresh.
    moved = start.copy()
    moved[:3, 3] += 0.01
    opt.vertex(0).set_estimate(moved)
    calls.clear()
    opt.optimize(1)
    assert calls


class _EdgeCurveBuffers(EdgeCurve):
    """:class:`EdgeCurve` returning its own buffers, overwritten by every call (``out=``)."""

    _e = np.zeros(0)
    _J = np.zeros(0)

    @classmethod
    def error(cls, x, measurement, ctx):  # noqa: ANN001, ANN206
        e = EdgeCurve.error(x, measurement, ctx)
        if cls._e.shape != e.shape:
            cls._e = np.empty_like(e)
        np.copyto(cls._e, e)
        return cls._e

    @classmethod
    def jacobians(cls, x, measurement, ctx):  # noqa: ANN001, ANN206
        (J,) = EdgeCurve.jacobians(x, measurement, ctx)
        if cls._J.shape != J.shape:
            cls._J = np.empty_like(J)
        np.copyto(cls._J, J)
        return (cls._J,)


@pytest.mark.parametrize("edge", [_EdgeCurveBuffers, EdgeCurveAutodiff])
def test_the_memo_keeps_copies_of_a_types_buffers(edge: type) -> None:
    """A type that returns buffers its next call overwrites (a user's ``out=``, autodiff's
    kept scratch): rounds restarted from one estimate, the memo answering, run the iterations
    of the plain type."""
    meas = curve_data(60)
    runs = []
    for etype in (EdgeCurve, edge):
        opt = SparseOptimizer("lm", "dense")
        opt.add_vertices(VertexCurve, [0], [[0.5, 1.5, 0.5]])
        opt.add_edges(etype, np.zeros((len(meas), 1), int), meas)
        out = []
        for _ in range(3):
            opt.vertex(0).set_estimate([0.5, 1.5, 0.5])
            opt.initialize_optimization()
            res = opt.optimize(4)  # fewer evaluations than the memo keeps
            out.append(([i.chi2 for i in res.info], opt.vertex(0).estimate.copy()))
        assert isinstance(opt.problem, SingleVertexProblem)
        runs.append(out)
    for (chi_a, x_a), (chi_b, x_b) in zip(*runs, strict=True):
        np.testing.assert_allclose(chi_b, chi_a, rtol=1e-9)
        np.testing.assert_allclose(x_b, x_a, rtol=1e-9)
    assert runs[1][1][0] == runs[1][0][0]  # the second round retraced the first


def test_the_state_keys_lone_form_is_the_general_one_after_every_edit() -> None:
    """:meth:`Linearizer.state_key`'s form for one store and one group equals the general one
    (every store's version, every group's activity version) after each edit that makes
    evaluations stale, and an evaluation keeps it; so does the errors' key for the edge sets
    (a query after a run reuses the run's errors)."""
    lone = SparseOptimizer("lm", "dense")
    lone.add_vertices(VertexSE3Expmap, [0], one_free_pose(False).vertex(0).estimate[None])
    rng = np.random.default_rng(1)
    es = lone.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((30, 1), dtype=int),
                        rng.uniform(100, 500, (30, 2)), params=CAM,
                        data={"Xw": rng.uniform(-1, 1, (30, 3)) + [0, 0, 5]},
                        robust_kernel=RobustKernelHuber(2.0))
    for opt in (lone, one_free_pose(True)):
        opt.initialize_optimization(0)
        p = opt.problem
        assert isinstance(p, SingleVertexProblem)
        lz = p.linearizer
        assert (lz._lone is not None) == (opt is lone)
        g = opt.edge_groups()[0]
        kernel = RobustKernelHuber(3.0)
        for edit in range(5):
            if edit == 1:
                g.set_levels(np.arange(5), 1)
            elif edit == 2:
                g.set_kernel(np.arange(3), kernel)
            elif edit == 3:
                kernel.set_delta(2.5)
            elif edit == 4:
                opt.vertex(0).set_estimate(opt.vertex(0).estimate * 1.0)
            assert lz.state_key() == (lz._state(), tuple(g.activity_version
                                                         for g in lz.groups))
            p.evaluate()
            assert p.linearizer.last_state == p.linearizer.state_key()
    lone.optimize(3)
    kept = lone.edge_groups()[0].raw_eval
    assert kept is not None and kept[0][0] == lone.problem.linearizer.state_key()[0]
    np.testing.assert_array_equal(es.chi2() > 0, np.ones(30, dtype=bool))
