"""graphopt.g2o's records and reference counting: a finished program's graph (optimizer, records,
batches, banks, graphopt's optimizer behind them) has no reference cycle, so it is freed when
the program drops it, without the cyclic collector; records used after their optimizer is gone
keep their values or say clearly what is missing."""

from __future__ import annotations

import gc
import sys
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import graphopt.g2o as g2o
from graphopt.errors import GraphError

sys.path.insert(0, str(Path(__file__).parent))
import g2o_programs as programs  # noqa: E402


@pytest.fixture
def no_collector() -> Iterator[None]:
    """The cyclic collector off (what is freed is freed by reference counting), garbage from
    before the test collected."""
    gc.collect()
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _cyclic_graphopt_garbage() -> list[str]:
    """The types of graphopt's objects that only the cyclic collector would free."""
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        gc.collect()
        found = sorted({f"{type(o).__module__}.{type(o).__qualname__}" for o in gc.garbage
                        if type(o).__module__.startswith("graphopt")})
    finally:
        gc.garbage.clear()
        gc.set_debug(0)
    return found


def _local_ba(n_points: int = 40) -> dict[str, Any]:
    """A small ORB-SLAM-style local BA using most of the record API; returns weak references to
    its objects, and the records and values the caller may keep."""
    sc = programs.scene(4, n_points, 3, seed=5)
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(
        g2o.BlockSolverSE3(g2o.LinearSolverEigenSE3())))
    kfs, pts, edges = [], [], []
    for i, (R, t) in enumerate(zip(sc["R0"], sc["t0"], strict=True)):
        v = g2o.VertexSE3Expmap()
        v.set_estimate(g2o.SE3Quat(R, t))
        v.set_id(i)
        v.set_fixed(i >= 2)
        opt.add_vertex(v)
        kfs.append(v)
    for j, X in enumerate(sc["X0"]):
        v = g2o.VertexPointXYZ()
        v.set_estimate(X)
        v.set_id(len(kfs) + j)
        v.set_marginalized(True)
        opt.add_vertex(v)
        pts.append(v)
    for p, k, uv in sc["obs"]:
        e = g2o.EdgeSE3ProjectXYZ()
        e.set_vertex(0, pts[p])
        e.set_vertex(1, kfs[k])
        e.set_measurement(uv)
        e.set_information(np.identity(2))
        e.set_robust_kernel(g2o.RobustKernelHuber(np.sqrt(programs.CHI2_MONO)))
        e.fx, e.fy, e.cx, e.cy = programs.FX, programs.FY, programs.CX, programs.CY
        opt.add_edge(e)
        edges.append(e)
    opt.set_verbose(False)
    opt.initialize_optimization()
    opt.optimize(3)
    for e in edges:
        if e.chi2() > programs.CHI2_MONO or not e.is_depth_positive():
            e.set_level(1)
        e.set_robust_kernel(None)
    opt.remove_edge(edges[-1])
    opt.initialize_optimization(0)
    opt.optimize(3)
    opt.compute_active_errors()
    assert opt.active_edges() and opt.vertices() and opt.edges()
    core = opt.core
    return {"opt": weakref.ref(opt), "core": weakref.ref(core), "kfs": kfs, "pts": pts,
            "edges": edges, "chi2": [e.chi2() for e in edges[:-1]],
            "estimates": [v.estimate().matrix() for v in kfs]}


def test_a_finished_local_ba_is_freed_by_reference_counting(no_collector: None) -> None:
    out = _local_ba()
    edge, point = weakref.ref(out["edges"][0]), weakref.ref(out["pts"][0])
    assert out["opt"]() is None and out["core"]() is None  # the program dropped the optimizer
    del out
    assert edge() is None and point() is None
    assert _cyclic_graphopt_garbage() == []


@pytest.mark.parametrize("program", [
    lambda: programs.ba_demo(g2o, n_points=60, outlier_ratio=0.1, robust=True),
    lambda: programs.motion_only(g2o, programs.scene(2, 80, 2, seed=2), 60),
    lambda: programs.pose_graph_se2(g2o, n=30),
    lambda: programs.optimize_sim3(g2o, n=30),
    lambda: programs.gicp_demo(g2o, n_points=60),
    lambda: programs.sensor_types_chi2(g2o),
    lambda: programs.offset_types_chi2(g2o),
], ids=["ba_demo", "motion_only", "pose_graph_se2", "sim3", "gicp", "sensor", "offset"])
def test_g2o_programs_leave_no_cycles(program: Callable[[], Any], no_collector: None) -> None:
    program()
    assert _cyclic_graphopt_garbage() == []


