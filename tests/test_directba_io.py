"""The direct-BA loader (errors name file and line) and the synthetic scene."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from graphopt.apps.direct_ba_scene import synthetic_scene
from graphopt.io.directba import DEFAULT_INTRINSICS, DirectBAFormatError, load_directba
from graphopt.lie import quat_to_rot, so3_log

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "directba"

POSES = [
    "1.0 0.1 0.2 0.3 0 0 0 1",
    "2.0 0.5 0.0 -0.1 0.0 0.7071068 0 0.7071068",
]
POINT = "0.1 0.2 3.0 " + " ".join(str(200.5 + i) for i in range(16))


def make_folder(root: Path, poses: list[str] = POSES, points: list[str] | None = None,
                n_images: int = 2) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "poses.txt").write_text("\n".join(poses) + "\n")
    (root / "points.txt").write_text("\n".join(points or [POINT, POINT]) + "\n")
    img = (np.arange(48 * 64).reshape(48, 64) % 251).astype(np.uint8)
    for i in range(n_images):
        cv2.imwrite(str(root / f"{i}.png"), cv2.merge([img, img, img]))
    return root


def test_load_valid(tmp_path: Path) -> None:
    d = load_directba(make_folder(tmp_path / "ok"))
    assert d.poses.shape == (2, 4, 4) and d.points.shape == (2, 3) and d.patches.shape == (2, 16)
    assert d.images.shape == (2, 48, 64) and d.images.dtype == np.float64
    assert d.intrinsics == DEFAULT_INTRINSICS
    np.testing.assert_allclose(d.poses[0], np.c_[np.eye(4)[:, :3], [0.1, 0.2, 0.3, 1]])
    # qx qy qz qw with w last: 90° about y.
    np.testing.assert_allclose(d.poses[1, :3, :3], quat_to_rot(np.array([[0, 0.7071068, 0,
                                                                          0.7071068]]))[0])
    assert d.patches[0, 15] == pytest.approx(215.5)  # values above 255 are allowed too
    d2 = load_directba(tmp_path / "ok", intrinsics=(100, 101, 30, 20))
    assert d2.intrinsics == (100.0, 101.0, 30.0, 20.0)


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("missing_image", r"1\.png: image not found"),
        ("pose_columns", r"poses\.txt:2: expected 8 columns"),
        ("point_columns", r"points\.txt:2: expected 19 columns"),
        ("zero_quat", r"poses\.txt:2: bad quaternion"),
        ("nan_quat", r"poses\.txt:1: bad quaternion"),
        ("not_number", r"points\.txt:1: not a number"),
        ("no_points", r"points\.txt: no "),
        ("no_poses_file", r"poses\.txt: .*not found"),
        ("no_folder", r"data folder not found"),
        ("bad_image", r"0\.png: not a readable image"),
    ],
)
def test_load_errors(tmp_path: Path, case: str, match: str) -> None:
    root = tmp_path / case
    if case == "missing_image":
        make_folder(root, n_images=1)
    elif case == "pose_columns":
        make_folder(root, poses=[POSES[0], "2.0 0.5 0.0 -0.1 0 0 1"])
    elif case == "point_columns":
        make_folder(root, points=[POINT, POINT + " 3.0"])
    elif case == "zero_quat":
        make_folder(root, poses=[POSES[0], "2.0 0.5 0.0 -0.1 0 0 0 0"])
    elif case == "nan_quat":
        make_folder(root, poses=["1.0 0 0 0 nan 0 0 1", POSES[1]])
    elif case == "not_number":
        make_folder(root, points=[POINT.replace("200.5", "abc"), POINT])
    elif case == "no_points":
        make_folder(root)
        (root / "points.txt").write_text("\n\n")
    elif case == "no_poses_file":
        make_folder(root)
        (root / "poses.txt").unlink()
    elif case == "bad_image":
        make_folder(root)
        (root / "0.png").write_bytes(b"not a png")
    with pytest.raises(DirectBAFormatError, match=match):
        load_directba(root)


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real data not found at {REAL}")
def test_load_real() -> None:
    d = load_directba(REAL)
    assert d.poses.shape == (7, 4, 4) and d.points.shape == (4118, 3)
    assert d.images.shape == (7, 480, 640)
    assert d.patches.max() > 255  # the task's intensities are not clipped


def test_synthetic_scene_deterministic() -> None:
    a = synthetic_scene(n_frames=3, n_points=200, size=(320, 240), seed=3)
    b = synthetic_scene(n_frames=3, n_points=200, size=(320, 240), seed=3)
    c = synthetic_scene(n_frames=3, n_points=200, size=(320, 240), seed=4)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.poses, c.poses)
    assert len(a.points) == 200 and a.patches.shape == (200, 16)
    np.testing.assert_array_equal(a.poses[0], a.true_poses[0])  # the gauge pose is exact
    # Perturbation magnitudes: 1° and 3 cm per pose (default).
    dR = a.poses[1:, :3, :3] @ np.swapaxes(a.true_poses[1:, :3, :3], 1, 2)
    np.testing.assert_allclose(np.degrees(np.linalg.norm(so3_log(dR), axis=1)), 1.0, rtol=1e-6)
    assert a.images.shape == (3, 240, 320)
