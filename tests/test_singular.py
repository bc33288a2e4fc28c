"""Singular systems get the same answer from every solver and every BLAS kernel (issue 13 §3).

The rank rule lives in ``graphopt/solvers/rank.py``: a system is singular when the smallest
eigenvalue of ``A`` scaled to a unit diagonal is within ``SINGULAR_TOLERANCE`` (1e-12) of 0.
The scaled test systems below have that eigenvalue set exactly (``λ_min = eps``), far from both
the threshold and rounding noise, so their outcome cannot depend on rounding.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp
from custom_types import EdgeSE2, VertexSE2, pose_graph, relative

from graphopt import LevenbergConfig, SparseOptimizer, StoppingConfig
from graphopt.errors import NotPositiveDefiniteError, SingularSystemError
from graphopt.solvers import (
    CHOLMOD_AVAILABLE,
    LinearSolver,
    LinearSolverCholmod,
    LinearSolverDense,
    LinearSolverPCG,
    LinearSolverScipy,
)

NO_CHOLMOD = "CHOLMOD (scikit-sparse) is not installed: 'cholmod' would fall back to 'scipy'"
DIRECT = ["dense", "cholmod", "cholmod-supernodal", "scipy"]
DIRECT_PARAMS = [
    pytest.param(name, marks=pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason=NO_CHOLMOD))
    if name.startswith("cholmod") else name
    for name in DIRECT
]
LOOPS = [(n, seed) for n in (4, 5, 6, 8, 10, 13, 17, 24, 33, 41) for seed in (0, 1, 2)]


def make(name: str) -> LinearSolver:
    """A fresh solver by test name (``cholmod`` is CHOLMOD's own choice, simplicial here)."""
    if name == "dense":
        return LinearSolverDense()
    if name == "scipy":
        return LinearSolverScipy()
    if name == "pcg":
        return LinearSolverPCG()
    return LinearSolverCholmod("supernodal" if name.endswith("supernodal") else "auto")


def solve_matrix(name: str, a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve a dense symmetric ``a`` with a solver analysed on its full pattern (3x3 blocks)."""
    solver = make(name)
    n = len(a)
    solver.analyze(sp.csc_matrix(np.ones((n, n))), np.full(n // 3, 3))
    return solver.solve(a.ravel(order="F").copy(), rhs)


def scaled_system(eps: float, n: int = 12, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``A = D C_eps D`` with ``C_eps`` a unit-diagonal matrix whose smallest eigenvalue is
    ``eps`` (``(1 - eps) C + eps I``, ``C`` a rank ``n - 1`` correlation matrix) and ``D²``
    spanning 1e-6..1e8; and ``D``."""
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, n - 1))
    c = g @ g.T
    s = np.sqrt(np.diag(c))
    c = c / s[:, None] / s[None, :]
    d = np.logspace(-3, 4, n)[rng.permutation(n)]
    a = ((1 - eps) * c + eps * np.eye(n)) * d[:, None] * d[None, :]
    return (a + a.T) / 2, d


