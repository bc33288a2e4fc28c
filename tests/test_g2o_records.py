"""graphopt.g2o's records as the program sees them through the fast paths: float vectors kept as
bytes until filing, the compiled ``__init__`` of the edge classes, the per-edge getters' cached
lists (valid while the stores' estimates are unchanged) and the inlined level and kernel
setters — each checked against a direct computation or the slow path's answer."""

from __future__ import annotations

import numpy as np
import pytest

import graphopt.g2o as g2o
from graphopt.errors import GraphError

FX, FY, CX, CY = 500.0, 480.0, 320.0, 240.0


def _pose(x: float = 0.0) -> g2o.SE3Quat:
    return g2o.SE3Quat(np.eye(3), np.array([x, 0.0, 0.0]))


def _projection(T: g2o.SE3Quat, X: np.ndarray) -> np.ndarray:
    Xc = T * X
    return np.array([FX * Xc[0] / Xc[2] + CX, FY * Xc[1] / Xc[2] + CY])


def _graph(n: int = 6) -> tuple[g2o.SparseOptimizer, list, list, np.ndarray]:
    """Two poses (the first fixed), ``n`` points, one projection edge per pose and point, the
    measurements 0.5 px off the projections of the starting estimates."""
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(g2o.BlockSolverSE3(
        g2o.LinearSolverDenseSE3())))
    poses = []
    for i in range(2):
        v = g2o.VertexSE3Expmap()
        v.set_id(i)
        v.set_estimate(_pose(0.3 * i))
        v.set_fixed(i == 0)
        opt.add_vertex(v)
        poses.append(v)
    rng = np.random.default_rng(3)
    X = rng.random((n, 3)) + [0.0, 0.0, 4.0]
    edges = []
    for k in range(n):
        p = g2o.VertexPointXYZ()
        p.set_id(10 + k)
        p.set_estimate(X[k])
        p.set_marginalized(True)
        opt.add_vertex(p)
        for v in poses:
            e = g2o.EdgeSE3ProjectXYZ()
            e.set_vertex(0, p)
            e.set_vertex(1, v)
            e.set_measurement(_projection(v.estimate(), X[k]) + 0.5)
            e.set_information(np.eye(2))
            e.fx, e.fy, e.cx, e.cy = FX, FY, CX, CY
            opt.add_edge(e)
            edges.append(e)
    return opt, poses, edges, X


def _chi2(e: g2o.EdgeSE3ProjectXYZ) -> float:
    r = e.measurement() - _projection(e.vertex(1).estimate(), e.vertex(0).estimate())
    return float(r @ r)


def test_vectors_are_copied_when_set() -> None:
    opt, _, edges, X = _graph(2)
    e, p = edges[0], opt.vertex(10)
    z = e.measurement()
    buf = z.copy()
    e.set_measurement(buf)
    est = X[0].copy()
    p.set_estimate(est)
    buf += 100.0  # the program reuses its arrays: the records keep the values they were given
    est += 100.0
    assert np.array_equal(e.measurement(), z) and e.measurement().shape == (2,)
    assert np.array_equal(p.estimate(), X[0]) and p.estimate().shape == (3,)
    opt.initialize_optimization()
    assert np.array_equal(e.measurement(), z) and np.array_equal(p.estimate(), X[0])
    assert e.chi2() == pytest.approx(0.5, rel=1e-9)  # 0.5 px on both axes


def test_loose_vectors_give_the_same_arrays() -> None:
    """Column vectors, lists, integer and float32 arrays (the old bindings' inputs) take the
    slower paths and file to the same numbers as float vectors."""
    opt, _, edges, X = _graph(3)
    ref = [e.measurement() for e in edges]
    edges[0].set_measurement(ref[0].reshape(2, 1))
    edges[1].set_measurement(ref[1].tolist())
    edges[2].set_measurement(ref[2].astype(np.float32))
    opt.vertex(10).set_estimate(X[0].reshape(3, 1))
    opt.vertex(11).set_estimate(np.array([1, 2, 5]))
    assert np.array_equal(opt.vertex(11).estimate(), [1.0, 2.0, 5.0])
    opt.initialize_optimization()
    assert np.array_equal(edges[0].measurement(), ref[0])
    assert np.array_equal(edges[1].measurement(), ref[1])
    assert np.array_equal(edges[2].measurement(), ref[2].astype(np.float32).astype(float))
    assert np.array_equal(opt.vertex(10).estimate(), X[0])
    for e in edges:
        assert e.chi2() == pytest.approx(_chi2(e), rel=1e-12)


