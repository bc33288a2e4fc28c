"""Jets: derivative rules against central differences, the edge-level selection and errors."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from graphopt import (
    BaseEdge,
    GraphError,
    RobustKernelCauchy,
    SparseOptimizer,
    VertexVector,
    edge_jacobians,
)
from graphopt.autodiff import Jet

RNG = np.random.default_rng(5)


def _jet(x: np.ndarray) -> Jet:
    """``x (m, d)`` as a jet w.r.t. its own ``d`` columns."""
    return Jet.seeded(x, 0, x.shape[1])


def _check(f: Any, x: np.ndarray, tol: float = 1e-7) -> Jet:
    """``f``'s jet derivative against central differences over the columns of ``x``."""
    r = f(_jet(x))
    h = 1e-6
    for i in range(x.shape[1]):
        d = np.zeros_like(x)
        d[:, i] = h
        num = (f(x + d) - f(x - d)) / (2 * h)
        np.testing.assert_allclose(r.tangent[i], num, rtol=tol, atol=tol)
    np.testing.assert_allclose(r.value, f(x), rtol=1e-14, atol=1e-14)
    return r


def test_elementwise_rules() -> None:
    x = RNG.uniform(0.2, 0.8, (7, 3))
    _check(lambda a: np.stack([
        np.sqrt(a[:, 0]) * np.exp(a[:, 1]) - np.log(a[:, 2]) / a[:, 0] ** 3,
        np.sin(a[:, 0]) * np.cos(a[:, 1]) + np.tan(a[:, 2]) - np.arcsin(a[:, 0]),
        np.arccos(a[:, 1]) + np.arctan(a[:, 2]) + np.arctan2(a[:, 0], -a[:, 1]),
        np.hypot(a[:, 0], a[:, 1]) + np.abs(a[:, 2] - 0.5) + np.tanh(a[:, 0]) * np.cosh(a[:, 1]),
        np.minimum(a[:, 0], a[:, 1]) + np.maximum(a[:, 1], 0.5) + a[:, 2] ** a[:, 0],
        np.sum(a * a, axis=1) + np.prod(a, axis=1) + np.mean(a, axis=1) + np.log1p(a[:, 0]),
    ], axis=1), x)


def test_where_clip_and_norm_at_zero() -> None:
    x = np.array([[0.3, -0.2], [2.0, 0.5], [-3.0, 1.0]])
    r = _check(lambda a: np.stack([np.where(a[:, 0] > 0, a[:, 0] * a[:, 1], -a[:, 1] ** 2),
                                   np.clip(a[:, 0], -1.0, 1.0)], 1), x)
    # The tangent follows the chosen branch per element; clipped elements have zero derivative.
    np.testing.assert_array_equal(r.tangent[0, :, 1], [1.0, 0.0, 0.0])
    z = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]])
    n = np.linalg.norm(_jet(z), axis=1)
    assert np.all(np.isfinite(n.tangent))
    np.testing.assert_array_equal(n.tangent[:, 0], 0.0)  # at 0: the zero subgradient
    np.testing.assert_allclose(n.tangent[:, 1], [0.6, 0.8, 0.0])
    s = np.sqrt(np.sum(_jet(z) ** 2, axis=1))  # sqrt at 0 with a zero tangent: 0, not NaN
    np.testing.assert_array_equal(s.tangent[:, 0], 0.0)


def test_einsum_matmul_dot_cross() -> None:
    x = RNG.normal(size=(5, 9))
    M = RNG.normal(size=(5, 3, 3))
    _check(lambda a: np.concatenate([
        np.einsum("mij,mj->mi", a.reshape(5, 3, 3), a[:, :3]),
        (a.reshape(5, 3, 3) @ M).reshape(5, 9),
        np.einsum("mii->m", a.reshape(5, 3, 3) @ a.reshape(5, 3, 3).transpose(0, 2, 1))[:, None],
        np.cross(a[:, :3], a[:, 3:6]),
        np.dot(a[:, :3], np.arange(3.0))[:, None],
        np.linalg.inv(a.reshape(5, 3, 3) + 4 * np.eye(3)).reshape(5, 9),
        np.linalg.det(a.reshape(5, 3, 3))[:, None],
    ], axis=1), x)


def test_indexed_assignment_and_shapes() -> None:
    x = RNG.normal(size=(6, 3))

    def f(a: Any) -> Any:
        out = np.zeros_like(a)
        out[:, 0] = a[:, 1] * a[:, 2]
        out[:, 1:] = a[:, :2] ** 2
        out[[0, 2], 2] = 7.0 * a[[0, 2], 0]
        buf = np.empty((len(a), 2), like=a)
        np.subtract(a[:, 0], 1.0, out=buf[:, 0])
        buf[:, 1] = np.take_along_axis(a, np.argmax(a, axis=1)[:, None], axis=1)[:, 0]
        t = np.moveaxis(np.expand_dims(a, 2), 1, 2).squeeze(1)
        return np.hstack([out, buf, np.swapaxes(t[:, None, :], 1, 2)[:, ::-1, 0],
                          np.take(a, [2, 0], axis=1), np.broadcast_to(a[:, :1], (6, 2))])

    _check(f, x)


