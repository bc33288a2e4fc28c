"""SLAM types (g2o's slam2d/slam3d): every analytic Jacobian against the numeric one, errors and
updates against hand-computed values and g2o's formulas."""

from __future__ import annotations

import numpy as np
import pytest

from graphopt.edge import EdgeContext
from graphopt.lie import quat_to_rot, so3_exp
from graphopt.numeric import numeric_jacobians
from graphopt.types import (
    EdgeSE2,
    EdgeSE2PointXY,
    EdgeSE2Prior,
    EdgeSE3,
    EdgeSE3PointXYZ,
    EdgeSE3Prior,
    ParameterSE3Offset,
    VertexSE2,
    VertexSE3,
)
from graphopt.types.isometry3 import (
    compact_quaternion,
    matrix_to_quat,
    orthonormalize,
    pose_from_qt,
    pose_to_qt,
    quat_to_matrix,
)
from graphopt.types.slam2d import normalize_theta

CTX = EdgeContext()
S45 = np.sqrt(0.5)


def _se2(rng: np.random.Generator, m: int) -> np.ndarray:
    """Random poses; the first rows have angles near ±π."""
    x = rng.normal(0.0, 3.0, (m, 3))
    x[:, 2] = rng.uniform(-np.pi, np.pi, m)
    x[:4, 2] = [np.pi - 1e-3, -np.pi + 1e-3, np.pi - 1e-7, -np.pi + 2e-7]
    return x


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis, float)
    return so3_exp((a / np.linalg.norm(a) * angle)[None])[0]


def _se3(rng: np.random.Generator, m: int) -> np.ndarray:
    """Random ``[R | t]``; the first rows rotate by nearly 180° (and by exactly 180°)."""
    T = np.empty((m, 3, 4))
    T[:, :, :3] = so3_exp(rng.normal(0.0, 1.5, (m, 3)))
    for k, angle in enumerate([np.pi - 1e-3, np.pi - 1e-6, np.pi, 2.5]):
        T[k, :, :3] = _rot(rng.normal(size=3), angle)
    T[:, :, 3] = rng.normal(0.0, 3.0, (m, 3))
    return T


def _assert_jacobians(etype: type, x: tuple, z: np.ndarray, ctx: EdgeContext = CTX) -> None:
    lin = etype.linearize(x, z, ctx)
    np.testing.assert_array_equal(lin.error, etype.error(x, z, ctx))
    num = numeric_jacobians(etype, x, z, ctx)
    assert len(lin.jacobians) == len(etype.vertex_types)
    for pos, (a, n) in enumerate(zip(lin.jacobians, num, strict=True)):
        assert a.shape == (len(z), etype.dimension, etype.vertex_types[pos].dimension)
        scale = max(np.abs(n).max(), 1.0)
        assert np.abs(a - n).max() < 1e-7 * scale, (etype.__name__, pos)


def test_se2_jacobians_match_numeric() -> None:
    rng = np.random.default_rng(1)
    m = 300
    xi, xj, z = _se2(rng, m), _se2(rng, m), _se2(rng, m)
    # Error angles u anywhere but within the difference step of the wrap, some near ±π.
    u = rng.uniform(-np.pi + 1e-4, np.pi - 1e-4, m)
    u[4:8] = np.array([1, -1, 1, -1]) * (np.pi - 1e-4)
    z[:, 2] = normalize_theta(xj[:, 2] - xi[:, 2] - u)
    np.testing.assert_allclose(EdgeSE2.error((xi, xj), z, CTX)[:, 2], u, atol=1e-12)
    _assert_jacobians(EdgeSE2, (xi, xj), z)
    _assert_jacobians(EdgeSE2PointXY, (xi, rng.normal(0, 5, (m, 2))), rng.normal(0, 5, (m, 2)))
    _assert_jacobians(EdgeSE2Prior, (xi,), z)


