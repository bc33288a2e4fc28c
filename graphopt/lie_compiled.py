"""``exp([ω, υ]) · T`` of one twist and one pose in one compiled call (imports numba: loaded
through :func:`graphopt.compiled.load`): the SE(3) vertex's ``oplus`` at every step of a
single-vertex problem, 0.6 against 3.6 µs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from graphopt.lie import SMALL_ANGLE2

__all__ = ["se3_exp_left_one"]


@numba.njit(cache=True, error_model="numpy")
def se3_exp_left_one(xi: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``se3_exp(xi[None])[0] @ T`` ``(4, 4)``: :func:`~graphopt.lie.se3_exp`'s one-twist
    formulas (``_se3_exp_one``, operation for operation), then the product.

    Args:
        xi: ``(6,)`` twist ``[ω, υ]``.
        T: ``(4, 4)`` transform.
    """
    wx, wy, wz, ux, uy, uz = xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]
    t2 = wx * wx + wy * wy + wz * wz
    if t2 < SMALL_ANGLE2:
        a, b, c = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        th = math.sqrt(t2)
        sn = math.sin(th)
        a, b, c = sn / th, (1.0 - math.cos(th)) / t2, (th - sn) / (t2 * th)
    xx, yy, zz = wx * wx - t2, wy * wy - t2, wz * wz - t2
    xy, xz, yz = wx * wy, wx * wz, wy * wz
    E = np.empty((4, 4))
    E[0, 0], E[0, 1], E[0, 2] = 1.0 + b * xx, -a * wz + b * xy, a * wy + b * xz
    E[1, 0], E[1, 1], E[1, 2] = a * wz + b * xy, 1.0 + b * yy, -a * wx + b * yz
    E[2, 0], E[2, 1], E[2, 2] = -a * wy + b * xz, a * wx + b * yz, 1.0 + b * zz
    v00, v01, v02 = 1.0 + c * xx, -b * wz + c * xy, b * wy + c * xz
    v10, v11, v12 = b * wz + c * xy, 1.0 + c * yy, -b * wx + c * yz
    v20, v21, v22 = -b * wy + c * xz, b * wx + c * yz, 1.0 + c * zz
    E[0, 3] = v00 * ux + v01 * uy + v02 * uz
    E[1, 3] = v10 * ux + v11 * uy + v12 * uz
    E[2, 3] = v20 * ux + v21 * uy + v22 * uz
    E[3, 0], E[3, 1], E[3, 2], E[3, 3] = 0.0, 0.0, 0.0, 1.0
    out = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            out[i, j] = (E[i, 0] * T[0, j] + E[i, 1] * T[1, j]) + (E[i, 2] * T[2, j]
                                                                 + E[i, 3] * T[3, j])
    return out
