"""Batched SO(3)/SE(3) helpers: Rodrigues' rotation, logarithm, left Jacobian, SE(3) exponential,
quaternions and rigid transforms.

All functions take arrays whose leading axis runs over many elements: ``(n, 3)`` vectors,
``(n, 3, 3)`` rotations, ``(n, 4, 4)`` homogeneous transforms (``T = [[R, t], [0, 1]]``).

Small angles: every map built on ``θ = |ω|`` (:func:`so3_exp`, :func:`angle_axis_rotate`,
:func:`so3_left_jacobian`, :func:`se3_exp`) evaluates its coefficients ``a = sinθ/θ``,
``b = (1−cosθ)/θ²`` and ``c = (θ−sinθ)/θ³`` by their second-order Taylor series when
``θ² < SMALL_ANGLE2`` (``1e-8``, θ below 1e-4 rad); the first omitted terms are below
``θ⁴/120 < 1e-18``. Above it the closed forms are used. Accuracy (against 40-digit
arithmetic): rotations are within 2e-16 up to θ = 1 and 5e-16 up to π. In the left Jacobian
(and so in the translation of :func:`se3_exp`), ``b`` multiplies ``[ω]×`` and the cancellation
in ``1−cosθ`` shows: its error peaks at ≈ 3e-13 just above θ = 1e-4 and is below 1e-14 from
θ = 1e-3 on.
(The half-angle form ``2 sin²(θ/2)/θ²`` would avoid that, but it changes every result in the
last bits, which bit-sensitive direct-BA runs amplify; it is left for a deliberate change.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from graphopt.compiled import Lazy

__all__ = [
    "SMALL_ANGLE2",
    "angle_axis_rotate",
    "hat",
    "make_transform",
    "quat_to_rot",
    "relative_transform",
    "rot_to_quat",
    "se3_exp",
    "se3_exp_left",
    "se3_exp_rows",
    "so3_exp",
    "so3_left_jacobian",
    "so3_log",
    "transform_inverse",
    "transform_points",
]

#: Below this squared angle (radians²) the rotation coefficients use their Taylor series.
SMALL_ANGLE2 = 1e-8

#: Derivative rules for the jets of automatic differentiation, by function name: registered
#: by :mod:`graphopt.autodiff` (which this module does not import). A rule returns ``None``
#: for an argument it does not handle; the function then runs as written.
JET_RULES: dict[str, Callable[[Any], Any]] = {}


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[w]×``.

    Args:
        w: ``(n, 3)`` vectors.

    Returns:
        ``(n, 3, 3)`` matrices with ``hat(w) @ v == cross(w, v)``.
    """
    n = len(w)
    out = np.zeros((n, 3, 3), like=w)  # like=: a jet w gives a jet (graphopt.autodiff)
    out[:, 0, 1], out[:, 0, 2] = -w[:, 2], w[:, 1]
    out[:, 1, 0], out[:, 1, 2] = w[:, 2], -w[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -w[:, 1], w[:, 0]
    return out


def _coefficients(theta2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a = sinθ/θ``, ``b = (1−cosθ)/θ²``, ``c = (θ−sinθ)/θ³``, by series below
    :data:`SMALL_ANGLE2`."""
    small = theta2 < SMALL_ANGLE2
    if not small.any():  # the closed forms alone (the same values, fewer calls)
        theta = np.sqrt(theta2)
        s = np.sin(theta)
        return s / theta, (1.0 - np.cos(theta)) / theta2, (theta - s) / (theta2 * theta)
    t2 = np.where(small, 1.0, theta2)
    theta = np.sqrt(t2)
    s, c = np.sin(theta), np.cos(theta)
    a = np.where(small, 1.0 - theta2 / 6.0, s / theta)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - c) / t2)
    cc = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - s) / (t2 * theta))
    return a, b, cc


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula ``exp([w]×) = I + (sinθ/θ)[w]× + ((1−cosθ)/θ²)[w]×²``.

    This is graphopt's one angle-axis rotation: the BAL camera, the SE(3) vertex and the
    data loaders all use it (see the module docstring for the small-angle series).

    Args:
        w: ``(n, 3)`` rotation vectors (angle-axis).

    Returns:
        ``(n, 3, 3)`` rotation matrices (C-contiguous, so ``.reshape(n, 9)`` gives the
        row-major entries without a copy).
    """
    if type(w) is not np.ndarray and "so3_exp" in JET_RULES:
        out = JET_RULES["so3_exp"](w)
        if out is not None:
            return out  # type: ignore[no-any-return]
    theta2 = np.einsum("ni,ni->n", w, w)
    a, b, _ = _coefficients(theta2)
    W = hat(w)
    WW = W @ W
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * WW


def angle_axis_rotate(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate many vectors: ``exp([w_i]×) v_i``.

    Args:
        w: ``(m, 3)`` angle-axis vectors.
        v: ``(m, 3)`` vectors.

    Returns:
        ``(m, 3)`` rotated vectors.
    """
    return np.einsum("nij,nj->ni", so3_exp(w), v)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`so3_exp`, valid on the whole of SO(3) (including angles near π).

    Args:
        R: ``(n, 3, 3)`` rotation matrices.

    Returns:
        ``(n, 3)`` rotation vectors with angle in ``[0, π]``.
    """
    if type(R) is not np.ndarray and "so3_log" in JET_RULES:
        out = JET_RULES["so3_log"](R)
        if out is not None:
            return out  # type: ignore[no-any-return]
    tr = np.einsum("nii->n", R)
    cos = np.clip(0.5 * (tr - 1.0), -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    sin = np.sin(theta)
    small = theta < 1e-4
    near_pi = theta > np.pi - 1e-3
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    w = v * scale[:, None]
    if np.any(near_pi):
        # Near π, sinθ → 0: the axis comes from the symmetric part,
        # R + Rᵀ = 2cosθ I + 2(1−cosθ)aaᵀ.
        idx = np.flatnonzero(near_pi)
        Rs = R[idx]
        B = (Rs + np.swapaxes(Rs, 1, 2)) * 0.5 - cos[idx, None, None] * np.eye(3)
        col = np.argmax(np.einsum("nii->ni", B), axis=1)
        axis = B[np.arange(len(idx)), :, col]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        sign = np.sign(np.einsum("ni,ni->n", axis, v[idx]))
        sign[sign == 0] = 1.0
        w[idx] = axis * (sign * theta[idx])[:, None]
    return w


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3), ``J_l(w) = I + b[w]× + c[w]×²``.

    Args:
        w: ``(n, 3)`` rotation vectors.

    Returns:
        ``(n, 3, 3)`` matrices.
    """
    theta2 = np.einsum("ni,ni->n", w, w)
    _, b, c = _coefficients(theta2)
    W = hat(w)
    return np.eye(3) + b[:, None, None] * W + c[:, None, None] * (W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential of ``se(3)`` in g2o's order ``xi = [ω, υ]``.

    Args:
        xi: ``(n, 6)`` twists, rotation part first.

    Returns:
        ``(n, 4, 4)`` homogeneous transforms ``[[exp(ω), J_l(ω) υ], [0, 1]]``.
    """
    if len(xi) == 1 and type(xi) is np.ndarray:  # one pose (motion-only BA): scalar arithmetic,
        return _se3_exp_one(*xi[0].tolist())  # a fifth of the calls (not for a jet)
    w, u = xi[:, :3], xi[:, 3:]
    # so3_exp and so3_left_jacobian's expressions, sharing θ², the coefficients and [ω]×.
    a, b, c = _coefficients(np.einsum("ni,ni->n", w, w))
    W = hat(w)
    WW = W @ W
    T = np.zeros((len(xi), 4, 4), like=xi)
    eye = np.eye(3)
    T[:, :3, :3] = eye + a[:, None, None] * W + b[:, None, None] * WW
    V = eye + b[:, None, None] * W + c[:, None, None] * WW
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, u)
    T[:, 3, 3] = 1.0
    return T


def se3_exp_left(xi: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``se3_exp(xi) @ T``: the SE(3) vertex's ``oplus``; one twist on one pose in one compiled
    call where numba is available (:mod:`graphopt.lie_compiled`; the same exponential, the
    product summed in its own order).

    Args:
        xi: ``(n, 6)`` twists, rotation part first.
        T: ``(n, 4, 4)`` transforms.
    """
    if len(xi) == 1 and type(xi) is np.ndarray and type(T) is np.ndarray and T.shape == (1, 4, 4):
        fn = _EXP_LEFT.get()
        if fn is not None:
            return fn(xi[0], T[0])[None]
    return se3_exp(xi) @ T


_EXP_LEFT = Lazy("graphopt.lie_compiled", "se3_exp_left_one")


def se3_exp_rows(wx: float, wy: float, wz: float, ux: float, uy: float, uz: float
                 ) -> tuple[float, ...]:
    """The top three rows of :func:`se3_exp` of one twist, row by row (12 floats): the same
    formulas and series in scalar arithmetic, the products of ``[ω]×²`` as ``ωωᵀ − θ²I`` (so
    the last bits may differ from the batched form's). Plain Python that numba also compiles
    (:mod:`graphopt.lie_compiled`)."""
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < SMALL_ANGLE2:
        a, b, c = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        th = math.sqrt(t2)
        sn = math.sin(th)
        a, b, c = sn / th, (1.0 - math.cos(th)) / t2, (th - sn) / (t2 * th)
    xx, yy, zz = wx * wx - t2, wy * wy - t2, wz * wz - t2  # diagonal of [ω]×² = ωωᵀ − θ²I
    xy, xz, yz = wx * wy, wx * wz, wy * wz
    t0 = (1.0 + c * xx) * ux + (-b * wz + c * xy) * uy + (b * wy + c * xz) * uz
    t1 = (b * wz + c * xy) * ux + (1.0 + c * yy) * uy + (-b * wx + c * yz) * uz
    t2_ = (-b * wy + c * xz) * ux + (b * wx + c * yz) * uy + (1.0 + c * zz) * uz
    return (1.0 + b * xx, -a * wz + b * xy, a * wy + b * xz, t0,
            a * wz + b * xy, 1.0 + b * yy, -a * wx + b * yz, t1,
            -a * wy + b * xz, a * wx + b * yz, 1.0 + b * zz, t2_)


def _se3_exp_one(wx: float, wy: float, wz: float, ux: float, uy: float, uz: float
                 ) -> np.ndarray:
    """:func:`se3_exp` of one twist in Python floats (:func:`se3_exp_rows`)."""
    return np.array([*se3_exp_rows(wx, wy, wz, ux, uy, uz), 0.0, 0.0, 0.0, 1.0]).reshape(1, 4, 4)


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from Hamilton quaternions ``[qx, qy, qz, qw]`` (normalised first).

    Args:
        q: ``(n, 4)`` quaternions, scalar last.

    Returns:
        ``(n, 3, 3)`` rotation matrices.
    """
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1),
        ],
        1,
    )


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Hamilton quaternions ``[qx, qy, qz, qw]`` with ``qw >= 0`` from rotation matrices.

    Args:
        R: ``(n, 3, 3)`` rotation matrices.

    Returns:
        ``(n, 4)`` unit quaternions, scalar last.
    """
    w = so3_log(R)
    theta = np.linalg.norm(w, axis=1)
    half = 0.5 * theta
    s = np.where(theta < 1e-12, 0.5, np.sin(half) / np.where(theta < 1e-12, 1.0, theta))
    return np.concatenate([w * s[:, None], np.cos(half)[:, None]], axis=1)


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotations and translations into ``(n, 4, 4)`` homogeneous transforms.

    Args:
        R: ``(n, 3, 3)`` rotations.
        t: ``(n, 3)`` translations.
    """
    T = np.zeros((len(R), 4, 4), like=R)
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, t, 1.0
    return T


def transform_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms.

    Args:
        T: ``(n, 4, 4)`` rigid transforms.
    """
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    return make_transform(Rt, -np.einsum("nij,nj->ni", Rt, T[:, :3, 3]))


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply rigid transforms to points: ``R_i p_i + t_i``.

    Args:
        T: ``(m, 4, 4)`` transforms.
        p: ``(m, 3)`` points.

    Returns:
        ``(m, 3)`` transformed points.
    """
    return rotate_points(T[:, :3, :3], p) + T[:, :3, 3]


def rotate_points(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``R_i p_i`` for ``(m, 3, 3)`` matrices (any, not only rotations) and ``(m, 3)`` points.

    One matrix broadcast over every point (stride 0, as the linearizer gathers a vertex that
    every edge of a group shares) is one ``(m, 3) × (3, 3)`` product: 3-4x faster than ``m``
    small ones at 100-500 points.

    Args:
        R: ``(m, 3, 3)`` matrices.
        p: ``(m, 3)`` points.
    """
    if type(R) is np.ndarray and type(p) is np.ndarray and R.strides[0] == 0 and len(R):
        return p @ R[0].T
    return np.matmul(R, p[:, :, None])[:, :, 0]


def relative_transform(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of ``T_b T_a⁻¹`` (frame ``a`` to frame ``b`` for ``T_·w``).

    With world-to-camera poses ``T_aw`` and ``T_bw`` this is ``T_ba``: ``R = R_b R_aᵀ``,
    ``t = t_b − R t_a``.

    Args:
        T_a: ``(m, 4, 4)`` transforms.
        T_b: ``(m, 4, 4)`` transforms.

    Returns:
        ``(R (m, 3, 3), t (m, 3))``.
    """
    R = T_b[:, :3, :3] @ np.swapaxes(T_a[:, :3, :3], 1, 2)
    t = T_b[:, :3, 3] - np.matmul(R, T_a[:, :3, 3][:, :, None])[:, :, 0]
    return R, t
