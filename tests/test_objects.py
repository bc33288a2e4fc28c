"""Objects added one at a time (graphopt.object_batch): thin records buffered by the graph and
taken into the arrays in bulk — the same arrays and optimum as the bulk calls, the same checks
(naming the object), g2o's object semantics before and after the flush."""

from __future__ import annotations

import numpy as np
import pytest
from ba_scene import CAMERA, build, local_ba_scene
from custom_types import EdgeSE2, VertexSE2

from graphopt import GraphError, RobustKernelCauchy, RobustKernelHuber, SparseOptimizer
from graphopt.types import EdgeSE3ProjectXYZ, VertexPointXYZ, VertexSE3Expmap


def test_objects_give_the_bulk_arrays_and_optimum() -> None:
    """The local-BA window built object by object (vertex objects and ids mixed, a kernel
    object per edge, information per edge) equals the bulk build, to the last bit."""
    sc = local_ba_scene(free=3, fixed=2, points=30, per_point=3, outliers=0.1, seed=5)
    c = len(sc.poses)
    info = np.eye(2)[None] * (1.0 + (np.arange(len(sc.ids)) % 3))[:, None, None]
    bulk = SparseOptimizer("lm", "dense")
    bulk.add_vertices(VertexSE3Expmap, np.arange(c), sc.poses, fixed=sc.fixed)
    bulk.add_vertices(VertexPointXYZ, c + np.arange(30), sc.points, marginalized=True)
    bulk.add_edges(EdgeSE3ProjectXYZ, sc.ids, sc.meas, information=info, params=CAMERA,
                   robust_kernel=RobustKernelHuber(2.0))
    opt = SparseOptimizer("lm", "dense")
    verts = {}
    buf = np.empty((4, 4))
    for i in range(c):
        buf[:] = sc.poses[i]  # a reused buffer: the vertex keeps its own copy
        v = VertexSE3Expmap(i, buf, fixed=bool(sc.fixed[i]))
        opt.add_vertex(v)
        verts[i] = v
    for j in range(30):
        v = VertexPointXYZ()
        v.set_id(c + j)
        v.set_estimate(list(sc.points[j]))
        v.set_marginalized(True)
        opt.add_vertex(v)
        verts[c + j] = v
    assert opt.vertex(c) is verts[c]  # a buffered vertex is found by id
    np.testing.assert_array_equal(verts[0].estimate, sc.poses[0])
    for n, ((a, b), z) in enumerate(zip(sc.ids.tolist(), sc.meas, strict=True)):
        e = EdgeSE3ProjectXYZ(params=CAMERA)
        e.set_vertex(0, verts[a] if n % 2 else a)  # objects or ids
        e.set_vertex(1, verts[b])
        e.set_measurement(z)
        e.set_information(info[n])
        e.set_robust_kernel(RobustKernelHuber(2.0))  # one object per edge, one value
        opt.add_edge(e)
    g_obj, g_bulk = opt.edge_groups(), bulk.edge_groups()
    assert len(g_obj) == len(g_bulk) == 1 and len(g_obj[0].kernels) == 1
    for name in ("vertex_ids", "measurements", "information"):
        np.testing.assert_array_equal(getattr(g_obj[0], name), getattr(g_bulk[0], name))
    r1, r2 = bulk.optimize(10), opt.optimize(10)
    assert r1.chi2_history == r2.chi2_history
    np.testing.assert_array_equal(verts[c + 3].estimate, bulk.vertex(c + 3).estimate)
    assert opt.edges()[5].chi2() == pytest.approx(float(bulk.edge_sets()[0].chi2()[5]), rel=1e-12)


