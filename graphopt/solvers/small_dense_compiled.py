"""The compiled first screen of :func:`~graphopt.solvers.small_dense.damped_solve`: ``H + λD``
factored and solved in one loop (0.7 against 4 µs for ``d = 6``), accepted only where the rank
rule's screen — every pivot large against its diagonal — passes and the step is finite; the
caller's LAPACK path decides every other case. Imports numba: loaded through
:func:`graphopt.compiled.load`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from graphopt.solvers.rank import PIVOT_SCREEN

__all__ = ["screened_solve"]


@numba.njit(cache=True, error_model="numpy")
def screened_solve(h_data: np.ndarray, b: np.ndarray, lam: float, damping: np.ndarray
                   ) -> tuple[np.ndarray, bool]:
    """``((H + λD)⁻¹ b, True)`` when the Cholesky factor's pivots pass the screen and the step
    is finite, else ``(…, False)``.

    Args:
        h_data: ``H``'s column-major data ``(d²,)`` (symmetric; not modified).
        b: ``(d,)`` right-hand side.
        lam: λ.
        damping: ``(d,)`` the diagonal ``D``.
    """
    d = b.shape[0]
    L = np.empty((d, d))
    x = np.empty(d)
    for j in range(d):
        q = h_data[j * d + j] + lam * damping[j]
        s = q
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > PIVOT_SCREEN * abs(q):  # p² against the damped diagonal (NaN fails)
            return x, False
        p = math.sqrt(s)
        L[j, j] = p
        for i in range(j + 1, d):
            t = h_data[j * d + i]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / p
    for i in range(d):  # L y = b
        t = b[i]
        for k in range(i):
            t -= L[i, k] * x[k]
        x[i] = t / L[i, i]
    total = 0.0
    for i in range(d - 1, -1, -1):  # Lᵀ x = y
        t = x[i]
        for k in range(i + 1, d):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]
        total += x[i]
    return x, math.isfinite(total)
