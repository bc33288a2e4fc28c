"""The damped solve of one small dense block (a single-vertex problem's ``H + λD``).

LAPACK's ``dpotrf``/``dpotrs`` on a Fortran view of the damped matrix (no copy), held to the
dense solver's rank rule (:mod:`graphopt.solvers.rank`): its first screen — every pivot large
against its diagonal — in Python floats (``d`` pivots: 1 µs, not 4), or with numba the whole
screened solve in one compiled loop (:mod:`~graphopt.solvers.small_dense_compiled`); any doubt
goes through :func:`~graphopt.solvers.dense.cholesky_solve`, the dense solver's full rule.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla

from graphopt.compiled import Lazy
from graphopt.solvers.dense import cholesky_solve, factor_in_place, is_definite
from graphopt.solvers.rank import PIVOT_SCREEN, shift_diagonal


def damped_solve(h_data: np.ndarray, b: np.ndarray, diag: np.ndarray, lam: float,
                 damping: np.ndarray) -> np.ndarray:
    """``(H + λD)⁻¹ b`` for a symmetric ``d × d`` ``H``.

    Args:
        h_data: ``H``'s column-major data ``(d², )`` (not modified).
        b: ``(d,)`` right-hand side.
        diag: ``(d,)`` the diagonal's positions in ``h_data``.
        lam: λ (0 for none).
        damping: ``(d,)`` the diagonal ``D``.

    Raises:
        NotPositiveDefiniteError: as the dense solver (``SingularSystemError`` when rank
            deficient).
    """
    d = len(diag)
    screened = _SCREENED.get()
    if screened is not None:
        du, ok = screened(h_data, b, lam, damping)
        if ok:
            return du
    data = _damped(h_data, diag, lam, damping)
    pivots = data[::d + 1].tolist()
    # Symmetric: the column-major data read as a (d, d) C array and transposed is a
    # Fortran-ordered view that LAPACK factors in place.
    c, info = factor_in_place(data, d)
    if info == 0:
        for p, q in zip(c.diagonal().tolist(), pivots, strict=True):
            if not p * p > PIVOT_SCREEN * abs(q):
                break
        else:
            du, info = sla.lapack.dpotrs(c, b, lower=1)
            if info == 0 and math.isfinite(sum(du.tolist())):
                return du
    data = _damped(h_data, diag, lam, damping)  # again: the first was factored over
    return cholesky_solve("dense", factor_in_place(data.copy(), d), data[diag], b.copy(),
                          lambda s: is_definite(factor_in_place(shift_diagonal(data, diag, s),
                                                                d)))


_SCREENED = Lazy("graphopt.solvers.small_dense_compiled", "screened_solve")


def _damped(h_data: np.ndarray, diag: np.ndarray, lam: float, damping: np.ndarray
            ) -> np.ndarray:
    """A copy of ``H``'s data with ``λD`` added to its diagonal (``diag``'s positions, every
    ``d + 1``-th entry: written through a strided view, no fancy indexing)."""
    data = h_data.copy()
    if lam:
        data[::len(diag) + 1] += lam * damping
    return data
