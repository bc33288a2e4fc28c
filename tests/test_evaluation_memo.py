"""EvaluationMemo: read-only copies, a linearisation serving an evaluation, the oldest entries
dropped past the count or the byte budget."""

from __future__ import annotations

import numpy as np
import pytest

import graphopt.evaluation_memo as em
from graphopt.edge import Linearization


def _out(m: int, value: float, jac: bool = True) -> Linearization:
    e = np.full((m, 2), value)
    return Linearization(e, (np.full((m, 2, 6), value),) if jac else ())


def test_copies_are_kept_read_only_and_a_linearisation_serves_an_evaluation() -> None:
    memo = em.EvaluationMemo()
    out = _out(5, 1.0)
    memo.put("linearize", b"x", out)
    out.error[:] = 7.0  # the type's buffer, overwritten by its next call
    out.jacobians[0][:] = 7.0
    kept = memo.get("evaluate", b"x")
    assert kept is not None and kept.error is not out.error
    np.testing.assert_array_equal(kept.error, 1.0)
    np.testing.assert_array_equal(kept.jacobians[0], 1.0)
    with pytest.raises(ValueError):
        kept.error[0, 0] = 2.0
    assert memo.get("linearize", b"y") is None
    memo.put("evaluate", b"y", _out(5, 3.0, jac=False))
    assert memo.get("linearize", b"y") is None  # errors alone do not serve a linearisation
    assert memo.get("evaluate", b"y").error[0, 0] == 3.0


def test_the_oldest_go_past_the_count_and_the_byte_budget(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    memo = em.EvaluationMemo()
    for k in range(em.MEMO_STATES + 3):
        memo.put("linearize", bytes([k]), _out(4, float(k)))
    assert memo.get("linearize", bytes([0])) is None
    assert memo.get("linearize", bytes([2])) is None
    assert memo.get("linearize", bytes([3])).error[0, 0] == 3.0
    one = 10 * 14 * 8  # the bytes of a 10-edge evaluation: errors and one Jacobian
    monkeypatch.setattr(em, "MEMO_BYTES", 3 * one)
    memo = em.EvaluationMemo()
    for k in range(5):
        memo.put("linearize", bytes([k]), _out(10, float(k)))
    assert [memo.get("linearize", bytes([k])) is not None for k in range(5)] == [
        False, False, True, True, True]
    memo.put("linearize", b"big", _out(40, 1.0))  # larger than the budget: not kept
    assert memo.get("linearize", b"big") is None
    assert memo.get("linearize", bytes([4])) is not None