def test_load_and_save_leave_no_cycles(tmp_path: Path, no_collector: None) -> None:
    opt = programs.se2_chain(g2o, [(float(i), 0.1 * i, 0.0) for i in range(5)],
                             g2o.SE2(1.0, 0.0, 0.0), np.identity(3))
    opt.save(tmp_path / "a.g2o")
    ref = weakref.ref(opt)
    del opt  # (the records were the helper's locals)
    assert ref() is None
    opt = g2o.SparseOptimizer()
    opt.load(tmp_path / "a.g2o")
    opt.initialize_optimization()
    opt.optimize(5)
    opt.save(tmp_path / "b.g2o")
    ref = weakref.ref(opt)
    del opt
    assert ref() is None
    assert _cyclic_graphopt_garbage() == []


def test_records_outlive_their_optimizer() -> None:
    out = _local_ba()
    assert out["opt"]() is None
    kfs, edges = out["kfs"], out["edges"]
    # Estimates and edge values are the last ones the optimizer had.
    for v, m in zip(kfs, out["estimates"], strict=True):
        np.testing.assert_array_equal(v.estimate().matrix(), m)
    assert [e.chi2() for e in edges[:-1]] == out["chi2"]
    assert isinstance(edges[0].is_depth_positive(), bool)
    # A changed estimate changes the edges' values (the arrays are still there).
    p = out["pts"][0]
    p.set_estimate(p.estimate() + 1.0)
    on_p = [i for i, e in enumerate(edges[:-1]) if e.vertex(0) is p]
    assert on_p and all(edges[i].chi2() != out["chi2"][i] for i in on_p)
    assert all(edges[i].chi2() == c for i, c in enumerate(out["chi2"]) if i not in on_p)
    # Levels and kernels are accepted (nothing to tell), structural edits need an optimizer.
    edges[0].set_level(0)
    edges[0].set_robust_kernel(g2o.RobustKernelHuber(1.0))
    edges[0].set_measurement(np.array([300.0, 200.0]))
    with pytest.raises(GraphError, match="EdgeSE3ProjectXYZ on vertices .*optimizer was deleted"):
        edges[0].chi2()
    # The removed edge was never evaluated alone: it needs an optimizer.
    with pytest.raises(RuntimeError, match="add the edge to an optimizer first"):
        edges[-1].chi2()


def test_records_join_a_new_optimizer_after_theirs_is_gone() -> None:
    out = _local_ba()
    kfs, pts, edges = out["kfs"], out["pts"], out["edges"]
    opt = g2o.SparseOptimizer()
    assert all(opt.add_vertex(v) for v in kfs + pts)
    assert all(opt.add_edge(e) for e in edges)
    assert not opt.add_edge(edges[0])  # now in this optimizer
    opt.initialize_optimization()
    # The vertices start where the old optimizer left them; the edges keep their levels.
    np.testing.assert_allclose(kfs[0].estimate().matrix(), out["estimates"][0])
    active = opt.active_edges()
    assert len(active) == sum(e.level() == 0 for e in edges)
    assert [e.chi2() for e in edges[:-1]] == pytest.approx(out["chi2"], rel=1e-12)
    opt.optimize(2)
    assert opt.remove_vertex(pts[0]) and opt.remove_edge(edges[-1])
    opt.initialize_optimization()
    opt.optimize(1)
    assert np.isfinite(opt.active_chi2())


def test_edge_vertex_positions() -> None:
    """Vertices 0 and 1 live in slots, further ones in a list: positions, bounds and the
    variable-count edges behave as a list of the type's length."""
    vs = []
    for i in range(4):
        v = g2o.VertexPointXY()
        v.set_id(i)
        vs.append(v)
    one, two = g2o.EdgeXYPrior(), g2o.EdgePointXY()
    three = g2o.EdgeSE2TwoPointsXY()
    assert one.vertices() == [None] and two.vertices() == [None, None]
    assert three.vertices() == [None, None, None]
    with pytest.raises(IndexError):
        one.set_vertex(1, vs[0])
    with pytest.raises(IndexError):
        two.set_vertex(2, vs[0])
    two.set_vertex(-1, vs[1])
    two.set_vertex(0, vs[0])
    three.set_vertex(2, vs[2])
    assert two.vertices() == [vs[0], vs[1]] and two.vertex(-2) is vs[0]
    assert three.vertex(2) is vs[2] and three.vertices() == [None, None, vs[2]]
    lots = g2o.EdgeSE2LotsOfXY()
    lots.resize(4)
    for i, v in enumerate(vs):
        lots.set_vertex(i, v)
    assert lots.vertices() == vs and lots.dimension() == 6
    lots.resize(2)
    assert lots.vertices() == [None, None] and lots.dimension() == 2
    opt = g2o.SparseOptimizer()
    for v in vs:
        opt.add_vertex(v)
    assert not opt.add_edge(three)  # vertex 0 and 1 missing
    three.set_vertex(0, vs[0])
    three.set_vertex(1, vs[2])
    assert not opt.add_edge(three)  # vertex 2 named twice
    three.set_vertex(1, vs[1])
    assert opt.add_edge(three) and opt.add_edge(two)
    assert not opt.add_edge(one)  # no vertex
