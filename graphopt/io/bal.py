"""BAL ("Bundle Adjustment in the Large") problem files: :class:`BALProblem`, :func:`read_bal`,
:func:`write_bal` and :class:`BALFormatError`.

File format (plain, ``.gz`` or ``.bz2``)::

    <num_cameras> <num_points> <num_observations>
    <camera_index> <point_index> <x> <y>          (one line per observation)
    <camera parameters>                           (9 per camera: ω, t, f, k1, k2)
    <point coordinates>                           (3 per point)

Parameters and points may be laid out one value per line (as the BAL site serves them) or several
per line; observations must be one per line. The reader streams the file in blocks of whole lines,
each parsed with numpy in a few vectorised passes (no Python loop per line) straight into the
output arrays, and still reports every error with the file name and the 1-based line number, as
a one-line :class:`BALFormatError`. :class:`BALWriter` writes large problems in pieces.
"""

from __future__ import annotations

import bz2
import dataclasses
import gzip
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from graphopt.io.atomic import atomic_path
from graphopt.io.bal_stream import BALWriter, format_fixed, quantize
from graphopt.io.text import DECOMPRESSION_ERRORS, WHITESPACE, FileFormatError, open_stream
from graphopt.lie import angle_axis_rotate

__all__ = ["BALFormatError", "BALProblem", "BALWriter", "format_fixed", "quantize", "read_bal",
           "write_bal"]

class BALFormatError(FileFormatError):
    """A BAL file that cannot be read; the message is one line naming the file and line.

    Args:
        path: The file.
        message: What is wrong.
        line: 1-based line number, if the problem is on a line.
    """

    kind = "BAL file"


@dataclass
class BALProblem:
    """A bundle adjustment problem in BAL's conventions.

    Args:
        cameras: ``(c, 9)`` camera parameters ``[ω, t, f, k1, k2]`` (world to camera).
        points: ``(n, 3)`` world points.
        camera_index: ``(m,)`` camera of each observation.
        point_index: ``(m,)`` point of each observation.
        observations: ``(m, 2)`` pixels (origin at the image centre, y up).
        path: Source file, if read from one.

    The camera model (projection, residuals, cost) lives with the BA types:
    :func:`graphopt.types.bal.reprojection_errors` and :func:`graphopt.types.bal.bal_cost`.
    """

    cameras: np.ndarray
    points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    observations: np.ndarray
    path: str | None = None

    @property
    def num_cameras(self) -> int:
        """Number of cameras."""
        return len(self.cameras)

    @property
    def num_points(self) -> int:
        """Number of points."""
        return len(self.points)

    @property
    def num_observations(self) -> int:
        """Number of observations."""
        return len(self.observations)

    def copy(self) -> BALProblem:
        """A deep copy."""
        return dataclasses.replace(
            self,
            cameras=self.cameras.copy(),
            points=self.points.copy(),
            camera_index=self.camera_index.copy(),
            point_index=self.point_index.copy(),
            observations=self.observations.copy(),
        )

    def camera_centers(self) -> np.ndarray:
        """Camera centres ``C = −Rᵀ t`` in the world frame, ``(c, 3)``."""
        return -angle_axis_rotate(-self.cameras[:, :3], self.cameras[:, 3:6])


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

#: Text parsed per pass (whole lines): bounds the reader's working memory (~8x this) whatever
#: the file's size.
CHUNK_BYTES = 1 << 22


def _line_blocks(path: Path, f: BinaryIO) -> Iterator[bytes]:
    """The text in blocks of about :data:`CHUNK_BYTES` that end at a line end (or the file's)."""
    rest = b""
    while True:
        try:
            block = f.read(CHUNK_BYTES)
        except DECOMPRESSION_ERRORS as exc:
            raise BALFormatError(path, f"corrupt or truncated compressed file ({exc})") from None
        if not block:
            if rest:
                yield rest
            return
        data = rest + block if rest else block
        cut = data.rfind(b"\n") + 1
        if cut == 0:
            rest = data
            continue
        yield data[:cut] if cut < len(data) else data
        rest = data[cut:]


def _token_text(data: bytes, start: int) -> str:
    end = start
    while end < len(data) and not WHITESPACE[data[end]]:
        end += 1
    text = data[start:end].decode("ascii", errors="replace")
    return text if len(text) <= 40 else text[:37] + "..."


def _section(k: int, n_obs: int, n_cam: int) -> str:
    """Describe which value the flat token index ``k`` was expected to be."""
    if k < 3:
        return "the header (num_cameras num_points num_observations)"
    k -= 3
    if k < 4 * n_obs:
        return f"observation {k // 4} (camera point x y)"
    k -= 4 * n_obs
    if k < 9 * n_cam:
        return f"camera {k // 9} parameters"
    return f"point {(k - 9 * n_cam) // 3} coordinates"


