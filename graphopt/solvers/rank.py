"""The one rank-deficiency rule every direct solver applies (``dense``, ``cholmod``,
``scipy``), so that a singular system is reported the same way whatever the solver, the
ordering or the BLAS kernel. The rule is stated on ``Ã = S^-½ A S^-½``, ``A`` scaled to a unit
diagonal (``s_k = A_kk``, floored at ``u · max_j |A_jj|`` so that a zero row has a scale): the
system is **singular** when ``λ_min(Ã) ≤ τ`` (``τ =`` :data:`SINGULAR_TOLERANCE`) and
``λ_min(Ã) ≥ −τ``, **not positive definite** (indefinite) when ``λ_min(Ã) < −τ``. Being
relative to the diagonal, it does not depend on the units of the unknowns. A factorisation
``PAPᵀ = LDLᵀ`` (``D_k = L_kk²`` for ``LLᵀ``, ``U_kk`` for ``LU`` with diagonal pivots)
tests it in three steps:

1. **Screen.** If every pivot is positive and ``D_k > σ · s_k`` (``σ =``
   :data:`PIVOT_SCREEN`), the system is accepted: ``O(n)``, the common case.
2. **Small pivot.** If every pivot is positive but one is at most ``σ · s_k``, one step of
   inverse iteration with the factor, ``y = A⁻¹b`` for ``b = S^½ g`` and a fixed pseudo-random
   ``g``, gives the Rayleigh quotient ``ρ = yᵀAy / yᵀSy = bᵀy / yᵀSy``, an upper bound of
   ``λ_min(Ã)``; on a rank-deficient system ``y`` is dominated by the null space and ``ρ`` is
   rounding noise. ``ρ ≤ τ``: singular, else accepted. ``b`` is solved for as one more column
   of the right-hand side, so the probe costs a fraction of a solve.
3. **Non-positive pivot** (the factorisation stopped, or an ``LDLᵀ``/``LU`` pivot is not
   positive): ``A + τ·S`` is factorised; positive definite means ``λ_min(Ã) > −τ``: singular;
   otherwise not positive definite.

Why not the pivot ratio ``D_k / s_k`` alone: on a singular system the first negligible pivot
is the rounding noise divided by the squared share of the null vector at that unknown, which
depends on the ordering (up to 7e-10 measured, below), while the smallest ratio of a well-posed
system can be 8e-8: too close. ``λ_min(Ã)`` separates them by orders of magnitude.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np

from graphopt.errors import NotPositiveDefiniteError, SingularSystemError

#: ``τ``: the system is singular when ``|λ_min(S^-½ A S^-½)| ≤ τ``. Measured (GN systems at
#: λ = 0): rank-deficient systems have ``|λ_min(Ã)|`` — and ``ρ`` of step 2 — of at most 7e-15
#: (gauge-free SE2 loops of 5–41 poses: 2e-16; gauge-free w10000, 30,000 unknowns: 8e-17; BAL
#: reduced camera systems, whose 7-dimensional gauge is free: 4e-16 on Dubrovnik-16, 7e-15 on
#: Ladybug-49); the smallest ``λ_min(Ã)`` of a well-posed system seen was 4.6e-11 (w10000 with
#: its first pose fixed, at its odometry initialisation; its ``ρ`` stayed ≥ 3.3e-11 over GN's
#: iterations). 1e-12 is 140x above the noise and 33x below that.
SINGULAR_TOLERANCE = 1e-12

#: ``σ``: pivots ``D_k ≤ σ · s_k`` send the system to step 2. On rank-deficient systems the first
#: such ratio was at most 7e-10 (BAL systems in CHOLMOD's and SuperLU's orderings; ≤ 1e-13 on
#: the SE2 loops and w10000; every solver, OpenBLAS core types Haswell, Zen, SkylakeX,
#: Prescott), so 1e-6 leaves three orders of magnitude for larger systems, whose null vectors
#: are spread thinner. Well-posed systems reach it too (w10000 with a pose fixed: 8e-8; BAL
#: cameras under LM once λ is small): they pay one more solve and product (step 2) and pass.
PIVOT_SCREEN = 1e-6

_PROBE_SEED = 20240613  # g of step 2: fixed, so that every run and solver makes the same test


@lru_cache(maxsize=4)
def _probe_vector(n: int) -> np.ndarray:
    """The fixed pseudo-random ``g`` of step 2 (read-only)."""
    g = np.random.default_rng(_PROBE_SEED).standard_normal(n)
    g.setflags(write=False)
    return g


def pivot_scale(diag: np.ndarray) -> np.ndarray:
    """The scale ``s_k``: ``A_kk``, floored at ``u · max |A_jj|`` (a zero row gets a scale).

    Args:
        diag: ``A``'s diagonal, in any order.
    """
    top = float(np.max(np.abs(diag), initial=0.0))
    floor = max(np.finfo(float).eps * top, np.finfo(float).tiny)
    if not np.isfinite(floor):  # non-finite values: every test below rejects them
        floor = 1.0
    return np.maximum(diag, floor)


def shift_diagonal(data: np.ndarray, diag_pos: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The values of ``A + τ·S``: a copy of ``data`` with ``τ · s_k`` added to the diagonal.

    Args:
        data: ``A``'s values in the pattern.
        diag_pos: Data position of every diagonal entry, in unknown order.
        scale: :func:`pivot_scale` of the diagonal, in unknown order.
    """
    shifted = np.array(data, dtype=float)
    shifted[diag_pos] += SINGULAR_TOLERANCE * scale
    return shifted


