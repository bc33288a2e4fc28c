"""The compiled loop of the pose-only projection edges (``EdgeSE3ProjectXYZOnlyPose`` and its
stereo twin) on one pose: errors, g2o's Jacobian rows, robust weights and the normal equations'
terms in one pass over the edges (see :mod:`graphopt.compiled`). Imports numba: loaded through
:func:`graphopt.compiled.load`.
"""

from __future__ import annotations

import numba
import numpy as np

from graphopt.compiled_math import add_row6, mirror, robust

__all__ = ["pose_only_terms"]


@numba.njit(cache=True, error_model="numpy")
def pose_only_terms(T: np.ndarray, Xw: np.ndarray, z: np.ndarray, cam: np.ndarray,
                    info: np.ndarray, active: np.ndarray, code: int, delta: float, lin: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                               float, float]:
    """:class:`~graphopt.compiled.CompiledUnary`'s loop for ``e = z − π(T X_w)`` (``z`` with
    3 columns: ``[u, v, u − bf/z]``, stereo).

    Args:
        T: ``(4, 4)`` the pose ``T_cw``.
        Xw: ``(m, 3)`` world points.
        z: ``(m, 2|3)`` pixels.
        cam: ``(fx, fy, cx, cy, bf)``.
        info: ``(m|1, rows)`` the information's diagonal.
        active: ``(m,)`` the active edges, or ``(0,)``: all.
        code: Robust kernel code.
        delta: Its width.
        lin: Also the Jacobians, ``H`` and ``b``.

    Returns:
        ``(e (m, rows), every (m,), s (m,), H (6, 6), b (6,), chi2, robust chi2)``.
    """
    m, rows = z.shape
    fx, fy, cx, cy, bf = cam[0], cam[1], cam[2], cam[3], cam[4]
    e = np.empty((m, rows))
    every = np.empty(m)
    s = np.empty(m)
    H = np.zeros((6, 6))
    b = np.zeros(6)
    shared = info.shape[0] == 1
    everyone = active.shape[0] == 0
    chi = 0.0
    rchi = 0.0
    for k in range(m):
        X, Y, Z = Xw[k, 0], Xw[k, 1], Xw[k, 2]
        px = T[0, 0] * X + T[0, 1] * Y + T[0, 2] * Z + T[0, 3]
        py = T[1, 0] * X + T[1, 1] * Y + T[1, 2] * Z + T[1, 3]
        pz = T[2, 0] * X + T[2, 1] * Y + T[2, 2] * Z + T[2, 3]
        iz = 1.0 / pz
        u = px * iz
        v = py * iz
        pu = fx * u + cx
        e[k, 0] = z[k, 0] - pu
        e[k, 1] = z[k, 1] - (fy * v + cy)
        if rows == 3:
            e[k, 2] = z[k, 2] - (pu - bf * iz)
        q = 0 if shared else k
        sk = 0.0
        for i in range(rows):
            sk += e[k, i] * (e[k, i] * info[q, i])
        every[k] = sk
        on = everyone or active[k]
        s[k] = sk if on else 0.0
        if not on:
            continue
        chi += sk
        rho, r1 = robust(sk, code, delta)
        rchi += rho
        if lin:  # g2o's rows under T ← exp([ω, υ]) T, weighed by ρ'·Ω
            a0, a1, a2, a3, a5 = fx * u * v, -fx * (1.0 + u * u), fx * v, -fx * iz, fx * u * iz
            add_row6(H, b, info[q, 0] * r1, e[k, 0], a0, a1, a2, a3, 0.0, a5)
            add_row6(H, b, info[q, 1] * r1, e[k, 1], fy * (1.0 + v * v), -fy * u * v, -fy * u,
                     0.0, -fy * iz, fy * v * iz)
            if rows == 3:  # u_r = u − bf·iz: row 0 plus bf·[−v·iz, u·iz, 0, 0, 0, −iz²]
                add_row6(H, b, info[q, 2] * r1, e[k, 2], a0 - bf * v * iz, a1 + bf * u * iz, a2,
                         a3, 0.0, a5 - bf * iz * iz)
    if lin:
        mirror(H)
    return e, every, s, H, b, chi, rchi
