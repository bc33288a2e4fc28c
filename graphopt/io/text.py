"""What the text-file readers share: one-line format errors naming file and line, reading a
possibly compressed file, and locating whitespace-separated tokens with numpy."""

from __future__ import annotations

import bz2
import gzip
import lzma
import os
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

#: Bytes that separate tokens: exactly what ``bytes.split()`` splits on.
WHITESPACE = np.zeros(256, dtype=bool)
WHITESPACE[[9, 10, 11, 12, 13, 32]] = True


class FileFormatError(ValueError):
    """A file that cannot be read; the message is one line naming the file and line.

    Args:
        path: The file.
        message: What is wrong.
        line: 1-based line number, if the problem is on a line.
    """

    #: What the reader expected, for "is a directory, not a ..." messages.
    kind = "file"

    def __init__(self, path: str | os.PathLike[str], message: str, line: int | None = None):
        self.path = str(path)
        self.line = None if line is None else int(line)
        where = f"{self.path}:{self.line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")


#: What a truncated or corrupt compressed stream raises while it is read.
DECOMPRESSION_ERRORS = (OSError, EOFError, ValueError, zlib.error, lzma.LZMAError)


def open_stream(path: Path, error: type[FileFormatError]) -> BinaryIO:
    """The file as a binary stream, decompressed when its magic bytes say bzip2, gzip or xz.

    Reading it may raise one of :data:`DECOMPRESSION_ERRORS` on a corrupt compressed file.

    Args:
        path: The file.
        error: The reader's error class (raised naming the file when it cannot be opened).
    """
    try:
        f = open(path, "rb")  # noqa: SIM115 - the caller closes the stream
    except FileNotFoundError:
        raise error(path, "file not found") from None
    except IsADirectoryError:
        raise error(path, f"is a directory, not a {error.kind}") from None
    except OSError as exc:
        raise error(path, f"cannot read file: {exc.strerror or exc}") from None
    try:
        magic = f.read(6)
        f.seek(0)
    except OSError as exc:
        f.close()
        raise error(path, f"cannot read file: {exc.strerror or exc}") from None
    if magic[:3] == b"BZh":
        return bz2.BZ2File(f)  # type: ignore[return-value]
    if magic[:2] == b"\x1f\x8b":
        return gzip.GzipFile(fileobj=f)  # type: ignore[return-value]
    if magic == b"\xfd7zXZ\x00":
        return lzma.LZMAFile(f)  # type: ignore[return-value]
    return f


def read_bytes(path: Path, error: type[FileFormatError]) -> bytes:
    """The file's content, decompressed when its magic bytes say bzip2, gzip or xz.

    Args:
        path: The file.
        error: The reader's error class (raised naming the file).
    """
    with open_stream(path, error) as f:
        try:
            return f.read()
        except DECOMPRESSION_ERRORS as exc:
            raise error(path, f"corrupt or truncated compressed file ({exc})") from None
        except OSError as exc:  # pragma: no cover - a read error of a plain file
            raise error(path, f"cannot read file: {exc.strerror or exc}") from None


def token_layout(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Start offsets of whitespace-separated tokens and their 1-based line numbers.

    Args:
        data: The file's content.
    """
    a = np.frombuffer(data, dtype=np.uint8)
    if len(a) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ws = WHITESPACE[a]
    prev_ws = np.empty_like(ws)
    prev_ws[0] = True
    prev_ws[1:] = ws[:-1]
    starts = np.flatnonzero(~ws & prev_ws)
    newlines = np.flatnonzero(a == 10)
    lines = np.searchsorted(newlines, starts, side="right") + 1
    return starts, lines