class _Block:
    """One block of whole lines: its tokens, their values and (on demand) their lines.

    Args:
        data: The text.
        line0: Lines of the file before this block.
    """

    def __init__(self, data: bytes, line0: int) -> None:
        self.data, self.line0 = data, line0
        a = np.frombuffer(data, dtype=np.uint8)
        ws = WHITESPACE[a]
        first = np.empty_like(ws)  # a token starts where a non-space follows a space
        first[:1] = ~ws[:1]
        np.greater(ws[:-1], ws[1:], out=first[1:])
        self.starts = np.flatnonzero(first)
        self._lines: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.starts)

    @property
    def lines(self) -> np.ndarray:
        """1-based line of every token."""
        if self._lines is None:
            nl = np.flatnonzero(np.frombuffer(self.data, dtype=np.uint8) == 10)
            self._lines = np.searchsorted(nl, self.starts, side="right") + self.line0 + 1
        return self._lines

    def line_of(self, t: int) -> int:
        """1-based line of token ``t``."""
        return self.line0 + 1 + self.data.count(b"\n", 0, int(self.starts[t]))

    def text(self, t: int) -> str:
        """Token ``t`` as written (shortened)."""
        return _token_text(self.data, int(self.starts[t]))

    def values(self, path: Path) -> np.ndarray:
        """Every token as a float; on failure, name the first token that is not a number."""
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # numpy warns (will raise) at unmatched data
                values = np.fromstring(self.data, dtype=float, sep=" ")  # C parser
            if len(values) == len(self.starts):
                return values
        except (ValueError, DeprecationWarning):
            pass
        for k, tok in enumerate(self.data.split()):  # slow path, only for broken files
            try:
                float(tok)
            except ValueError:
                raise BALFormatError(path, f"not a number: {self.text(k)!r}",
                                     self.line_of(k)) from None
        raise BALFormatError(path, "could not parse the numbers in the file")


def _header(path: Path, blk: _Block) -> tuple[int, int, int]:
    """The three positive counts on the first non-blank line."""
    lines = blk.lines
    head_line = int(lines[0])
    n_head = int(np.count_nonzero(lines[:4] == head_line))
    if n_head != 3:
        raise BALFormatError(
            path,
            f"header must be 'num_cameras num_points num_observations', found {n_head} values",
            head_line,
        )
    counts = []
    for t, name in enumerate(("num_cameras", "num_points", "num_observations")):
        tok = blk.text(t)
        try:
            v = int(tok)
        except ValueError:
            raise BALFormatError(path, f"header {name} is not an integer: {tok!r}",
                                 head_line) from None
        if v <= 0:
            raise BALFormatError(path, f"header {name} must be positive, got {v}", head_line)
        counts.append(v)
    return counts[0], counts[1], counts[2]


