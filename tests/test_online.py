"""The incremental optimizer: online replays end at the batch optimum, the grown factor is the
system's factor, the fallbacks keep the estimate finite, a lone vertex is a clear error."""

from __future__ import annotations

import json
from typing import ClassVar

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from test_slam_graph import DATA, GRAPHOPT_LM

from graphopt import GraphError, SparseOptimizer
from graphopt.apps.slam_scene import manhattan_world
from graphopt.edge import EdgeContext, Linearization
from graphopt.io.g2o import read_graph
from graphopt.online import IncrementalConfig, IncrementalOptimizer
from graphopt.types.slam2d import EdgeSE2, EdgeSE2PointXY, VertexPointXY, VertexSE2
from graphopt.types.slam_graph import build_graph
from graphopt.types.slam_online import replay, replay_schedule

pytest.importorskip("sksparse")
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"data folder {DATA} is absent")
INFO = np.diag([400.0, 400.0, 2500.0])


def _batch_chi2(graph, guess: bool = False) -> float:
    slam = build_graph(graph, guess=guess)
    slam.optimizer.optimize(100)
    slam.optimizer.compute_active_errors()
    return float(slam.optimizer.chi2())


def _replayed_chi2(graph, guess: bool = False, **config) -> tuple[float, object]:
    out = replay(replay_schedule(build_graph(graph, guess=guess)), IncrementalConfig(**config))
    assert all(np.isfinite(out.poses).all() for _ in [0])
    return out.incremental.chi2(), out


@needs_data
@pytest.mark.parametrize(("name", "guess"), [("w100.graph", False), ("pose2example.txt", False),
                                             ("pose3example.txt", False),
                                             ("victoriaPark_reduced_1k.g2o", True)])
def test_replay_of_the_small_data_sets_ends_at_the_batch_optimum(name: str, guess: bool) -> None:
    graph = read_graph(DATA / name)
    chi2, out = _replayed_chi2(graph, guess)
    best = GRAPHOPT_LM[name]
    assert chi2 <= best * 1.005
    assert chi2 >= best * (1 - 1e-6)  # not below the optimum: the chi2 is the graph's
    assert len(out.steps) == len(out.poses)


def test_replay_of_a_manhattan_world_ends_at_the_batch_optimum() -> None:
    graph = manhattan_world(300, 1)[0]
    chi2, out = _replayed_chi2(graph)
    assert chi2 <= _batch_chi2(graph) * 1.005
    kinds = {r.factor for r in out.incremental.reports}
    assert {"pending", "updated", "rebuilt"} <= kinds  # every path ran


def test_the_grown_factor_solves_like_a_fresh_factorisation() -> None:
    graph = manhattan_world(120, 2)[0]
    schedule = replay_schedule(build_graph(graph))
    out = replay(schedule, IncrementalConfig(reserve=150, relinearize_threshold=1e9))
    inc = out.incremental
    assert sum(r.factor == "rebuilt" for r in inc.reports) == 1  # updates only after the first
    H, g = inc.system()
    f = inc.factor
    n = len(g)
    rhs = np.zeros(f.size)
    rhs[:n] = g
    x = f.solve(rhs)[:n]
    fresh = spla.spsolve(H, g)
    assert np.abs(x - fresh).max() <= 1e-9 * np.abs(fresh).max()
    assert np.abs(x[n:]).max(initial=0.0) == 0.0
    # The model check's short form ‖r‖² + gᵀΔ is the linear model edge by edge at the solve.
    delta = -f.solve(inc._g)
    _, model = inc._state.model_check(delta, inc._g)
    assert model == pytest.approx(inc._state.model_residuals(delta), rel=1e-9, abs=1e-9)


def _chain(opt: SparseOptimizer, n: int) -> None:
    opt.add_vertices(VertexSE2, np.arange(n), np.column_stack([np.arange(n), np.zeros(n),
                                                               np.zeros(n)]),
                     fixed=np.arange(n) == 0)
    z = np.tile([1.0, 0.0, 0.0], (n - 1, 1))
    opt.add_edges(EdgeSE2, np.column_stack([np.arange(n - 1), np.arange(1, n)]), z, INFO)


