"""Batched similarity transforms as g2o computes them (``g2o/types/sim3/sim3.h`` and
``SE3Quat::log``), and the exact derivative of their logarithm.

A similarity ``S = (R, t, s)`` acts as ``S·x = s R x + t``; graphopt keeps it as the ``(4, 4)``
matrix ``[[sR, t], [·, 0, 0, 1]]`` (:class:`~graphopt.types.sim3.VertexSim3Expmap` uses the
bottom-left entry as its fix-scale flag, which no function here reads). Tangent vectors are in
g2o's order ``[ω, υ, σ]``: rotation, translation, log-scale.

**g2o's exp and log.** ``Sim3(update)`` and ``Sim3::log`` switch to limits by thresholds
(``|σ| < 1e-5``: ``C = 1``; ``d = (tr R − 1)/2 > 1 − 1e-5``: ``ω = ½ deltaR(R)``, ``A = ½``,
``B = ⅙``), which differ from the exact maps by up to ``|σ|/2`` and ``θ²/6`` relative;
:func:`sim3_exp` and :func:`sim3_log` follow the same branches, so that errors and chi2
equal g2o's. ``SE3Quat::log`` (:func:`se3quat_log`) switches at ``|d| > 0.99999``; near
``θ = π`` (``d < −0.99999``, where g2o's ``abs`` takes the small-angle branch and its result
is wrong) the exact rotation log is used instead.

**Derivative of the log.** :func:`log_left_jacobian` is ``∂ log(exp(a)·E) / ∂a`` at ``a = 0``
(the inverse of the left Jacobian) of the *exact* log, in closed form per block; the scalar
coefficients of ``W = A Ω + B Ω² + C I`` and their derivatives are integrals
``∫₀¹ e^{τσ} τ^p f(τθ) dτ`` of smooth functions, evaluated as power series in ``θ²`` over the
moments ``∫₀¹ τ^j e^{τσ} dτ`` (20-point Gauss–Legendre; error below 1e-16 for ``θ ≤ π``,
``|σ| ≤ 5``), which needs no small-angle or small-scale branches. Where g2o's log takes a
limit branch it differs from the exact one by less than the thresholds above; the Jacobians
are those of the exact log.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from graphopt.lie import SMALL_ANGLE2, hat, so3_exp, so3_log

__all__ = [
    "log_left_jacobian",
    "se3quat_log",
    "sim3_adjoint",
    "sim3_exp",
    "sim3_exp_one",
    "sim3_inverse",
    "sim3_log",
    "sim3_matrix",
    "sim3_parts",
    "sim3_product",
]

#: g2o's threshold in ``Sim3`` (``eps``) and in ``SE3Quat::log`` (``1 − 0.99999``).
G2O_EPS = 1e-5

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(20)


def _like(*arrays: Any) -> Any:
    """The first operand that is not a plain ndarray (a jet of ``graphopt.autodiff``), else the
    first: the ``like=`` of the arrays built here, so that errors run on jets too."""
    return next((a for a in arrays if type(a) is not np.ndarray), arrays[0])
_TAU = 0.5 * (_NODES + 1.0)          # nodes on [0, 1]
_W = 0.5 * _WEIGHTS


def sim3_parts(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R (n, 3, 3), t (n, 3), s (n,))`` of ``(n, 4, 4)`` similarities ``[[sR, t], …]``.

    Args:
        S: ``(n, 4, 4)`` similarity matrices.
    """
    sR = S[:, :3, :3]
    s = np.sqrt(np.einsum("nij,nij->n", sR, sR) / 3.0)
    return sR / s[:, None, None], S[:, :3, 3], s


def sim3_matrix(R: np.ndarray, t: np.ndarray, s: np.ndarray,
                fix_scale: np.ndarray | bool = False) -> np.ndarray:
    """``(n, 4, 4)`` matrices ``[[sR, t], [f, 0, 0, 1]]`` (``f`` the fix-scale flag, 0 or 1).

    Args:
        R: ``(n, 3, 3)`` rotations.
        t: ``(n, 3)`` translations.
        s: ``(n,)`` positive scales.
        fix_scale: Scalar or ``(n,)`` flags for :class:`~graphopt.types.sim3.VertexSim3Expmap`.
    """
    n = len(R)
    S = np.zeros((n, 4, 4), like=_like(R, t, s))
    S[:, :3, :3] = np.reshape(s, (-1,))[:, None, None] * R
    S[:, :3, 3] = t
    S[:, 3, 3] = 1.0
    S[:, 3, 0] = np.broadcast_to(np.asarray(fix_scale, float), (n,))
    return S