class _Reader:
    """The state of one pass over a BAL file: counts, outputs, the token and line reached."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.k = 0  # tokens before the current block
        self.counts: tuple[int, int, int] | None = None
        self.prev_line = 0  # line of the last observation (the header's, at first)

    def start(self, blk: _Block) -> None:
        """Read the header from the first block with tokens; allocate the outputs."""
        n_cam, n_pt, n_obs = self.counts = _header(self.path, blk)
        self.expected = 3 + 4 * n_obs + 9 * n_cam + 3 * n_pt
        self.prev_line = int(blk.lines[0])
        self.camera_index = np.empty(n_obs, dtype=np.int64)
        self.point_index = np.empty(n_obs, dtype=np.int64)
        self.observations = np.empty((n_obs, 2))
        self.params = np.empty(9 * n_cam + 3 * n_pt)

    def block(self, blk: _Block) -> None:
        """Check and store the tokens of one block."""
        assert self.counts is not None
        n_cam, _, n_obs = self.counts
        k, T, end_obs = self.k, len(blk), 3 + 4 * n_obs
        a, b = max(k, 3), min(k + T, end_obs)
        if a < b:
            self._check_layout(blk, a - k, b - k, (a - 3) // 4, b == k + T and b < end_obs)
        if k + T > self.expected:
            raise BALFormatError(
                self.path,
                f"unexpected extra value after the {n_cam} cameras and {self.counts[1]} points "
                f"announced by the header (wrong counts in the header?)",
                int(blk.lines[self.expected - k]),
            )
        values = blk.values(self.path)
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            t = int(bad[0])
            raise BALFormatError(self.path, f"non-finite value {blk.text(t)!r} in "
                                 f"{_section(k + t, n_obs, n_cam)}", blk.line_of(t))
        if a < b:
            self._observations(blk, values[a - k:a - k + (b - a) // 4 * 4], (a - 3) // 4, a - k)
        lo = max(k, end_obs)
        if lo < k + T:
            self.params[lo - end_obs:k + T - end_obs] = values[lo - k:]
        self.k += T

    def _check_layout(self, blk: _Block, t0: int, t1: int, i0: int, cut: bool) -> None:
        """Observations ``i0…`` (tokens ``t0:t1`` of the block): four values on one line each.
        ``cut``: the block ends inside an observation (its values went on another line)."""
        nf = (t1 - t0) // 4
        lines = blk.lines[t0:t0 + 4 * nf].reshape(nf, 4)
        ok = (lines == lines[:, :1]).all(axis=1)
        if nf:
            ok[0] &= lines[0, 0] > self.prev_line
            ok[1:] &= lines[1:, 0] > lines[:-1, 3]
            self.prev_line = int(lines[-1, 3])
        bad = np.flatnonzero(~ok)
        if len(bad) or (cut and (t1 - t0) % 4):
            i = int(bad[0]) if len(bad) else nf
            raise BALFormatError(
                self.path,
                f"observation {i0 + i}: expected 4 values 'camera_index point_index x y' on one "
                f"line (wrong num_observations in the header?)",
                int(blk.lines[t0 + 4 * i]),
            )

    def _observations(self, blk: _Block, vals: np.ndarray, i0: int, t0: int) -> None:
        """Store observations ``i0…`` (their values ``vals``; token ``t0`` of the block)."""
        assert self.counts is not None
        obs = vals.reshape(-1, 4)
        i1 = i0 + len(obs)
        for col, name, limit, out in ((0, "camera", self.counts[0], self.camera_index),
                                      (1, "point", self.counts[1], self.point_index)):
            idx = obs[:, col]
            wrong = np.flatnonzero((idx != np.floor(idx)) | (idx < 0) | (idx >= limit))
            if len(wrong):
                i = int(wrong[0])
                raise BALFormatError(
                    self.path, f"observation {i0 + i}: {name} index {blk.text(t0 + 4 * i + col)}"
                    f" is not an integer in [0, {limit - 1}]", blk.line_of(t0 + 4 * i))
            out[i0:i1] = idx
        self.observations[i0:i1] = obs[:, 2:]

    def finish(self, last_line: int) -> BALProblem:
        """The problem, once every block was read (``last_line``: the last token's line)."""
        if self.counts is None:
            raise BALFormatError(self.path, "file is empty")
        n_cam, n_pt, n_obs = self.counts
        if self.k < self.expected:
            raise BALFormatError(
                self.path,
                f"file is truncated: the header announces {n_cam} cameras, {n_pt} points and "
                f"{n_obs} observations ({self.expected} values) but the file ends after "
                f"{self.k} values, in {_section(self.k, n_obs, n_cam)}",
                last_line,
            )
        return BALProblem(
            cameras=self.params[:9 * n_cam].reshape(n_cam, 9),
            points=self.params[9 * n_cam:].reshape(n_pt, 3),
            camera_index=self.camera_index,
            point_index=self.point_index,
            observations=self.observations,
            path=str(self.path),
        )


def read_bal(path: str | os.PathLike[str]) -> BALProblem:
    """Read a BAL problem (``.txt``, ``.txt.gz``, ``.txt.bz2``; detected from the content).

    The file is read as a stream, in blocks of whole lines (:data:`CHUNK_BYTES`), each parsed
    by numpy's C float parser straight into the output arrays: the reader's memory is the
    problem (32 bytes per observation) plus one block's work, however large the file.

    Args:
        path: The file.

    Returns:
        The problem, with ``camera_index``/``point_index`` as ``int64``.

    Raises:
        BALFormatError: Missing, empty, truncated or corrupt file; bad header counts; a
            non-numeric token; an index out of range; a NaN or inf; trailing extra values. The
            message names the file and (where it applies) the line.
    """
    path = Path(path)
    reader = _Reader(path)
    line0, last_line = 0, 0
    with open_stream(path, BALFormatError) as f:
        for data in _line_blocks(path, f):
            blk = _Block(data, line0)
            if len(blk):
                if reader.counts is None:
                    reader.start(blk)
                reader.block(blk)
                last_line = blk.line_of(len(blk) - 1)
            line0 += data.count(b"\n")
    return reader.finish(last_line)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _format_rows(fmt: str, arr: np.ndarray) -> str:
    if len(arr) == 0:
        return ""
    return "\n".join(fmt % tuple(row) for row in arr.tolist()) + "\n"


def write_bal(path: str | os.PathLike[str], problem: BALProblem) -> None:
    """Write a BAL file; ``.gz``/``.bz2`` suffixes compress. Values keep full precision.

    The file is written to a temporary file first and renamed over ``path`` when complete.

    Args:
        path: Destination file.
        problem: The problem to write.

    Raises:
        ValueError: The problem contains NaN or inf (a BAL file must not).
    """
    for name in ("cameras", "points", "observations"):
        if not np.isfinite(getattr(problem, name)).all():
            raise ValueError(f"write_bal: {name} contain NaN or inf")
    parts = [f"{problem.num_cameras} {problem.num_points} {problem.num_observations}\n"]
    obs = np.column_stack(
        [problem.camera_index.astype(object), problem.point_index.astype(object),
         problem.observations[:, 0], problem.observations[:, 1]]
    )
    parts.append(_format_rows("%d %d %.17g %.17g", obs))
    parts.append(_format_rows("%.17g", problem.cameras.reshape(-1, 1)))
    parts.append(_format_rows("%.17g", problem.points.reshape(-1, 1)))
    payload = "".join(parts).encode("ascii")
    name = str(path)
    if name.endswith(".bz2"):
        payload = bz2.compress(payload, 9)
    elif name.endswith(".gz"):
        payload = gzip.compress(payload, 6, mtime=0)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(payload)
