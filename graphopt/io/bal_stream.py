"""Writing large BAL files in pieces: :class:`BALWriter` streams observations in chunks, then
cameras, then points, formatted by :func:`format_fixed` (vectorised fixed-point text, no Python
call per value) and compressed by suffix; :func:`quantize` gives the values a reader gets back.
"""

from __future__ import annotations

import bz2
import gzip
import os
from typing import Any

import numpy as np

from graphopt.io.atomic import PendingFile

__all__ = ["BALWriter", "format_fixed", "quantize"]


def quantize(x: np.ndarray, decimals: int) -> np.ndarray:
    """``x`` rounded to ``decimals`` decimal places, as :func:`format_fixed` writes it.

    The result is the double nearest to the written decimal, so reading the text back gives
    exactly these values (``q / 10^d`` of two exact doubles is correctly rounded).

    Args:
        x: Values with ``|x| · 10^decimals < 2^52``.
        decimals: Decimal places.
    """
    scale = 10.0**decimals
    return np.copysign(np.rint(np.abs(x) * scale), x) / scale


def format_fixed(columns: list[np.ndarray], decimals: list[int]) -> bytes:
    """Rows of fixed-point numbers as text, vectorised (no Python call per value).

    Each row is ``c0 c1 ... ck\\n`` with column ``j`` written with ``decimals[j]`` decimal
    places (0: an integer without a point), no padding: 0.45 s per million observation rows,
    about 3x faster than ``%`` formatting row by row. Every field is laid out in one
    fixed-width byte matrix (sign, zero-padded digits, point) and the padding is then dropped
    by one boolean mask.

    Args:
        columns: ``(m,)`` arrays of one row count (integers, or finite floats with
            ``|x| · 10^decimals < 2^52``).
        decimals: Decimal places per column.
    """
    m = len(columns[0])
    if m == 0:
        return b""
    fields = []
    for col, d in zip(columns, decimals, strict=True):
        col = np.asarray(col)
        if col.dtype.kind in "iu":
            q, neg = np.abs(col.astype(np.int64)), col < 0
        else:
            scaled = np.abs(col) * 10.0**d
            if not (np.isfinite(scaled).all() and scaled.max(initial=0.0) < 2.0**62):
                raise ValueError(f"format_fixed: a value is not finite or too large for "
                                 f"{d} decimal places")
            q = np.rint(scaled).astype(np.int64)
            neg = (col < 0) & (q > 0)
        fields.append((q, neg, d, max(d + 1, len(str(int(q.max()))))))
    # Per field: sign, digits, point (if decimals), separator.
    total = sum(1 + w + (d > 0) + 1 for _, _, d, w in fields)
    mat = np.empty((m, total), np.uint8)
    keep = np.ones((m, total), bool)
    c = 0
    for j, (q, neg, d, width) in enumerate(fields):
        mat[:, c] = np.where(neg, ord("-"), ord(" "))
        keep[:, c] = neg
        c += 1
        cols = [c + i + (d > 0 and i >= width - d) for i in range(width)]  # skip the point
        x = q.copy()
        for i in range(width - 1, -1, -1):  # digits from the right, one division each
            y = x // 10
            mat[:, cols[i]] = x - 10 * y + ord("0")
            x = y
        for i in range(width - d - 1):  # leading zeros of the integer part are dropped
            keep[:, cols[i]] = q >= 10 ** (width - 1 - i)
        if d:
            mat[:, c + width - d] = ord(".")
        c += width + (d > 0)
        mat[:, c] = ord("\n") if j == len(fields) - 1 else ord(" ")
        c += 1
    return mat[keep].tobytes()


class BALWriter:
    """A BAL file written in pieces (observations in chunks, then cameras, then points), for
    problems too large to format at once; compressed by suffix (``.gz``, ``.bz2``) and atomic:
    the file appears complete on :meth:`close`, or not at all.

    Observations and points are written with a fixed number of decimals (:func:`quantize`
    gives the values a reader gets back), cameras with 17 significant digits (exact).
    Usable as a context manager (closed on success, discarded on an exception).

    Args:
        path: Destination file.
        num_cameras: Cameras announced in the header.
        num_points: Points announced.
        num_observations: Observations announced.
        decimals: Decimal places of observations and points.
    """

    def __init__(self, path: str | os.PathLike[str], num_cameras: int, num_points: int,
                 num_observations: int, decimals: int = 6) -> None:
        self.counts = (num_cameras, num_points, num_observations)
        self.decimals = decimals
        self._written = [0, 0, 0]  # cameras, points, observations
        self._pending = PendingFile(path)
        name = str(path)
        self._file: Any
        if name.endswith(".bz2"):
            self._file = bz2.open(self._pending.tmp, "wb", compresslevel=9)
        elif name.endswith(".gz"):
            self._file = gzip.GzipFile(self._pending.tmp, "wb", compresslevel=1, mtime=0)
        else:
            self._file = open(self._pending.tmp, "wb")  # noqa: SIM115 - closed in close()
        self._file.write(f"{num_cameras} {num_points} {num_observations}\n".encode())

    def _check_order(self, stage: int, n: int) -> None:
        """Stages come in order (observations 2, cameras 0, points 1) within the counts."""
        order = (2, 0, 1)
        later = order[order.index(stage) + 1:]
        if any(self._written[s] for s in later):
            raise ValueError("BALWriter: write observations, then cameras, then points")
        if self._written[stage] + n > self.counts[stage]:
            raise ValueError(f"BALWriter: more {('cameras', 'points', 'observations')[stage]} "
                             f"than the header's {self.counts[stage]}")
        self._written[stage] += n

    def observations(self, camera_index: np.ndarray, point_index: np.ndarray,
                     xy: np.ndarray) -> None:
        """Append observations, one per line.

        Args:
            camera_index: ``(k,)`` cameras.
            point_index: ``(k,)`` points.
            xy: ``(k, 2)`` pixels.
        """
        self._check_order(2, len(xy))
        d = self.decimals
        self._file.write(format_fixed([camera_index, point_index, xy[:, 0], xy[:, 1]],
                                      [0, 0, d, d]))

    def cameras(self, cameras: np.ndarray) -> None:
        """Append camera parameters, one value per line (as the BAL site's files).

        Args:
            cameras: ``(k, 9)`` cameras.
        """
        self._check_order(0, len(cameras))
        text = "".join(f"{v:.17g}\n" for v in cameras.reshape(-1).tolist())
        self._file.write(text.encode("ascii"))

    def points(self, points: np.ndarray) -> None:
        """Append points, one per line.

        Args:
            points: ``(k, 3)`` points.
        """
        self._check_order(1, len(points))
        self._file.write(format_fixed([points[:, 0], points[:, 1], points[:, 2]],
                                      [self.decimals] * 3))

    def close(self) -> None:
        """Finish the file and move it into place.

        Raises:
            ValueError: Fewer cameras, points or observations than the header announced (the
                file is then discarded).
        """
        self._file.close()
        if self._written != [self.counts[0], self.counts[1], self.counts[2]]:
            self._pending.discard()
            raise ValueError(f"BALWriter: wrote {self._written[0]} cameras, {self._written[1]} "
                             f"points and {self._written[2]} observations, the header announces "
                             f"{self.counts[0]}, {self.counts[1]} and {self.counts[2]}")
        self._pending.commit()

    def discard(self) -> None:
        """Close and delete the unfinished file."""
        self._file.close()
        self._pending.discard()

    def __enter__(self) -> BALWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()
