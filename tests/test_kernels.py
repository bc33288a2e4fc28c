"""Robust kernels: ρ', ρ'' against finite differences of ρ, and g2o's values."""

import numpy as np
import pytest

from graphopt import RobustKernel, make_kernel
from graphopt.robust_kernel import KERNELS

S = np.concatenate([np.linspace(0.01, 0.9, 15), np.linspace(1.1, 30.0, 25)])


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("delta", [0.5, 1.0, 3.0])
def test_derivatives_match_finite_differences(name: str, delta: float) -> None:
    k = make_kernel(name, delta)
    rho, d1, d2 = k.robustify(S)
    h = 1e-6
    # Skip points within h of a kink (Huber/Tukey/Saturated/DCS switch at δ² or δ).
    kinks = np.array([delta**2, delta])
    ok = np.min(np.abs(S[:, None] - kinks[None, :]), axis=1) > 1e-3
    rp, d1p, _ = k.robustify(S + h)
    rm, d1m, _ = k.robustify(S - h)
    np.testing.assert_allclose(d1[ok], ((rp - rm) / (2 * h))[ok], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(d2[ok], ((d1p - d1m) / (2 * h))[ok], rtol=1e-4, atol=1e-7)
    assert np.all(np.isfinite(rho)) and np.all(rho >= 0)
    # Every kernel is the identity to first order at zero.
    r0, w0, _ = k.robustify(np.array([1e-16]))
    assert abs(r0[0] - 1e-16) < 1e-22 and abs(w0[0] - 1.0) < 1e-6


def test_huber_values_match_g2o() -> None:
    k = make_kernel("huber", 2.0)
    rho, w, _ = k.robustify(np.array([1.0, 9.0]))
    # Inside: s; outside: 2δ√s − δ² = 2·2·3 − 4 = 8, weight δ/√s = 2/3.
    np.testing.assert_allclose(rho, [1.0, 8.0])
    np.testing.assert_allclose(w, [1.0, 2.0 / 3.0])


def test_cauchy_value() -> None:
    rho, w, _ = make_kernel("cauchy", 2.0).robustify(np.array([4.0]))
    np.testing.assert_allclose(rho, [4.0 * np.log(2.0)])
    np.testing.assert_allclose(w, [0.5])


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_delta_rejected(bad: float) -> None:
    with pytest.raises(ValueError, match="delta"):
        make_kernel("huber", bad)


def test_unknown_kernel_named() -> None:
    with pytest.raises(ValueError, match="unknown robust kernel 'bogus'"):
        make_kernel("bogus")


def test_all_g2o_kernels_present() -> None:
    assert set(KERNELS) == {"huber", "pseudohuber", "cauchy", "gemanmcclure", "welsch", "fair",
                            "tukey", "saturated", "dcs"}
    assert all(issubclass(k, RobustKernel) for k in KERNELS.values())
