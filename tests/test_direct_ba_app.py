"""graphopt-direct-ba: the task's real data, the synthetic scene and the command line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from graphopt.apps import direct_ba
from graphopt.apps.direct_ba import main
from graphopt.apps.direct_ba_problem import build_problem
from graphopt.apps.direct_ba_report import truth_report
from graphopt.apps.direct_ba_scene import synthetic_scene
from graphopt.io.directba import load_directba

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "directba"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"real data not found at {REAL}")

#: Synthetic test scene: 5 frames, 1000 points, 640x480; perturbation 1° and 3 cm per pose
#: (poses 1-4; pose 0 fixes the gauge), 2 cm per point axis.
SCENE = {"n_frames": 5, "n_points": 1000, "seed": 1}
#: Accepted residual pose error as a fraction of the perturbation (measured: rotation 1-2 %,
#: scale-aligned translation 2-4 %, raw translation 2-12 %: the inverse-depth start carries a
#: small scale bias, and scale is a free gauge direction of monocular BA).
ROT_FRACTION = 0.05
TRANS_ALIGNED_FRACTION = 0.05
TRANS_RAW_FRACTION = 0.15


@pytest.fixture(scope="module")
def real_data():
    if not REAL.is_dir():
        pytest.skip(f"real data not found at {REAL}")
    return load_directba(REAL)


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(**SCENE)


@needs_real
def test_real_data_task_numbers(real_data) -> None:
    """28826 edges, ~24460 active, chi2 ≈ 1.875e6, monotone under LM, −20 % in 40 iterations."""
    problem = build_problem(real_data, "xyz", "huber", 0.5, "cholmod", "lm")
    opt = problem.optimizer
    assert problem.n_edges == 28826 == opt.num_edges()
    opt.compute_active_errors()
    assert abs(opt.active_edge_count() - 24460) <= 50
    initial = opt.active_robust_chi2()
    assert initial == pytest.approx(1.875e6, rel=2e-3)
    seen: list[float] = []
    opt.add_callback("post_iteration", lambda o, info: seen.append(info.chi2))
    res = opt.optimize(40)
    assert res.initial_chi2 == pytest.approx(initial)
    hist = [res.initial_chi2, *seen]
    assert all(b <= a for a, b in zip(hist, hist[1:], strict=False)), "chi2 increased"
    assert res.final_chi2 <= 0.8 * res.initial_chi2
    assert np.isfinite(problem.points()).all() and np.isfinite(problem.poses()).all()
    # The gauge pose did not move.
    np.testing.assert_array_equal(problem.poses()[0], real_data.poses[0])


@needs_real
def test_real_data_inverse_depth_same_start(real_data) -> None:
    """Inverse depth describes the same geometry: the same edges and initial chi2; LM monotone."""
    problem = build_problem(real_data, "inverse-depth", "huber", 0.5)
    opt = problem.optimizer
    assert problem.n_edges == 28826 and problem.dropped_points == 0
    opt.compute_active_errors()
    assert abs(opt.active_edge_count() - 24460) <= 50
    assert opt.active_robust_chi2() == pytest.approx(1.875e6, rel=2e-3)
    np.testing.assert_allclose(problem.points(), real_data.points, atol=1e-9)
    res = opt.optimize(8)
    hist = [res.initial_chi2, *res.chi2_history]
    assert all(b <= a for a, b in zip(hist, hist[1:], strict=False))
    assert res.final_chi2 < res.initial_chi2


@pytest.mark.parametrize("parametrization", ["xyz", "inverse-depth"])
def test_synthetic_scene_recovers_poses(scene, parametrization: str) -> None:
    problem = build_problem(scene, parametrization, "huber", 0.5)
    res = problem.optimizer.optimize(40)
    assert res.final_chi2 < 0.05 * res.initial_chi2
    rep = truth_report(problem)
    assert rep["initial_rotation_error_deg_mean"] == pytest.approx(1.0)
    assert rep["initial_translation_error_m_mean"] == pytest.approx(0.03, rel=0.01)
    assert rep["final_rotation_error_deg_mean"] < ROT_FRACTION * 1.0
    assert rep["final_translation_error_scale_aligned_m_mean"] < TRANS_ALIGNED_FRACTION * 0.03
    assert rep["final_translation_error_m_mean"] < TRANS_RAW_FRACTION * 0.03
    assert rep["final_point_error_m_median"] < rep["initial_point_error_m_median"]


@needs_real
def test_cli_outputs(tmp_path: Path, capsys) -> None:
    js, png, rrd = tmp_path / "out.json", tmp_path / "out.png", tmp_path / "out.rrd"
    js.write_text("old")
    code = main([str(REAL), "--iterations", "3", "--json", str(js), "--png", str(png),
                 "--rrd", str(rrd)])
    assert code == 0
    out = capsys.readouterr().out
    assert "iteration= 0" in out and "chi2=" in out and "edges= " in out
    summary = json.loads(js.read_text())
    for key in ("edges", "active_edges", "initial_chi2", "final_chi2", "iterations", "seconds",
                "seconds_per_iteration"):
        assert key in summary
    assert summary["edges"] == 28826 and summary["iterations"] == 3
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert rrd.stat().st_size > 100_000  # frusta with images
    assert not list(tmp_path.glob(".*.tmp"))


def test_cli_synthetic_quiet_json(tmp_path: Path, monkeypatch, capsys) -> None:
    small = {"n_frames": 3, "n_points": 300, "size": (320, 240), "seed": 2,
             "intrinsics": (140.0, 145.0, 160.0, 120.0)}
    monkeypatch.setattr(direct_ba, "SYNTHETIC", small)
    js, png = tmp_path / "s.json", tmp_path / "s.png"
    assert main(["--iterations", "5", "--quiet", "--json", str(js), "--png", str(png),
                 "--parametrization", "inverse-depth", "--patch", "6"]) == 0
    assert capsys.readouterr().out == ""
    summary = json.loads(js.read_text())
    assert summary["patch"] == 6 and summary["edges"] == 900
    assert "final_rotation_error_deg_mean" in summary
    # The shifts are far below a pixel: they are drawn as magnified arrows (camera arrows in
    # (0, 120, 0) BGR, thick enough to count), beside a scale bar.
    import cv2

    img = cv2.imread(str(png))
    assert int(np.all(img == (0, 120, 0), axis=2).sum()) > 100


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["/nonexistent/folder"], "data folder not found"),
        (["{real}", "--patch", "6"], "4x4 patches"),
        (["{real}", "--json", "/nonexistent/dir/x.json"], "does not exist"),
        (["{real}", "--robust", "bogus"], "unknown robust kernel"),
        (["{real}", "--robust-delta", "-1"], "robust-delta"),
    ],
)
def test_cli_errors_one_line(tmp_path: Path, capsys, argv: list[str], match: str) -> None:
    if any("{real}" in a for a in argv) and not REAL.is_dir():
        pytest.skip("real data not found")
    js = tmp_path / "keep.json"
    js.write_text("old")
    argv = [a.replace("{real}", str(REAL)) for a in argv] + (
        [] if "--json" in argv else ["--json", str(js)])
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1 and "Traceback" not in err
    assert js.read_text() == "old"  # untouched on failure


def test_cli_missing_image(tmp_path: Path, capsys) -> None:
    import cv2

    root = tmp_path / "d"
    root.mkdir()
    (root / "poses.txt").write_text("0 0 0 0 0 0 0 1\n0 0.1 0 0 0 0 0 1\n")
    (root / "points.txt").write_text("0 0 3 " + " ".join(["100"] * 16) + "\n")
    cv2.imwrite(str(root / "0.png"), np.zeros((48, 64), np.uint8))
    assert main([str(root)]) == 1
    err = capsys.readouterr().err
    assert "1.png: image not found" in err and "Traceback" not in err


def test_usage_error_and_module_entry() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--parametrization", "polar"])
    assert exc.value.code == 2
    out = subprocess.run([sys.executable, "-m", "graphopt.apps.direct_ba", "--help"],
                         capture_output=True, text=True, cwd="/tmp", check=True).stdout
    for opt in ("--iterations", "--robust", "--robust-delta", "--parametrization", "--patch",
                "--solver", "--rrd", "--png", "--json", "--quiet"):
        assert opt in out
