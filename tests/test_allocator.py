"""graphopt.allocator: glibc's malloc thresholds set once per process, cheaply, and not at all
when the user opts out."""

from __future__ import annotations

import ctypes.util
import platform

import pytest

from graphopt import allocator

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="needs glibc's mallopt")


@glibc
def test_tune_runs_no_subprocess(monkeypatch) -> None:
    """The first problem's set-up does not run ldconfig (``find_library``: 3.5 ms)."""
    def no(name: str) -> None:
        raise AssertionError("find_library called")

    monkeypatch.setattr(ctypes.util, "find_library", no)
    monkeypatch.setattr(allocator, "_done", None)
    assert allocator.tune() is True


def test_opting_out_is_remembered(monkeypatch) -> None:
    """``GRAPHOPT_MALLOC_TUNE=0`` at the first problem leaves the allocator alone for good, and
    any outcome (a failure too) is decided once, not at every problem built."""
    monkeypatch.setattr(allocator, "_done", None)
    monkeypatch.setenv("GRAPHOPT_MALLOC_TUNE", "0")
    assert allocator.tune() is False
    monkeypatch.delenv("GRAPHOPT_MALLOC_TUNE")
    assert allocator.tune() is False


@pytest.mark.parametrize("free_poses", [1, 2])
def test_every_problem_tunes_the_allocator(monkeypatch, free_poses: int) -> None:
    """The single-vertex problem as the general one: without the thresholds a 2,000-match
    motion-only BA's arrays (over 128 KB) were fresh pages at every iteration (8.0 against
    4.3 ms a call)."""
    from test_single_block import one_free_pose

    calls = []
    monkeypatch.setattr(allocator, "tune", lambda: calls.append(1) or True)
    import graphopt.problem
    import graphopt.single_vertex
    monkeypatch.setattr(graphopt.problem, "tune_allocator", allocator.tune)
    monkeypatch.setattr(graphopt.single_vertex, "tune_allocator", allocator.tune)
    opt = one_free_pose(False)
    if free_poses == 2:
        opt.vertex(1).set_fixed(False)
    opt.initialize_optimization()
    assert calls == [1]
