"""BAL reader/writer, bad input, normalize/perturb, synthetic scene, PLY and atomic writes."""

from __future__ import annotations

import bz2
import gzip
import os
from pathlib import Path

import numpy as np
import pytest

from graphopt.apps.bal_preprocess import normalize, perturb
from graphopt.apps.bal_scene import ground_truth_errors, synthetic_scene
from graphopt.io.atomic import PendingFile, atomic_path, atomic_write
from graphopt.io.bal import BALFormatError, BALProblem, read_bal, write_bal
from graphopt.io.ply import camera_centers_from_poses, write_ply, write_scene_ply
from graphopt.lie import make_transform, so3_exp
from graphopt.types.bal import bal_cost

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bal"

GOOD = """2 3 4
0 0 -1.5 2.5
1 0 3.0 -4.0
0 1 1e1 2E-1
1 2 0 0
0.1
0.2
0.3
1
2
3
500
0.01
0.001
0 0 0 0 0 -1 400 0 0
1 2 3
4 5 6
7 8 9
"""


def _write(tmp_path: Path, text: str, name: str = "p.txt") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_read_good_file(tmp_path: Path) -> None:
    p = read_bal(_write(tmp_path, GOOD))
    assert (p.num_cameras, p.num_points, p.num_observations) == (2, 3, 4)
    assert p.camera_index.tolist() == [0, 1, 0, 1]
    assert p.point_index.tolist() == [0, 0, 1, 2]
    np.testing.assert_allclose(p.observations[2], [10.0, 0.2])
    np.testing.assert_allclose(p.cameras[1], [0, 0, 0, 0, 0, -1, 400, 0, 0])
    np.testing.assert_allclose(p.points[2], [7, 8, 9])
    assert p.camera_index.dtype == np.int64


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        ("", None, "empty"),
        ("   \n\n", None, "empty"),
        (GOOD.replace("2 3 4\n", "2 3\n", 1), 1, "header"),
        (GOOD.replace("2 3 4\n", "2 x 4\n", 1), 1, "not an integer"),
        (GOOD.replace("2 3 4\n", "2 3 -4\n", 1), 1, "positive"),
        (GOOD.replace("2 3 4\n", "2 3 5\n", 1), 6, "observation 4"),  # wrong count → shifted
        (GOOD.replace("2 3 4\n", "2 4 4\n", 1), 18, "truncated"),
        (GOOD.replace("2 3 4\n", "2 2 4\n", 1), 18, "extra"),
        (GOOD.rsplit("\n", 2)[0] + "\n", 17, "truncated"),  # last line cut
        (GOOD.replace("0 1 1e1 2E-1", "0 1 1e1"), 4, "observation 2"),
        (GOOD.replace("1 0 3.0 -4.0", "1 0 3.0 abc"), 3, "not a number: 'abc'"),
        (GOOD.replace("1 0 3.0 -4.0", "1 0 3.0 -4.0x"), 3, "not a number"),
        (GOOD.replace("0.2\n", "nan\n", 1), 7, "non-finite value 'nan' in camera 0"),
        (GOOD.replace("4 5 6", "4 inf 6"), 17, "point 1"),
        (GOOD.replace("1 2 0 0", "1 3 0 0"), 5, "point index 3"),
        (GOOD.replace("1 2 0 0", "2 2 0 0"), 5, "camera index 2"),
        (GOOD.replace("1 2 0 0", "-1 2 0 0"), 5, "camera index -1"),
        (GOOD.replace("1 2 0 0", "1 1.5 0 0"), 5, "point index 1.5"),
    ],
)
def test_bad_input_names_file_and_line(tmp_path: Path, text: str, line: int | None, fragment: str):
    path = _write(tmp_path, text)
    with pytest.raises(BALFormatError) as info:
        read_bal(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(str(path))
    assert fragment in msg, msg
    assert info.value.line == line, msg
    if line is not None:
        assert msg.startswith(f"{path}:{line}: ")
    assert isinstance(info.value, ValueError)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(BALFormatError, match="file not found"):
        read_bal(tmp_path / "nope.txt")
    with pytest.raises(BALFormatError, match="directory"):
        read_bal(tmp_path)


def test_corrupt_and_truncated_compressed(tmp_path: Path) -> None:
    data = bz2.compress(GOOD.encode())
    (tmp_path / "t.txt.bz2").write_bytes(data[: len(data) // 2])
    with pytest.raises(BALFormatError, match="corrupt or truncated"):
        read_bal(tmp_path / "t.txt.bz2")
    gz = gzip.compress(GOOD.encode())
    (tmp_path / "t.txt.gz").write_bytes(gz[:20])
    with pytest.raises(BALFormatError, match="corrupt or truncated"):
        read_bal(tmp_path / "t.txt.gz")


def test_binary_garbage(tmp_path: Path) -> None:
    (tmp_path / "g.txt").write_bytes(b"2 3 4\n\x00\xff\xfe 1 2 3\n")
    with pytest.raises(BALFormatError) as info:
        read_bal(tmp_path / "g.txt")
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("suffix", [".txt", ".txt.gz", ".txt.bz2"])
def test_write_read_round_trip(tmp_path: Path, suffix: str) -> None:
    scene = synthetic_scene(num_cameras=4, num_points=50, seed=1)
    path = tmp_path / f"s{suffix}"
    write_bal(path, scene.problem)
    back = read_bal(path)
    for name in ("cameras", "points", "observations", "camera_index", "point_index"):
        assert np.array_equal(getattr(back, name), getattr(scene.problem, name)), name
    raw = path.read_bytes()
    assert raw[:3] == b"BZh" if suffix.endswith("bz2") else True
    assert raw[:2] == b"\x1f\x8b" if suffix.endswith("gz") else True


def test_write_rejects_nan_and_keeps_old_file(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    path.write_text("old")
    p = read_bal(_write(tmp_path, GOOD))
    p.points[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_bal(path, p)
    assert path.read_text() == "old"


def test_normalize_matches_ceres_definition() -> None:
    scene = synthetic_scene(num_cameras=5, num_points=300, seed=2)
    p = scene.problem
    n = normalize(p)
    med = np.sort(n.points, axis=0)[len(n.points) // 2]  # Ceres' (upper) median
    np.testing.assert_allclose(med, 0.0, atol=1e-9)
    mad = np.sort(np.abs(n.points).sum(1))[len(n.points) // 2]
    np.testing.assert_allclose(mad, 100.0, rtol=1e-12)
    # A similarity of the scene: reprojections (hence the cost) are unchanged.
    np.testing.assert_allclose(bal_cost(n), bal_cost(p), rtol=1e-9)
    np.testing.assert_allclose(n.cameras[:, [0, 1, 2, 6, 7, 8]], p.cameras[:, [0, 1, 2, 6, 7, 8]])
    assert np.array_equal(p.points, scene.problem.points)  # input untouched


def test_perturb_is_deterministic() -> None:
    p = synthetic_scene(num_cameras=5, num_points=100, seed=3).truth
    a = perturb(p, 0.01, 0.1, 0.2, seed=7)
    b = perturb(p, 0.01, 0.1, 0.2, seed=7)
    c = perturb(p, 0.01, 0.1, 0.2, seed=8)
    assert np.array_equal(a.cameras, b.cameras) and np.array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)
    np.testing.assert_allclose(np.std(a.points - p.points), 0.2, rtol=0.15)
    # Rotation noise alone keeps the camera centres.
    r = perturb(p, 0.05, 0.0, 0.0, seed=1)
    np.testing.assert_allclose(r.camera_centers(), p.camera_centers(), atol=1e-9)
    assert not np.allclose(r.cameras[:, :3], p.cameras[:, :3])
    z = perturb(p, 0.0, 0.0, 0.0, seed=1)
    assert np.array_equal(z.cameras, p.cameras) and np.array_equal(z.points, p.points)
    with pytest.raises(ValueError):
        perturb(p, -1.0, 0.0, 0.0)


def test_synthetic_scene_ground_truth() -> None:
    s = synthetic_scene(num_cameras=6, num_points=200, seed=4)
    assert bal_cost(s.truth) == 0.0
    assert bal_cost(s.problem) > 0.0
    assert np.bincount(s.problem.point_index).min() >= 2
    assert s.problem.point_index.max() == s.problem.num_points - 1
    err = ground_truth_errors(s.truth, s.truth)
    assert err["point_rms"] < 1e-9 and err["rotation_deg_rms"] < 1e-6
    err = ground_truth_errors(s.problem, s.truth)
    assert err["point_rms"] > 0.01
    # Errors are gauge-invariant: a similarity of the truth has zero error.
    a = s.truth.copy()
    a.points = 2.0 * a.points + 1.0
    c = a.camera_centers()
    a.cameras[:, 3:6] = -np.einsum(
        "nij,nj->ni", so3_exp(
            a.cameras[:, :3]), 2.0 * (c * 0.5 + s.truth.camera_centers() * 0.5) + 1.0
    )
    assert ground_truth_errors(a, s.truth)["point_rms"] < 1e-9


def test_synthetic_scene_deterministic() -> None:
    a = synthetic_scene(num_cameras=4, num_points=40, seed=9).problem
    b = synthetic_scene(num_cameras=4, num_points=40, seed=9).problem
    assert np.array_equal(a.observations, b.observations) and np.array_equal(a.cameras, b.cameras)


@pytest.mark.skipif(not DATA.is_dir(), reason=f"real data folder {DATA} is absent")
def test_read_real_files() -> None:
    p = read_bal(DATA / "dubrovnik-3-7-pre.txt")
    assert (p.num_cameras, p.num_points, p.num_observations) == (3, 7, 19)
    p = read_bal(DATA / "problem-49-7776-pre.txt.bz2")
    assert (p.num_cameras, p.num_points, p.num_observations) == (49, 7776, 31843)
    np.testing.assert_allclose(bal_cost(p), 8.509125e5, rtol=1e-6)  # Ceres' initial cost


# --- PLY and atomic writes --------------------------------------------------------------------


def test_ply_scene_ascii_and_binary(tmp_path: Path) -> None:
    pts = np.arange(12.0).reshape(4, 3)
    cams = np.array([[0.0, 0.0, -1.0]])
    write_scene_ply(tmp_path / "a.ply", pts, cams, binary=False)
    text = (tmp_path / "a.ply").read_text().splitlines()
    assert text[0] == "ply" and "element vertex 5" in text and "end_header" in text
    body = text[text.index("end_header") + 1 :]
    assert body[0].endswith("0 255 0") and all(b.endswith("255 255 255") for b in body[1:])
    write_scene_ply(tmp_path / "b.ply", pts, cams)
    raw = (tmp_path / "b.ply").read_bytes()
    head, data = raw.split(b"end_header\n", 1)
    assert b"binary_little_endian" in head and len(data) == 5 * 27
    rec = np.frombuffer(data, dtype=[("xyz", "<f8", 3), ("rgb", "u1", 3)])
    np.testing.assert_array_equal(rec["xyz"][1:], pts)


def test_ply_rejects_nan_and_keeps_old(tmp_path: Path) -> None:
    path = tmp_path / "c.ply"
    path.write_text("old")
    with pytest.raises(ValueError, match="NaN"):
        write_ply(path, np.array([[0.0, np.nan, 0.0]]))
    assert path.read_text() == "old"
    assert sorted(os.listdir(tmp_path)) == ["c.ply"]


def test_camera_centers_from_poses() -> None:
    T = np.eye(4)[None].repeat(2, 0)
    T[1, :3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(camera_centers_from_poses(T), [[0, 0, 0], [-1, -2, -3]])


def test_atomic_write_failure_leaves_old_file(tmp_path: Path) -> None:
    path = tmp_path / "f.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(path) as f:
        f.write("partial")
        raise RuntimeError("boom")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["f.txt"]
    with atomic_write(path) as f:
        f.write("new")
    assert path.read_text() == "new"
    with atomic_path(tmp_path / "g.bin") as tmp:
        assert tmp.parent == tmp_path and not (tmp_path / "g.bin").exists()
        tmp.write_bytes(b"x")
    assert (tmp_path / "g.bin").read_bytes() == b"x"


def test_pending_file_commit_and_discard(tmp_path: Path) -> None:
    dest = tmp_path / "out.bin"
    dest.write_bytes(b"old")
    dest.chmod(0o640)
    pending = PendingFile(dest)
    assert pending.tmp.parent == tmp_path and pending.tmp.name.startswith(".out.bin.")
    assert pending.tmp.name.endswith(".tmp") and pending.tmp.read_bytes() == b""
    pending.tmp.write_bytes(b"new")
    assert dest.read_bytes() == b"old"  # nothing visible before the commit
    pending.commit()
    assert dest.read_bytes() == b"new" and dest.stat().st_mode & 0o777 == 0o640
    assert sorted(os.listdir(tmp_path)) == ["out.bin"]
    other = PendingFile(dest)
    other.tmp.write_bytes(b"discarded")
    other.discard()
    other.discard()  # a second discard is harmless
    assert dest.read_bytes() == b"new" and sorted(os.listdir(tmp_path)) == ["out.bin"]
    with pytest.raises(FileNotFoundError, match="does not exist"):
        PendingFile(tmp_path / "missing" / "x.bin")


def test_bal_problem_is_dataclass() -> None:
    p = BALProblem(np.zeros((1, 9)), np.zeros((1, 3)), np.zeros(1, int), np.zeros(1, int),
                   np.zeros((1, 2)))
    assert p.copy().num_observations == 1


# --- rerun recording --------------------------------------------------------------------------


def test_recorder_writes_and_aborts(tmp_path: Path) -> None:
    from graphopt.recording import Recorder

    T = make_transform(so3_exp(np.array([[0.0, 0.1, 0.0], [0.0, -0.1, 0.0]])),
                       np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    path = tmp_path / "r.rrd"
    with Recorder(path, camera_xyz="RUB", world_xyz="rdf") as rec:
        for it in range(2):
            rec.set_iteration(it)
            rec.log_points(np.random.default_rng(it).normal(size=(50, 3)))
            rec.log_cameras(T, focal=[500.0, 520.0], resolution=(64, 48),
                            images=[np.zeros((48, 64), np.uint8), None] if it == 0 else None)
            rec.log_scalar("cost", 10.0 / (it + 1))
            rec.log_scalar("cost", float("nan"))  # skipped, not an error
        assert not path.exists()  # only renamed into place on close
    assert path.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.rrd"]
    # An error inside the block discards the recording and keeps the old file.
    with pytest.raises(RuntimeError), Recorder(path) as rec:
        rec.log_points(np.zeros((3, 3)))
        raise RuntimeError("boom")
    assert path.stat().st_size > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.rrd"]
    with pytest.raises(ValueError, match="view coordinates"):
        Recorder(tmp_path / "x.rrd", camera_xyz="sideways")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.rrd"]


def test_recorder_focal_forms(tmp_path: Path) -> None:
    from graphopt.recording import Recorder

    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[:, 0, 3] = [0.0, 1.0, 2.0]
    with Recorder(tmp_path / "f.rrd") as rec:
        rec.log_cameras(T, focal=[277.3, 291.4], resolution=(640, 480))  # one (fx, fy)
        rec.log_cameras(T, focal=300.0, resolution=(640, 480))
        rec.log_cameras(T, focal=[300.0, 310.0, 320.0], resolution=(640, 480))  # per camera
        rec.log_cameras(T, focal=np.full((3, 2), 300.0), resolution=(640, 480))
        with pytest.raises(ValueError, match=r"focal must be .* got shape \(4,\)"):
            rec.log_cameras(T, focal=np.ones(4), resolution=(640, 480))
    assert (tmp_path / "f.rrd").stat().st_size > 0


# --- streaming reader and writer --------------------------------------------------------------

BAD_CASES = [  # (text, line, fragment) that every block size reports alike
    (GOOD.replace("2 3 4\n", "2 3 5\n", 1), 6, "observation 4"),
    (GOOD.replace("2 3 4\n", "2 4 4\n", 1), 18, "truncated"),
    (GOOD.rsplit("\n", 2)[0] + "\n", 17, "truncated"),
    (GOOD.replace("0 1 1e1 2E-1", "0 1 1e1"), 4, "observation 2"),
    (GOOD.replace("1 0 3.0 -4.0", "1 0 3.0 abc"), 3, "not a number: 'abc'"),
    (GOOD.replace("0.2\n", "nan\n", 1), 7, "non-finite value 'nan' in camera 0"),
    (GOOD.replace("4 5 6", "4 inf 6"), 17, "point 1"),
    (GOOD.replace("1 2 0 0", "1 3 0 0"), 5, "point index 3"),
    (GOOD + "\n\n1\n", 21, "extra"),
]


@pytest.mark.parametrize("block", [1, 7, 40])
def test_reader_blocks_do_not_change_the_result(tmp_path: Path, monkeypatch, block: int):
    """The file is parsed in blocks of whole lines; results and errors (file, line, what) do
    not depend on where the blocks end."""
    import graphopt.io.bal as bal_io

    ref = read_bal(_write(tmp_path, GOOD))
    monkeypatch.setattr(bal_io, "CHUNK_BYTES", block)
    p = read_bal(_write(tmp_path, GOOD))
    for name in ("cameras", "points", "observations", "camera_index", "point_index"):
        assert np.array_equal(getattr(p, name), getattr(ref, name)), name
    for text, line, fragment in BAD_CASES:
        path = _write(tmp_path, text)
        with pytest.raises(BALFormatError) as info:
            read_bal(path)
        assert info.value.line == line and fragment in str(info.value), (block, str(info.value))


def test_reader_holds_one_block_at_a_time(tmp_path: Path, monkeypatch) -> None:
    """A large file goes through the parser in blocks of about CHUNK_BYTES, never whole, and a
    broken token deep in it is reported with its own line."""
    import graphopt.io.bal as bal_io

    scene = synthetic_scene(num_cameras=6, num_points=400, seed=5)
    path = tmp_path / "s.txt"
    write_bal(path, scene.problem)
    sizes: list[int] = []
    real = bal_io._Block

    def spy(data: bytes, line0: int) -> bal_io._Block:
        sizes.append(len(data))
        return real(data, line0)

    monkeypatch.setattr(bal_io, "CHUNK_BYTES", 4096)
    monkeypatch.setattr(bal_io, "_Block", spy)
    back = read_bal(path)
    assert np.array_equal(back.observations, scene.problem.observations)
    assert len(sizes) > 10 and max(sizes) < 4096 + 100  # a block plus one line
    lines = path.read_text().splitlines()
    k = len(lines) - 200  # a point coordinate near the end
    lines[k] = "1.5e"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(BALFormatError, match="not a number: '1.5e'") as info:
        read_bal(path)
    assert info.value.line == k + 1


def test_format_fixed_and_quantize() -> None:
    from graphopt.io.bal import format_fixed, quantize

    x = np.array([-1.5, 0.0, -4e-7, 123456.7890004, 6e-7, -2.0, 9.9999996])
    text = format_fixed([np.array([0, 10, -3, 1, 2, 3, 40]), x], [0, 6]).decode()
    assert text.splitlines() == ["0 -1.500000", "10 0.000000", "-3 0.000000",
                                 "1 123456.789000", "2 0.000001", "3 -2.000000",
                                 "40 10.000000"]
    q = quantize(x, 6)
    assert np.array_equal(np.array([float(v.split()[1]) for v in text.splitlines()]), q)
    with pytest.raises(ValueError, match="too large"):
        format_fixed([np.array([1e300])], [6])


def test_bal_writer_streams_atomically(tmp_path: Path) -> None:
    from graphopt.io.bal import BALWriter, quantize

    scene = synthetic_scene(num_cameras=4, num_points=60, seed=6)
    p = scene.problem
    path = tmp_path / "w.txt.gz"
    with BALWriter(path, p.num_cameras, p.num_points, p.num_observations) as w:
        half = p.num_observations // 2
        for sl in (slice(0, half), slice(half, None)):
            w.observations(p.camera_index[sl], p.point_index[sl], p.observations[sl])
        w.cameras(p.cameras)
        w.points(p.points[:10])
        w.points(p.points[10:])
        assert not path.exists()  # only complete files appear
    back = read_bal(path)
    assert np.array_equal(back.observations, quantize(p.observations, 6))
    assert np.array_equal(back.points, quantize(p.points, 6))
    assert np.array_equal(back.cameras, p.cameras)  # 17 significant digits: exact
    assert np.array_equal(back.point_index, p.point_index)
    # Wrong counts or order: an error, and the old file stays.
    with pytest.raises(ValueError, match="header announces"), \
            BALWriter(path, p.num_cameras, p.num_points, p.num_observations) as w:
        w.cameras(p.cameras)
    with pytest.raises(ValueError, match="then cameras"), \
            BALWriter(path, p.num_cameras, p.num_points, p.num_observations) as w:
        w.cameras(p.cameras)
        w.observations(p.camera_index, p.point_index, p.observations)
    assert np.array_equal(read_bal(path).observations, back.observations)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["w.txt.gz"]