def test_plain_output_and_unsupported_function_raise() -> None:
    a = _jet(RNG.normal(size=(4, 2)))
    with pytest.raises(GraphError, match="out=<plain array>"):
        np.add(a, 1.0, out=np.empty((4, 2)))
    with pytest.raises(GraphError, match="np.sort"):
        np.sort(a, axis=1)
    with pytest.raises(GraphError, match="plain array"):
        np.empty((4, 2))[:] = a


class VertexABC(VertexVector):
    dimension = 3


class EdgeCurve(BaseEdge):
    """The README's curve fit: no Jacobians written."""

    dimension = 1
    vertex_types = (VertexABC,)
    measurement_shape = (2,)

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        a, b, c = x[0].T
        return (z[:, 1] - np.exp(a * z[:, 0] ** 2 + b * z[:, 0] + c))[:, None]


class EdgeCurveAnalytic(EdgeCurve):
    @classmethod
    def jacobians(cls, x: Any, z: np.ndarray, ctx: Any) -> tuple[np.ndarray]:
        a, b, c = x[0].T
        f = np.exp(a * z[:, 0] ** 2 + b * z[:, 0] + c)
        return (-(f[:, None] * np.stack([z[:, 0] ** 2, z[:, 0], np.ones(len(z))], 1))[:, None],)


class EdgeCurveSorted(EdgeCurve):
    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        e = super().error(x, z, ctx)
        return e - np.mean(e)  # mixes edges


class EdgeCurveSorting(EdgeCurve):
    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        return np.sort(super().error(x, z, ctx), axis=1)


def _fit(edge: type) -> Any:
    xs = np.linspace(0, 1, 100)
    data = np.stack([xs, np.exp(xs**2 + 2 * xs + 1)], 1)
    opt = SparseOptimizer(algorithm="lm", solver="dense")
    opt.add_vertices(VertexABC, ids=[0], estimates=[[0.0, 0.0, 0.0]])
    opt.add_edges(edge, np.zeros((100, 1), int), data, robust_kernel=RobustKernelCauchy(1.0))
    return opt.optimize(30), opt.vertex(0).estimate


def test_readme_example_converges_as_with_analytic_jacobians() -> None:
    assert EdgeCurve.differentiation_method() == "autodiff"
    assert EdgeCurveAnalytic.differentiation_method() == "analytic"
    auto, xa = _fit(EdgeCurve)
    ana, xb = _fit(EdgeCurveAnalytic)
    assert auto.iterations == ana.iterations
    np.testing.assert_allclose(xa, [1.0, 2.0, 1.0], atol=1e-8)
    np.testing.assert_allclose(xa, xb, atol=1e-10)
    x = [np.tile([0.5, 1.5, 0.7], (5, 1))]
    z = np.stack([np.linspace(0, 1, 5), np.ones(5)], 1)
    (ja,) = edge_jacobians(EdgeCurveAnalytic, x, z, method="analytic")
    (jd,) = edge_jacobians(EdgeCurve, x, z)
    np.testing.assert_allclose(jd, ja, rtol=1e-14)


def test_unsupported_and_cross_edge_errors_name_the_type() -> None:
    with pytest.raises(GraphError, match="EdgeCurveSorting.*np.sort"):
        _fit(EdgeCurveSorting)
    with pytest.raises(GraphError, match="EdgeCurveSorted.*mixes edges"):
        _fit(EdgeCurveSorted)

    class EdgeCurveNumeric(EdgeCurveSorting):
        differentiation = "numeric"

    _fit(EdgeCurveNumeric)  # numeric differences do not need the jet
    with pytest.raises(GraphError, match="differentiation must be one of"):
        type("Bad", (EdgeCurve,), {"differentiation": "symbolic"})


def test_advanced_indexing_views_and_mixed_supports() -> None:
    x = RNG.normal(size=(5, 6))

    def f(a: Any) -> Any:
        y = a.reshape(5, 2, 3)
        picked = y[np.arange(5), :, np.array([2, 0, 1, 2, 0])]  # non-adjacent: (5, 2)
        c = np.zeros_like(a[:, :2])
        view = c[:, :]
        np.multiply(a[:, 4], 2.0, out=view[:, 1])  # widens c through two views
        c[:, 0] = a[:, 3] * a[:, 5]
        mixed = np.concatenate([a[:, :1], np.ones((5, 1)), a[:, 5:] ** 2], axis=1)
        p = np.prod(np.concatenate([a[:, :2], np.zeros((5, 1))], axis=1), axis=1)
        return np.column_stack([picked, c, mixed, p, np.max(a, axis=1), np.sum(a[:, 2:4], 1)])

    _check(f, x)