def test_a_partial_relinearisation_keeps_the_factor_the_systems(monkeypatch) -> None:
    # Every relinearisation that can be partial is: the factor, downdated and updated, still
    # solves the freshly assembled system of the mixed linearisation points.
    graph = manhattan_world(300, 2)[0]
    seen = []
    partly = IncrementalOptimizer._relinearize_partly

    def checked(self, report) -> bool:
        ran = partly(self, report)
        if ran:
            H, g = self.system()
            rhs = np.zeros(self.factor.size)
            rhs[:len(g)] = g
            fresh = spla.spsolve(H, g)
            seen.append(np.abs(self.factor.solve(rhs)[:len(g)] - fresh).max()
                        / np.abs(fresh).max())
            _, model = self._state.model_check(self._delta, self._g)  # rows swapped: r2 too
            assert model == pytest.approx(self._state.model_residuals(self._delta), rel=1e-9)
        return ran

    monkeypatch.setattr(IncrementalOptimizer, "_relinearize_partly", checked)
    chi2, out = _replayed_chi2(graph, partial_fraction=1.0, relinearize_threshold=0.05)
    assert len(seen) >= 3 and max(seen) <= 1e-6
    assert sum(r.reason == "relinearize" and r.factor == "updated"
               for r in out.incremental.reports) == len(seen)
    assert chi2 <= _batch_chi2(graph) * 1.005


def test_a_vertex_without_edges_is_a_clear_error() -> None:
    opt = SparseOptimizer()
    _chain(opt, 4)
    inc = IncrementalOptimizer(opt)
    inc.update()
    opt.add_vertices(VertexSE2, [7], [[3.0, 1.0, 0.0]])
    with pytest.raises(GraphError, match=r"vertex 7 \(VertexSE2\) has no edge"):
        inc.update()
    opt.add_edges(EdgeSE2, [[3, 7]], [[0.0, 1.0, 0.0]], INFO)  # then it goes on
    report = inc.update()
    assert report.vertices == 1 and report.edges == 1
    assert np.allclose(opt.vertex(7).estimate, [3.0, 1.0, 0.0])


def test_a_loop_closure_updates_the_factor_and_moves_the_estimate() -> None:
    opt = SparseOptimizer()
    _chain(opt, 6)
    inc = IncrementalOptimizer(opt)
    inc.update()
    before = opt.estimates_of(VertexSE2).copy()
    opt.add_edges(EdgeSE2, [[0, 5]], [[5.05, 0.0, 0.0]], INFO)
    report = inc.update()
    assert report.solved and report.factor == "updated" and report.edges == 1
    after = opt.estimates_of(VertexSE2)
    assert after[5, 0] > before[5, 0]  # pulled towards the closure
    batch = SparseOptimizer()
    _chain(batch, 6)
    batch.add_edges(EdgeSE2, [[0, 5]], [[5.05, 0.0, 0.0]], INFO)
    batch.optimize(20)
    assert np.allclose(after, batch.estimates_of(VertexSE2), atol=1e-8)


class WrongSignEdgeSE2(EdgeSE2):
    """EdgeSE2 with Jacobians of the wrong sign: every Gauss-Newton step goes uphill."""

    vertex_types: ClassVar = (VertexSE2, VertexSE2)

    @classmethod
    def linearize(cls, x, measurement, ctx: EdgeContext) -> Linearization:
        lin = super().linearize(x, measurement, ctx)
        return Linearization(lin.error, tuple(-J for J in lin.jacobians))


