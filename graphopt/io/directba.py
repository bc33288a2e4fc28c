"""Direct bundle adjustment data: :class:`DirectBAData` and the task's loader.

Format of a data folder (the task's, see ``shared/data/directba/README.md``):

* ``poses.txt``: one line per camera, ``time tx ty tz qx qy qz qw`` — ``T_cw`` (world to camera),
  Hamilton quaternion with ``w`` last;
* ``points.txt``: one line per point, ``x y z`` and the ``P²`` reference intensities (16 for the
  task) in the order ``k = P (dx + P/2) + (dy + P/2)``;
* ``0.png``, ``1.png``, …: one greyscale image per pose.

:func:`load_directba` validates everything and raises :class:`DirectBAFormatError` naming the
file and line. A synthetic textured scene with ground truth is
:func:`graphopt.apps.direct_ba_scene.synthetic_scene`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graphopt.lie import make_transform, quat_to_rot

#: The task's intrinsics (fx, fy, cx, cy).
DEFAULT_INTRINSICS = (277.34, 291.402, 312.234, 239.777)


class DirectBAFormatError(ValueError):
    """A direct-BA data folder is missing something or malformed (message names file and line)."""


@dataclass
class DirectBAData:
    """A direct BA problem.

    Args:
        poses: ``(n, 4, 4)`` camera poses ``T_cw``.
        points: ``(N, 3)`` world points.
        patches: ``(N, P²)`` reference intensities.
        images: ``(n, H, W)`` float64 greyscale images.
        intrinsics: ``(fx, fy, cx, cy)``.
        timestamps: ``(n,)`` timestamps from poses.txt (meaningless in the task's data).
        true_poses: Ground-truth poses (synthetic scene only).
        true_points: Ground-truth points (synthetic scene only).
        hosts: ``(N,)`` index of the image each patch was taken from, when known.
        source: Where the problem came from (folder path or ``"synthetic"``).
        extra: Generation settings of the synthetic scene (seed, noise levels, outlier indices).
    """

    poses: np.ndarray
    points: np.ndarray
    patches: np.ndarray
    images: np.ndarray
    intrinsics: tuple[float, float, float, float] = DEFAULT_INTRINSICS
    timestamps: np.ndarray | None = None
    true_poses: np.ndarray | None = None
    true_points: np.ndarray | None = None
    hosts: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def patch(self) -> int:
        """Patch side ``P``."""
        return int(round(np.sqrt(self.patches.shape[1])))


def _read_table(
    path: Path, columns: int, what: str, check_finite: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Whitespace-separated numbers with exactly ``columns`` per non-empty line.

    Returns the ``(n, columns)`` values and the 1-based line number of every row.
    """
    if not path.is_file():
        raise DirectBAFormatError(f"{path}: {what} file not found")
    rows: list[list[float]] = []
    linenos: list[int] = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DirectBAFormatError(f"{path}: cannot read ({exc})") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != columns:
            raise DirectBAFormatError(
                f"{path}:{lineno}: expected {columns} columns ({what}), got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise DirectBAFormatError(
                f"{path}:{lineno}: not a number in {line.strip()!r}"
            ) from None
        if check_finite and not np.all(np.isfinite(values)):
            raise DirectBAFormatError(f"{path}:{lineno}: non-finite value")
        rows.append(values)
        linenos.append(lineno)
    if not rows:
        raise DirectBAFormatError(f"{path}: no {what} found")
    return np.asarray(rows, dtype=np.float64), np.asarray(linenos)


def read_image(path: Path) -> np.ndarray:
    """Read an image as float64 greyscale (colour files are converted).

    Args:
        path: Image file.

    Raises:
        DirectBAFormatError: If the file is missing or not an image.
    """
    import cv2

    if not path.is_file():
        raise DirectBAFormatError(f"{path}: image not found")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DirectBAFormatError(f"{path}: not a readable image")
    return img.astype(np.float64)


def poses_from_rows(
    rows: np.ndarray, path: Path | str = "poses", linenos: np.ndarray | None = None
) -> np.ndarray:
    """``T_cw`` from rows ``time tx ty tz qx qy qz qw``.

    Args:
        rows: ``(n, 8)`` numbers.
        path: File name for error messages.
        linenos: Line number of every row (``1..n`` by default).

    Raises:
        DirectBAFormatError: If a quaternion has zero or non-finite norm.
    """
    q = rows[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    bad = ~np.isfinite(norm) | (norm < 1e-12)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        line = i + 1 if linenos is None else int(linenos[i])
        raise DirectBAFormatError(
            f"{path}:{line}: bad quaternion {q[i].tolist()} (norm {norm[i]:g})"
        )
    return make_transform(quat_to_rot(q / norm[:, None]), rows[:, 1:4])


def load_directba(
    folder: str | Path,
    intrinsics: tuple[float, float, float, float] = DEFAULT_INTRINSICS,
    patch: int = 4,
) -> DirectBAData:
    """Load the task's data folder.

    Args:
        folder: Folder with ``poses.txt``, ``points.txt`` and ``0.png``… .
        intrinsics: ``(fx, fy, cx, cy)``; the task's values by default.
        patch: Patch side ``P``; points.txt must then have ``3 + P²`` columns.

    Returns:
        The problem (images as float64 greyscale).

    Raises:
        DirectBAFormatError: Missing folder/file/image, wrong column count, bad number or
            quaternion, images of different sizes.
    """
    root = Path(folder)
    if not root.is_dir():
        raise DirectBAFormatError(f"{root}: data folder not found")
    pose_path = root / "poses.txt"
    # Quaternions are checked first so that a NaN there is reported as a bad quaternion.
    rows, lines = _read_table(pose_path, 8, "time tx ty tz qx qy qz qw", check_finite=False)
    poses = poses_from_rows(rows, pose_path, lines)
    bad = ~np.isfinite(rows[:, 1:4]).all(axis=1)
    if bad.any():
        raise DirectBAFormatError(f"{pose_path}:{lines[np.flatnonzero(bad)[0]]}: non-finite value")
    pts, _ = _read_table(
        root / "points.txt", 3 + patch * patch, f"x y z and {patch * patch} intensities"
    )
    images = []
    for i in range(len(poses)):
        images.append(read_image(root / f"{i}.png"))
        if images[-1].shape != images[0].shape:
            raise DirectBAFormatError(
                f"{root / f'{i}.png'}: size {images[-1].shape[::-1]} differs from 0.png's "
                f"{images[0].shape[::-1]}"
            )
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise DirectBAFormatError(f"bad intrinsics {intrinsics}")
    return DirectBAData(
        poses=poses,
        points=pts[:, :3].copy(),
        patches=pts[:, 3:].copy(),
        images=np.stack(images),
        intrinsics=(fx, fy, cx, cy),
        timestamps=rows[:, 0].copy(),
        source=str(root),
    )
