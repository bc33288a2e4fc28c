"""Derivative rules of :mod:`graphopt.lie` functions for jets (registered in
:data:`graphopt.lie.JET_RULES`).

A vertex's ``oplus`` and ``derived`` run forward on jets, once per distinct vertex; there the
cost is Python's per operation (~10 µs on a few hundred vertices), and Rodrigues' formula
with its small-angle series is ~40 of them. Its derivative has a closed form,
``∂exp(w)/∂w · ẇ = (J_l(w) ẇ)^ exp(w)`` (``J_l`` the left Jacobian of SO(3)), which costs a
handful of batched operations for all directions at once.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.autodiff.jet import Jet, Tape
from graphopt.lie import JET_RULES, hat, so3_exp, so3_left_jacobian

__all__ = ["so3_exp_jet"]


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


JET_RULES["so3_exp"] = so3_exp_jet
