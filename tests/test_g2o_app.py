"""graphopt-g2o: the generated Manhattan world, g2o's chi2 on the real files, outputs and errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_slam_graph import DATA, G2O_GUESS_VICTORIA, G2O_INITIAL, G2O_LM

from graphopt import StopReason
from graphopt.apps import _cli, g2o
from graphopt.apps.g2o import main
from graphopt.io.g2o import read_graph

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"data folder {DATA} is absent")

#: The summary's keys (``--json``), always all present (``None`` where they do not apply).
KEYS = {
    "input", "vertices", "edges", "vertex_types", "edge_types", "loop_closures", "fixed",
    "guessed", "skipped", "notes", "algorithm", "lm_schedule", "solver", "solver_requested",
    "robust_kernel",
    "initial_chi2", "final_chi2", "initial_robust_chi2", "final_robust_chi2", "iterations",
    "seconds", "seconds_per_iteration", "read_seconds", "build_seconds",
    "setup_seconds", "stop_reason", "ground_truth", "marginals", "output", "equiv", "online",
}
MARGINAL_KEYS = {"poses", "free_poses", "sampled", "max_position_sigma",
                 "max_position_sigma_vertex", "median_position_sigma", "max_rotation_sigma_rad",
                 "seconds"}


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def _summary(args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
             ) -> tuple[dict, str, str]:
    js = tmp_path / "summary.json"
    code, out, err = _run([*args, "--json", js], capsys)
    assert code == 0, err
    return json.loads(js.read_text()), out, err


def _one_error_line(err: str, pattern: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("graphopt-g2o: error: ")
    assert pattern in lines[0], lines[0]
    assert "Traceback" not in err


# --- the generated graph ---------------------------------------------------------------------


def test_generated_run_reports_truth_and_g2o_lines(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    s, out, err = _summary(["--poses", "150"], tmp_path, capsys)
    assert set(s) == KEYS
    assert s["input"] == "generated Manhattan world (150 poses, seed 0)"
    assert s["vertex_types"] == {"VERTEX_SE2": 150} and s["vertices"] == 150
    assert s["edges"] == s["edge_types"]["EDGE_SE2"] == 149 + s["loop_closures"]
    assert s["fixed"] == {"0": "FIX line"} and s["algorithm"] == "lm"
    assert s["solver_requested"] == "auto" and s["solver"] in ("dense", "cholmod", "scipy")
    assert s["final_chi2"] < min(0.1 * s["initial_chi2"], 2 * 3 * s["edges"])  # ~ dof at best
    assert s["initial_robust_chi2"] == pytest.approx(s["initial_chi2"])  # no kernel
    g0, g = s["ground_truth"]["initial"], s["ground_truth"]["final"]
    assert g["rms_position"] < 0.2 * g0["rms_position"] and g["rms_position"] < 0.1
    assert g["rms_heading"] < g0["rms_heading"]
    assert s["marginals"] is None and s["output"] is None
    assert 0 < s["iterations"] <= 20
    assert s["seconds_per_iteration"] == pytest.approx(s["seconds"] / s["iterations"])
    assert err.count("iteration= ") == s["iterations"]
    # g2o's iteration lines on stderr, the notes and the summary on stdout, each note once.
    assert err.startswith("iteration= 0\t chi2= ") and "\t levenbergIter= " in err
    assert out.count("note: Manhattan world: 150 poses") == 1
    assert "vs ground truth (first pose aligned): position RMS" in out
    assert f"linear solver {s['solver']}" in out


def test_quiet_prints_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["--poses", "30", "--quiet", "-i", "3"], capsys) == (0, "", "")


@pytest.mark.parametrize("options", [["--algorithm", "gn"], ["--algorithm", "dogleg"],
                                     ["--solver", "pcg"], ["--solver", "cholmod"],
                                     ["--guess"]])
def test_algorithms_solvers_guess(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                  options: list[str]) -> None:
    s, _, _ = _summary(["--poses", "80", "--quiet", "-i", "30", *options], tmp_path, capsys)
    assert s["final_chi2"] < min(s["initial_chi2"], 2 * 3 * s["edges"])
    assert s["ground_truth"]["final"]["rms_position"] < 0.1
    if options[0] == "--solver":
        assert s["solver"] == options[1] or (options[1] == "cholmod" and s["solver"] == "scipy")
    if options == ["--guess"]:
        assert s["guessed"] == 79


def test_robust_kernel(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s, out, _ = _summary(["--poses", "60", "--robust-kernel", "huber", "--robust-delta", "2"],
                         tmp_path, capsys)
    assert s["robust_kernel"] == "huber:2"
    assert s["initial_robust_chi2"] < s["initial_chi2"]  # Huber down-weights large errors
    assert "robust kernel huber:2" in out and "with the kernel" in out
    code, _, err = _run(["--robust-kernel", "nope"], capsys)
    assert code == 1
    _one_error_line(err, "unknown robust kernel 'nope'")


def test_cholmod_fallback_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import graphopt.solvers as solvers

    monkeypatch.setattr(solvers, "CHOLMOD_AVAILABLE", False)
    monkeypatch.setattr(solvers, "_warned", False)
    monkeypatch.setattr(_cli, "CHOLMOD_AVAILABLE", False)
    s, out, err = _summary(["--poses", "40", "--solver", "cholmod", "-i", "2"], tmp_path, capsys)
    assert s["solver"] == "scipy"
    assert "linear solver scipy (CHOLMOD's fallback: scikit-sparse is not installed)" in out
    assert "Warning" not in err


def test_marginals_all_and_sampled(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    s, out, _ = _summary(["--poses", "40", "--marginals"], tmp_path, capsys)
    m = s["marginals"]
    assert set(m) == MARGINAL_KEYS
    assert m["poses"] == m["free_poses"] == 39 and not m["sampled"]
    assert 0 < m["median_position_sigma"] <= m["max_position_sigma"] < 1
    assert 0 < m["max_rotation_sigma_rad"] < 0.1
    assert "largest position sigma" in out
    monkeypatch.setattr(g2o, "MARGINALS_MAX", 7)
    s, out, _ = _summary(["--poses", "40", "--marginals", "--quiet"], tmp_path, capsys)
    assert s["marginals"]["poses"] == 7 and s["marginals"]["sampled"]


# --- the real data ---------------------------------------------------------------------------


@needs_data
@pytest.mark.parametrize("name", sorted(G2O_LM))
def test_real_files_reach_g2os_chi2(name: str, tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    guess = ["--guess"] if name.startswith("victoria") else []
    s, out, _ = _summary([DATA / name, "-i", "100", "--function-tolerance", "1e-10", *guess],
                         tmp_path, capsys)
    assert set(s) == KEYS
    assert s["final_chi2"] == pytest.approx(G2O_LM[name], rel=1e-6)
    assert s["initial_chi2"] == pytest.approx(G2O_INITIAL.get(name, G2O_GUESS_VICTORIA),
                                              rel=1e-9)
    assert StopReason(s["stop_reason"]).converged and s["ground_truth"] is None
    assert s["fixed"] == {"0": "first pose fixed for the gauge"}
    assert out.count("note: vertex 0 fixed: first pose fixed for the gauge") == 1


@needs_data
def test_real_file_counts_and_notes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s, out, _ = _summary([DATA / "victoriaPark_reduced_1k.g2o", "--guess", "-i", "1"],
                         tmp_path, capsys)
    assert s["vertex_types"] == {"VERTEX_SE2": 1000, "VERTEX_XY": 48}
    assert s["edge_types"] == {"EDGE_SE2": 999, "EDGE_SE2_XY": 606}
    assert s["guessed"] == 1047 and s["loop_closures"] == 0
    assert "1047 estimated by --guess" in out and "note: LANDMARK2 (GTSAM" in out
    s, out, _ = _summary([DATA / "w100.graph", "-i", "1"], tmp_path, capsys)
    assert s["equiv"] == 40 and s["loop_closures"] == 300 - 99
    assert out.count("note: EDGE2 information read in TORO's") == 1


@needs_data
@pytest.mark.parametrize("name", ["w100.graph", "known_landmark_localization_20.g2o"])
def test_output_round_trip(name: str, tmp_path: Path,
                           capsys: pytest.CaptureFixture[str]) -> None:
    written = tmp_path / "out.g2o"
    s, out, _ = _summary([DATA / name, "-i", "5", "-o", written], tmp_path, capsys)
    assert s["output"] == str(written) and f"wrote {written}" in out
    assert "EQUIV" not in written.read_text()
    if name == "w100.graph":
        assert "(without the 40 EQUIV pairs: g2o has no such line)" in out
    again, _, _ = _summary([written, "-i", "0", "--quiet"], tmp_path, capsys)
    # 3D: VertexSE3 lets a rotation drift up to 1e-5 from orthonormal before re-normalising it
    # (here 2e-6); the written quaternion is of the nearest rotation, which moves chi2 by ~1e-5.
    assert again["initial_chi2"] == pytest.approx(s["final_chi2"],
                                                  rel=1e-9 if name == "w100.graph" else 1e-4)
    assert again["vertex_types"] == s["vertex_types"]
    assert again["edge_types"] == s["edge_types"]
    assert list(again["fixed"]) == ["0"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.g2o", "summary.json"]


# --- outputs ---------------------------------------------------------------------------------


def _colour_pixels(png: Path, bgr: tuple[int, int, int]) -> int:
    """Pixels within 40 (per channel) of a colour: lines are anti-aliased."""
    import cv2

    image = cv2.imread(str(png)).astype(int)
    return int((np.abs(image - np.array(bgr)).max(axis=2) <= 40).sum())


def test_png_before_after(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from graphopt.apps import g2o_report

    png = tmp_path / "g.png"
    code, _, err = _run(["--poses", "120", "--quiet", "--png", png], capsys)
    assert code == 0, err
    import cv2

    assert cv2.imread(str(png)).shape == (g2o_report._HEAD + g2o_report._PANEL,
                                          2 * g2o_report._PANEL, 3)
    assert png.stat().st_size > 20_000
    assert _colour_pixels(png, g2o_report._BEFORE) > 300
    assert _colour_pixels(png, g2o_report._AFTER) > 300
    assert _colour_pixels(png, g2o_report._TRUTH) > 300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.png"]


@needs_data
def test_png_3d_with_landmarks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from graphopt.apps import g2o_report

    png = tmp_path / "k.png"
    code, _, err = _run([DATA / "known_landmark_localization_20.g2o", "--quiet", "--png", png],
                        capsys)
    assert code == 0, err
    assert _colour_pixels(png, g2o_report._BEFORE) > 100
    assert _colour_pixels(png, g2o_report._AFTER) > 100


def test_rrd_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rerun")
    rrd = tmp_path / "g.rrd"
    s, _, _ = _summary(["--poses", "60", "--quiet", "--rrd", rrd], tmp_path, capsys)
    assert rrd.stat().st_size > 10_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.rrd", "summary.json"]
    rerun = Path(sys.executable).parent / "rerun"
    if rerun.exists():
        res = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True,
                             text=True, timeout=120, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        for entity in ("/world/after/trajectory", "/world/before/trajectory",
                       "/world/truth/trajectory", "/world/after/loop_closures",
                       "/metrics/log10_chi2", "/summary"):
            assert entity in res.stdout, entity  # the layout: tests/test_recording.py


# --- errors ----------------------------------------------------------------------------------


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


EDGE = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
VERTICES = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.1 0 0\n"


def test_missing_file(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code, out, err = _run([tmp_path / "nope.g2o"], capsys)
    assert code == 1 and out == ""
    _one_error_line(err, f"{tmp_path / 'nope.g2o'}: file not found")


def test_unknown_tags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, "u.g2o", VERTICES + "FOO 1 2\n" + EDGE + "BAR\nFOO 3\n")
    code, out, err = _run([path], capsys)
    assert code == 1 and out == ""
    _one_error_line(err, f"{path}:3: unknown tag 'FOO'")
    s, out, _ = _summary([path, "--skip-unknown"], tmp_path, capsys)
    assert s["skipped"] == {"BAR": 1, "FOO": 2}
    assert "skipped lines with unknown tags: BAR 1, FOO 2" in out
    assert s["final_chi2"] < 1e-12 and s["edges"] == 1


@pytest.mark.parametrize(("text", "line", "what"), [
    (VERTICES.replace("1.1 0 0", "1.1 x 0") + EDGE, 2, "not a number: 'x'"),
    (VERTICES + "EDGE_SE2 0 1 1 0\n", 3, "EDGE_SE2 needs 11 values"),
    (VERTICES + EDGE.replace(" 1\n", " -1\n"), 3, "not positive definite"),
    (VERTICES + "VERTEX_SE2 1 0 0 0\n" + EDGE, 3, "duplicate VERTEX_SE2 id 1"),
])
def test_malformed_line_names_file_and_line(text: str, line: int, what: str, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, "bad.g2o", text)
    code, out, err = _run([path], capsys)
    assert code == 1 and out == ""
    _one_error_line(err, f"{path}:{line}: ")
    assert what in err


def test_edges_only_needs_guess(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, "e.g2o", EDGE + EDGE.replace("0 1 1", "1 2 1"))
    code, _, err = _run([path], capsys)
    assert code == 1
    _one_error_line(err, f"{path}:1: EDGE_SE2 names vertex 0, which has no vertex line (use "
                         "--guess")
    s, out, _ = _summary([path, "--guess"], tmp_path, capsys)
    assert s["guessed"] == 2 and s["final_chi2"] < 1e-12
    assert "note: vertex 0 fixed: first pose fixed for the gauge" in out


def test_outputs_are_checked_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    path = _write(tmp_path, "g.g2o", VERTICES + EDGE)
    code, out, err = _run([path, "-o", path], capsys)
    assert code == 1 and out == ""
    _one_error_line(err, f"-o {path}: refusing to overwrite the input")
    code, _, err = _run([path, "--png", tmp_path / "no" / "x.png"], capsys)
    _one_error_line(err, "--png")
    assert code == 1 and "does not exist" in err
    code, _, err = _run([path, "--json", tmp_path], capsys)
    _one_error_line(err, "is a directory")
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = g2o._cli.os.access
    monkeypatch.setattr(g2o._cli.os, "access",
                        lambda p, mode: Path(p) != locked and real_access(p, mode))
    # The input does not exist: the output is refused first, before anything is read.
    code, out, err = _run([tmp_path / "absent.g2o", "-o", locked / "x.g2o"], capsys)
    assert code == 1 and out == ""
    _one_error_line(err, f"-o {locked / 'x.g2o'}: folder {locked} is not writable")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.g2o", "locked"]


def test_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    for args, message in ((["-i", "-1"], "--iterations must be >= 0"),
                          (["--robust-delta", "0"], "--robust-delta must be positive"),
                          (["--poses", "1"], "--poses must be >= 2")):
        code, _, err = _run(args, capsys)
        assert code == 1
        _one_error_line(err, message)
    with pytest.raises(SystemExit) as info:
        main(["--algorithm", "newton"])
    assert info.value.code == 2
    _one_error_line(capsys.readouterr().err, "invalid choice: 'newton'")


@needs_data
def test_module_entry_point(tmp_path: Path) -> None:
    src = tmp_path / "pose2example.txt"
    shutil.copy(DATA / "pose2example.txt", src)
    res = subprocess.run([sys.executable, "-P", "-m", "graphopt.apps.g2o", str(src), "-o",
                          str(tmp_path / "o.g2o")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "graphopt-g2o: " in res.stdout and "iteration= 0" in res.stderr
    assert len(read_graph(tmp_path / "o.g2o").vertices["VERTEX_SE2"].ids) == 11