def sim3_product(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A·B`` of ``(n, 4, 4)`` similarities (bottom row ``[0, 0, 0, 1]``).

    Args:
        A: ``(n, 4, 4)``.
        B: ``(n, 4, 4)``.
    """
    out = np.zeros(np.broadcast_shapes(A.shape, B.shape), like=_like(A, B))
    out[:, :3, :3] = A[:, :3, :3] @ B[:, :3, :3]
    out[:, :3, 3] = np.matmul(A[:, :3, :3], B[:, :3, 3, None])[:, :, 0] + A[:, :3, 3]
    out[:, 3, 3] = 1.0
    return out


def sim3_inverse(S: np.ndarray) -> np.ndarray:
    """``S⁻¹ = [[Rᵀ/s, −Rᵀt/s], [0, 0, 0, 1]]`` of ``(n, 4, 4)`` similarities.

    Args:
        S: ``(n, 4, 4)``.
    """
    R, t, s = sim3_parts(S)
    out = np.zeros(S.shape, like=S)
    Rt = np.swapaxes(R, 1, 2) / s[:, None, None]
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.matmul(Rt, t[:, :, None])[:, :, 0]
    out[:, 3, 3] = 1.0
    return out


def _g2o_abc(theta: np.ndarray, sigma: np.ndarray, s: np.ndarray,
             small_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """g2o's ``A, B, C`` of ``W = AΩ + BΩ² + CI``, with its branches."""
    small_s = np.abs(sigma) < G2O_EPS
    th = np.where(small_rot, 1.0, theta)
    sg = np.where(small_s, 1.0, sigma)
    th2, sg2 = th * th, sg * sg
    # |σ| < eps: the rotation-only coefficients.
    A0 = np.where(small_rot, 0.5, (1.0 - np.cos(th)) / th2)
    B0 = np.where(small_rot, 1.0 / 6.0, (th - np.sin(th)) / (th2 * th))
    C = np.where(small_s, 1.0, (s - 1.0) / sg)
    # θ small, σ not.
    A1 = ((sg - 1.0) * s + 1.0) / sg2
    B1 = ((0.5 * sg2 - sg + 1.0) * s - 1.0) / (sg2 * sg)
    # General case.
    a, b, c = s * np.sin(th), s * np.cos(th), th2 + sg2
    A2 = (a * sg + (1.0 - b) * th) / (th * c)
    B2 = (C - ((b - 1.0) * sg + a * th) / c) / th2
    A = np.where(small_s, A0, np.where(small_rot, A1, A2))
    B = np.where(small_s, B0, np.where(small_rot, B1, B2))
    return A, B, C


def _w_matrix(Omega: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    return (A[:, None, None] * Omega + B[:, None, None] * (Omega @ Omega)
            + C[:, None, None] * np.eye(3))


def sim3_exp(xi: np.ndarray) -> np.ndarray:
    """g2o's ``Sim3(update)``: ``(n, 7)`` tangents ``[ω, υ, σ]`` to ``(n, 4, 4)`` similarities.

    ``R = exp([ω]×)`` (Rodrigues; g2o's first-order rotation below 1e-5 rad and its quaternion
    normalisation differ from it by ~1e-16), ``s = e^σ``, ``t = W υ`` with g2o's ``W``.

    Args:
        xi: ``(n, 7)``.
    """
    w, u, sigma = xi[:, :3], xi[:, 3:6], xi[:, 6]
    theta = np.sqrt(np.einsum("ni,ni->n", w, w))
    s = np.exp(sigma)
    A, B, C = _g2o_abc(theta, sigma, s, theta < G2O_EPS)
    W = _w_matrix(hat(w), A, B, C)
    return sim3_matrix(so3_exp(w), np.matmul(W, u[:, :, None])[:, :, 0], s)


def sim3_exp_one(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sim3_exp` of one tangent ``(7,)`` in Python floats (one Sim3 vertex, as in
    ``OptimizeSim3``, is updated every iteration: ~8 µs instead of ~45).

    Args:
        xi: ``(7,)`` tangent ``[ω, υ, σ]``.

    Returns:
        ``(sR (3, 3), t (3,))``.
    """
    wx, wy, wz, ux, uy, uz, sigma = (float(v) for v in xi)
    th2 = wx * wx + wy * wy + wz * wz
    theta = math.sqrt(th2)
    s = math.exp(sigma)
    small_rot, small_s = theta < G2O_EPS, abs(sigma) < G2O_EPS
    if small_s:
        C = 1.0
        A, B = (0.5, 1.0 / 6.0) if small_rot else (
            (1.0 - math.cos(theta)) / th2, (theta - math.sin(theta)) / (th2 * theta))
    else:
        C = (s - 1.0) / sigma
        sg2 = sigma * sigma
        if small_rot:
            A = ((sigma - 1.0) * s + 1.0) / sg2
            B = ((0.5 * sg2 - sigma + 1.0) * s - 1.0) / (sg2 * sigma)
        else:
            a, b, c = s * math.sin(theta), s * math.cos(theta), th2 + sg2
            A = (a * sigma + (1.0 - b) * theta) / (theta * c)
            B = (C - ((b - 1.0) * sigma + a * theta) / c) / th2
    # Rodrigues' coefficients, by series below SMALL_ANGLE2 as graphopt.lie.so3_exp.
    if th2 < SMALL_ANGLE2:
        ra, rb = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        ra, rb = math.sin(theta) / theta, (1.0 - math.cos(theta)) / th2
    # Ω = [ω]×, Ω² = ωωᵀ − θ²I, entry by entry (Python floats: no 3 x 3 numpy calls).
    xx, yy, zz, xy, xz, yz = wx * wx - th2, wy * wy - th2, wz * wz - th2, wx * wy, wx * wz, wy * wz
    R = np.array([[1.0 + rb * xx, -ra * wz + rb * xy, ra * wy + rb * xz],
                  [ra * wz + rb * xy, 1.0 + rb * yy, -ra * wx + rb * yz],
                  [-ra * wy + rb * xz, ra * wx + rb * yz, 1.0 + rb * zz]])
    t = np.array([(C + B * xx) * ux + (-A * wz + B * xy) * uy + (A * wy + B * xz) * uz,
                  (A * wz + B * xy) * ux + (C + B * yy) * uy + (-A * wx + B * yz) * uz,
                  (-A * wy + B * xz) * ux + (A * wx + B * yz) * uy + (C + B * zz) * uz])
    return s * R, t


def _delta_r(R: np.ndarray) -> np.ndarray:
    return np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0],
                     R[:, 1, 0] - R[:, 0, 1]], axis=1)


def _rotation_log(R: np.ndarray, small: np.ndarray) -> np.ndarray:
    """g2o's ``ω``: ``½ deltaR(R)`` where ``small``, the exact log elsewhere."""
    omega = so3_log(R)
    return np.where(small[:, None], 0.5 * _delta_r(R), omega)


def sim3_log(S: np.ndarray) -> np.ndarray:
    """g2o's ``Sim3::log``: ``(n, 4, 4)`` similarities to ``(n, 7)`` tangents ``[ω, υ, σ]``.

    Args:
        S: ``(n, 4, 4)``.
    """
    R, t, s = sim3_parts(S)
    sigma = np.log(s)
    d = 0.5 * (np.einsum("nii->n", R) - 1.0)
    small_rot = d > 1.0 - G2O_EPS
    omega = _rotation_log(R, small_rot)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    A, B, C = _g2o_abc(theta, sigma, s, small_rot)
    W = _w_matrix(hat(omega), A, B, C)
    out = np.empty((len(S), 7), like=_like(S, omega))
    out[:, :3] = omega
    out[:, 3:6] = np.linalg.solve(W, t[:, :, None])[:, :, 0]
    out[:, 6] = sigma
    return out


def se3quat_log(T: np.ndarray) -> np.ndarray:
    """g2o's ``SE3Quat::log``: ``(n, 4, 4)`` rigid transforms to ``(n, 6)`` ``[ω, υ]``.

    Args:
        T: ``(n, 4, 4)`` (or ``(n, 3, 4)``) rigid transforms.
    """
    R, t = T[:, :3, :3], T[:, :3, 3]
    d = 0.5 * (np.einsum("nii->n", R) - 1.0)
    small = d > 0.99999
    omega = _rotation_log(R, small)
    th = np.where(small, 1.0, np.arccos(np.clip(d, -1.0, 1.0)))
    coef = np.where(small, 1.0 / 12.0, (1.0 - th / (2.0 * np.tan(th / 2.0))) / (th * th))
    Om = hat(omega)
    V_inv = np.eye(3) - 0.5 * Om + coef[:, None, None] * (Om @ Om)
    return np.concatenate([omega, np.matmul(V_inv, t[:, :, None])[:, :, 0]], axis=1)


def sim3_adjoint(S: np.ndarray, scaled: bool = True) -> np.ndarray:
    """Adjoints ``Ad_S`` with ``S·exp(a)·S⁻¹ = exp(Ad_S a)``, tangent order ``[ω, υ, σ]``.

    ``[[R, 0, 0], [[t]×R, sR, −t], [0, 0, 1]]`` (g2o's ``adj_Sji``); with ``scaled=False`` the
    ``(n, 6, 6)`` SE(3) adjoint ``[[R, 0], [[t]×R, R]]`` of a rigid ``S`` (g2o's ``SE3Quat::adj``).

    Args:
        S: ``(n, 4, 4)`` similarities (rigid transforms for ``scaled=False``).
        scaled: Similarity (7×7) or rigid (6×6) adjoint.
    """
    if scaled:
        R, t, s = sim3_parts(S)
    else:
        R, t, s = S[:, :3, :3], S[:, :3, 3], np.ones(len(S))
    k = 7 if scaled else 6
    out = np.zeros((len(S), k, k))
    out[:, :3, :3] = R
    out[:, 3:6, :3] = hat(t) @ R
    out[:, 3:6, 3:6] = s[:, None, None] * R
    if scaled:
        out[:, 3:6, 6] = -t
        out[:, 6, 6] = 1.0
    return out


# --- the derivative of the log ---------------------------------------------------------------

def _series(x2: np.ndarray, coefs: list[float]) -> np.ndarray:
    out = np.full_like(x2, coefs[-1])
    for c in coefs[-2::-1]:
        out = out * x2 + c
    return out


def _fact(n: int) -> float:
    return float(np.prod(np.arange(1, n + 1, dtype=float)))


# W = ∫₀¹ e^{τσ} e^{τΩ} dτ = A Ω + B Ω² + C I with, for x = τθ,
#   A = ∫ e^{τσ} τ sinc(x),  B = ∫ e^{τσ} τ² h(x),  C = ∫ e^{τσ},
#   A_θ/θ = ∫ e^{τσ} τ³ g(x),  B_θ/θ = ∫ e^{τσ} τ⁴ k(x),
#   A_σ = ∫ e^{τσ} τ² sinc(x),  B_σ = ∫ e^{τσ} τ³ h(x),  C_σ = ∫ e^{τσ} τ,
# sinc = sin x/x, h = (1 − cos x)/x², g = (x cos x − sin x)/x³, k = (x sin x − 2(1 − cos x))/x⁴.
# Each kernel is Σ_n c_n x^{2n}, so every integral is Σ_n c_n θ^{2n} M_{p+2n}(σ) with the
# moments M_j = ∫₀¹ τ^j e^{τσ} dτ. Fifteen terms reach 1e-19 at θ = π; the moments come from
# one (m, 20) × (20, 33) product with 20-point Gauss–Legendre (exact to degree 39 in τ).
_TERMS = 15
_COEF = {
    "sinc": np.array([(-1) ** n / _fact(2 * n + 1) for n in range(_TERMS)]),
    "h": np.array([(-1) ** n / _fact(2 * n + 2) for n in range(_TERMS)]),
    "g": np.array([(-1) ** n * 2 * n / _fact(2 * n + 1) for n in range(1, _TERMS + 1)]),
    "k": np.array([(-1) ** m * 2 * m / _fact(2 * m + 2) for m in range(1, _TERMS + 1)]),
}
#: (name, kernel, power p of τ)
_INTEGRALS = [("A", "sinc", 1), ("B", "h", 2), ("A_t", "g", 3), ("B_t", "k", 4),
              ("A_s", "sinc", 2), ("B_s", "h", 3)]
_MOMENTS = 4 + 2 * _TERMS - 1
_POWERS = _TAU[:, None] ** np.arange(_MOMENTS)[None, :] * _W[:, None]


def _w_coefficients(theta: np.ndarray, sigma: np.ndarray) -> dict[str, np.ndarray]:
    """Exact ``A, B, C`` of ``W = ∫₀¹ e^{τ(σI + Ω)} dτ`` and the derivatives the log needs:
    ``A_θ/θ``, ``B_θ/θ``, ``A_σ``, ``B_σ``, ``C_σ`` (moment series, above)."""
    M = np.exp(sigma[:, None] * _TAU[None, :]) @ _POWERS            # (m, moments)
    t2n = np.cumprod(np.concatenate([np.ones((len(theta), 1)),
                                     np.repeat((theta * theta)[:, None], _TERMS - 1, 1)], 1), 1)
    out = {"C": M[:, 0], "C_s": M[:, 1]}
    for name, kernel, p in _INTEGRALS:
        out[name] = (M[:, p:p + 2 * _TERMS:2] * t2n) @ _COEF[kernel]
    return out


def _so3_left_jacobian_inverse(w: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``J_l(ω)⁻¹ = I − ½Ω + (1/θ² − (1 + cosθ)/(2θ sinθ)) Ω²``."""
    small = theta < 0.1
    th = np.where(small, 1.0, theta)
    coef = np.where(small, _series(theta**2, [1 / 12, 1 / 720, 1 / 30240, 1 / 1209600]),
                    1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th)))
    Om = hat(w)
    return np.eye(3) - 0.5 * Om + coef[:, None, None] * (Om @ Om)


def log_left_jacobian(S: np.ndarray, scaled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The exact log of similarities (or rigid transforms) and its left-perturbation
    derivative ``D = ∂ log(exp(a)·S) / ∂a`` at ``a = 0``.

    With ``exp(a) ≈ (I + [a_ω]×, a_υ, 1 + a_σ)``: ``dω = J_l(ω)⁻¹ a_ω``, ``dσ = a_σ`` and, from
    ``υ = W⁻¹ t`` with ``dt = a_υ − [t]× a_ω + t a_σ``, ``dυ = W⁻¹(dt − dW·υ)``.

    Args:
        S: ``(n, 4, 4)`` similarities (``scaled``) or rigid transforms.
        scaled: 7-D Sim(3) or 6-D SE(3) (``σ = 0``).

    Returns:
        ``(log (n, k), D (n, k, k))``, ``k`` = 7 or 6.
    """
    if scaled:
        R, t, s = sim3_parts(S)
        sigma = np.log(s)
    else:
        R, t, sigma = S[:, :3, :3], S[:, :3, 3], np.zeros(len(S))
    w = so3_log(R)
    theta = np.sqrt(np.einsum("ni,ni->n", w, w))
    c = _w_coefficients(theta, sigma)
    Om = hat(w)
    W = _w_matrix(Om, c["A"], c["B"], c["C"])
    Winv = np.linalg.inv(W)
    u = np.matmul(Winv, t[:, :, None])[:, :, 0]
    Ou = np.matmul(Om, u[:, :, None])[:, :, 0]
    O2u = np.matmul(Om, Ou[:, :, None])[:, :, 0]
    hu = hat(u)
    # M_ω = ∂(W υ)/∂ω at fixed υ.
    M = (c["A_t"][:, None, None] * (Ou[:, :, None] * w[:, None, :])
         - c["A"][:, None, None] * hu
         + c["B_t"][:, None, None] * (O2u[:, :, None] * w[:, None, :])
         - c["B"][:, None, None] * (hat(Ou) + Om @ hu))
    Jinv = _so3_left_jacobian_inverse(w, theta)
    k = 7 if scaled else 6
    D = np.zeros((len(S), k, k))
    D[:, :3, :3] = Jinv
    D[:, 3:6, :3] = Winv @ (-hat(t) - M @ Jinv)
    D[:, 3:6, 3:6] = Winv
    log = np.empty((len(S), k))
    log[:, :3], log[:, 3:6] = w, u
    if scaled:
        m_s = (c["A_s"][:, None] * Ou + c["B_s"][:, None] * O2u + c["C_s"][:, None] * u)
        D[:, 3:6, 6] = np.matmul(Winv, (t - m_s)[:, :, None])[:, :, 0]
        D[:, 6, 6] = 1.0
        log[:, 6] = sigma
    return log, D
