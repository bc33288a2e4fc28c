"""Arithmetic on steps in the problem's layout ``(u part, [v part per V class])``, for the
algorithms: inner products, linear combinations, LM's predicted decrease."""

from __future__ import annotations

import numpy as np

#: ``(u part (n,), [v part (n_c, d_c) per V class])`` (as :data:`graphopt.problem.Step`).
Step = tuple[np.ndarray, list[np.ndarray]]


def dot(a: Step, b: Step) -> float:
    """``aᵀb`` over both parts.

    Args:
        a: A vector in the step layout.
        b: Another.
    """
    if not a[1] and not b[1]:  # nothing marginalised: the u parts alone
        return float(a[0] @ b[0])
    return float(a[0] @ b[0] + sum(float(np.vdot(x, y)) for x, y in zip(a[1], b[1], strict=True)))


def axpy(alpha: float, a: Step, beta: float, b: Step) -> Step:
    """``α a + β b``.

    Args:
        alpha: Factor of ``a``.
        a: A vector in the step layout.
        beta: Factor of ``b``.
        b: Another.
    """
    return alpha * a[0] + beta * b[0], [
        alpha * x + beta * y for x, y in zip(a[1], b[1], strict=True)
    ]


def predicted_decrease(step: Step, damp: Step, lam: float, b: Step) -> float:
    """``Δᵀ(λDΔ + b)``, the decrease of chi2 the damped model predicts: ``dot(Δ, axpy(λ, DΔ,
    1, b))``, the same operations in the same order, without the intermediate steps.

    Args:
        step: ``Δ``.
        damp: The damping diagonal ``D``.
        lam: ``λ``.
        b: The right-hand side.
    """
    du = step[0]
    u = du @ (lam * (damp[0] * du) + b[0])
    if not step[1]:
        return float(u)
    return float(u + sum(float(np.vdot(x, lam * (d * x) + y))
                         for x, d, y in zip(step[1], damp[1], b[1], strict=True)))