def _rayleigh(b: np.ndarray, y: np.ndarray, scale: np.ndarray) -> float:
    """``ρ = yᵀAy / yᵀSy`` for ``y = A⁻¹b``, with ``yᵀAy = bᵀy`` (no product with ``A``);
    ``NaN`` if ``y`` is not finite."""
    top = float(np.max(np.abs(y), initial=0.0))
    if not np.isfinite(top) or top == 0:
        return float("nan")
    u = y / top  # a null direction makes y huge: keep its squares finite
    return float(b @ u) / (top * float(u @ (scale * u)))


def _where(pivots: np.ndarray, scale: np.ndarray, k: int, unknowns: np.ndarray | None) -> str:
    """The first pivot that failed the screen, for messages.

    Args:
        pivots: ``D_k`` in elimination order.
        scale: ``s_k`` in elimination order.
        k: The step (``-1``: unknown).
        unknowns: The unknown eliminated at each step, or ``None`` for the identity.
    """
    if k < 0:
        return "the factorisation stopped at a zero column"
    row = k if unknowns is None else int(unknowns[k])
    if k < len(pivots):
        return (f"pivot {k} (unknown {row}) is {pivots[k] / scale[k]:.2g} of its diagonal "
                f"{scale[k]:.3g}")
    return f"pivot {k} (unknown {row}) is not positive"


def checked_solve(
    solver: str,
    pivots: np.ndarray,
    diag: np.ndarray,
    solve: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    shifted_is_definite: Callable[[np.ndarray], bool],
    unknowns: np.ndarray | None = None,
    stopped_at: int | None = None,
) -> np.ndarray:
    """Apply the rank-deficiency rule (module docstring) to one factorisation and, if it is
    accepted, solve with it.

    Args:
        solver: The solver's name, for messages.
        pivots: ``D_k`` in elimination order (those computed, if the factorisation stopped).
        diag: ``A``'s diagonal in unknown order.
        solve: Applies the factorisation's ``A⁻¹`` to an ``(n,)`` or ``(n, k)`` array.
        rhs: The right-hand side, ``(n,)`` or ``(n, k)``.
        shifted_is_definite: Given ``s`` (unknown order), factorises ``A + τ·S`` and says
            whether it is positive definite (step 3).
        unknowns: The unknown (row of ``A``) eliminated at each step; ``None`` for the identity.
        stopped_at: The step at which the factorisation stopped at a non-positive pivot
            (``-1``: at a step it does not say).

    Returns:
        ``A⁻¹ rhs``.

    Raises:
        SingularSystemError: if ``A`` is positive semi-definite and rank deficient.
        NotPositiveDefiniteError: if ``A`` is not positive semi-definite (or not finite).
    """
    n = len(pivots)
    step_diag = diag[:n] if unknowns is None else diag[unknowns[:n]]
    # Step 1 in a few array operations. D_k > σ·|A_kk| for every k makes every pivot positive:
    # A is positive definite, so A_kk > 0 (pivot_scale's floor matters to steps 2 and 3).
    if stopped_at is None and bool((pivots > PIVOT_SCREEN * np.abs(step_diag)).all()):
        return solve(rhs)
    scale = pivot_scale(diag)
    step_scale = scale[:n] if unknowns is None else scale[unknowns[:n]]
    bad = np.flatnonzero(~(pivots > PIVOT_SCREEN * step_scale))  # NaN fails
    k = int(bad[0]) if len(bad) else int(stopped_at)  # type: ignore[arg-type]
    tau = SINGULAR_TOLERANCE
    if stopped_at is None and bool(np.all(pivots > 0)):  # step 2, with the solve itself
        b = np.sqrt(scale) * _probe_vector(len(scale))
        x = solve(np.column_stack([rhs, b]))  # the probe rides along with the solve
        rho = _rayleigh(b, x[:, -1], scale)
        if rho > tau:
            return x[:, 0] if rhs.ndim == 1 else x[:, :-1]
        if rho == rho:  # not NaN: a direction of negligible curvature
            raise SingularSystemError(
                f"{solver}: the system is singular (rank deficient): "
                f"{_where(pivots, step_scale, k, unknowns)}, and inverse "
                f"iteration finds a direction of curvature {rho:.2g} of the diagonal (at most "
                f"{tau:g} is singular)")
    where = _where(pivots, step_scale, k, unknowns)
    if shifted_is_definite(scale):  # step 3
        raise SingularSystemError(
            f"{solver}: the system is singular (rank deficient): {where}, and A + {tau:g}·diag(A) "
            "is positive definite")
    raise NotPositiveDefiniteError(
        f"{solver}: the system is not positive definite: {where}, and A + {tau:g}·diag(A) is "
        "not positive definite either")