def loop_optimizer(n: int, seed: int, algorithm, solver, fix_first: bool = False):
    """A noisy SE2 loop with loop closures; no vertex fixed (a 3-dof gauge) unless asked."""
    _, init, edges, meas = pose_graph(n, seed)
    # Run until no step improves (g2o's rule): the optima are compared to 1e-9.
    opt = SparseOptimizer(algorithm, make(solver) if isinstance(solver, str) else solver,
                          stopping=StoppingConfig.iterations_only())
    opt.add_vertices(VertexSE2, np.arange(n), init, fixed=np.arange(n) == 0 if fix_first else None)
    opt.add_edges(EdgeSE2, edges, meas)
    return opt, init


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
@pytest.mark.parametrize("eps", [0.0, 1e-14, -1e-14])
def test_rank_deficient_scaled_systems_are_singular(solver: str, eps: float) -> None:
    a, _ = scaled_system(eps)
    with pytest.raises(SingularSystemError, match=r"singular .*pivot \d+ \(unknown \d+\)"):
        solve_matrix(solver, a, np.ones(len(a)))


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
def test_indefinite_systems_are_not_called_singular(solver: str) -> None:
    a, _ = scaled_system(-1e-6)  # λ_min(Ã) = -1e-6: beyond the tolerance
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite") as info:
        solve_matrix(solver, a, np.ones(len(a)))
    assert not isinstance(info.value, SingularSystemError)
    swap = np.kron(np.eye(4), [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(NotPositiveDefiniteError) as info:  # zero diagonal, full rank
        solve_matrix(solver, swap + np.diag(np.r_[np.zeros(3), np.ones(9)]), np.ones(12))
    assert not isinstance(info.value, SingularSystemError)
    a[2, 7] = a[7, 2] = np.nan
    with pytest.raises(NotPositiveDefiniteError) as info:  # not finite: not "singular"
        solve_matrix(solver, a, np.ones(len(a)))
    assert not isinstance(info.value, SingularSystemError)


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
@pytest.mark.parametrize("eps", [0.3, 1e-9])
def test_badly_scaled_regular_systems_are_solved(solver: str, eps: float) -> None:
    # Diagonal from 1e-6 to 1e8: only a rule relative to each pivot's own diagonal passes it.
    a, d = scaled_system(eps)
    x_true = np.random.default_rng(1).standard_normal(len(a)) / d
    x = solve_matrix(solver, a, a @ x_true)
    # Error in the scaled unknowns d·x, bounded by cond(Ã)·u = u/eps.
    np.testing.assert_allclose(d * x, d * x_true, rtol=0, atol=1e-9 if eps > 0.1 else 1e-4)


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
def test_an_unobserved_unknown_is_singular(solver: str) -> None:
    a, _ = scaled_system(0.3)
    a[4, :] = a[:, 4] = 0.0  # a direction no edge sees: a zero row and column
    with pytest.raises(SingularSystemError, match=r"singular"):
        solve_matrix(solver, a, np.ones(len(a)))


def test_a_positive_pivot_of_rounding_size_is_rejected() -> None:
    # The case: LAPACK factorises a numerically singular matrix without complaint.
    a, _ = scaled_system(1e-14)
    c, info = sla.lapack.dpotrf(a, lower=1)
    assert info == 0 and np.min(np.diag(c) ** 2 / np.diag(a)) < 1e-12
    with pytest.raises(SingularSystemError, match=r"curvature \S+ of the diagonal"):
        solve_matrix("dense", a, np.ones(len(a)))


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
def test_gauss_newton_reports_singular_on_every_gauge_free_loop(solver: str) -> None:
    reasons = {}
    for n, seed in LOOPS:
        opt, init = loop_optimizer(n, seed, "gn", solver)
        res = opt.optimize(3)
        reasons[n, seed] = str(res.stop_reason)
        np.testing.assert_array_equal(opt.estimates_of(VertexSE2), init)
    assert set(reasons.values()) == {"singular"}, reasons


@pytest.mark.parametrize("solver", DIRECT_PARAMS + ["pcg"])
@pytest.mark.parametrize("algorithm", ["lm", "dogleg"])
def test_damped_solves_converge_on_gauge_free_loops(algorithm: str, solver: str) -> None:
    for n, seed in ((6, 0), (17, 1), (41, 2)):
        ref, _ = loop_optimizer(n, seed, "lm", "dense", fix_first=True)
        optimum = ref.optimize(50).final_chi2
        opt, _ = loop_optimizer(n, seed, algorithm, solver)
        res = opt.optimize(50)
        assert np.all(np.isfinite(opt.estimates_of(VertexSE2)))
        assert res.stop_reason == "converged" and res.initial_chi2 > 2 * optimum
        assert res.final_chi2 == pytest.approx(optimum, rel=1e-9)  # the gauge changes no error


@pytest.mark.parametrize("solver", DIRECT_PARAMS)
def test_lm_retries_a_numerically_singular_damped_system(solver: str) -> None:
    # λ = 1e-20·max diag(H) leaves the gauge at λ_min(Ã) ≈ 1e-20: singular; LM must raise λ.
    opt, _ = loop_optimizer(17, 1, LevenbergConfig(tau=1e-20), solver)
    res = opt.optimize(50)
    ref, _ = loop_optimizer(17, 1, "lm", "dense", fix_first=True)
    assert res.info[0].not_pd >= 1 and res.info[0].trials > res.info[0].not_pd
    assert res.final_chi2 == pytest.approx(ref.optimize(50).final_chi2, rel=1e-9)


def test_gauss_newton_with_pcg_steps_through_the_gauge_freedom() -> None:
    ref, _ = loop_optimizer(25, 1, "gn", "dense", fix_first=True)
    optimum = ref.optimize(10).final_chi2
    opt, _ = loop_optimizer(25, 1, "gn", "pcg")
    res = opt.optimize(3)
    assert res.iterations == 3 and res.chi2_history[-1] == pytest.approx(optimum, rel=1e-9)
    # Same poses up to the gauge: the relative poses of the loop agree.
    est, fixed = opt.estimates_of(VertexSE2), ref.estimates_of(VertexSE2)
    np.testing.assert_allclose(relative(est[:-1], est[1:]), relative(fixed[:-1], fixed[1:]),
                               atol=1e-7)


def test_pcg_on_singular_systems() -> None:
    regular, d = scaled_system(0.3)  # badly scaled but regular (its tolerance is on residuals)
    x = solve_matrix("pcg", regular, regular @ (1 / d))
    np.testing.assert_allclose(d * x, 1.0, rtol=0, atol=1e-8)
    a, _ = scaled_system(0.0)
    w, v = np.linalg.eigh(a / np.sqrt(np.outer(np.diag(a), np.diag(a))))
    null = v[:, 0] / np.sqrt(np.diag(a))  # A's null vector
    b = a @ np.random.default_rng(2).standard_normal(len(a))  # consistent
    x = solve_matrix("pcg", a, b)
    assert np.linalg.norm(a @ x - b) <= 1e-9 * np.linalg.norm(b)
    with pytest.raises(SingularSystemError, match="inconsistent"):
        solve_matrix("pcg", a, b + np.diag(a) * null)
    blocked = scaled_system(0.3)[0]
    blocked[3:6, :] = blocked[:, 3:6] = 0.0  # an unobserved vertex: a zero diagonal block
    b = blocked @ np.ones(len(a))
    x = solve_matrix("pcg", blocked, b)
    np.testing.assert_allclose(x, np.r_[np.ones(3), np.zeros(3), np.ones(6)], atol=1e-8)
    with pytest.raises(SingularSystemError, match="null space of a diagonal block"):
        solve_matrix("pcg", blocked, b + np.eye(len(a))[4])
    with pytest.raises(NotPositiveDefiniteError, match="negative .*curvature"):
        solve_matrix("pcg", scaled_system(-0.2)[0], np.ones(len(a)))


def test_badly_scaled_bal_cameras_are_not_singular() -> None:
    from graphopt.apps.bal_scene import synthetic_scene
    from graphopt.types import VertexPointXYZ
    from graphopt.types.bal import EdgeBALProjection, VertexCameraBAL

    prob = synthetic_scene(num_cameras=6, num_points=400, seed=0).problem
    nc, npt = prob.num_cameras, prob.num_points
    chi2, reasons = {}, {}
    for solver in [s for s in DIRECT if CHOLMOD_AVAILABLE or not s.startswith("cholmod")]:
        for fixed in (0, 2):  # no gauge fixed (7 dof: similarity), then two cameras fixed
            opt = SparseOptimizer("gn", make(solver), stopping=StoppingConfig.iterations_only())
            opt.add_vertices(VertexCameraBAL, np.arange(nc), prob.cameras,
                             fixed=np.arange(nc) < fixed)
            opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), prob.points, marginalized=True)
            opt.add_edges(EdgeBALProjection,
                          np.column_stack([prob.camera_index, nc + prob.point_index]),
                          prob.observations)
            res = opt.optimize(4)
            reasons[solver, fixed] = str(res.stop_reason)
            if fixed:
                chi2[solver] = res.final_chi2
                opt.initialize_optimization()
                asm, _ = opt.problem.linearize()
                s, _, _ = opt.linear_system.reduce(asm, 0.0)
                diag = s[opt.solver.diag_pos]
                assert diag.max() / diag.min() > 1e7  # focal length vs distortion
    assert {r for (_, fixed), r in reasons.items() if fixed == 0} == {"singular"}, reasons
    assert {r for (_, fixed), r in reasons.items() if fixed} == {"iterations"}, reasons
    values = list(chi2.values())
    np.testing.assert_allclose(values, values[0], rtol=1e-9)