def test_buffered_objects_behave_as_g2o_objects() -> None:
    opt = SparseOptimizer("lm", "dense")
    a, b = VertexSE2(0, [0.0, 0.0, 0.0], fixed=True), VertexSE2(1, [1.0, 0.0, 0.0])
    opt.add_vertex(a)
    opt.add_vertex(b)
    with pytest.raises(GraphError, match=r"duplicate vertex id 1 \(VertexSE2\)"):
        opt.add_vertex(VertexSE2(1, [0.0, 0.0, 0.0]))
    with pytest.raises(GraphError, match="already added"):
        opt.add_vertex(b)
    b.set_estimate([2.0, 0.0, 0.0])  # before the flush: the object's own value is taken
    e = EdgeSE2([a, b], [1.0, 0.0, 0.0])
    opt.add_edge(e)
    with pytest.raises(GraphError, match="already added"):
        opt.add_edge(e)
    e.set_level(1)
    e.set_robust_kernel(RobustKernelCauchy(1.0))
    assert e.level() == 1 and isinstance(e.robust_kernel, RobustKernelCauchy)
    opt.initialize_optimization(1)  # the flush; then the arrays answer
    assert opt.active_edge_count() == 1 and e.level() == 1
    assert e.chi2() == pytest.approx(1.0)
    assert isinstance(e.robust_kernel, RobustKernelCauchy)
    np.testing.assert_array_equal(b.estimate, [2.0, 0.0, 0.0])
    opt.optimize(10)
    np.testing.assert_allclose(b.estimate, [1.0, 0.0, 0.0], atol=1e-6)


def test_kernels_of_one_value_share_a_slot() -> None:
    sc = local_ba_scene(free=2, fixed=1, points=10, per_point=2, outliers=0.0, seed=1)
    opt, _ = build(sc, kernel=False)
    for n, (ids, z) in enumerate(zip(sc.ids.tolist(), sc.meas, strict=True)):
        kernel = RobustKernelHuber(1.0 + n % 2) if n % 3 else None
        opt.add_edge(EdgeSE3ProjectXYZ(ids, z, robust_kernel=kernel, params=CAMERA))
    g = opt.edge_groups()[0]
    assert sorted(k.delta for k in g.kernels) == [1.0, 2.0]
    kernels = [g.kernel_of(i) for i in range(g.size)]
    assert [None if k is None else k.delta for k in kernels[len(sc.ids):]] == [
        None if n % 3 == 0 else 1.0 + n % 2 for n in range(len(sc.ids))]


def test_a_rejected_vertex_takes_its_edges_down_with_a_clear_error() -> None:
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertex(VertexSE2(0, [0.0, 0.0, 0.0], fixed=True))
    opt.add_vertex(VertexSE2(1, [0.0, np.nan, 0.0]))
    opt.add_edge(EdgeSE2([0, 1], [1.0, 0.0, 0.0]))
    with pytest.raises(GraphError, match=r"vertex 1 \(VertexSE2\): invalid estimate"):
        opt.optimize(1)
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 1\]: vertex 1 \(position 1\) "
                                         "does not exist"):
        opt.optimize(1)
    assert opt.num_edges() == 0 and opt.vertex_ids() == [0]


def test_an_edge_returns_the_kernel_object_it_was_given() -> None:
    """Kernels equal by value share one slot of the group; each edge still returns its own
    object, after the flush and after removal, and a kernel set on the group since wins."""
    from graphopt.edge_set import EdgeSet

    sc = local_ba_scene(free=2, fixed=1, points=4, per_point=2, outliers=0.0, seed=1)
    opt, _ = build(sc, rows=np.arange(3, len(sc.ids)))
    kernels, edges = [], []
    for (a, b), z in zip(sc.ids.tolist()[:3], sc.meas[:3], strict=True):
        k = RobustKernelHuber(np.sqrt(5.991))  # equal to build()'s kernel
        e = EdgeSE3ProjectXYZ((a, b), z, params=CAMERA, robust_kernel=k)
        opt.add_edge(e)
        kernels.append(k)
        edges.append(e)
    opt.initialize_optimization()  # flushed: one slot for the three equal kernels
    g = edges[0]._group
    assert len(g.kernels) == 1 and g.kernels[0] is not kernels[1]
    assert [e.robust_kernel for e in edges] == kernels
    assert all(e.robust_kernel is k for e, k in zip(edges, kernels, strict=True))
    other = RobustKernelCauchy(1.0)
    EdgeSet(opt.graph, g, np.array([edges[1]._uid])).set_robust_kernel(other)
    assert edges[1].robust_kernel is other and edges[2].robust_kernel is kernels[2]
    opt.remove_edge(edges[2])
    assert edges[2].robust_kernel is kernels[2]
