"""Compiled loops (:mod:`graphopt.compiled`): the pose-only projection loop gives the numpy
path's numbers to rounding — errors, Jacobian rows (and through them finite differences),
``e'Ωe``, robust sums, ``H`` and ``b`` — for mono and stereo, every weighing it takes; runs with
levels and kernel edits between rounds take the same iterations; what it does not take (other
kernels, a full information matrix, a numerically differentiated subclass, no numba) runs on
the numpy path."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from graphopt import BaseEdge, RobustKernelCauchy, RobustKernelHuber, SparseOptimizer, compiled
from graphopt.compiled import CompiledUnary
from graphopt.edge import EdgeContext
from graphopt.types import (
    CameraParameters,
    EdgeSE3ProjectXYZOnlyPose,
    EdgeStereoSE3ProjectXYZOnlyPose,
    StereoCameraParameters,
    VertexPointXYZ,
    VertexSE3Expmap,
)
from graphopt.unary_terms import compiled_group, compiled_terms, unary_terms, weighing

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import slam_backend_scenes as scenes  # noqa: E402

pytestmark = pytest.mark.skipif(not compiled.available(), reason="numba is not installed")

CAM = CameraParameters(520.0, 515.0, 320.0, 240.0)
STEREO = StereoCameraParameters(520.0, 515.0, 320.0, 240.0, 40.0)


def _problem(m: int, stereo: bool, kernel: object, info: str, levels: bool,
             seed: int = 0, at_centre: int | None = None
             ) -> tuple[SparseOptimizer, scenes.MotionOnlyScene]:
    """A motion-only BA of ``m`` matches; ``info``: ``"edge"`` (σ⁻²·I per edge), ``"shared"``
    (one diagonal for all) or ``"identity"``; ``at_centre``: that edge's point moved to the
    camera's centre at its first step (depth 0 exactly: the start pose is a translation)."""
    s = scenes.motion_only(m, stereo, seed)
    if at_centre is not None:
        s.T_init[:3, :3] = np.eye(3)
        s.Xw[at_centre] = -s.T_init[:3, 3]
    r = 3 if stereo else 2
    if info == "edge":
        om = s.inv_sigma2[:, None, None] * np.eye(r)
    elif info == "shared":
        om = np.broadcast_to(np.diag(np.arange(1.0, r + 1.0)), (m, r, r)).copy()
    else:
        om = None
    opt = SparseOptimizer(algorithm="lm", solver="dense")
    opt.add_vertices(VertexSE3Expmap, [0], s.T_init[None])
    es = opt.add_edges(EdgeStereoSE3ProjectXYZOnlyPose if stereo else EdgeSE3ProjectXYZOnlyPose,
                       np.zeros((m, 1), dtype=int), s.z, information=om, robust_kernel=kernel,
                       params=STEREO if stereo else CAM, data={"Xw": s.Xw})
    if levels:
        es.set_level((np.arange(m) % 4 == 0).astype(int))
    return opt, s