def singular_outcomes() -> dict[str, str]:
    """What the rank rule decides on the fixed test systems (run under each OpenBLAS kernel)."""
    names = [s for s in DIRECT if CHOLMOD_AVAILABLE or not s.startswith("cholmod")]
    out: dict[str, str] = {}
    for solver in names:
        for eps in (0.0, 1e-14, -1e-14, -1e-6, 1e-9, 0.3):
            try:
                solve_matrix(solver, scaled_system(eps)[0], np.ones(12))
                out[f"{solver} eps={eps:g}"] = "solved"
            except NotPositiveDefiniteError as exc:
                out[f"{solver} eps={eps:g}"] = type(exc).__name__
        for n, seed in LOOPS[::4]:
            opt, _ = loop_optimizer(n, seed, "gn", solver)
            out[f"{solver} gn loop {n}/{seed}"] = str(opt.optimize(2).stop_reason)
    return out


def expected_outcomes() -> dict[str, str]:
    """The outcomes every kernel must give."""
    names = [s for s in DIRECT if CHOLMOD_AVAILABLE or not s.startswith("cholmod")]
    by_eps = {0.0: "SingularSystemError", 1e-14: "SingularSystemError",
              -1e-14: "SingularSystemError", -1e-6: "NotPositiveDefiniteError", 1e-9: "solved",
              0.3: "solved"}
    out = {f"{s} eps={eps:g}": r for s in names for eps, r in by_eps.items()}
    out.update({f"{s} gn loop {n}/{seed}": "singular" for s in names for n, seed in LOOPS[::4]})
    return out