def test_se2_cached_trigonometry_gives_the_same_linearisation() -> None:
    """The optimizer hands EdgeSE2 the poses' cos/sin (``VertexSE2.derived``) and the
    measurements' constants (``measurement_derived``); the result equals the uncached one
    (whose Jacobians the test above checks against numeric ones)."""
    rng = np.random.default_rng(4)
    m = 200
    xi, xj, z = _se2(rng, m), _se2(rng, m), _se2(rng, m)
    p = rng.normal(0, 5, (m, 2))
    ctx = EdgeContext(derived=(VertexSE2.derived(xi), VertexSE2.derived(xj)),
                      measured=EdgeSE2.measurement_derived(z))
    for etype, x, zz, c in ((EdgeSE2, (xi, xj), z, ctx),
                            (EdgeSE2PointXY, (xi, p), p[::-1], EdgeContext(derived=ctx.derived))):
        plain, cached = etype.linearize(x, zz, CTX), etype.linearize(x, zz, c)
        np.testing.assert_allclose(cached.error, plain.error, rtol=0, atol=1e-12)
        for a, b in zip(cached.jacobians, plain.jacobians, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        assert np.abs(plain.jacobians[0]).max() > 1.0  # real numbers, not zeros
    # A slice of the context (chunked linearisation) keeps the rows of the measured values.
    sub = ctx.subset(slice(10, 20))
    np.testing.assert_array_equal(sub.measured, ctx.measured[10:20])


def test_se3_jacobians_match_numeric() -> None:
    rng = np.random.default_rng(2)
    m = 300
    xi, xj, z = _se3(rng, m), _se3(rng, m), _se3(rng, m)
    # Error rotations near 180° (q_w ≈ 5e-4 > 0) exercise Eigen's non-trace branches.
    for k in range(4, 8):
        R_err = _rot(rng.normal(size=3), np.pi - 1e-3)
        z[k, :, :3] = xi[k, :, :3].T @ xj[k, :, :3] @ R_err.T
    e = EdgeSE3.error((xi, xj), z, CTX)
    assert np.all(np.linalg.norm(e[4:8, 3:], axis=1) > 1 - 1e-6)
    _assert_jacobians(EdgeSE3, (xi, xj), z)
    offset = ParameterSE3Offset(_se3(rng, 5)[4], id=3)
    points, meas = rng.normal(0, 5, (m, 3)), rng.normal(0, 5, (m, 3))
    _assert_jacobians(EdgeSE3PointXYZ, (xi, points), meas, EdgeContext(offset))
    _assert_jacobians(EdgeSE3PointXYZ, (xi, points), meas)  # no params: identity offset
    _assert_jacobians(EdgeSE3Prior, (xi,), z, EdgeContext(offset))
    _assert_jacobians(EdgeSE3Prior, (xi,), z)


def test_normalize_theta_is_g2os() -> None:
    # g2o: fmod(θ + π, 2π), then +π if ≤ 0 else −π: the range is (−π, π].
    theta = np.array([0.0, np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 4.0, -4.0, 7.0, 1e-17])
    expect = np.array([0.0, np.pi, np.pi, np.pi, np.pi, 4.0 - 2 * np.pi, 2 * np.pi - 4.0,
                       7.0 - 2 * np.pi, 1e-17])
    np.testing.assert_allclose(normalize_theta(theta), expect, rtol=0, atol=1e-15)


def test_se2_errors_by_hand() -> None:
    xi = np.array([[1.0, 2.0, np.pi / 2]])
    xj = np.array([[1.0, 3.0, np.pi / 2]])  # one metre ahead of xi, same heading
    np.testing.assert_allclose(EdgeSE2.error((xi, xj), np.array([[1.0, 0.0, 0.0]]), CTX),
                               [[0.0, 0.0, 0.0]], atol=1e-15)
    z = np.array([[0.5, 0.0, 0.1]])
    # Z⁻¹ (1, 0, 0) = (R(−0.1) (0.5, 0), −0.1)
    np.testing.assert_allclose(EdgeSE2.error((xi, xj), z, CTX),
                               [[0.5 * np.cos(0.1), -0.5 * np.sin(0.1), -0.1]], atol=1e-15)
    # The angle of the error is wrapped: 3 rad to −3 rad is a turn of 2π − 6 ≈ +0.283.
    e = EdgeSE2.error((np.array([[0.0, 0.0, 3.0]]), np.array([[0.0, 0.0, -3.0]])),
                      np.zeros((1, 3)), CTX)
    np.testing.assert_allclose(e[0, 2], 2 * np.pi - 6.0, atol=1e-15)
    # A point at (1, 3) seen from (1, 1) looking along +y is 2 m straight ahead.
    pose = np.array([[1.0, 1.0, np.pi / 2]])
    np.testing.assert_allclose(
        EdgeSE2PointXY.error((pose, np.array([[1.0, 3.0]])), np.array([[2.0, 0.5]]), CTX),
        [[0.0, -0.5]], atol=1e-15)
    # Prior: the pose 1 m along world x from the prior, which faces +y: 1 m to its right.
    prior = np.array([[1.0, 2.0, np.pi / 2]])
    np.testing.assert_allclose(
        EdgeSE2Prior.error((np.array([[2.0, 2.0, np.pi / 2 + 0.2]]),), prior, CTX),
        [[0.0, -1.0, 0.2]], atol=1e-15)


def test_vertex_se2_oplus_is_g2os() -> None:
    x = np.array([[0.0, 0.0, 3.1], [1.0, -1.0, -3.0]])
    d = np.array([[1.0, 2.0, 0.1], [0.5, 0.5, -0.5]])
    before = x.copy()
    out = VertexSE2.oplus(x, d)
    np.testing.assert_allclose(out, [[1.0, 2.0, 3.2 - 2 * np.pi], [1.5, -0.5, 2 * np.pi - 3.5]],
                               atol=1e-15)
    np.testing.assert_array_equal(x, before)


def test_quaternions_as_g2o_reads_them() -> None:
    # g2opy 2.3.0 loads "VERTEX_SE3:QUAT 0 1 2 3 0 0 0.6 1.6" as [[0.28, -1.92, 0], [1.92, 0.28,
    # 0], [0, 0, 1]]: Eigen's toRotationMatrix of the quaternion as written.
    T = pose_from_qt(np.array([[1.0, 2.0, 3.0, 0.0, 0.0, 0.6, 1.6]]))
    np.testing.assert_allclose(T[0], [[0.28, -1.92, 0, 1], [1.92, 0.28, 0, 2], [0, 0, 1, 3]],
                               atol=1e-14)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(quat_to_matrix(q), quat_to_rot(q), atol=1e-15)


@pytest.mark.parametrize("axis", [[0, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1], [1, -2, 0.5]])
@pytest.mark.parametrize("angle", [0.0, 0.3, 2.0, 2.2, np.pi - 1e-9, np.pi])
def test_matrix_to_quat_all_branches(axis: list[float], angle: float) -> None:
    R = _rot(axis, angle)[None] if angle else np.eye(3)[None]
    q = matrix_to_quat(R)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)
    np.testing.assert_allclose(quat_to_rot(q), R, atol=1e-14)
    c = compact_quaternion(R)
    assert c[0, 3] >= 0.0
    np.testing.assert_allclose(c[0, :3] * np.sign(q[0, 3] or 1.0), q[0, :3], atol=1e-15)
    np.testing.assert_allclose(pose_to_qt(pose_from_qt(np.r_[1.0, 2, 3, q[0]][None]))[0],
                               np.r_[1.0, 2, 3, q[0]], atol=1e-14)


