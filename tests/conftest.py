"""Shared fixtures."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from graphopt import compiled


@pytest.fixture
def numpy_path() -> Iterator[None]:
    """Compiled loops (:mod:`graphopt.compiled`) off for the test: what it checks is the numpy
    path's (its memo, its bits)."""
    compiled.set_enabled(False)
    yield
    compiled.set_enabled(True)
