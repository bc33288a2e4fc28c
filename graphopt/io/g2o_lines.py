"""What the g2o file reader's parts share: :class:`GraphFormatError` and the conversions of
id columns and information triangles (:mod:`graphopt.io.g2o`, :mod:`graphopt.io.g2o_layouts`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from graphopt.io.text import FileFormatError

__all__ = ["GraphFormatError", "parse_ids", "positive_definite", "symmetric"]

_MAX_ID = 2.0**53  # ids are read as doubles: exact below this


class GraphFormatError(FileFormatError):
    """A graph file that cannot be read; the message is one line naming the file and line.

    Args:
        path: The file.
        message: What is wrong.
        line: 1-based line number, if the problem is on a line.
    """

    kind = "graph file"


def symmetric(values: np.ndarray, rows: Sequence[int], cols: Sequence[int]) -> np.ndarray:
    """``(m, d, d)`` symmetric matrices with ``values[:, k]`` at ``(rows[k], cols[k])``."""
    d = max(cols) + 1
    out = np.zeros((len(values), d, d))
    out[:, rows, cols] = values
    out[:, cols, rows] = values
    return out


def positive_definite(info: np.ndarray) -> np.ndarray:
    """``(m,)`` whether each symmetric matrix is positive definite (all Cholesky pivots > 0)."""
    a = np.array(info, dtype=float)
    ok = np.ones(len(a), dtype=bool)
    for k in range(a.shape[-1]):
        pivot = a[:, k, k]
        ok &= pivot > 0
        col = a[:, k + 1:, k] / np.where(ok, pivot, 1.0)[:, None]
        a[:, k + 1:, k + 1:] -= col[:, :, None] * a[:, None, k, k + 1:]
    return ok


def parse_ids(path: Path, tag: str, values: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Id columns as int64; an error on a negative, fractional or huge one."""
    bad = (values < 0) | (values != np.floor(values)) | (values >= _MAX_ID)
    if bad.any():
        k = int(np.flatnonzero(bad.any(axis=1))[0])
        v = values[k][bad[k]][0]
        raise GraphFormatError(path, f"{tag}: id {v:g} is not a non-negative integer",
                               int(lines[k]))
    return values.astype(np.int64)
