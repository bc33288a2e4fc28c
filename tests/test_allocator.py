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