def test_singular_outcomes_under_openblas_core_types() -> None:
    # OpenBLAS picks its kernels when it loads, from OPENBLAS_CORETYPE: one process per kernel.
    # A kernel this CPU cannot run falls back to another (OpenBLAS says which on stderr).
    assert singular_outcomes() == expected_outcomes()
    code = "import json, test_singular as t; print(json.dumps(t.singular_outcomes()))"
    tests = str(Path(__file__).parent)
    runs = {}
    for core in ("Haswell", "Zen", "SkylakeX", "Prescott"):
        path = [tests] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
        env = dict(os.environ, OPENBLAS_CORETYPE=core, OPENBLAS_VERBOSE="2",
                   OPENBLAS_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(path))
        runs[core] = subprocess.Popen([sys.executable, "-P", "-c", code], env=env, cwd=tests,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for core, proc in runs.items():
        stdout, stderr = proc.communicate(timeout=120)
        loaded = sorted({line.strip() for line in stderr.splitlines() if "Core" in line})
        assert proc.returncode == 0, f"{core}: {stderr[-2000:]}"
        assert json.loads(stdout) == expected_outcomes(), f"OPENBLAS_CORETYPE={core} {loaded}"


def test_verbose_gauss_newton_names_a_singular_system() -> None:
    import io

    opt, _ = loop_optimizer(6, 0, "gn", "dense")
    opt.stream = io.StringIO()
    opt.set_verbose(True)
    assert opt.optimize(3).stop_reason == "singular"
    assert "# gn: the system was singular (rank deficient) 1 time(s)" in opt.stream.getvalue()