def test_wrong_sizes_are_named_at_initialisation() -> None:
    opt, _, edges, _ = _graph(2)
    edges[1].set_measurement(np.zeros(3))
    assert edges[1].measurement().shape == (3,)  # as given, until filing says what is wrong
    with pytest.raises(GraphError, match=r"EdgeSE3ProjectXYZ on vertices \[10, 1\]: bad "
                                         "measurement"):
        opt.initialize_optimization()
    opt, _, edges, _ = _graph(2)
    opt.vertex(11).set_estimate(np.zeros(4))
    with pytest.raises(GraphError, match=r"vertex 11 \(VertexPointXYZ\): estimate has shape"):
        opt.vertex(11).estimate()
    with pytest.raises(GraphError, match="vertex 11"):
        opt.initialize_optimization()


def test_compiled_constructors_set_every_field() -> None:
    e = g2o.EdgeSE3ProjectXYZOnlyPose()
    assert (e.fx, e.fy, e.cx, e.cy) == (0.0, 0.0, 0.0, 0.0) and np.array_equal(e.Xw, np.zeros(3))
    assert e.level() == 0 and e.id() == -1 and e.robust_kernel() is None
    assert e.vertex(0) is None and e.vertices() == [None]
    s = g2o.EdgeStereoSE3ProjectXYZOnlyPose()
    assert s.bf == 0.0 and s.fx == 0.0 and s.dimension() == 3
    a, b = g2o.EdgeProjectPSI2UV(), g2o.EdgeProjectPSI2UV()
    a.set_vertex(2, g2o.VertexSE3Expmap())
    assert b.vertices() == [None, None, None]  # each record its own list of further vertices
    assert type(g2o.EdgeSE3ProjectXYZ.__init__).__name__ == "function"

    class Mine(g2o.EdgeSE3ProjectXYZ):  # a program's subclass gets the fields too
        __slots__ = ("tag",)
        _defaults = {"tag": "x"}

    m = Mine()
    assert m.tag == "x" and m.fx == 0.0 and m.level() == 0

    class Own(g2o.EdgeSE3ProjectXYZ):  # ... and one with an __init__ of its own keeps it
        __slots__ = ("n",)

        def __init__(self) -> None:
            super().__init__()
            self.n = 7

    o = Own()
    assert o.n == 7 and o.fx == 0.0 and o.vertices() == [None, None]


def test_getters_follow_every_estimate_change() -> None:
    """``chi2()`` and ``is_depth_positive()`` read cached lists: they must change with
    ``set_estimate``, ``optimize`` and ``set_estimates_of``, and equal a direct computation."""
    opt, poses, edges, X = _graph()
    opt.initialize_optimization()
    assert [e.chi2() for e in edges] == pytest.approx([_chi2(e) for e in edges], rel=1e-12)
    assert all(e.is_depth_positive() for e in edges)
    poses[1].set_estimate(_pose(0.3) * g2o.SE3Quat(np.eye(3), np.array([0.0, 0.0, -9.0])))
    assert [e.chi2() for e in edges] == pytest.approx([_chi2(e) for e in edges], rel=1e-12)
    assert [e.is_depth_positive() for e in edges] == [e.vertex(1) is poses[0] for e in edges]
    poses[1].set_estimate(_pose(0.3))
    before = [e.chi2() for e in edges]
    opt.optimize(3)
    after = [e.chi2() for e in edges]
    assert after == pytest.approx([_chi2(e) for e in edges], rel=1e-9) and sum(after) < sum(before)
    opt.set_estimates_of(g2o.VertexPointXYZ, X + [0.0, 0.0, 1.0])
    assert [e.chi2() for e in edges] == pytest.approx([_chi2(e) for e in edges], rel=1e-12)
    assert edges[0].is_depth_positive()  # a depth test first, then chi2 at the same state
    assert edges[0].chi2() == pytest.approx(_chi2(edges[0]), rel=1e-12)


