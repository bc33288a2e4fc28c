"""PLY point-cloud writer (MeshLab, CloudCompare, Open3D read it).

Vertices carry ``x y z`` as doubles and ``red green blue`` as ``uchar``. The file is written
atomically (:mod:`graphopt.io.atomic`): an existing file is replaced only by a complete one.

Example::

    write_scene_ply("after.ply", points=X, camera_centers=C)   # cameras green, points white
    write_ply("cloud.ply", X, colors=rgb, binary=False)
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from graphopt.io.atomic import atomic_write

__all__ = [
    "CAMERA_COLOR",
    "POINT_COLOR",
    "camera_centers_from_poses",
    "write_ply",
    "write_scene_ply",
]

#: Default colour of camera centres (green, as Ceres' bundle_adjuster writes them).
CAMERA_COLOR: tuple[int, int, int] = (0, 255, 0)
#: Default colour of scene points.
POINT_COLOR: tuple[int, int, int] = (255, 255, 255)


def _as_colors(colors: Any, n: int) -> np.ndarray:
    c = np.asarray(colors)
    if c.ndim == 1:
        c = np.broadcast_to(c, (n, 3))
    if c.shape != (n, 3):
        raise ValueError(f"colors must have shape (3,) or ({n}, 3), got {c.shape}")
    if np.issubdtype(c.dtype, np.floating) and c.size and np.nanmax(c) <= 1.0:
        c = c * 255.0  # floats in [0, 1]
    return np.clip(np.nan_to_num(c), 0, 255).astype(np.uint8)


def write_ply(
    path: str | os.PathLike[str],
    points: Any,
    colors: Any = POINT_COLOR,
    *,
    binary: bool = True,
    comment: str | None = None,
) -> None:
    """Write coloured 3D points as a PLY file.

    Args:
        path: Destination file (replaced atomically).
        points: ``(n, 3)`` coordinates. Non-finite points are rejected (they break viewers).
        colors: ``(3,)`` colour for all points or ``(n, 3)`` per point; ``uint8`` 0–255 or floats
            in [0, 1].
        binary: Binary little-endian (compact, fast) if True, else ASCII.
        comment: Optional comment line for the header.

    Raises:
        ValueError: Wrong shapes or non-finite coordinates.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points contain NaN or inf; refusing to write a PLY file")
    n = len(pts)
    rgb = _as_colors(colors, n)
    fmt = "binary_little_endian" if binary else "ascii"
    header = ["ply", f"format {fmt} 1.0"]
    if comment:
        header.append("comment " + comment.replace("\n", " "))
    header += [
        f"element vertex {n}",
        "property double x",
        "property double y",
        "property double z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "end_header",
    ]
    head = ("\n".join(header) + "\n").encode("ascii")
    with atomic_write(path, "wb") as f:
        f.write(head)
        if binary:
            rec = np.empty(n, dtype=[("xyz", "<f8", 3), ("rgb", "u1", 3)])
            rec["xyz"], rec["rgb"] = pts, rgb
            f.write(rec.tobytes())
        else:
            lines = [
                f"{x:.17g} {y:.17g} {z:.17g} {r} {g} {b}"
                for (x, y, z), (r, g, b) in zip(pts.tolist(), rgb.tolist(), strict=True)
            ]
            f.write(("\n".join(lines) + ("\n" if lines else "")).encode("ascii"))


def write_scene_ply(
    path: str | os.PathLike[str],
    points: Any,
    camera_centers: Any,
    *,
    point_color: Any = POINT_COLOR,
    camera_color: Any = CAMERA_COLOR,
    binary: bool = True,
) -> None:
    """Write a reconstruction: camera centres as coloured points, then the scene points.

    Args:
        path: Destination file (replaced atomically).
        points: ``(n, 3)`` scene points.
        camera_centers: ``(c, 3)`` camera centres in the world frame (see
            :func:`camera_centers_from_poses`).
        point_color: Colour of scene points (white by default).
        camera_color: Colour of camera centres, ``(3,)`` or ``(c, 3)`` (green by default).
        binary: Binary little-endian if True, else ASCII.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    cams = np.asarray(camera_centers, dtype=float).reshape(-1, 3)
    colors = np.concatenate(
        [_as_colors(camera_color, len(cams)), _as_colors(point_color, len(pts))]
    )
    write_ply(
        path,
        np.concatenate([cams, pts]),
        colors,
        binary=binary,
        comment=f"{len(cams)} camera centres then {len(pts)} points",
    )


def camera_centers_from_poses(T_cw: Any) -> np.ndarray:
    """Camera centres ``C = −Rᵀ t`` from world-to-camera transforms.

    Args:
        T_cw: ``(c, 4, 4)`` (or ``(c, 3, 4)``) world-to-camera transforms.

    Returns:
        ``(c, 3)`` centres in the world frame.
    """
    T = np.asarray(T_cw, dtype=float)
    R, t = T[:, :3, :3], T[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)
