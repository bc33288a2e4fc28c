"""The apps' recordings: colour scale, outliers, summary, blueprint, the entities each app logs,
the step timeline, the size of a Dubrovnik-sized run, and the warnings' truth.

What the viewer shows of them is checked in a real browser by ``test_recording_browser.py``.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from graphopt import RobustKernelCauchy, RobustKernelHuber
from graphopt.recording_view import ErrorScale, error_colors, outlier_mask, summary_markdown

pytest.importorskip("rerun")

RERUN = Path(sys.executable).with_name("rerun")
DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DUBROVNIK = DATA / "bal" / "problem-16-22106-pre.txt.bz2"


def _print(rrd: Path, *flags: str) -> str:
    """``rerun rrd print`` of a recording."""
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    res = subprocess.run([str(RERUN), "rrd", "print", *flags, str(rrd)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    return res.stdout


def _entities(rrd: Path, column: str = "") -> dict[str, int]:
    """Entity path → rows logged (all chunks with a data column containing ``column``), from
    ``rerun rrd print``."""
    rows: dict[str, int] = {}
    for n, path, columns in re.findall(r"with (\d+) rows .* - (/\S*) - data columns: \[(.*)\]",
                                       _print(rrd)):
        if column in columns:
            rows[path] = rows.get(path, 0) + int(n)
    return rows


def _chunk_text(text: str, entity: str) -> str:
    """The ``-vvv`` print of the chunks of one entity."""
    return "".join(c for c in text.split("Chunk(") if f" - {entity} - " in c.split("\n")[0])


# --- colours, outliers, summary ------------------------------------------------------------


def test_error_colors_hit_the_stops_and_interpolate() -> None:
    c = error_colors([0.0, 1.0, 2.0, 3.0, 30.0, np.nan, 0.5], 3.0)
    assert c.dtype == np.uint8 and c.shape == (7, 3)
    assert c[0].tolist() == [40, 90, 220]  # blue
    assert c[1].tolist() == [30, 185, 160]  # teal
    assert c[2].tolist() == [240, 200, 40]  # yellow
    assert c[3].tolist() == [215, 35, 35] == c[4].tolist() == c[5].tolist()  # red and above
    assert c[6].tolist() == [35, 138, 190]  # half way from blue to teal


def test_error_scale_is_three_final_medians() -> None:
    s = ErrorScale.from_final([1.0, 2.0, 3.0, 100.0, np.nan, 0.0], "error", "px")
    assert s.top == pytest.approx(7.5)  # 3 × median(1, 2, 3, 100)
    assert "blue 0 px" in s.legend() and "red 7.5 px and above" in s.legend()
    assert ErrorScale.from_final([], "error").top == 1.0
    assert s.colors([7.5]).tolist() == [[215, 35, 35]]


def test_outliers_are_edges_downweighted_beyond_the_width() -> None:
    huber, cauchy = RobustKernelHuber(1.0), RobustKernelCauchy(2.0)
    s = np.array([0.5, 1.0, 1.5, 9.0, 3.0, 5.0, 100.0])
    group = SimpleNamespace(last_chi2=s, kernel_index=np.array([0, 0, 0, 0, 1, 1, -1]),
                            kernels=[huber, cauchy])
    assert outlier_mask(group).tolist() == [False, False, True, True, False, True, False]
    # For Huber the mask is exactly ρ' < 1.
    s = np.linspace(0.0, 10.0, 101)
    g = SimpleNamespace(last_chi2=s, kernel_index=np.zeros(101, int), kernels=[huber])
    assert (outlier_mask(g) == (huber.robustify(s)[1] < 1.0)).all()


def test_summary_markdown_has_a_table_and_notes() -> None:
    text = summary_markdown("app", [("input", "x"), ("chi2", "2 → 1")], ["**Colours**: …"])
    assert text.splitlines()[:5] == ["### app", "", "| input | x |", "|---|---|",
                                     "| chi2 | 2 → 1 |"]
    assert text.endswith("**Colours**: …\n")


# --- the Recorder ----------------------------------------------------------------------------


def test_recorder_step_timeline_cost_and_document(tmp_path: Path) -> None:
    from graphopt.recording import Recorder
    from graphopt.recording_view import run_blueprint

    path = tmp_path / "online.rrd"
    with Recorder(path) as rec:
        rec.send_blueprint(run_blueprint(timeline="step"))
        for step in range(2):
            rec.set_step(step)
            for it in range(3):
                rec.set_iteration(it)
                rec.log_trajectory(np.arange(9.0).reshape(3, 3) + step)
                rec.log_cost(10.0 ** (3 - it))
        rec.log_cost(0.0)  # no logarithm: only the plain series
        rec.log_document("# done")
    rows = _entities(path, "Scalars:scalars")
    assert rows["/metrics/chi2"] == 7 and rows["/metrics/log10_chi2"] == 6
    rows = _entities(path)
    assert rows["/world/trajectory"] == 6 and rows["/summary"] == 1
    text = _print(path, "-vvv")
    assert "index_name: step" in text and "index_name: iteration" in text
    logs = _chunk_text(text, "/metrics/log10_chi2")
    values = sorted(float(v) for v in re.findall(r"┆ \[(-?[\d.]+)\]\s+│", logs))
    assert values == [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]  # log10 of 1000, 100, 10 at both steps


# --- the apps' recordings --------------------------------------------------------------------


def test_bal_recording_layout_and_outliers(tmp_path: Path) -> None:
    from graphopt.apps import bal

    rrd = tmp_path / "bal.rrd"
    s = bal.run(bal.build_parser().parse_args(
        ["--robust", "huber", "--robust-delta", "1", "--rrd", str(rrd), "--quiet", "-i", "5"]))
    rows = _entities(rrd)
    for entity in ("/world/before/points", "/world/before/cameras", "/world/after/points",
                   "/world/after/cameras/0", "/world/after/outliers", "/metrics/log10_chi2",
                   "/metrics/iteration_seconds", "/summary"):
        assert entity in rows, entity
    assert rows["/world/after/outliers"] == 1  # at the last iteration
    scalars = _entities(rrd, "Scalars:scalars")
    assert scalars["/metrics/log10_chi2"] == s["iterations"] + 1
    assert scalars["/metrics/iteration_seconds"] == s["iterations"]
    text = _print(rrd, "-vvv")
    assert "[text/markdown]" in text and "[### graphopt-bal" in text
    for view in ("[3D]", "[TimeSeries]", "[TextDocument]"):
        assert view in text, view


def test_bal_summary_document_says_what_ran() -> None:
    from graphopt.apps.bal_report import recording_markdown

    s = {"input": "x.txt", "cameras": 3, "points": 7, "observations": 19, "algorithm": "lm",
         "lm_damping": "diagonal", "lm_schedule": "g2o", "solver_text": "dense (chosen by auto)",
         "robust_kernel": "huber:1", "stop_reason": "function_tolerance", "iterations": 4,
         "initial_chi2": 100.0, "final_chi2": 1.5, "initial_rms_px": 3.0, "rms_px": 0.25,
         "seconds": 0.5, "seconds_per_iteration": 0.125}
    rec = SimpleNamespace(shown=np.arange(7), outliers=2,
                          scale=ErrorScale(0.6, "per-point RMS reprojection error", "px"))
    text = recording_markdown("graphopt-bal", s, rec)
    for part in ("| algorithm | lm (g2o schedule, diagonal damping) |",
                 "| linear solver | dense (chosen by auto) |",
                 "| stop | function_tolerance after 4 iterations |", "| chi2 | 100 → 1.5 |",
                 "| RMS reprojection error | 3 px → 0.25 px |", "red 0.6 px and above",
                 "`world/after/outliers` (2 observations"):
        assert part in text, part


def test_point_rms_matches_the_observations() -> None:
    from graphopt.apps.bal_report import point_rms
    from graphopt.apps.bal_scene import synthetic_scene
    from graphopt.types.bal import reprojection_errors

    p = synthetic_scene(4, 30, seed=3).problem
    rms = point_rms(p, p.cameras, p.points)
    r, _ = reprojection_errors(p)
    for j in (0, 7, p.num_points - 1):
        mine = np.flatnonzero(p.point_index == j)
        assert rms[j] == pytest.approx(np.sqrt((r[mine] ** 2).sum() / len(mine)), rel=1e-12)


def test_g2o_recording_colours_closures_by_chi2(tmp_path: Path) -> None:
    from graphopt.apps import g2o

    rrd = tmp_path / "g.rrd"
    s = g2o.run(g2o.build_parser().parse_args(
        ["--poses", "60", "--quiet", "--rrd", str(rrd), "--robust-kernel", "huber",
         "--robust-delta", "0.5"]))
    rows = _entities(rrd)
    for entity in ("/world/before/trajectory", "/world/after/trajectory",
                   "/world/after/loop_closures", "/world/after/outliers",
                   "/world/truth/trajectory", "/summary"):
        assert entity in rows, entity
    # Positions at every logged iteration, then their colours at each of them.
    assert rows["/world/after/loop_closures"] == 2 * (s["iterations"] + 1)


def test_direct_ba_recording_has_the_images_and_patches(tmp_path: Path) -> None:
    from graphopt.apps import direct_ba

    rrd = tmp_path / "d.rrd"
    s = direct_ba.run(direct_ba.build_parser().parse_args(
        ["--rrd", str(rrd), "--quiet", "-i", "3"]))
    rows = _entities(rrd)
    for k in range(7):
        assert rows[f"/images/{k}/image"] == 1
        assert rows[f"/images/{k}/patches"] == 2 * (s["iterations"] + 1)
    assert "/world/after/points" in rows and "/world/before/points" in rows
    text = _print(rrd, "-vvv")
    # One view per image (in each blueprint sent: a second one hides many outliers).
    assert text.count("[2D]") % 7 == 0 and text.count("[2D]") // 7 == text.count("[3D]")


# --- size --------------------------------------------------------------------------------------


@pytest.mark.skipif(not DUBROVNIK.exists(), reason=f"{DUBROVNIK} not found (real data)")
def test_dubrovnik_recording_of_100_iterations_stays_under_50_mb(tmp_path: Path) -> None:
    """The worst case, every iteration moving every point visibly: the start and 10 iterations
    are recorded, and 100 iterations extrapolated from the bytes per iteration (the whole run
    takes 25 s here; it measured 39 MB, docs/recordings.md)."""
    from graphopt.apps.bal_report import BALRecording
    from graphopt.io.bal import read_bal

    p = read_bal(DUBROVNIK)
    rng = np.random.default_rng(0)
    done = SimpleNamespace(compute_active_errors=lambda: None, edge_groups=lambda: [])
    sizes = []
    for iterations in (0, 10):
        path = tmp_path / f"d{iterations}.rrd"
        rec = BALRecording(str(path), "test", p, 10.0)
        rec.log_start(p.cameras, p.points, 1e6)
        for it in range(1, iterations + 1):
            pts = p.points + rng.normal(0.0, 0.01, p.points.shape)
            rec.log_state(it, p.cameras, pts, 1e6 / it, 0.1)
        rec.finish(done, p.points)
        rec.close()
        assert len(rec.shown) == p.num_points  # every point
        sizes.append(path.stat().st_size)
    per_iteration = (sizes[1] - sizes[0]) / 10
    assert per_iteration > 12 * p.num_points  # at least the positions of every point
    assert sizes[0] + 100 * per_iteration < 50e6, f"{sizes}"


# --- what the apps say -------------------------------------------------------------------------


def test_stop_warning_fits_the_algorithm() -> None:
    from graphopt.apps.bal import stop_warning

    assert stop_warning("lm", "function_tolerance", 5) is None
    assert stop_warning("lm", "converged", 5) is None
    gn = stop_warning("gn", "singular", 1)
    assert gn.startswith("no step was possible: the normal equations are singular")
    assert "--algorithm lm or dogleg" in gn
    assert "not positive definite or the step made the cost non-finite" in stop_warning(
        "gn", "failed", 3)
    for reason in ("failed", "singular"):
        lm = stop_warning("lm", reason, 4)
        assert "--algorithm" not in lm and "--lm-damping identity" in lm
        assert lm.startswith("the run stopped at iteration 4 without a step")
        assert "--lm-damping" not in stop_warning("lm", reason, 4, "identity")
        assert "--algorithm" not in stop_warning("dogleg", reason, 1)


def test_bal_never_suggests_lm_to_an_lm_run(monkeypatch: pytest.MonkeyPatch,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    from graphopt.apps import _cli, bal

    real = _cli.optimize_recorded

    def singular(opt, iterations, recording):  # type: ignore[no-untyped-def]
        res = real(opt, 1, recording)
        res.stop_reason = "singular"
        return res

    monkeypatch.setattr(_cli, "optimize_recorded", singular)
    assert bal.main(["--algorithm", "lm"]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "--algorithm lm" not in err
    assert bal.main(["--algorithm", "gn"]) == 0
    assert "use --algorithm lm or dogleg" in capsys.readouterr().err


def test_the_browser_check_sees_a_blank_view_as_blank() -> None:
    from browser_viewer import ViewerResult

    image = np.full((100, 200, 3), 240, np.uint8)  # the viewer's light grey background
    image[40:60, :] = (90, 90, 90)  # grid lines and text are grey too
    res = ViewerResult([], [], [], Path("x.png"), image)
    assert res.colourful_fraction((0.0, 0.0, 1.0, 1.0)) == 0.0
    image[10:20, 100:110] = (215, 35, 35)  # 100 red pixels of the error colours
    assert res.colourful_fraction((0.5, 0.0, 1.0, 1.0)) == pytest.approx(100 / 10_000)


def test_slam_recording_of_an_online_run_uses_the_step_timeline(tmp_path: Path) -> None:
    from graphopt import SparseOptimizer
    from graphopt.apps.g2o_report import SlamRecording, graph_view
    from graphopt.apps.slam_scene import manhattan_world
    from graphopt.types.slam_graph import build_graph

    graph, _ = manhattan_world(40, 0)
    slam = build_graph(graph, SparseOptimizer(algorithm="lm"))
    opt = slam.optimizer
    rrd = tmp_path / "online.rrd"
    rec = SlamRecording(str(rrd), "graphopt-g2o", graph_view(slam), timeline="step")
    for step in range(2):
        rec.relayout(graph_view(slam))  # an online run does this when the graph grew
        opt.compute_active_errors()
        rec.log_state(0, opt.active_robust_chi2(), step=step)
        for it in range(1, 3):
            res = opt.optimize(1)
            rec.log_state(it, res.final_chi2, seconds=res.seconds, step=step)
    opt.compute_active_errors()
    rec.finish()
    rec.close()
    rows = _entities(rrd, "LineStrips3D:strips")
    assert rows["/world/after/trajectory"] == 6  # 2 steps x 3 states
    assert _entities(rrd, "LineStrips3D:colors")["/world/after/trajectory"] == 6
    text = _print(rrd, "-vvv")
    assert "index_name: step" in text
    assert "[step]" in text  # the time panel's timeline