@pytest.mark.parametrize("stereo", [False, True])
@pytest.mark.parametrize("kernel", [None, RobustKernelHuber(1.5)])
@pytest.mark.parametrize("info", ["edge", "shared", "identity"])
@pytest.mark.parametrize("levels", [False, True])
def test_the_loop_gives_the_numpy_paths_numbers(stereo: bool, kernel: object, info: str,
                                                 levels: bool) -> None:
    opt, s = _problem(50, stereo, kernel, info, levels)
    opt.initialize_optimization(0)
    g = opt.edge_groups()[0]
    etype, ctx = g.etype, g.context()
    T = opt.vertex(0).estimate
    wg = weighing(g)
    assert wg is not None
    cg = compiled_group(etype.compiled_unary(g.measurements, ctx), wg)
    assert cg is not None
    out = etype.linearize((np.repeat(T[None], g.size, 0),), g.measurements, ctx)
    every, s_np, chi, rchi, H, b = unary_terms(wg, out.error, out.jacobians[0])
    for lin in (True, False):
        e_c, every_c, s_c, H_c, b_c, chi_c, rchi_c = compiled_terms(cg, T, lin)
        np.testing.assert_allclose(e_c, out.error, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(every_c, every, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(s_c, s_np, rtol=1e-10, atol=1e-12)
        assert chi_c == pytest.approx(chi, rel=1e-12)
        assert rchi_c == pytest.approx(rchi, rel=1e-12)
        if lin:
            np.testing.assert_allclose(H_c, H, rtol=1e-10, atol=1e-8 * np.abs(H).max())
            np.testing.assert_allclose(b_c, b, rtol=1e-10, atol=1e-8 * np.abs(b).max())
            np.testing.assert_array_equal(H_c, H_c.T)
        else:
            assert not H_c.any() and not b_c.any()
    if levels:  # inactive edges: their own e'Ωe, zero in s
        off = g.levels != 0
        assert np.all(every_c[off] > 0) and np.all(s_c[off] == 0)


@pytest.mark.parametrize("stereo", [False, True])
def test_the_loops_jacobian_is_the_errors_derivative(stereo: bool) -> None:
    """``H`` and ``b`` are those of central differences of the loop's own errors under
    ``T ← exp([ω, υ]) T`` (Huber weights at the point)."""
    from graphopt.lie import se3_exp

    opt, _ = _problem(20, stereo, RobustKernelHuber(3.0), "edge", False, seed=3)
    opt.initialize_optimization(0)
    g = opt.edge_groups()[0]
    cg = compiled_group(g.etype.compiled_unary(g.measurements, g.context()), weighing(g))
    assert cg is not None
    T = opt.vertex(0).estimate
    e, every, _, H, b, _, _ = compiled_terms(cg, T, True)
    h = 1e-6
    J = np.empty((*e.shape, 6))
    for c in range(6):
        d = np.zeros((1, 6))
        d[0, c] = h
        ep = compiled_terms(cg, se3_exp(d)[0] @ T, False)[0]
        em = compiled_terms(cg, se3_exp(-d)[0] @ T, False)[0]
        J[:, :, c] = (ep - em) / (2 * h)
    w = cg.info * (cg.delta / np.maximum(np.sqrt(every), cg.delta))[:, None]  # ρ'·Ω
    assert 0 < (w[:, 0] < cg.info[:, 0]).sum() < len(w)  # some edges down-weighted
    np.testing.assert_allclose(H, np.einsum("mri,mr,mrj->ij", J, w, J), rtol=1e-5)
    np.testing.assert_allclose(b, np.einsum("mri,mr,mr->i", J, w, e), rtol=1e-5)


def _rounds(opt: SparseOptimizer, s: scenes.MotionOnlyScene) -> list[tuple[float, int, bool]]:
    """ORB-SLAM's four rounds: levels from chi2 after each, kernels dropped after the third."""
    out = []
    g = opt.edge_groups()[0]
    for r in range(4):
        opt.vertex(0).set_estimate(s.T_init)
        opt.initialize_optimization(0)
        res = opt.optimize(10)
        out += [(i.chi2, i.trials, i.failed) for i in res.info]
        g.set_levels(np.arange(g.size), (g.last_chi2 > 5.991).astype(int)
                     if r < 3 else g.levels)
        if r == 2:
            g.set_kernel(np.arange(g.size), None)
    return out


@pytest.mark.parametrize("stereo", [False, True])
def test_runs_take_the_numpy_paths_iterations(stereo: bool) -> None:
    runs = []
    for on in (True, False):
        compiled.set_enabled(on)
        try:
            opt, s = _problem(120, stereo, RobustKernelHuber(np.sqrt(5.991)), "edge", False)
            rounds = _rounds(opt, s)
        finally:
            compiled.set_enabled(True)
        assert (opt.problem._compiled[0][2] is not None) == on  # type: ignore[union-attr]
        runs.append((rounds, opt.vertex(0).estimate, opt.edge_groups()[0].levels.copy()))
    (a, Ta, la), (b, Tb, lb) = runs
    assert len(a) == len(b) > 8
    for x, y in zip(a, b, strict=True):
        assert x[0] == pytest.approx(y[0], rel=1e-9)
        assert x[1:] == y[1:]
    np.testing.assert_allclose(Ta, Tb, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(la, lb)
    assert 0 < la.sum() < len(la)  # some edges were outliers


@pytest.mark.parametrize("case", ["cauchy", "full information", "numeric subclass"])
def test_what_the_loop_does_not_take_runs_on_the_numpy_path(case: str) -> None:
    if case == "cauchy":
        opt, _ = _problem(30, False, RobustKernelCauchy(1.0), "edge", False)
    elif case == "full information":
        opt, s = _problem(30, False, None, "edge", False)
        opt = SparseOptimizer(algorithm="lm", solver="dense")
        opt.add_vertices(VertexSE3Expmap, [0], s.T_init[None])
        full = np.array([[2.0, 0.3], [0.3, 1.0]])
        opt.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((30, 1), dtype=int), s.z,
                      information=np.broadcast_to(full, (30, 2, 2)).copy(), params=CAM,
                      data={"Xw": s.Xw})
    else:
        class Numeric(EdgeSE3ProjectXYZOnlyPose):
            differentiation = "numeric"

        s = scenes.motion_only(30, False)
        opt = SparseOptimizer(algorithm="lm", solver="dense")
        opt.add_vertices(VertexSE3Expmap, [0], s.T_init[None])
        opt.add_edges(Numeric, np.zeros((30, 1), dtype=int), s.z, params=CAM,
                      data={"Xw": s.Xw})
        assert Numeric.compiled_unary(s.z, EdgeContext(CAM, {"Xw": s.Xw})) is None
    res = opt.optimize(5)
    assert opt.problem._compiled[0][2] is None  # type: ignore[union-attr]
    assert res.final_chi2 < res.initial_chi2


@pytest.mark.filterwarnings("ignore:divide by zero:RuntimeWarning",
                            "ignore:invalid value:RuntimeWarning")
def test_a_non_finite_error_is_named_as_on_the_numpy_path() -> None:
    messages = []
    for on in (True, False):
        compiled.set_enabled(on)
        try:
            opt, _ = _problem(20, False, RobustKernelHuber(2.0), "edge", False, at_centre=7)
            opt.initialize_optimization(0)
            with pytest.raises(FloatingPointError) as err:
                opt.optimize(3)
            messages.append(str(err.value))
            # The linearisation names the edge from the type's own Jacobians (the loop keeps
            # none).
            with pytest.raises(FloatingPointError) as err:
                opt.problem.linearize()  # type: ignore[union-attr]
            messages.append(str(err.value))
        finally:
            compiled.set_enabled(True)
    assert messages[:2] == messages[2:]
    assert "not finite: EdgeSE3ProjectXYZOnlyPose on vertices [0]" in messages[0]
    assert "EdgeSE3ProjectXYZOnlyPose on vertices [0]: non-finite error or Jacobian" in messages[1]


def test_switched_off_without_numba_or_by_the_environment(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    code = "from graphopt import compiled; print(compiled.available())"
    out = subprocess.run([sys.executable, "-P", "-c", code], capture_output=True, text=True,
                         env={"GRAPHOPT_JIT": "0", "PATH": "/usr/bin:/bin"}, check=True)
    assert out.stdout.strip() == "False"

    def missing(name: str) -> None:
        raise ImportError(f"No module named {name!r}")

    monkeypatch.setattr(compiled.importlib, "import_module", missing)
    assert compiled.load("graphopt.types.pose_only_compiled") is None
    assert EdgeSE3ProjectXYZOnlyPose.compiled_unary(
        np.zeros((3, 2)), EdgeContext(CAM, {"Xw": np.ones((3, 3))})) is None


def test_the_screened_solve_is_the_damped_systems_solution() -> None:
    from graphopt.solvers.small_dense import damped_solve
    from graphopt.solvers.small_dense_compiled import screened_solve

    rng = np.random.default_rng(4)
    for d in (1, 3, 6, 7):
        A = rng.normal(size=(d + 3, d))
        H = A.T @ A
        b = rng.normal(size=d)
        D = rng.uniform(0.5, 2.0, d)
        for lam in (0.0, 1e-3, 10.0):
            du, ok = screened_solve(H.T.ravel().copy(), b, lam, D)
            assert ok
            np.testing.assert_allclose(du, np.linalg.solve(H + lam * np.diag(D), b),
                                       rtol=1e-9, atol=1e-12)
            diag = np.arange(d) * (d + 1)
            compiled.set_enabled(False)
            try:
                ref = damped_solve(H.T.ravel().copy(), b, diag, lam, D)
            finally:
                compiled.set_enabled(True)
            np.testing.assert_allclose(damped_solve(H.T.ravel().copy(), b, diag, lam, D), ref,
                                       rtol=1e-9, atol=1e-12)
    # What the screen does not accept goes to the dense solver's rule: a rank-deficient H,
    # an indefinite one, a non-finite one.
    v = rng.normal(size=(6, 1))
    for H in (v @ v.T, np.diag([1.0, 1.0, -1.0, 1.0, 1.0, 1.0]), np.full((6, 6), np.nan)):
        assert not screened_solve(H.ravel().copy(), np.ones(6), 0.0, np.ones(6))[1]


class EdgePointPrior(BaseEdge):
    """``e = z − x`` on a point, with the loop of ``compiled_prior.py`` (docs/compiled.md)."""

    dimension = 3
    vertex_types = (VertexPointXYZ,)

    @classmethod
    def error(cls, x: Any, measurement: np.ndarray, ctx: EdgeContext) -> np.ndarray:
        return measurement - x[0]

    @classmethod
    def jacobians(cls, x: Any, measurement: np.ndarray, ctx: EdgeContext
                  ) -> tuple[np.ndarray, ...]:
        return (np.broadcast_to(-np.eye(3), (len(measurement), 3, 3)).copy(),)

    @classmethod
    def compiled_unary(cls, measurement: np.ndarray, ctx: EdgeContext) -> CompiledUnary | None:
        mod = compiled.load("compiled_prior")
        if mod is None:
            return None
        return CompiledUnary(mod.prior_terms, (np.ascontiguousarray(measurement, float),), 3)


def test_a_users_loop_runs_as_its_types_numpy_methods() -> None:
    rng = np.random.default_rng(8)
    z = rng.normal([1.0, 2.0, 3.0], 0.1, (200, 3))
    z[:20] += rng.normal(0.0, 3.0, (20, 3))  # outliers, for Huber
    info = rng.uniform(50, 100, (200, 1, 1)) * np.eye(3)
    runs = []
    for on in (True, False):
        compiled.set_enabled(on)
        try:
            opt = SparseOptimizer(algorithm="lm", solver="dense")
            opt.add_vertices(VertexPointXYZ, [0], np.zeros((1, 3)))
            es = opt.add_edges(EdgePointPrior, np.zeros((200, 1), dtype=int), z,
                               information=info,
                               robust_kernel=RobustKernelHuber(1.0))
            es[np.arange(200) % 9 == 0].set_level(1)
            res = opt.optimize(20)
        finally:
            compiled.set_enabled(True)
        assert (opt.problem._compiled[0][2] is not None) == on  # type: ignore[union-attr]
        runs.append(([i.chi2 for i in res.info], opt.vertex(0).estimate, es.chi2()))
    (a, xa, ca), (b, xb, cb) = runs
    assert len(a) == len(b) >= 2
    np.testing.assert_allclose(a, b, rtol=1e-10)
    np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ca, cb, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(xa, [1.0, 2.0, 3.0], atol=0.03)  # the outliers are down-weighted


def test_the_se3_step_is_the_exponential_times_the_pose() -> None:
    from graphopt.lie import se3_exp, se3_exp_left

    rng = np.random.default_rng(6)
    T = se3_exp(rng.normal(size=(1, 6)))
    for scale in (1e-9, 1e-5, 0.3, 2.5):  # the series below SMALL_ANGLE2, the closed forms
        xi = rng.normal(size=(1, 6)) * scale
        got = se3_exp_left(xi, T)
        assert got.shape == (1, 4, 4)
        np.testing.assert_allclose(got, se3_exp(xi) @ T, rtol=0, atol=1e-15)
        compiled.set_enabled(False)
        try:
            assert np.array_equal(se3_exp_left(xi, T), se3_exp(xi) @ T)
        finally:
            compiled.set_enabled(True)
    many = rng.normal(size=(3, 6))  # several poses: the batched exponential
    Ts = se3_exp(rng.normal(size=(3, 6)))
    assert np.array_equal(se3_exp_left(many, Ts), se3_exp(many) @ Ts)


def test_a_loop_beside_numpy_groups_takes_the_same_iterations() -> None:
    """A pose with its projections (one kernel: the loop) and relative-pose edges to fixed
    poses (numpy): the same run with and without loops."""
    from graphopt.lie import se3_exp
    from graphopt.types import EdgeSE3Expmap

    s = scenes.motion_only(80, False, seed=2)
    rng = np.random.default_rng(2)
    others = se3_exp(rng.normal(0.0, 0.3, (3, 6)))
    runs = []
    for on in (True, False):
        compiled.set_enabled(on)
        try:
            opt = SparseOptimizer(algorithm="lm", solver="dense")
            opt.add_vertices(VertexSE3Expmap, [0, 1, 2, 3],
                             np.concatenate([s.T_init[None], others]),
                             fixed=[False, True, True, True])
            opt.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((80, 1), dtype=int), s.z,
                          information=s.inv_sigma2[:, None, None] * np.eye(2),
                          robust_kernel=RobustKernelHuber(2.0), params=CAM,
                          data={"Xw": s.Xw})
            rel = others @ np.linalg.inv(s.T_true)  # T_j T_0⁻¹, exact at the truth
            opt.add_edges(EdgeSE3Expmap, np.array([[0, 1], [0, 2], [3, 0]]),
                          np.stack([rel[0], rel[1], np.linalg.inv(rel[2])]),
                          information=np.eye(6) * 100.0)
            res = opt.optimize(10)
        finally:
            compiled.set_enabled(True)
        p = opt.problem
        assert [c is not None and c[2] is not None for c in p._compiled] == [on, False]
        runs.append(([(i.chi2, i.trials) for i in res.info], opt.vertex(0).estimate))
    (a, Ta), (b, Tb) = runs
    assert len(a) == len(b) >= 3
    for x, y in zip(a, b, strict=True):
        assert x[0] == pytest.approx(y[0], rel=1e-9) and x[1] == y[1]
    np.testing.assert_allclose(Ta, Tb, rtol=0, atol=1e-10)