def test_levels_and_kernels_set_per_edge_reach_the_optimizer() -> None:
    opt, _, edges, _ = _graph()
    opt.initialize_optimization()
    off = edges[::3]
    for e in off:
        e.set_level(1)
        e.set_level(1)  # repeated: nothing more
    for e in edges:
        e.set_robust_kernel(g2o.RobustKernelHuber(0.1))
    opt.initialize_optimization(0)
    opt.compute_active_errors()
    on = [e for e in edges if e.level() == 0]
    assert len(opt.active_edges()) == len(on) == len(edges) - len(off)
    assert opt.active_chi2() == pytest.approx(sum(_chi2(e) for e in on), rel=1e-12)
    huber = sum(2 * 0.1 * np.sqrt(c) - 0.01 if c > 0.01 else c for c in map(_chi2, on))
    assert opt.active_robust_chi2() == pytest.approx(huber, rel=1e-12)
    for e in edges:
        e.set_robust_kernel(None)
        e.set_level(0)
    opt.initialize_optimization(0)
    opt.compute_active_errors()
    assert len(opt.active_edges()) == len(edges)
    assert opt.active_robust_chi2() == pytest.approx(opt.active_chi2(), rel=1e-12)
    with pytest.raises(GraphError, match="level must be a non-negative integer"):
        edges[0].set_level(-1)


def test_edits_after_filing_file_again() -> None:
    opt, _, edges, _ = _graph()
    opt.initialize_optimization()
    e = edges[2]
    z = e.measurement()
    e.set_measurement(z + 1.0)  # bytes again, after the record was an index into a batch
    e.set_information(np.diag([4.0, 1.0]))
    opt.initialize_optimization()
    assert np.array_equal(e.measurement(), z + 1.0)
    r = z + 1.0 - _projection(e.vertex(1).estimate(), e.vertex(0).estimate())
    assert e.chi2() == pytest.approx(4 * r[0] ** 2 + r[1] ** 2, rel=1e-12)
    assert np.array_equal(e.information(), np.diag([4.0, 1.0]))
    assert [f.chi2() for f in edges if f is not e] == pytest.approx(
        [_chi2(f) for f in edges if f is not e], rel=1e-12)


def test_vertex_classes_are_filed_in_the_order_added() -> None:
    """Vertices of several classes interleaved: each bank keeps its records' order."""
    opt = g2o.SparseOptimizer()
    ids = []
    for i in range(6):
        v = g2o.VertexSE2() if i % 2 else g2o.VertexPointXY()
        v.set_id(100 - i)
        v.set_estimate(g2o.SE2(i, 0.0, 0.0) if i % 2 else np.array([float(i), 0.0]))
        opt.add_vertex(v)
        ids.append(100 - i)
    for i in range(0, 6, 2):
        e = g2o.EdgeSE2PointXY()
        e.set_vertex(0, opt.vertex(ids[i + 1]))
        e.set_vertex(1, opt.vertex(ids[i]))
        e.set_measurement(np.zeros(2))
        opt.add_edge(e)
    opt.initialize_optimization()
    stores = opt.core.graph.stores
    by_name = {t.__name__: s for t, s in stores.items()}
    assert by_name["VertexPointXY"].ids.tolist() == [100, 98, 96]
    assert by_name["VertexSE2"].ids.tolist() == [99, 97, 95]
    assert [opt.vertex(i).estimate()[0] for i in (100, 98, 96)] == [0.0, 2.0, 4.0]
