"""The city-scale BAL generator (``graphopt-bal-city``): exact counts, determinism, local
co-visibility, ground truth, the written file read back, and ``graphopt-bal``'s progress lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

import graphopt.apps.bal as bal_app
from graphopt.apps import bal_city
from graphopt.apps.bal_city import (
    FINAL_13682,
    CityConfig,
    city_scene,
    co_visibility,
    preset,
    write_city,
)
from graphopt.io.bal import read_bal
from graphopt.types.bal import bal_project

SMALL = CityConfig(cameras=300, points=8000, observations=52000, seed=3)


@pytest.fixture(scope="module")
def scene() -> bal_city.CityScene:
    return city_scene(SMALL)


def test_counts_are_exact_and_tracks_bounded(scene: bal_city.CityScene) -> None:
    p = scene.problem
    assert (p.num_cameras, p.num_points, p.num_observations) == (300, 8000, 52000)
    track = np.bincount(p.point_index, minlength=p.num_points)
    assert track.min() >= 2 and track.max() <= SMALL.max_track
    assert track.sum() == 52000
    per_camera = np.bincount(p.camera_index, minlength=p.num_cameras)
    assert per_camera.min() >= 20  # every camera is constrained
    # Observations come by point, then camera, with no camera twice on a point.
    key = p.point_index * p.num_cameras + p.camera_index
    assert np.all(np.diff(key) > 0)


def test_deterministic_for_a_seed(scene: bal_city.CityScene) -> None:
    again = city_scene(SMALL)
    other = city_scene(CityConfig(cameras=300, points=8000, observations=52000, seed=4))
    for name in ("cameras", "points", "observations", "camera_index", "point_index"):
        assert np.array_equal(getattr(again.problem, name), getattr(scene.problem, name)), name
    assert np.array_equal(again.truth.points, scene.truth.points)
    assert not np.array_equal(other.problem.observations[:100], scene.problem.observations[:100])


def test_co_visibility_is_local(scene: bal_city.CityScene) -> None:
    p = scene.problem
    cov = co_visibility(p.num_cameras, p.camera_index, p.point_index)
    # Consecutive cameras along the path, plus a few on other passes: far fewer than all.
    assert np.median(cov) >= 2 * (SMALL.max_track - 1) - 2
    assert cov.max() <= 60 < p.num_cameras - 1
    # Revisits: some tracks jump along the path (another pass through the same place).
    jumps = (np.diff(p.camera_index) > SMALL.max_track) & (np.diff(p.point_index) == 0)
    assert 0.01 < jumps.sum() / p.num_points < SMALL.revisit
    # Against the definition, with a chunked pass that splits no point.
    inc = sp.csr_matrix((np.ones(p.num_observations), (p.point_index, p.camera_index)))
    ref = (inc.T @ inc).astype(bool)
    np.testing.assert_array_equal(co_visibility(p.num_cameras, p.camera_index, p.point_index,
                                                chunk=999), np.diff(ref.indptr) - 1)
    np.testing.assert_array_equal(cov, np.diff(ref.indptr) - 1)


def test_ground_truth_reprojects_to_the_noise_free_observations(scene: bal_city.CityScene
                                                                ) -> None:
    t, p = scene.truth, scene.problem
    uv, pz = bal_project(t.cameras[t.camera_index], t.points[t.point_index])
    np.testing.assert_array_equal(uv, t.observations)
    assert pz.max() < -1.0  # in front of every camera that sees it
    assert np.abs(uv).max() < SMALL.half_image  # inside every image
    noise = p.observations - t.observations
    np.testing.assert_allclose(noise.std(), SMALL.pixel_sigma, rtol=0.03)
    assert abs(noise.mean()) < 0.02
    np.testing.assert_allclose((p.points - t.points).std(), SMALL.point_sigma, rtol=0.05)
    # Initial cameras: the truth perturbed (small rotations and moves), intrinsics kept.
    moved = np.linalg.norm(p.camera_centers() - t.camera_centers(), axis=1)
    assert 0 < moved.max() < 0.15
    turned = np.linalg.norm(p.cameras[:, :3] - t.cameras[:, :3], axis=1)
    assert 0 < turned.max() < 0.01
    np.testing.assert_array_equal(p.cameras[:, 6:], t.cameras[:, 6:])
    # Points lie on the ground, the façades and up to the roofs (30 m); cameras at 1.6 m.
    assert t.points[:, 2].min() > -1e-9 and t.points[:, 2].max() <= 30.0
    np.testing.assert_allclose(t.camera_centers()[:, 2], 1.6, atol=0.3)


@pytest.mark.parametrize("suffix", [".txt", ".txt.gz", ".txt.bz2"])
def test_written_file_reads_back_exactly(tmp_path: Path, scene: bal_city.CityScene,
                                         suffix: str) -> None:
    out, truth = tmp_path / f"c{suffix}", tmp_path / "truth.txt"
    seen: list[int] = []
    stats = write_city(str(out), SMALL, truth=str(truth), progress=seen.append)
    back = read_bal(out)
    for name in ("cameras", "points", "observations", "camera_index", "point_index"):
        assert np.array_equal(getattr(back, name), getattr(scene.problem, name)), name
    t = read_bal(truth)
    np.testing.assert_array_equal(t.cameras, scene.truth.cameras)
    np.testing.assert_allclose(t.points, scene.truth.points, rtol=0, atol=1e-9)
    np.testing.assert_allclose(t.observations, scene.truth.observations, rtol=0, atol=1e-9)
    assert seen[-1] == SMALL.observations
    per = np.bincount(scene.problem.camera_index)
    assert stats.per_camera == (per.min(), int(np.median(per)), per.max())
    assert sorted(x.name for x in tmp_path.iterdir()) == sorted([out.name, truth.name])


def test_presets_scale_final_13682() -> None:
    assert (lambda c: (c.cameras, c.points, c.observations))(preset("29M")) == FINAL_13682
    c = preset("1M")
    assert c.observations == 1_000_000
    assert abs(c.observations / c.points - FINAL_13682[2] / FINAL_13682[1]) < 1e-3
    assert abs(c.observations / c.cameras - FINAL_13682[2] / FINAL_13682[0]) < 5
    with pytest.raises(ValueError, match="between 6000"):
        CityConfig(cameras=50, points=3000, observations=5000).check()
    with pytest.raises(ValueError, match="max_track"):
        CityConfig(cameras=5, points=10, observations=30, max_track=12).check()


def test_cli_writes_and_reports_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "c.txt"
    assert bal_city.main([str(out), "--cameras", "40", "--points", "500", "--observations",
                          "3000", "--seed", "2"]) == 0
    text = capsys.readouterr().out
    assert "40 cameras, 500 points, 3,000 observations" in text
    assert read_bal(out).num_observations == 3000
    assert bal_city.main([str(out), "--cameras", "40"]) == 1
    assert "all three" in capsys.readouterr().err
    assert bal_city.main([str(out), "--cameras", "40", "--points", "500", "--observations",
                          "100"]) == 1
    assert "between 1000 and 6000" in capsys.readouterr().err
    assert bal_city.main([str(out), "--preset", "lots"]) == 1
    assert "--preset" in capsys.readouterr().err
    assert bal_city.main([str(tmp_path / "missing" / "c.txt"), "--cameras", "40", "--points",
                          "500", "--observations", "3000"]) == 1


def test_graphopt_bal_progress_lines(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture) -> None:
    """Slow loading and set-up steps say what they do and how long they took, one line each;
    quick ones (and --quiet runs) print nothing."""
    path = tmp_path / "c.txt"
    write_city(str(path), CityConfig(cameras=30, points=400, observations=2400, seed=1))
    argv = [str(path), "--iterations", "1"]
    assert bal_app.main(argv) == 0
    assert "reading" not in capsys.readouterr().err  # under PROGRESS_DELAY
    monkeypatch.setattr(bal_app, "PROGRESS_DELAY", 0.0)
    assert bal_app.main(argv) == 0
    err = capsys.readouterr().err.splitlines()
    steps = [x for x in err if x.startswith("graphopt-bal: ") and x.endswith(" s")]
    assert [x.split(" ...")[0] for x in steps] == [
        f"graphopt-bal: reading {path}", "graphopt-bal: initial cost",
        "graphopt-bal: building the graph (2,400 observations)",
        "graphopt-bal: set-up (structure, Schur complement plan, symbolic factorisation)"]
    assert bal_app.main([*argv, "--quiet"]) == 0
    assert capsys.readouterr().err == ""
