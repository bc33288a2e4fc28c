"""Traced block programs (``graphopt.autodiff.replay`` / ``programs``) give the tape's results.

A linearisation in several blocks whose signature was seen before traces one block, checks the
program on another against the tape, then replays it; every result here is compared, bit for
bit, with the tape alone (``programs.ENABLED = False``), across linearisations at changed
estimates. The cases: the BAL projection (replayed), an error selecting with ``np.where`` by
data (replayed: the selection is a step), one with a Python branch on data (not replayable:
poisoned, through the tape), one that copies its measurements outside NumPy's dispatch or tests
the type of its arrays (caught by the check; the traced block is computed again), a change of
block length between calls (a second program), a signature seen once (not traced).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

import graphopt.autodiff.jacobians as jacobians
import graphopt.autodiff.programs as programs
from graphopt import BaseEdge, EdgeContext, VertexVector
from graphopt.autodiff.jacobians import autodiff_linearize, distinct_vertices
from graphopt.types import EdgeBALProjection, VertexCameraBAL


class VertexP2(VertexVector):
    dimension = 2


@pytest.fixture(autouse=True)
def _small_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jacobians, "BLOCK_EDGES", 50)
    programs.clear()
    yield
    programs.clear()


def _both(etype: type, x: Any, z: np.ndarray, ctx: Any) -> tuple[Any, Any]:
    """``(program, tape)`` results of one linearisation."""
    with_programs = autodiff_linearize(etype, x, z, ctx)
    programs.ENABLED = False
    try:
        tape_only = autodiff_linearize(etype, x, z, ctx)
    finally:
        programs.ENABLED = True
    return with_programs, tape_only


def _same(a: Any, b: Any) -> None:
    assert np.array_equal(a[0], b[0])
    for ja, jb in zip(a[1], b[1], strict=True):
        assert np.array_equal(ja, jb)
    assert (a[2] is None) == (b[2] is None)


def _plans(etype: type) -> list[programs.Plan]:
    return [p for key, p in programs._PLANS.items() if key[0] is etype]


class EdgeBALAuto(EdgeBALProjection):
    differentiation = "autodiff"


def _bal(rng: np.random.Generator, m: int) -> tuple[Any, np.ndarray, EdgeContext]:
    cams = np.c_[rng.normal(0, 0.3, (6, 3)), rng.normal(0, 1, (6, 3)),
                 rng.uniform(400, 900, 6), rng.normal(0, 0.1, 6), rng.normal(0, 0.01, 6)]
    ci, pi = rng.integers(0, 6, m), rng.integers(0, 40, m)
    pts = rng.normal(0, 1, (40, 3)) + [0, 0, -8]
    ctx = EdgeContext(derived=(np.asfortranarray(VertexCameraBAL.derived(cams)[ci]), None),
                      vertices=(distinct_vertices(ci), distinct_vertices(pi)))
    x = (np.asfortranarray(cams[ci]), np.asfortranarray(pts[pi]))
    return x, rng.normal(0, 100, (m, 2)), ctx


def test_bal_blocks_replayed_equal_the_tape() -> None:
    rng = np.random.default_rng(5)
    for _ in range(4):  # new estimates each time, one signature: seen, traced, replayed twice
        x, z, ctx = _bal(rng, 200)
        _same(*_both(EdgeBALAuto, x, z, ctx))
    (plan,) = _plans(EdgeBALAuto)
    assert plan.checked and not plan.dead and plan.program is not None


def _edge(fn: Callable[[Any, Any, Any], Any]) -> type:
    return type("EdgeReplayed", (BaseEdge,), {
        "dimension": 2, "vertex_types": (VertexP2, VertexP2), "measurement_shape": (2,),
        "error": classmethod(lambda cls, x, z, ctx: fn(x[0], x[1], z)),
    })


def _selected(a: Any, b: Any, z: Any) -> Any:
    d = a - b
    return np.where(d > 0.0, d * d, np.sin(d) * b) - z  # which branch: per edge, by data


def _branching(a: Any, b: Any, z: Any) -> Any:
    d = a - b
    if np.any(d[:, 0] > 0.0):  # a Python branch on data: a block may take either side
        return d * d - z
    return np.sin(d) * b - z


def _copying(a: Any, b: Any, z: Any) -> Any:
    w = np.empty(z.shape)
    w[...] = z  # a copy the trace cannot see (an assignment into a plain array)
    return a * b - w


def _typed(a: Any, b: Any, z: Any) -> Any:
    # Another formula for another array type: traced, the block computes something else (the
    # check finds it, and the traced block is computed again by the tape).
    return a * b - (z if type(z) is np.ndarray else 2.0 * z)


@pytest.mark.parametrize(("fn", "replayed"), [(_selected, True), (_branching, False),
                                              (_copying, False), (_typed, False)])
def test_data_dependent_errors(fn: Callable[..., Any], replayed: bool) -> None:
    etype = _edge(fn)
    rng = np.random.default_rng(8)
    for shift in (-1.0, 0.0, 1.0, 0.5):  # blocks whose edges all take one branch, or mixed
        a = rng.normal(size=(200, 2)) + shift * (np.arange(200) // 50 % 2)[:, None]
        x, z = (a, rng.normal(size=(200, 2))), rng.normal(size=(200, 2))
        _same(*_both(etype, x, z, None))
    (plan,) = _plans(etype)
    assert (plan.checked and not plan.dead) == replayed


def test_where_values_and_derivatives() -> None:
    """The recorded ``np.where`` against central differences (the selected branch's)."""
    etype = _edge(_selected)
    rng = np.random.default_rng(9)
    a, b = rng.normal(size=(200, 2)), rng.normal(size=(200, 2))
    z = rng.normal(size=(200, 2))
    e, (ja, jb), _ = autodiff_linearize(etype, (a, b), z, None)
    h = 1e-6
    for k in range(2):
        dk = np.zeros(2)
        dk[k] = h
        num_a = (_selected(a + dk, b, z) - _selected(a - dk, b, z)) / (2 * h)
        num_b = (_selected(a, b + dk, z) - _selected(a, b - dk, z)) / (2 * h)
        assert np.allclose(ja[:, :, k], num_a, atol=1e-6)
        assert np.allclose(jb[:, :, k], num_b, atol=1e-6)
    assert np.array_equal(e, _selected(a, b, z))


def test_a_new_block_length_traces_a_new_program() -> None:
    rng = np.random.default_rng(10)
    for m in (200, 230, 200, 230):  # blocks of 50, of 46, of 50 again (traced), of 46 again
        x, z, ctx = _bal(rng, m)
        _same(*_both(EdgeBALAuto, x, z, ctx))
    plans = _plans(EdgeBALAuto)
    assert len(plans) == 2 and all(p.checked for p in plans)


def test_a_signature_seen_once_is_not_traced() -> None:
    rng = np.random.default_rng(12)
    x, z, ctx = _bal(rng, 200)
    _same(*_both(EdgeBALAuto, x, z, ctx))
    (plan,) = _plans(EdgeBALAuto)
    assert plan.program is None and plan.seen == 1