def test_se3_errors_by_hand() -> None:
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    ident = np.eye(3, 4)[None]
    xj = np.concatenate([Rz90, [[1.0], [0.0], [0.0]]], axis=1)[None]
    # Xj is 1 m along x, turned 90° about z: error [1, 0, 0, 0, 0, sin 45°].
    np.testing.assert_allclose(EdgeSE3.error((ident, xj), ident, CTX),
                               [[1, 0, 0, 0, 0, S45]], atol=1e-15)
    np.testing.assert_allclose(EdgeSE3.error((ident, xj), xj, CTX), np.zeros((1, 6)), atol=1e-15)
    # 200° about z has q = (0, 0, sin 100°, cos 100°) with q_w < 0: g2o flips the sign.
    x200 = np.eye(3, 4)[None].copy()
    x200[0, :, :3] = _rot([0, 0, 1], np.deg2rad(200))
    e = EdgeSE3.error((ident, x200), ident, CTX)
    np.testing.assert_allclose(e, [[0, 0, 0, 0, 0, -np.sin(np.deg2rad(100))]], atol=1e-15)
    # Offset: a sensor 1 m up, turned 90° about z, sees the world point (1, 0, 1) at (0, −1, 0).
    offset = ParameterSE3Offset(np.concatenate([Rz90, [[0.0], [0.0], [1.0]]], axis=1), id=7)
    e = EdgeSE3PointXYZ.error((ident, np.array([[1.0, 0.0, 1.0]])), np.zeros((1, 3)),
                              EdgeContext(offset))
    np.testing.assert_allclose(e, [[0.0, -1.0, 0.0]], atol=1e-15)
    moved = np.eye(3, 4)[None].copy()
    moved[0, 0, 3] = 2.0  # the pose 2 m along x: the point is then behind-left of the sensor
    e = EdgeSE3PointXYZ.error((moved, np.array([[1.0, 0.0, 1.0]])), np.zeros((1, 3)),
                              EdgeContext(offset))
    np.testing.assert_allclose(e, [[0.0, 1.0, 0.0]], atol=1e-15)
    # Prior with the offset: error of Z⁻¹·X·P; X = [I | (1, 0, 0)], P = [Rz90 | (0, 1, 0)].
    X = np.eye(3, 4)[None].copy()
    X[0, 0, 3] = 1.0
    P = ParameterSE3Offset(np.concatenate([Rz90, [[0.0], [1.0], [0.0]]], axis=1))
    np.testing.assert_allclose(EdgeSE3Prior.error((X,), ident, EdgeContext(P)),
                               [[1, 1, 0, 0, 0, S45]], atol=1e-15)
    XP = np.concatenate([Rz90, [[1.0], [1.0], [0.0]]], axis=1)[None]
    np.testing.assert_allclose(EdgeSE3Prior.error((X,), XP, EdgeContext(P)), np.zeros((1, 6)),
                               atol=1e-15)


