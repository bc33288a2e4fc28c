"""The linear solvers against each other (graphopt.solvers)."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import SOLVERS, build_pose_graph

from graphopt.solvers import CHOLMOD_AVAILABLE


@pytest.mark.parametrize("solver", SOLVERS)
def test_solvers_give_the_same_step(solver: str) -> None:
    steps = {}
    for name in ("dense", solver):
        opt, _, _ = build_pose_graph("lm", name)
        opt.initialize_optimization()
        asm, _ = opt.problem.linearize()
        steps[name] = opt.problem.solve(asm, 1e-2)[0]
    np.testing.assert_allclose(steps[solver], steps["dense"], rtol=1e-7, atol=1e-9)
    assert np.abs(steps["dense"]).max() > 1e-3  # a real step, not zeros


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
    asm, _ = opt.problem.linearize()
    ref = opt.problem.solve(asm, 1e-2)[0]
    system = opt.linear_system
    s, rhs, _ = system.reduce(asm, 1e-2)
    for cfg, close in ((PCGConfig(tolerance=1e-12), True), (PCGConfig(max_iterations=2), False)):
        pcg = LinearSolverPCG(cfg)
        pcg.analyze(system.pattern, system.udims)
        x = pcg.solve(s, rhs)
        assert np.allclose(x, ref, rtol=1e-7, atol=1e-9) == close
        if not close:
            assert pcg.last_iterations == 2


def test_auto_solver_chooses_by_size_and_fill() -> None:
    from graphopt.solvers import LinearSolverAuto

    opt, _, _ = build_pose_graph("lm", LinearSolverAuto())
    opt.initialize_optimization()
    assert opt.solver.chosen.name == "dense"  # 117 unknowns
    opt2, _, _ = build_pose_graph("lm", LinearSolverAuto(dense_max_size=50))
    opt2.initialize_optimization()
    assert opt2.solver.chosen.name in ("cholmod", "scipy")
    assert opt.optimize(20).final_chi2 == pytest.approx(opt2.optimize(20).final_chi2, rel=1e-9)


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_names_the_blas_it_runs_on() -> None:
    from graphopt.solvers import cholmod_blas

    path = cholmod_blas()  # e.g. /usr/lib/x86_64-linux-gnu/openblas-pthread/libblas.so.3
    assert "blas" in path.lower() and ".so" in path, path


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_modes_and_orderings_give_the_same_step() -> None:
    from graphopt.solvers import LinearSolverCholmod

    steps = []
    for mode, ordering in (("auto", "default"), ("simplicial", "amd"), ("supernodal", "nesdis")):
        opt, _, _ = build_pose_graph("lm", LinearSolverCholmod(mode, ordering))
        opt.initialize_optimization()
        asm, _ = opt.problem.linearize()
        steps.append(opt.problem.solve(asm, 1e-2)[0])
    for s in steps[1:]:
        np.testing.assert_allclose(s, steps[0], rtol=1e-9, atol=1e-12)
    assert np.abs(steps[0]).max() > 1e-3
    with pytest.raises(ValueError, match="unknown CHOLMOD mode"):
        LinearSolverCholmod("fast")


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_refuses_values_that_do_not_fit_the_pattern() -> None:
    import scipy.sparse as sp

    from graphopt.solvers import LinearSolverCholmod

    a = sp.csc_matrix(np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]]))
    solver = LinearSolverCholmod()
    solver.analyze(a, np.array([1, 1, 1]))
    rhs = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(solver.solve(a.data, rhs), np.linalg.solve(a.toarray(), rhs),
                               rtol=1e-12)
    with pytest.raises(ValueError, match="6 values for a pattern of 7"):
        solver.solve(a.data[:-1], rhs)
