"""The generated Manhattan world and the trajectory error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from graphopt.apps.slam_scene import manhattan_world, trajectory_error
from graphopt.io.g2o import read_graph, write_g2o


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ b`` for SE2 poses, written out independently of the module."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    dt = np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], dt])


@pytest.fixture(scope="module")
def world() -> tuple:
    return manhattan_world(2000, seed=7)


def test_deterministic_for_a_seed() -> None:
    (a, ta), (b, tb) = manhattan_world(300, seed=3), manhattan_world(300, seed=3)
    assert np.array_equal(ta, tb)
    for name in ("ids", "measurements", "information"):
        assert np.array_equal(getattr(a.edges["EDGE_SE2"], name),
                              getattr(b.edges["EDGE_SE2"], name))
    assert np.array_equal(a.vertices["VERTEX_SE2"].values, b.vertices["VERTEX_SE2"].values)
    _, tc = manhattan_world(300, seed=4)
    assert not np.array_equal(ta, tc)


def test_truth_walks_the_grid(world: tuple) -> None:
    graph, truth = world
    assert truth.shape == (2000, 3)
    assert np.array_equal(truth[:, :2], np.round(truth[:, :2]))
    steps = np.abs(np.diff(truth[:, :2], axis=0)).sum(1)
    assert (steps == 1).all()  # unit steps along the grid
    quarter = truth[:, 2] / (np.pi / 2)
    assert np.allclose(quarter, np.round(quarter)) and (np.abs(truth[:, 2]) <= np.pi).all()
    turns = np.round(np.diff(quarter)) % 4
    assert set(turns.tolist()) <= {0, 1, 3}  # never a U-turn in one step
    assert 0.2 < np.mean(turns != 0) < 0.5  # turn_probability 0.3, plus the walls
    side = max(4, round(np.sqrt(2000 / 10)))
    assert truth[:, :2].min() >= 0 and truth[:, :2].max() <= side
    assert graph.fixed.tolist() == [0] and graph.path == "<generated>"


def test_edge_structure_and_counts(world: tuple) -> None:
    graph, truth = world
    e = graph.edges["EDGE_SE2"]
    n = len(truth)
    assert np.array_equal(e.ids[: n - 1], np.column_stack([np.arange(n - 1), np.arange(1, n)]))
    loops = e.ids[n - 1:]
    assert (loops[:, 1] - loops[:, 0] > 1).all()
    assert len(np.unique(loops, axis=0)) == len(loops)
    assert (np.linalg.norm(truth[loops[:, 0], :2] - truth[loops[:, 1], :2], axis=1) <= 1).all()
    per_pose = np.bincount(loops[:, 1], minlength=n)
    assert per_pose.max() == 6  # max_closures
    # Every pose gets min(candidates, 6) closures; candidates counted by brute force.
    for k in range(0, n, 97):
        near = np.linalg.norm(truth[: max(k - 1, 0), :2] - truth[k, :2], axis=1) <= 1
        assert per_pose[k] == min(int(near.sum()), 6)
    assert 6.0 < len(e.ids) / n < 6.8  # like w10000's 6.43 edges per pose
    assert len(graph.vertices["VERTEX_SE2"].ids) == n and (e.lines == 0).all()


def test_noise_matches_the_information(world: tuple) -> None:
    graph, truth = world
    e = graph.edges["EDGE_SE2"]
    sigma = np.array([0.05, 0.05, 0.01])
    assert np.array_equal(e.information[0], np.diag(1 / sigma**2))
    assert (e.information == e.information[0]).all()
    residual = _between(_between(truth[e.ids[:, 0]], truth[e.ids[:, 1]]), e.measurements)
    std = residual.std(axis=0)
    np.testing.assert_allclose(std, sigma, rtol=0.05)  # 13k edges: ±1 % expected
    assert np.abs(residual.mean(axis=0)).max() < 0.05 * sigma.min() * 3
    chi2 = np.einsum("mi,mij,mj->m", residual, e.information, residual)
    assert abs(chi2.mean() / 3 - 1) < 0.05  # chi2 per edge ≈ its dimension


def test_initial_estimate_chains_the_odometry_and_drifts(world: tuple) -> None:
    graph, truth = world
    est = graph.vertices["VERTEX_SE2"].values
    odo = graph.edges["EDGE_SE2"].measurements[: len(truth) - 1]
    assert np.array_equal(est[0], truth[0])
    np.testing.assert_allclose(_between(est[:-1], est[1:]), odo, atol=1e-9)
    early = trajectory_error(est[:50], truth[:50])
    full = trajectory_error(est, truth)
    assert full["rms_position"] > 5 * early["rms_position"] > 0  # drift grows
    assert full["rms_position"] > 0.5 and full["rms_heading"] > 0.05
    err_truth = trajectory_error(truth, truth)
    assert err_truth["rms_position"] == 0 and err_truth["max_heading"] == 0


def test_trajectory_error_alignments() -> None:
    rng = np.random.default_rng(0)
    truth = np.column_stack([rng.uniform(-5, 5, (40, 2)), rng.uniform(-3, 3, 40)])
    # A rigid motion of the whole trajectory vanishes under both alignments.
    angle, shift = 0.7, np.array([3.0, -2.0])
    c, s = np.cos(angle), np.sin(angle)
    moved = np.column_stack([truth[:, :2] @ np.array([[c, s], [-s, c]]) + shift,
                             np.angle(np.exp(1j * (truth[:, 2] + angle)))])
    for align in ("first", "se2"):
        err = trajectory_error(moved, truth, align=align)
        assert err["rms_position"] < 1e-12 and err["rms_heading"] < 1e-12
        assert err["alignment"] == align and err["poses"] == 40
    # Half the poses off by 0.3 in x and 0.1 rad; the first pose exact: known RMS.
    off = truth.copy()
    off[20:, 0] += 0.3
    off[20:, 2] += 0.1
    err = trajectory_error(off, truth)
    assert err["rms_position"] == pytest.approx(np.sqrt(0.5 * 0.09), rel=1e-12)
    assert err["rms_heading"] == pytest.approx(np.sqrt(0.5 * 0.01), rel=1e-9)
    assert err["max_position"] == pytest.approx(0.3) and err["max_heading"] == pytest.approx(0.1)
    # The best rigid fit can only do better than pinning the first pose.
    assert trajectory_error(off, truth, align="se2")["rms_position"] <= err["rms_position"]
    with pytest.raises(ValueError, match="align must be"):
        trajectory_error(off, truth, align="sim3")
    with pytest.raises(ValueError, match=r"need two \(n, 3\) arrays"):
        trajectory_error(off[:, :2], truth[:, :2])


def test_generated_graph_round_trips_and_scales(tmp_path: Path) -> None:
    graph, _ = manhattan_world(500, seed=1)
    write_g2o(tmp_path / "world.g2o", graph)
    again = read_graph(tmp_path / "world.g2o")
    assert np.array_equal(again.vertices["VERTEX_SE2"].values, graph.vertices["VERTEX_SE2"].values)
    for name in ("ids", "measurements", "information"):
        assert np.array_equal(getattr(again.edges["EDGE_SE2"], name),
                              getattr(graph.edges["EDGE_SE2"], name))
    assert again.fixed.tolist() == [0]
    big, truth = manhattan_world(20000, seed=2)  # vectorised: well under a second
    assert len(truth) == 20000 and 6.0 < len(big.edges["EDGE_SE2"].ids) / 20000 < 6.8
    with pytest.raises(ValueError, match="at least 2 poses"):
        manhattan_world(1)