def test_vertex_se3_oplus_is_g2os() -> None:
    rng = np.random.default_rng(4)
    X = _se3(rng, 6)
    d = np.zeros((6, 6))
    d[:, :3] = rng.normal(size=(6, 3))
    d[:, 3:] = [0.0, 0.0, np.sin(np.pi / 8)]  # q = (0, 0, sin 22.5°, cos 22.5°): 45° about z
    d[5, 3:] = [0.8, 0.8, 0.0]  # |δq| > 1: g2o's fromCompactQuaternion gives the identity
    out = VertexSE3.oplus(X, d)
    Rz45 = _rot([0, 0, 1], np.pi / 4)
    np.testing.assert_allclose(out[:5, :, :3], X[:5, :, :3] @ Rz45, atol=1e-14)
    np.testing.assert_allclose(out[5, :, :3], X[5, :, :3], atol=1e-14)
    np.testing.assert_allclose(out[:, :, 3], X[:, :, 3] + np.einsum("nij,nj->ni", X[:, :, :3],
                                                                     d[:, :3]), atol=1e-14)


def test_vertex_se3_renormalises_by_need() -> None:
    # A rotation from a quaternion written with 6 digits (|q|² − 1 ≈ 1e-6) is kept as g2o keeps
    # it; a drifted one (deviation 1e-3) is pulled back by g2o's first-order step.
    q = np.array([[0.190253, 0.283162, -0.392318, 0.854230], [0.1, 0.2, 0.3, 0.93]])
    T = pose_from_qt(np.concatenate([np.zeros((2, 3)), q], axis=1))
    dev = [np.abs(R.T @ R - np.eye(3)).max() for R in T[:, :, :3]]
    assert 1e-7 < dev[0] < 1e-5 and dev[1] > 1e-3
    out = VertexSE3.oplus(T, np.zeros((2, 6)))
    np.testing.assert_array_equal(out[0], T[0])
    after = np.abs(out[1, :, :3].T @ out[1, :, :3] - np.eye(3)).max()
    assert after < 3 * dev[1] ** 2
    # Tolerance 0 corrects every matrix; an orthonormal one stays as it is.
    R = so3_exp(np.array([[0.3, -1.0, 2.0]]))
    np.testing.assert_allclose(orthonormalize(R), R, atol=1e-15)
