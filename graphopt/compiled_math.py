"""The arithmetic every compiled loop shares: robust weights and the normal equations' terms of
one edge. Imports numba: load it through :func:`graphopt.compiled.load` (modules of loops that
import it are loaded that way).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from graphopt.compiled import KERNEL_HUBER

__all__ = ["add_terms", "mirror", "robust"]


@numba.njit(cache=True, inline="always", error_model="numpy")
def robust(s: float, code: int, delta: float) -> tuple[float, float]:
    """``(ρ(s), ρ'(s))`` of the kernel ``code`` (:func:`~graphopt.compiled.kernel_code`):
    :class:`~graphopt.robust_kernel.RobustKernelHuber`'s ``cost_and_weight``, or ``(s, 1)``."""
    if code == KERNEL_HUBER and not s <= delta * delta:  # outside (or NaN, as numpy's)
        r = math.sqrt(s)
        return 2.0 * delta * r - delta * delta, delta / r
    return s, 1.0


@numba.njit(cache=True, inline="always", error_model="numpy")
def add_terms(H: np.ndarray, b: np.ndarray, J: np.ndarray, e: np.ndarray, w: np.ndarray) -> None:
    """``H += Jᵀ diag(w) J`` (upper triangle) and ``b += Jᵀ diag(w) e`` of one edge's rows
    ``J`` ``(rows, d)`` and errors ``e`` ``(rows,)``, row weights ``w`` (``ρ'·Ω`` diagonal)."""
    d = J.shape[1]
    for i in range(J.shape[0]):
        wi = w[i]
        wei = wi * e[i]
        for c in range(d):
            a = wi * J[i, c]
            b[c] += wei * J[i, c]
            for c2 in range(c, d):
                H[c, c2] += a * J[i, c2]


@numba.njit(cache=True, inline="always", error_model="numpy")
def mirror(H: np.ndarray) -> None:
    """The lower triangle of ``H`` from its upper one."""
    for c in range(H.shape[0]):
        for c2 in range(c):
            H[c, c2] = H[c2, c]