def test_a_step_that_raises_chi2_falls_back_to_damped_steps() -> None:
    opt = SparseOptimizer()
    _chain(opt, 5)
    opt.add_edges(WrongSignEdgeSE2, [[0, 4]], [[4.5, 0.3, 0.2]], INFO)
    inc = IncrementalOptimizer(opt, IncrementalConfig(check_chi2=True))
    report = inc.update()
    assert report.fallback and report.factor == "rebuilt"
    first = inc.chi2()
    opt.add_vertices(VertexSE2, [5], [[5.0, 0.0, 0.0]])
    opt.add_edges(EdgeSE2, [[4, 5]], [[1.0, 0.0, 0.0]], INFO)
    opt.add_edges(WrongSignEdgeSE2, [[1, 5]], [[3.6, -0.2, 0.1]], INFO)
    report = inc.update()
    assert report.fallback
    assert np.isfinite(opt.estimates_of(VertexSE2)).all()
    assert inc.chi2() <= first + float(np.sum(_edge_chi2_now(opt)))


def _edge_chi2_now(opt: SparseOptimizer) -> np.ndarray:
    opt.compute_active_errors()
    return np.array([opt.chi2()])


def test_a_vertex_constrained_in_too_few_directions_never_raises() -> None:
    opt = SparseOptimizer()
    _chain(opt, 3)
    opt.add_vertices(VertexPointXY, [10], [[1.0, 1.0]])
    opt.add_edges(EdgeSE2PointXY, [[1, 10]], [[0.0, 1.0]], np.eye(2))
    inc = IncrementalOptimizer(opt)
    inc.update()
    # A pose seen only through one point observation: 2 equations for 3 unknowns.
    opt.add_vertices(VertexSE2, [11], [[1.0, 2.0, 0.3]])
    opt.add_edges(EdgeSE2PointXY, [[11, 10]], [[0.5, 0.0]], np.eye(2))
    report = inc.update()
    assert report.factor == "rebuilt" and report.fallback
    for vtype in (VertexSE2, VertexPointXY):
        assert np.isfinite(opt.estimates_of(vtype)).all()


ONLINE_KEYS = {"steps", "total_seconds", "median_step_seconds", "p95_step_seconds",
               "max_step_seconds", "solves", "batch_steps", "fallbacks", "final_batch"}


def test_the_app_replays_online_and_reports_the_steps(tmp_path, capsys) -> None:
    from test_g2o_app import KEYS

    from graphopt.apps.g2o import main

    js = tmp_path / "online.json"
    assert main(["--poses", "150", "--online", "--json", str(js)]) == 0
    out, err = capsys.readouterr()
    assert "online step 150/150" in err
    # No batch iteration ran: the summary gives no per-iteration figure.
    assert "no batch iteration, stop: online" in out + err and "s/iteration" not in out + err
    s = json.loads(js.read_text())
    assert set(s) == KEYS and set(s["online"]) == ONLINE_KEYS
    o = s["online"]
    assert o["steps"] == 150 and not o["final_batch"] and s["iterations"] == 0
    assert o["median_step_seconds"] <= o["p95_step_seconds"] <= o["max_step_seconds"]
    assert o["total_seconds"] == pytest.approx(s["seconds"])
    graph = manhattan_world(150, 0)[0]
    assert s["final_chi2"] <= _batch_chi2(graph) * 1.005
    polished = tmp_path / "polished.json"
    assert main(["--poses", "150", "--online", "--online-final-batch", "--quiet",
                 "--json", str(polished)]) == 0
    p = json.loads(polished.read_text())
    assert p["online"]["final_batch"] and p["final_chi2"] <= s["final_chi2"] + 1e-9


def test_the_app_records_the_online_steps(tmp_path, capsys) -> None:
    pytest.importorskip("rerun")
    from graphopt.apps.g2o import main

    rrd = tmp_path / "online.rrd"
    assert main(["--poses", "60", "--online", "--quiet", "--rrd", str(rrd)]) == 0
    assert rrd.stat().st_size > 1000


def test_a_replay_with_a_robust_kernel_ends_at_the_robust_optimum() -> None:
    from graphopt import RobustKernelHuber

    graph = manhattan_world(200, 3, sigma_xy=0.2)[0]
    kernel = RobustKernelHuber(1.0)
    out = replay(replay_schedule(build_graph(graph)), kernel=kernel)
    slam = build_graph(graph)
    for group in slam.optimizer.edge_groups():
        group.set_kernel(slice(None), kernel)
    slam.optimizer.optimize(100)
    slam.optimizer.compute_active_errors()
    best = float(slam.optimizer.active_robust_chi2())
    assert out.incremental.chi2() <= best * 1.005


