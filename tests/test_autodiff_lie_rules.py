"""Closed-form jet rules of ``graphopt.lie`` (``graphopt.autodiff.lie_rules``) equal the
derivatives of the formulas they replace, carried through by the jets' own rules."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from graphopt import lie
from graphopt.autodiff import Jet
from graphopt.autodiff.lie_rules import so3_exp_jet

RNG = np.random.default_rng(3)


def _formula(w: Jet, monkeypatch: Any) -> Jet:
    with monkeypatch.context() as mp:
        mp.delitem(lie.JET_RULES, "so3_exp")
        return lie.so3_exp(w)


@pytest.mark.parametrize("scale", [0.0, 1e-6, 1e-3, 0.7, 3.0])
def test_so3_exp_rule_equals_formula(scale: float, monkeypatch: Any) -> None:
    v = RNG.normal(0.0, 1.0, (40, 3)) * scale
    # Directions 2…5 of 9: the derivative of w w.r.t. them is a random (4, n, 3) block.
    w = Jet(v, RNG.normal(0.0, 1.0, (4, 40, 3)), 2, 9)
    fast = lie.so3_exp(w)
    assert type(fast) is Jet and fast.lo == 2
    slow = _formula(w, monkeypatch)
    np.testing.assert_array_equal(fast.value, lie.so3_exp(v))
    t_slow = np.zeros((9,) + slow.value.shape)
    t_slow[slow.lo: slow.lo + len(slow.tangent)] = slow.tangent
    t_fast = np.zeros_like(t_slow)
    t_fast[2:6] = fast.tangent
    assert np.max(np.abs(t_fast - t_slow)) <= 1e-12 * max(1.0, np.max(np.abs(t_slow)))


def test_so3_exp_rule_declines_plain_arrays() -> None:
    assert so3_exp_jet(np.zeros((2, 3))) is None


def _log_formula(R: Jet, monkeypatch: Any) -> Jet:
    with monkeypatch.context() as mp:
        mp.delitem(lie.JET_RULES, "so3_log")
        return lie.so3_log(R)


@pytest.mark.parametrize("angle", [1e-5, 1e-3, 0.5, 2.0, np.pi - 1e-2, np.pi - 1e-4])
def test_so3_log_rule_equals_formula(angle: float, monkeypatch: Any) -> None:
    axis = RNG.normal(0.0, 1.0, (30, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    w0 = axis * angle
    # A rotation jet exp(δ) R at δ = 0 (as an oplus makes), and a general matrix tangent.
    d = Jet.seeded(np.zeros((30, 3)), 0, 6)
    R = lie.so3_exp(d) @ lie.so3_exp(w0)
    general = Jet(lie.so3_exp(w0), RNG.normal(0.0, 1.0, (6, 30, 3, 3)), 0, 6)
    for jet in (R, general):
        fast, slow = lie.so3_log(jet), _log_formula(jet, monkeypatch)
        np.testing.assert_array_equal(fast.value, lie.so3_log(jet.value))
        assert fast.lo == slow.lo and fast.tangent.shape == slow.tangent.shape
        scale = max(1.0, float(np.max(np.abs(slow.tangent))))
        assert np.max(np.abs(fast.tangent - slow.tangent)) <= 1e-11 * scale
