"""A user's compiled loop (docs/compiled.md): a unary position prior ``e = z − x`` on a
:class:`~graphopt.types.VertexPointXYZ`, whose ``oplus`` is ``x + δ`` (so ``J = −I``). Imports
numba: loaded through :func:`graphopt.compiled.load`."""

from __future__ import annotations

import numba
import numpy as np

from graphopt.compiled_math import add_terms, mirror, robust


@numba.njit(cache=True, error_model="numpy")
def prior_terms(x: np.ndarray, z: np.ndarray, info: np.ndarray, active: np.ndarray, code: int,
                delta: float, lin: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float,
                           float]:
    """:class:`~graphopt.compiled.CompiledUnary`'s loop of the prior (``x`` ``(3,)``, ``z``
    ``(m, 3)``)."""
    m, rows = z.shape
    e = np.empty((m, rows))
    every = np.empty(m)
    s = np.empty(m)
    H = np.zeros((rows, rows))
    b = np.zeros(rows)
    Jk = -np.eye(rows)  # ∂e/∂δ, the same for every edge
    w = np.empty(rows)
    chi = 0.0
    rchi = 0.0
    for k in range(m):
        q = 0 if info.shape[0] == 1 else k
        sk = 0.0
        for i in range(rows):
            e[k, i] = z[k, i] - x[i]
            sk += e[k, i] * (e[k, i] * info[q, i])
        every[k] = sk
        on = active.shape[0] == 0 or active[k]
        s[k] = sk if on else 0.0
        if not on:
            continue
        chi += sk
        rho, r1 = robust(sk, code, delta)
        rchi += rho
        if lin:
            for i in range(rows):
                w[i] = info[q, i] * r1
            add_terms(H, b, Jk, e[k], w)
    if lin:
        mirror(H)
    return e, every, s, H, b, chi, rchi