def test_a_switched_type_keeps_its_analytic_parent_for_checks() -> None:
    from custom_types import EdgeCurve as EdgeCurveAna
    from custom_types import EdgeCurveAutodiff

    from graphopt import check_jacobians

    assert EdgeCurveAutodiff.differentiation_method() == "autodiff"
    assert EdgeCurveAutodiff.analytic_type is EdgeCurveAna
    assert not EdgeCurveAutodiff.has_analytic_jacobians()
    x = [RNG.normal(0.5, 0.2, (6, 3))]
    z = np.stack([np.linspace(0, 1, 6), np.ones(6)], 1)
    assert check_jacobians(EdgeCurveAutodiff, x, z).worst < 1e-13
    lin = EdgeCurveAutodiff.linearize(x, z, None)
    (ja,) = EdgeCurveAna.jacobians(x, z, None)
    np.testing.assert_allclose(lin.jacobians[0], ja, rtol=1e-13)
    with pytest.raises(GraphError, match="position 0"):
        edge_jacobians(EdgeCurveAutodiff, [x[0][:, :2]], z)
    with pytest.raises(GraphError, match="method must be one of"):
        edge_jacobians(EdgeCurveAutodiff, x, z, method="symbolic")


def test_small_angle_branches_give_exact_derivatives_at_zero() -> None:
    from graphopt.lie import hat, se3_exp, so3_exp

    d = Jet.seeded(np.zeros((4, 3)), 0, 3)
    R = so3_exp(d)
    np.testing.assert_array_equal(R.value, np.broadcast_to(np.eye(3), (4, 3, 3)))
    for i in range(3):  # ∂exp([δ]×)/∂δ_i at 0 = [e_i]×, exactly
        np.testing.assert_array_equal(R.tangent[i], np.broadcast_to(hat(np.eye(3)[i:i + 1])[0],
                                                                    (4, 3, 3)))
    T = se3_exp(Jet.seeded(np.zeros((2, 6)), 0, 6))
    for i in range(3, 6):  # the translation part: ∂/∂υ_i = e_i
        np.testing.assert_array_equal(T.tangent[i][:, :3, 3], np.broadcast_to(np.eye(3)[i - 3],
                                                                             (2, 3)))
    # Inside the series' range (θ < 1e-4) the derivative matches the closed form's.
    w = np.array([[3e-5, -2e-5, 1e-5]])
    r = _check(lambda a: so3_exp(a).reshape(1, 9), w, tol=1e-9)
    assert np.all(np.isfinite(r.tangent))


def test_the_optimizers_vertex_grouping_gives_the_same_linearisation() -> None:
    """``ctx.vertices`` (which edges share a vertex, from the optimizer) and ``ctx.derived``
    change nothing: the same errors and Jacobians as found from the estimates, the error bit
    for bit the plain one; an LM run reaches the analytic type's cost."""
    from dataclasses import replace

    from graphopt import EdgeContext, LevenbergConfig, StoppingConfig
    from graphopt.autodiff.jacobians import autodiff_linearize, distinct_vertices
    from graphopt.types import EdgeBALProjection, VertexCameraBAL, VertexPointXYZ

    class EdgeBALAuto(EdgeBALProjection):
        differentiation = "autodiff"

    nc, npt, m = 4, 30, 120
    cams = np.c_[RNG.normal(0, 0.3, (nc, 3)), RNG.normal(0, 1, (nc, 3)),
                 RNG.uniform(400, 900, nc), RNG.normal(0, 0.1, nc), RNG.normal(0, 0.01, nc)]
    pts = RNG.normal(0, 1, (npt, 3)) + [0, 0, -10]
    ci, pi = np.r_[np.arange(nc), RNG.integers(0, nc, m - nc)], RNG.integers(0, npt, m)
    x = (np.asfortranarray(cams[ci]), np.asfortranarray(pts[pi]))
    z = EdgeBALProjection.error(x, np.zeros((m, 2)), None) + RNG.normal(0, 2, (m, 2))
    plain = EdgeContext(derived=(np.asfortranarray(VertexCameraBAL.derived(cams)[ci]), None))
    told = replace(plain, vertices=(distinct_vertices(ci), distinct_vertices(pi)))
    e0, j0, _ = autodiff_linearize(EdgeBALAuto, x, z, EdgeContext())
    e1, j1, _ = autodiff_linearize(EdgeBALAuto, x, z, told)
    np.testing.assert_array_equal(e1, EdgeBALProjection.evaluate(x, z, plain).error)
    np.testing.assert_allclose(e1, e0, rtol=1e-14, atol=1e-12)
    for a, b, c in zip(j1, j0, EdgeBALProjection.jacobians(x, z, plain), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(a, c, rtol=1e-10, atol=1e-7)

    def chi2(edge: type) -> float:
        opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True))
        opt.stopping = StoppingConfig.iterations_only()
        opt.add_vertices(VertexCameraBAL, np.arange(nc), cams)
        opt.add_vertices(VertexPointXYZ, nc + np.arange(npt), pts, marginalized=True)
        opt.add_edges(edge, np.column_stack([ci, nc + pi]), z)
        return opt.optimize(4).final_chi2

    np.testing.assert_allclose(chi2(EdgeBALAuto), chi2(EdgeBALProjection), rtol=1e-10)
