"""``exp([ω, υ]) · T`` of one twist and one pose in one compiled call (imports numba: loaded
through :func:`graphopt.compiled.load`): the SE(3) vertex's ``oplus`` at every step of a
single-vertex problem, 0.95 against 2.8 µs.
"""

from __future__ import annotations

import numba
import numpy as np

from graphopt.lie import se3_exp_rows

__all__ = ["se3_exp_left_one"]

_rows = numba.njit(cache=True, error_model="numpy")(se3_exp_rows)


@numba.njit(cache=True, error_model="numpy")
def se3_exp_left_one(xi: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``se3_exp(xi[None])[0] @ T`` ``(4, 4)``: :func:`~graphopt.lie.se3_exp_rows` compiled,
    then the product.

    Args:
        xi: ``(6,)`` twist ``[ω, υ]``.
        T: ``(4, 4)`` transform.
    """
    E = _rows(xi[0], xi[1], xi[2], xi[3], xi[4], xi[5])
    out = np.empty((4, 4))
    for j in range(4):
        for i in range(3):
            out[i, j] = (E[4 * i] * T[0, j] + E[4 * i + 1] * T[1, j]) + (
                E[4 * i + 2] * T[2, j] + E[4 * i + 3] * T[3, j])
        out[3, j] = T[3, j]  # the exponential's last row is [0, 0, 0, 1]
    return out