def test_fixing_a_vertex_between_updates_rebuilds_without_it() -> None:
    opt = SparseOptimizer()
    _chain(opt, 5)
    inc = IncrementalOptimizer(opt)
    inc.update()
    opt.vertex(4).set_fixed(True)
    opt.add_edges(EdgeSE2, [[0, 4]], [[4.05, 0.0, 0.0]], INFO)
    report = inc.update()
    assert report.factor == "rebuilt" and report.reason == "flags"
    assert inc.factor.used == 9  # poses 1-3 free
    assert np.allclose(opt.vertex(4).estimate, [4.0, 0.0, 0.0])


def test_kernels_edited_after_the_edges_were_taken_in_are_the_ones_used() -> None:
    """Edges taken in keep following their group's kernels: after an edit (which renumbers the
    group's kernels) the chi2 is the batch optimizer's at the same estimates, not an
    IndexError or the old kernels', and the next update runs."""
    from graphopt import RobustKernelCauchy, RobustKernelHuber

    opt = SparseOptimizer()
    opt.add_vertices(VertexSE2, np.arange(5), np.column_stack([np.arange(5.0), np.zeros(5),
                                                               np.zeros(5)]),
                     fixed=np.arange(5) == 0)
    odo = opt.add_edges(EdgeSE2, np.column_stack([np.arange(4), np.arange(1, 5)]),
                        np.tile([1.0, 0.0, 0.0], (4, 1)), INFO, RobustKernelHuber(0.5))
    opt.add_edges(EdgeSE2, [[0, 4]], [[4.3, 0.2, 0.1]], INFO, RobustKernelCauchy(0.5))
    inc = IncrementalOptimizer(opt)
    inc.update()
    odo.set_robust_kernel(RobustKernelCauchy(0.5))  # one kernel left: the slots renumbered
    assert inc.chi2() == pytest.approx(opt.active_robust_chi2(), rel=1e-12)
    odo.set_robust_kernel(None)
    assert inc.chi2() == pytest.approx(opt.active_robust_chi2(), rel=1e-12)
    inc.update()
    # An edit, then new edges (with new kernels) before anything reads the kernels.
    odo[:2].set_robust_kernel(RobustKernelHuber(0.3))
    odo[2:].set_robust_kernel(None)
    opt.add_edges(EdgeSE2, [[1, 3], [0, 2]], [[2.2, 0.1, 0.0], [2.1, 0.0, 0.1]], INFO,
                  RobustKernelHuber(0.5))
    inc.update()
    assert inc.chi2() == pytest.approx(opt.active_robust_chi2(), rel=1e-12)


def test_removing_every_edge_of_a_group_between_updates_starts_afresh() -> None:
    """The last loop closure of its group removed (the group leaves the graph, and with it
    its count of removals): the next update is a batch step without it."""
    opt = SparseOptimizer()
    _chain(opt, 5)
    inc = IncrementalOptimizer(opt)
    inc.update()
    loop = opt.add_edges(EdgeSE2, [[0, 4]], [[4.3, 0.2, 0.1]], INFO, params="loops")
    inc.update()
    assert inc.chi2() > 1.0  # the closure disagrees with the odometry
    loop.remove()
    opt.add_vertices(VertexSE2, [5], [[5.0, 0.0, 0.0]])
    opt.add_edges(EdgeSE2, [[4, 5]], [[1.0, 0.0, 0.0]], INFO)
    report = inc.update()
    assert report.factor == "rebuilt"
    assert inc.chi2() == pytest.approx(opt.active_robust_chi2(), abs=1e-12)
    assert inc.chi2() < 1e-12


