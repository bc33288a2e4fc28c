"""Derivative rules of :mod:`graphopt.lie` functions for jets (registered in
:data:`graphopt.lie.JET_RULES`).

A vertex's ``oplus`` and ``derived`` run forward on jets, once per distinct vertex; there the
cost is Python's per operation (~10 µs on a few hundred vertices), and Rodrigues' formula
with its small-angle series is ~40 of them. Its derivative has a closed form,
``∂exp(w)/∂w · ẇ = (J_l(w) ẇ)^ exp(w)`` (``J_l`` the left Jacobian of SO(3)), which costs a
handful of batched operations for all directions at once; the logarithm's formula is
differentiated by hand the same way (away from its small-angle and near-π branches).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.autodiff.jet import Jet, Tape
from graphopt.lie import JET_RULES, hat, so3_exp, so3_left_jacobian, so3_log

__all__ = ["so3_exp_jet", "so3_log_jet"]


def so3_exp_jet(w: Any) -> Jet | None:
    """:func:`graphopt.lie.so3_exp` of a jet ``(n, 3)`` with its derivatives in closed form,
    or ``None`` (not a jet, or one being recorded for reverse accumulation, which records
    the formula's operations instead)."""
    if type(w) is not Jet or w._tape is not None or Tape.active or w.value.ndim != 2:
        return None
    v = w.value
    R = so3_exp(v)
    t = w.tangent  # (k, n, 3)
    u = np.einsum("nij,knj->kni", so3_left_jacobian(v), t)
    k, n = t.shape[:2]
    dR = np.matmul(hat(u.reshape(k * n, 3)).reshape(k, n, 3, 3), R)
    return Jet(R, dR, w.lo, w.n)


def so3_log_jet(R: Any) -> Jet | None:
    """:func:`graphopt.lie.so3_log` of a jet ``(n, 3, 3)``: the derivative of its formula
    ``w = v θ / (2 sin θ)``, ``θ = arccos((tr R − 1)/2)``, ``v = (R₂₁ − R₁₂, R₀₂ − R₂₀,
    R₁₀ − R₀₁)`` written out, or ``None`` (not a jet, recorded, or an angle where the
    function takes its small-angle or near-π branch: the formula runs on the jet there)."""
    if type(R) is not Jet or R._tape is not None or Tape.active or R.value.shape[1:] != (3, 3):
        return None
    V = R.value
    w = so3_log(V)
    theta = np.sqrt(np.einsum("ni,ni->n", w, w))
    if len(theta) and not (theta.min() >= 2e-4 and theta.max() <= np.pi - 2e-3):
        return None
    t = R.tangent  # (k, n, 3, 3)
    dv = np.stack([t[..., 2, 1] - t[..., 1, 2], t[..., 0, 2] - t[..., 2, 0],
                   t[..., 1, 0] - t[..., 0, 1]], axis=-1)  # (k, n, 3)
    v = np.stack([V[:, 2, 1] - V[:, 1, 2], V[:, 0, 2] - V[:, 2, 0], V[:, 1, 0] - V[:, 0, 1]], 1)
    cos = np.clip(0.5 * (np.einsum("nii->n", V) - 1.0), -1.0, 1.0)
    th = np.arccos(cos)
    sin = np.sin(th)
    scale = th / (2.0 * sin)
    dtheta = -0.5 * np.einsum("knii->kn", t) / np.sqrt(1.0 - cos * cos)
    dscale = (sin - th * np.cos(th)) / (2.0 * sin * sin) * dtheta  # (k, n)
    return Jet(w, dv * scale[:, None] + v * dscale[..., None], R.lo, R.n)


JET_RULES["so3_exp"] = so3_exp_jet
JET_RULES["so3_log"] = so3_log_jet
