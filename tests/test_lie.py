"""graphopt/lie.py against independent references (SciPy's rotations and matrix exponential)
and finite differences, on both sides of the small-angle threshold."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from graphopt.lie import (
    SMALL_ANGLE2,
    angle_axis_rotate,
    hat,
    make_transform,
    quat_to_rot,
    relative_transform,
    rot_to_quat,
    se3_exp,
    so3_exp,
    so3_left_jacobian,
    so3_log,
    transform_inverse,
    transform_points,
)

#: Angles from zero through the series branch (θ² < 1e-8), across its threshold, up to and
#: beyond π.
ANGLES = [0.0, 1e-12, 1e-9, 1e-6, 0.99e-4, 1.01e-4, 1e-3, 0.5, 2.0, np.pi - 1e-6, np.pi, 3.5]


def _vectors(theta: float, n: int = 20, seed: int = 0) -> np.ndarray:
    """``n`` rotation vectors of angle ``theta`` with random axes."""
    axes = np.random.default_rng(seed).normal(size=(n, 3))
    return theta * axes / np.linalg.norm(axes, axis=1, keepdims=True)


def test_threshold_value() -> None:
    assert SMALL_ANGLE2 == 1e-8  # the documented value: θ < 1e-4 rad uses the series


@pytest.mark.parametrize("theta", ANGLES)
def test_so3_exp_matches_reference(theta: float) -> None:
    w = _vectors(theta)
    R = so3_exp(w)
    # A wrong or missing θ² series term would show as ≈ θ³/6 ≈ 1.7e-13 at the threshold.
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=2e-15)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               rtol=0, atol=2e-15)
    assert R.flags.c_contiguous
    v = np.random.default_rng(1).normal(size=w.shape)
    np.testing.assert_array_equal(angle_axis_rotate(w, v), np.einsum("nij,nj->ni", R, v))
    np.testing.assert_allclose(angle_axis_rotate(w, v), Rotation.from_rotvec(w).apply(v),
                               rtol=0, atol=1e-14)


def test_so3_exp_is_first_order_rotation_for_tiny_angles() -> None:
    w = np.array([[1e-10, -2e-10, 0.5e-10], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(so3_exp(w), np.eye(3) + hat(w), rtol=0, atol=1e-19)
    np.testing.assert_array_equal(so3_exp(w)[1], np.eye(3))


@pytest.mark.parametrize("theta", [1e-6, 0.99e-4, 1.01e-4, 0.3, 1.0, 2.5])
def test_so3_log_inverts_exp(theta: float) -> None:
    w = _vectors(theta, seed=2)
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("theta", [0.0, 1e-6, 0.99e-4, 1.01e-4, 0.7, 2.5])
def test_left_jacobian_matches_finite_differences(theta: float) -> None:
    """``exp(w + h e_i) ≈ exp(h J_l(w) e_i) exp(w)``: column i of J_l by central differences."""
    w = _vectors(theta, n=5, seed=3)
    J = so3_left_jacobian(w)
    h = 1e-6
    numeric = np.empty_like(J)
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        plus = so3_log(so3_exp(w + d) @ np.swapaxes(so3_exp(w), 1, 2))
        minus = so3_log(so3_exp(w - d) @ np.swapaxes(so3_exp(w), 1, 2))
        numeric[:, :, i] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(J, numeric, rtol=0, atol=1e-8)


@pytest.mark.parametrize("theta", [0.0, 1e-9, 0.99e-4, 1.01e-4, 0.5, 3.0])
def test_se3_exp_matches_matrix_exponential(theta: float) -> None:
    w = _vectors(theta, n=8, seed=4)
    u = np.random.default_rng(5).normal(size=(8, 3))
    T = se3_exp(np.concatenate([w, u], axis=1))
    for k in range(len(w)):
        twist = np.zeros((4, 4))
        twist[:3, :3] = hat(w[k : k + 1])[0]
        twist[:3, 3] = u[k]
        ref = expm(twist)
        np.testing.assert_allclose(T[k, :3, :3], ref[:3, :3], rtol=0, atol=2e-15)
        # The translation J_l(ω) υ: J_l loses digits just above the threshold (lie.py's
        # docstring: ≈ 3e-13 at θ = 1e-4).
        np.testing.assert_allclose(T[k, :3, 3], ref[:3, 3], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(T[k, 3], [0, 0, 0, 1.0])
    np.testing.assert_array_equal(T[:, :3, :3], so3_exp(w))  # the one Rodrigues formula


def test_quaternions_match_reference() -> None:
    R = so3_exp(np.random.default_rng(6).normal(0, 1.0, (30, 3)))
    q = rot_to_quat(R)
    ref = Rotation.from_matrix(R).as_quat()  # [x, y, z, w], like graphopt
    ref *= np.sign(ref[:, 3:4])
    np.testing.assert_allclose(q, ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(quat_to_rot(3.0 * q), R, rtol=0, atol=1e-12)  # normalises


def test_transforms() -> None:
    rng = np.random.default_rng(7)
    Ta = se3_exp(rng.normal(0, 0.8, (10, 6)))
    Tb = se3_exp(rng.normal(0, 0.8, (10, 6)))
    p = rng.normal(size=(10, 3))
    homogeneous = np.einsum("nij,nj->ni", Ta, np.c_[p, np.ones(10)])[:, :3]
    np.testing.assert_allclose(transform_points(Ta, p), homogeneous, rtol=0, atol=1e-14)
    R, t = relative_transform(Ta, Tb)
    expected = Tb @ np.linalg.inv(Ta)
    np.testing.assert_allclose(R, expected[:, :3, :3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(t, expected[:, :3, 3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(transform_inverse(Ta), np.linalg.inv(Ta), rtol=0, atol=1e-14)
    np.testing.assert_array_equal(make_transform(R, t)[:, :3, :3], R)
    np.testing.assert_array_equal(make_transform(R, t)[:, 3], np.tile([0, 0, 0, 1.0], (10, 1)))