def test_update_columns_come_sorted_and_determine_reads_each_new_vertex_block() -> None:
    from graphopt.incremental.whitened import Whitened, determine, update_columns

    rng = np.random.default_rng(3)
    cols = [np.array([6, 0]), np.array([3, 9])]  # edges (6, 3) and (0, 9): the first swapped
    blocks = [rng.normal(size=(2, 3, 3)), rng.normal(size=(2, 3, 3))]
    w = Whitened(cols, blocks, rng.normal(size=(2, 3)), np.ones(2), np.ones(2))
    C = update_columns([w], 12)
    assert C.has_sorted_indices
    for j in range(C.shape[1]):
        rows = C.indices[C.indptr[j]:C.indptr[j + 1]]
        assert (np.diff(rows) > 0).all()
    H = np.zeros((12, 12))
    for e in range(2):
        J = np.zeros((3, 12))
        for c, A in zip(cols, blocks, strict=True):
            J[:, c[e]:c[e] + 3] = A[e]
        H += J.T @ J
    assert np.allclose((C @ C.T).toarray(), H, atol=1e-12)
    # New unknowns 6..11: vertex 6 hangs on 3 (older), vertex 9 on 0 (older).
    assert determine([w], 6, 6)
    flat = [b.copy() for b in blocks]
    flat[1][1, :, 2] = 0.0  # vertex 9's block loses a direction
    assert not determine([Whitened(cols, flat, w.residual, w.chi2, w.weight)], 6, 6)


def test_the_recent_block_stays_only_while_loop_closures_reach_into_it() -> None:
    from graphopt.incremental.ordering import Ordering
    from graphopt.incremental.state import Batch

    def batch(group: object, ages: list[int], first: int) -> Batch:
        j = first + np.arange(len(ages))
        i = j - np.asarray(ages)
        m = len(ages)
        return Batch(group, np.column_stack([i, j]), np.zeros((m, 3)), np.zeros((m, 3, 3)),
                     np.full(m, -1), {}, [0, 0], [i, j], 0, 0)

    order, group = Ordering(64), object()
    near = batch(group, [1, 50, 1, 48, 51], 100)  # odometry and closures to the last ring
    assert order.recent_window([near]) == 64
    far = batch(group, [1, 50, 1, 48, 51, 900, 1, 700, 321, 1200, 2000], 100)
    assert order.recent_window([far]) == 0  # the six new edges: closures reach far back
    assert order.recent_window([far]) == 0  # nothing new: the decision stands


def _closure_graph(kernel: bool) -> tuple[SparseOptimizer, object]:
    """Six poses, odometry, and a closure that disagrees with it (down-weighted by a Huber
    kernel of width 2 when ``kernel``)."""
    from graphopt import RobustKernelHuber

    opt = SparseOptimizer()
    _chain(opt, 6)
    closure = opt.add_edges(EdgeSE2, [[0, 5]], [[4.6, 0.4, 0.2]], INFO,
                            RobustKernelHuber(2.0) if kernel else None)
    return opt, closure


def test_an_edited_kernel_reweighs_the_factor_at_the_next_update() -> None:
    """The closure's kernel removed after the factor was built with it: the next update is a
    batch step (without a new edge too) and ends at the kernel-free optimum (its model check
    stops the batch iterations 5e-6 above it); before, that update did nothing and the estimate
    stayed at the Huber optimum, 4.3 % above, until new edges came."""
    ref, _ = _closure_graph(kernel=False)
    ref.optimize(50)
    ref.compute_active_errors()
    optimum = float(ref.chi2())
    opt, closure = _closure_graph(kernel=True)
    inc = IncrementalOptimizer(opt)
    inc.update()
    closure.set_robust_kernel(None)
    assert inc.chi2() > optimum * (1 + 1e-3)  # the Huber optimum, kernel-free chi2
    report = inc.update()
    assert report.factor == "rebuilt" and report.reason == "weights"
    assert inc.chi2() == pytest.approx(optimum, rel=1e-5)
    assert inc.update().factor != "rebuilt"  # nothing edited since: no batch step
