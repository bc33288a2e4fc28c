"""Custom vertex and edge types written only against graphopt's public API (used by the tests)."""

from __future__ import annotations

import numpy as np

from graphopt import BaseEdge, BaseVertex, VertexVector


class VertexCurve(VertexVector):
    """Parameters (a, b, c) of y = exp(a x² + b x + c)."""

    dimension = 3


class EdgeCurve(BaseEdge):
    """Residual y − exp(a x² + b x + c); measurement (x, y)."""

    dimension = 1
    vertex_types = (VertexCurve,)
    measurement_shape = (2,)

    @classmethod
    def error(cls, x, measurement, ctx):
        p = x[0]
        xs, ys = measurement[:, 0], measurement[:, 1]
        return (ys - np.exp(p[:, 0] * xs**2 + p[:, 1] * xs + p[:, 2]))[:, None]

    @classmethod
    def jacobians(cls, x, measurement, ctx):
        p = x[0]
        xs = measurement[:, 0]
        f = np.exp(p[:, 0] * xs**2 + p[:, 1] * xs + p[:, 2])
        return (-np.stack([f * xs**2, f * xs, f], axis=1)[:, None, :],)


class EdgeCurveNumeric(EdgeCurve):
    """The same edge with the numeric Jacobian."""

    jacobians = BaseEdge.jacobians
    differentiation = "numeric"


class EdgeCurveAutodiff(EdgeCurve):
    """The same edge with Jacobians from automatic differentiation."""

    differentiation = "autodiff"


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


class VertexSE2(BaseVertex):
    """2D pose (x, y, θ) with g2o's additive update."""

    dimension = 3
    estimate_shape = (3,)

    @staticmethod
    def oplus(estimates, deltas):
        out = estimates + deltas
        out[:, 2] = wrap(out[:, 2])
        return out


def _rot(t):
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


class EdgeSE2(BaseEdge):
    """Relative pose error t2v(Z⁻¹ (X_i⁻¹ X_j)) with analytic Jacobians."""

    dimension = 3
    vertex_types = (VertexSE2, VertexSE2)

    @classmethod
    def error(cls, x, z, ctx):
        xi, xj = x
        Ri, Rz = _rot(xi[:, 2]), _rot(z[:, 2])
        dt = (xj[:, :2] - xi[:, :2])[:, :, None]
        t_ij = np.swapaxes(Ri, 1, 2) @ dt
        e_t = np.swapaxes(Rz, 1, 2) @ (t_ij - z[:, :2, None])
        e_th = wrap(xj[:, 2] - xi[:, 2] - z[:, 2])
        return np.concatenate([e_t[:, :, 0], e_th[:, None]], axis=1)

    @classmethod
    def jacobians(cls, x, z, ctx):
        xi, xj = x
        m = len(z)
        Ri, Rz = _rot(xi[:, 2]), _rot(z[:, 2])
        RzT_RiT = np.swapaxes(Rz, 1, 2) @ np.swapaxes(Ri, 1, 2)
        dt = (xj[:, :2] - xi[:, :2])[:, :, None]
        dRiT = np.swapaxes(_rot(xi[:, 2] + np.pi / 2), 1, 2)  # d(Riᵀ)/dθ = Rot(θ+π/2)ᵀ
        Ji = np.zeros((m, 3, 3))
        Jj = np.zeros((m, 3, 3))
        Ji[:, :2, :2] = -RzT_RiT
        Ji[:, :2, 2] = (np.swapaxes(Rz, 1, 2) @ dRiT @ dt)[:, :, 0]
        Ji[:, 2, 2] = -1.0
        Jj[:, :2, :2] = RzT_RiT
        Jj[:, 2, 2] = 1.0
        return Ji, Jj


def compose(a, b):
    """SE2 composition a ⊕ b for (n, 3) arrays."""
    R = _rot(a[:, 2])
    t = a[:, :2] + (R @ b[:, :2, None])[:, :, 0]
    return np.concatenate([t, wrap(a[:, 2] + b[:, 2])[:, None]], axis=1)


def relative(a, b):
    """a⁻¹ ⊕ b for (n, 3) arrays."""
    R = _rot(a[:, 2])
    t = (np.swapaxes(R, 1, 2) @ (b[:, :2] - a[:, :2])[:, :, None])[:, :, 0]
    return np.concatenate([t, wrap(b[:, 2] - a[:, 2])[:, None]], axis=1)


def pose_graph(n=40, seed=0, noise=(0.02, 0.01)):
    """A loop trajectory with odometry and loop closures. Returns truth, initial, edges, meas."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    truth = np.stack([5 * np.cos(t), 5 * np.sin(t), wrap(t + np.pi / 2)], 1)
    edges = [(i, i + 1) for i in range(n - 1)] + [(i, i + n // 2) for i in range(0, n // 2, 3)]
    edges = np.array(edges)
    meas = relative(truth[edges[:, 0]], truth[edges[:, 1]])
    meas[:, :2] += rng.normal(0, noise[0], (len(edges), 2))
    meas[:, 2] = wrap(meas[:, 2] + rng.normal(0, noise[1], len(edges)))
    # Initial guess: chain the noisy odometry.
    init = np.zeros_like(truth)
    init[0] = truth[0]
    for i in range(n - 1):  # builds test data, not part of an iteration
        init[i + 1] = compose(init[i:i + 1], meas[i:i + 1])[0]
    return truth, init, edges, meas
