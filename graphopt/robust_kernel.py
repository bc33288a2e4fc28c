"""Robust kernels with g2o's semantics: ρ applied to the squared error ``s = e'Ωe``.

``robustify(s)`` returns ``(ρ(s), ρ'(s), ρ''(s))`` for an array of ``s`` at once. The optimizer
uses ρ' to weight the information matrix (``ρ' Ω``, as g2o does) and Σρ(s) as the robust chi2.
Derivatives are exact (checked against finite differences in the tests); where g2o's own code
approximates a derivative (GemanMcClure's ρ'', DCS), the docstring says so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

Rho = tuple[np.ndarray, np.ndarray, np.ndarray]

#: Incremented whenever a kernel's width is set (``set_delta``, also in ``__init__``).
_changes = 0


def kernel_changes() -> int:
    """How many times a kernel's width was set (:meth:`RobustKernel.set_delta`): evaluations
    cached at an older count may use old widths (see ``EdgeGroup.activity_version``)."""
    return _changes


class RobustKernel:
    """Base class of the robust kernels.

    Args:
        delta: The kernel width, in units of the (whitened) error ``sqrt(e'Ωe)``.
    """

    name = "none"
    #: ``ρ' ≥ 0`` everywhere (the optimizer then need not clip the weights at 0).
    nonnegative_weight = False

    def __init__(self, delta: float = 1.0) -> None:
        self.set_delta(delta)

    def set_delta(self, delta: float) -> None:
        """Set the kernel width.

        Args:
            delta: A finite positive number.
        """
        delta = float(delta)
        if not math.isfinite(delta) or delta <= 0:  # math: 10x cheaper per kernel object
            raise ValueError(
                f"{type(self).__name__}: delta must be positive and finite, got {delta}"
            )
        global _changes  # a module global: a class attribute written would reset type caches
        self.delta = delta
        _changes += 1

    def robustify(self, s: np.ndarray) -> Rho:
        """``(ρ, ρ', ρ'')`` at squared errors ``s``.

        Args:
            s: Array of ``e'Ωe`` values (non-negative).
        """
        raise NotImplementedError

    def cost(self, s: np.ndarray) -> np.ndarray:
        """``ρ(s)`` alone (what a trial step's chi2 needs); kernels may compute it cheaper.

        Args:
            s: Array of ``e'Ωe`` values (non-negative).
        """
        return self.robustify(s)[0]

    def cost_and_weight(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ρ(s), ρ'(s))`` (what a linearisation needs); kernels may compute them cheaper.

        Args:
            s: Array of ``e'Ωe`` values (non-negative).
        """
        r0, r1, _ = self.robustify(s)
        return r0, r1

    def cost_and_clipped_weight(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(ρ(s), max(ρ'(s), 0))``: what the normal equations weigh rows by (an approximated
        ρ' below 0 weighs its row zero; a :attr:`nonnegative_weight` kernel's is kept as is).

        Args:
            s: Array of ``e'Ωe`` values (non-negative).
        """
        r0, r1 = self.cost_and_weight(s)
        return r0, r1 if self.nonnegative_weight else np.maximum(r1, 0.0)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(delta={self.delta:g})"


class RobustKernelHuber(RobustKernel):
    """Huber: ``s`` inside ``δ²``, ``2δ√s − δ²`` outside.

    Args:
        delta: Threshold on ``sqrt(e'Ωe)``.
    """

    name = "huber"
    nonnegative_weight = True

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d = self.delta
        inside = s <= d * d
        r = np.sqrt(np.where(inside, 1.0, s))
        rho0 = np.where(inside, s, 2.0 * d * r - d * d)
        rho1 = np.where(inside, 1.0, d / r)
        rho2 = np.where(inside, 0.0, -0.5 * d / (r * r * r))
        return rho0, rho1, rho2

    def cost(self, s: np.ndarray) -> np.ndarray:
        """See :meth:`RobustKernel.cost` (the same values as :meth:`robustify`'s ρ).

        Args:
            s: Squared errors.
        """
        d = self.delta
        return np.where(s <= d * d, s, 2.0 * d * np.sqrt(s) - d * d)

    def cost_and_weight(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :meth:`RobustKernel.cost_and_weight` (:meth:`robustify`'s values, in fewer
        calls: ``δ / max(√s, δ)`` is ``δ/√s`` outside and exactly 1 inside).

        Args:
            s: Squared errors.
        """
        d = self.delta
        r = np.sqrt(s)
        return np.where(s <= d * d, s, 2.0 * d * r - d * d), d / np.maximum(r, d)


class RobustKernelPseudoHuber(RobustKernel):
    """Pseudo-Huber: ``2δ²(√(1 + s/δ²) − 1)``.

    Args:
        delta: Width.
    """

    name = "pseudohuber"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d2 = self.delta**2
        aux = s / d2 + 1.0
        sq = np.sqrt(aux)
        # 2δ²(√aux − 1) written without cancellation for small s.
        return 2.0 * s / (sq + 1.0), 1.0 / sq, -0.5 / (d2 * aux * sq)


class RobustKernelCauchy(RobustKernel):
    """Cauchy: ``δ² log(1 + s/δ²)``.

    Args:
        delta: Width.
    """

    name = "cauchy"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d2 = self.delta**2
        aux = 1.0 / (1.0 + s / d2)
        return d2 * np.log1p(s / d2), aux, -aux * aux / d2


class RobustKernelGemanMcClure(RobustKernel):
    """Geman–McClure in g2o's form: ``δ s / (δ + s)`` (δ acts on ``s`` here, as in g2o).

    g2o returns ``ρ'' = −2 aux³``; the exact value ``−2 aux³ / δ`` is returned here.

    Args:
        delta: Width (on the squared error, as in g2o).
    """

    name = "gemanmcclure"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d = self.delta
        aux = d / (d + s)
        return s * aux, aux * aux, -2.0 * aux**3 / d


class RobustKernelWelsch(RobustKernel):
    """Welsch: ``δ² (1 − exp(−s/δ²))``.

    Args:
        delta: Width.
    """

    name = "welsch"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d2 = self.delta**2
        ex = np.exp(-s / d2)
        return -d2 * np.expm1(-s / d2), ex, -ex / d2


class RobustKernelFair(RobustKernel):
    """Fair: ``2δ² (a − log(1 + a))`` with ``a = √s / δ``.

    Args:
        delta: Width.
    """

    name = "fair"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d = self.delta
        r = np.sqrt(s)
        a = r / d
        rho1 = 1.0 / (1.0 + a)
        # ρ'' = −ρ'² / (2δ√s); at s = 0 the limit is −∞, clamp √s to keep it finite.
        rho2 = -0.5 * rho1 * rho1 / (np.maximum(r, 1e-12) * d)
        return 2.0 * d * d * (a - np.log1p(a)), rho1, rho2


class RobustKernelTukey(RobustKernel):
    """Tukey's biweight: ``δ²/3 (1 − (1 − s/δ²)³)`` inside ``δ²``, ``δ²/3`` outside.

    Args:
        delta: Width.
    """

    name = "tukey"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d2 = self.delta**2
        inside = s <= d2
        u = np.where(inside, s / d2, 1.0)
        one_m = 1.0 - u
        # 1 − (1 − u)³ = u (3 − 3u + u²), free of cancellation for small u.
        rho0 = np.where(inside, d2 * u * (3.0 - 3.0 * u + u * u) / 3.0, d2 / 3.0)
        return rho0, one_m**2, np.where(inside, -2.0 * one_m / d2, 0.0)


class RobustKernelSaturated(RobustKernel):
    """Saturated: ``s`` inside ``δ²``, ``δ²`` outside.

    Args:
        delta: Width.
    """

    name = "saturated"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d2 = self.delta**2
        inside = s <= d2
        zeros = np.zeros_like(s)
        return np.where(inside, s, d2), np.where(inside, 1.0, 0.0), zeros


class RobustKernelDCS(RobustKernel):
    """Dynamic Covariance Scaling: ``ρ = s·k²`` with ``k = min(1, 2δ/(δ + s))``.

    g2o returns ``ρ' = k²`` and ``ρ'' = 0`` (the DCS weight). The exact derivatives of the same ρ
    are returned here: ``ρ' = 4δ²(δ − s)/(δ + s)³`` beyond ``s = δ``; it turns negative for
    ``s > δ``, and the optimizer clips the weight ρ' at zero (as it does for every kernel).

    Args:
        delta: Φ of DCS (on the squared error, as in g2o).
    """

    name = "dcs"

    def robustify(self, s: np.ndarray) -> Rho:
        """See :meth:`RobustKernel.robustify`.

        Args:
            s: Squared errors.
        """
        d = self.delta
        inside = s <= d
        den = d + s
        k = 2.0 * d / den
        rho0 = np.where(inside, s, s * k * k)
        rho1 = np.where(inside, 1.0, 4.0 * d * d * (d - s) / den**3)
        rho2 = np.where(inside, 0.0, 8.0 * d * d * (s - 2.0 * d) / den**4)
        return rho0, rho1, rho2


KERNELS: dict[str, type[RobustKernel]] = {
    k.name: k
    for k in (
        RobustKernelHuber,
        RobustKernelPseudoHuber,
        RobustKernelCauchy,
        RobustKernelGemanMcClure,
        RobustKernelWelsch,
        RobustKernelFair,
        RobustKernelTukey,
        RobustKernelSaturated,
        RobustKernelDCS,
    )
}


def make_kernel(name: str, delta: float = 1.0) -> RobustKernel:
    """Create a kernel by (case-insensitive) name, as the apps' ``--robust`` option does.

    Args:
        name: One of ``huber, pseudohuber, cauchy, gemanmcclure, welsch, fair, tukey, saturated,
            dcs``.
        delta: Kernel width.
    """
    key = name.lower().replace("-", "").replace("_", "")
    if key not in KERNELS:
        raise ValueError(f"unknown robust kernel {name!r}; choose one of {', '.join(KERNELS)}")
    return KERNELS[key](delta)


def kernel_key(kernel: RobustKernel) -> Any:
    """What makes two kernels interchangeable: their type and parameters (or identity).

    Args:
        kernel: A kernel.
    """
    key = (type(kernel), *kernel.__dict__.values())
    try:
        hash(key)
    except TypeError:
        return id(kernel)
    return key
