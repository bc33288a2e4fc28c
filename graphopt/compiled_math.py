"""The arithmetic every compiled loop shares: robust weights and the normal equations' terms of
one edge. Imports numba: load it through :func:`graphopt.compiled.load` (modules of loops that
import it are loaded that way).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from graphopt.compiled import KERNEL_HUBER

__all__ = ["add_row6", "add_terms", "mirror", "robust"]


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
def add_row6(H: np.ndarray, b: np.ndarray, w: float, e: float, j0: float, j1: float,
             j2: float, j3: float, j4: float, j5: float) -> None:
    """:func:`add_terms` of one row ``[j0 … j5]`` of a 6-unknown vertex (a pose), written out
    (no triangular loops: the pose-only loop at 500 edges 14.6 → 11.8 µs; 27 accumulators in
    locals were slower, 16 µs, spilled registers)."""
    w0, w1, w2, w3, w4, w5 = w * j0, w * j1, w * j2, w * j3, w * j4, w * j5
    H[0, 0] += w0 * j0
    H[0, 1] += w0 * j1
    H[0, 2] += w0 * j2
    H[0, 3] += w0 * j3
    H[0, 4] += w0 * j4
    H[0, 5] += w0 * j5
    H[1, 1] += w1 * j1
    H[1, 2] += w1 * j2
    H[1, 3] += w1 * j3
    H[1, 4] += w1 * j4
    H[1, 5] += w1 * j5
    H[2, 2] += w2 * j2
    H[2, 3] += w2 * j3
    H[2, 4] += w2 * j4
    H[2, 5] += w2 * j5
    H[3, 3] += w3 * j3
    H[3, 4] += w3 * j4
    H[3, 5] += w3 * j5
    H[4, 4] += w4 * j4
    H[4, 5] += w4 * j5
    H[5, 5] += w5 * j5
    b[0] += w0 * e
    b[1] += w1 * e
    b[2] += w2 * e
    b[3] += w3 * e
    b[4] += w4 * e
    b[5] += w5 * e


@numba.njit(cache=True, inline="always", error_model="numpy")
def mirror(H: np.ndarray) -> None:
    """The lower triangle of ``H`` from its upper one."""
    for c in range(H.shape[0]):
        for c2 in range(c):
            H[c, c2] = H[c2, c]
