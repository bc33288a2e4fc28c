"""Atomic file output: a user's existing file is only replaced by a complete new one.

Writers create a temporary file in the destination's folder (same file system, so the final
``os.replace`` is atomic on POSIX and Windows), write and flush it completely, then rename it over
the destination. If writing fails, the temporary file is removed and the old file is untouched.

Example::

    with atomic_write("cloud.ply", "wb") as f:
        f.write(data)

    atomic_save("run.rrd", lambda tmp: recording.save(tmp))

    pending = PendingFile("run.rrd")   # when opening and finishing happen in different places
    ...                                # write pending.tmp
    pending.commit()                   # or pending.discard()
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["PendingFile", "atomic_path", "atomic_save", "atomic_write"]


class PendingFile:
    """A temporary file beside ``path`` that becomes ``path`` on :meth:`commit`.

    For writers whose lifetime is not one ``with`` block (e.g. a recording opened in one method
    and finished in another); otherwise prefer :func:`atomic_path`. The temporary file is
    created empty at once (so a missing folder is reported before any work is done), has a
    hidden name ending in ``.tmp`` and lives in the destination's folder.

    Args:
        path: The destination file.

    Raises:
        FileNotFoundError: The destination's folder does not exist.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        folder = self.path.parent if str(self.path.parent) else Path(".")
        if not folder.is_dir():
            raise FileNotFoundError(f"{self.path}: folder {folder} does not exist")
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=folder)
        os.close(fd)
        #: Where to write the content.
        self.tmp = Path(tmp)

    def commit(self) -> None:
        """Rename the temporary file over the destination (with the usual permissions)."""
        try:
            # mkstemp makes the file 0600; give it the destination's or the umask's mode.
            if self.path.exists():
                mode = self.path.stat().st_mode & 0o7777
            else:
                mode = 0o666 & ~_umask()
            os.chmod(self.tmp, mode)
        except OSError:
            pass  # permissions are cosmetic; the content is what matters
        os.replace(self.tmp, self.path)

    def discard(self) -> None:
        """Delete the temporary file; the destination keeps its old content."""
        with contextlib.suppress(OSError):
            self.tmp.unlink()


def _umask() -> int:
    """The process's file mode creation mask."""
    # os.umask can only be read by setting it; restore immediately.
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``.

    Use this for writers that insist on a file name (e.g. ``rerun``'s ``save``, ``cv2.imwrite``).
    If the body raises, the temporary file is deleted and ``path`` keeps its old content.

    Args:
        path: The destination file.

    Yields:
        The temporary path to write to (same folder, hidden name ending in ``.tmp``).
    """
    pending = PendingFile(path)
    try:
        yield pending.tmp
        pending.commit()
    except BaseException:
        pending.discard()
        raise


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str], mode: str = "w", encoding: str | None = None
) -> Iterator[IO[Any]]:
    """Open a temporary file for writing; rename it over ``path`` once closed without error.

    Args:
        path: The destination file.
        mode: ``"w"`` (text) or ``"wb"`` (binary).
        encoding: Text encoding (``"utf-8"`` by default in text mode).

    Yields:
        The open file object.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    if mode == "w" and encoding is None:
        encoding = "utf-8"
    with atomic_path(path) as tmp:
        with open(tmp, mode, encoding=encoding) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())


def atomic_save(path: str | os.PathLike[str], writer: Callable[[Path], Any]) -> Any:
    """Call ``writer(tmp_path)`` and move the result to ``path`` when it returns.

    Args:
        path: The destination file.
        writer: A function that writes the complete file to the path it is given.

    Returns:
        Whatever ``writer`` returns.
    """
    with atomic_path(path) as tmp:
        return writer(tmp)
