"""Editing a graph between runs (graphopt.edge_set, graphopt.activity): levels select edges as
g2o's do, kernels change, edges and vertices go and come back — without a new structure where
only numbers change — and bad edits are clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from ba_scene import CAMERA, build, local_ba_scene
from custom_types import EdgeSE2, VertexSE2, pose_graph

from graphopt import GraphError, RobustKernelHuber, SparseOptimizer, StoppingConfig
from graphopt.lie import transform_points
from graphopt.types import EdgeSE3Expmap, EdgeSE3ProjectXYZ, VertexPointXYZ, VertexSE3Expmap


@pytest.fixture(scope="module")
def scene():
    sc = local_ba_scene(free=4, fixed=2, points=50, per_point=4, outliers=0.0, seed=3)
    # One gross outlier in every third point's observations (each point keeps three inliers:
    # Gauss–Newton needs two), and every observation of point 0 (at level 0 it is idle).
    rng = np.random.default_rng(4)
    out = np.zeros((50, 4), bool)
    out[np.arange(0, 50, 3), rng.integers(0, 4, 17)] = True
    out[0] = True
    sc.outlier = out.ravel()
    sc.meas[sc.outlier] += rng.uniform(20, 60, (int(sc.outlier.sum()), 2))
    return sc


def _estimates(opt: SparseOptimizer, point_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.stack([opt.vertex(int(i)).estimate for i in point_ids])
    return opt.estimates_of(VertexSE3Expmap), pts


def _chi2_by_hand(sc, opt: SparseOptimizer) -> np.ndarray:
    """``eᵀe`` of every observation, projected here, not by the edge type."""
    T = opt.estimates_of(VertexSE3Expmap)[sc.ids[:, 0]]
    X = np.stack([opt.vertex(int(i)).estimate for i in sc.ids[:, 1]])
    P = transform_points(T, X)
    uv = np.column_stack([CAMERA.fx * P[:, 0] / P[:, 2] + CAMERA.cx,
                          CAMERA.fy * P[:, 1] / P[:, 2] + CAMERA.cy])
    return ((sc.meas - uv) ** 2).sum(1)


@pytest.mark.parametrize(("algorithm", "solver"), [("gn", "dense"), ("lm", "cholmod"),
                                                    ("lm", "implicit-schur")])
def test_levels_select_the_edges_as_a_graph_of_the_active_edges_only(scene, algorithm,
                                                                     solver) -> None:
    """Outliers at level 1, the optimizer initialised at level 0: the same chi2 and optimum as
    a graph built from the inliers alone; the idle point (all its edges inactive) stays put
    and does not make Gauss–Newton's system singular."""
    inl = np.flatnonzero(~scene.outlier)
    ref, _ = build(scene, inl, kernel=False, algorithm=algorithm, only_used=True, solver=solver)
    opt, es = build(scene, kernel=False, algorithm=algorithm, solver=solver)
    es.set_level(scene.outlier.astype(int))
    opt.initialize_optimization(0)
    assert opt.active_edge_count() == len(inl)
    assert opt.chi2() == pytest.approx(ref.chi2(), rel=1e-12)
    idle = len(scene.poses)
    before = opt.vertex(idle).estimate
    r1, r2 = ref.optimize(15), opt.optimize(15)
    assert r2.final_chi2 == pytest.approx(r1.final_chi2, rel=1e-9)
    assert r2.final_chi2 < 0.05 * r2.initial_chi2
    used = np.unique(scene.ids[inl, 1])
    for a, b in zip(_estimates(opt, used), _estimates(ref, used), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-5 if solver == "implicit-schur" else 1e-7)
    np.testing.assert_array_equal(opt.vertex(idle).estimate, before)
    # Level 1 alone: the outliers are the active edges now, the same structure.
    p = opt.problem
    opt.initialize_optimization(1)
    assert opt.problem is p and opt.active_edge_count() == int(scene.outlier.sum())
    assert opt.chi2() == pytest.approx(es.chi2()[scene.outlier].sum(), rel=1e-12)


def test_a_pose_whose_edges_are_all_inactive_does_not_move(scene) -> None:
    opt, es = build(scene, kernel=False, algorithm="gn")
    # The outliers and every observation by free keyframe 1 to level 1.
    levels = (scene.outlier | (scene.ids[:, 0] == 1)).astype(int)
    es.set_level(levels)
    before = opt.vertex(1).estimate
    res = opt.optimize(5)
    assert res.final_chi2 < 0.05 * res.initial_chi2
    np.testing.assert_array_equal(opt.vertex(1).estimate, before)


def test_chi2_per_edge_is_the_kernel_free_error_of_every_level(scene) -> None:
    opt, es = build(scene)
    opt.optimize(3)
    np.testing.assert_allclose(es.chi2(), _chi2_by_hand(scene, opt), rtol=1e-10)
    e = es.errors()
    assert e.shape == (len(es), 2)
    np.testing.assert_allclose((e**2).sum(1), es.chi2(), rtol=1e-12)
    es.set_level(scene.outlier.astype(int))  # per-edge chi2 does not depend on the level
    np.testing.assert_allclose(es.chi2(), _chi2_by_hand(scene, opt), rtol=1e-10)
    assert opt.chi2() == pytest.approx(es.chi2()[~scene.outlier].sum(), rel=1e-12)
    sub = es[scene.outlier]
    assert len(sub) == int(scene.outlier.sum())
    np.testing.assert_array_equal(sub.levels(), 1)
    np.testing.assert_array_equal(sub.ids, scene.ids[scene.outlier])
    np.testing.assert_allclose(sub.chi2(), es.chi2()[scene.outlier])


def test_chi2_after_a_run_with_inactive_edges_is_every_edges_own(scene) -> None:
    """The queries after a run reuse the run's last evaluation (ORB-SLAM's outlier checks):
    inactive edges get their own chi2 too, not the zero the optimiser weighs them with, and an
    edge removed and added again is not given another edge's value."""
    opt, es = build(scene)
    es.set_level(scene.outlier.astype(int))
    opt.initialize_optimization(0)
    opt.optimize(3)
    g = es.group
    assert g.raw_eval is not None and g.raw_eval[1].shape == (len(es), 2)  # reused below
    chi2 = es.chi2()
    np.testing.assert_allclose(chi2, _chi2_by_hand(scene, opt), rtol=1e-10)
    assert chi2[scene.outlier].min() > 100.0  # the gross outliers, not zeroed
    assert opt.chi2() == pytest.approx(chi2[~scene.outlier].sum(), rel=1e-12)
    first = np.arange(len(es)) == 0
    rest = es[~first]
    es[first].remove()
    again = opt.add_edges(EdgeSE3ProjectXYZ, scene.ids[:1], scene.meas[:1], params=CAMERA)
    assert again.group is g
    opt.optimize(1)
    by_hand = _chi2_by_hand(scene, opt)
    np.testing.assert_allclose(rest.chi2(), by_hand[1:], rtol=1e-10)
    np.testing.assert_allclose(again.chi2(), by_hand[:1], rtol=1e-10)


def test_dropping_the_kernel_reaches_the_kernel_free_optimum_on_the_same_structure(scene):
    inl = np.flatnonzero(~scene.outlier)
    ref, _ = build(scene, inl, kernel=False)
    ref.stopping = StoppingConfig.iterations_only()
    ref.optimize(40)
    opt, es = build(scene, inl)  # Huber kernels
    opt.stopping = ref.stopping
    opt.optimize(5)
    p = opt.problem
    es.set_robust_kernel(None)
    opt.initialize_optimization()
    assert opt.problem is p and opt.problem.system.pattern is p.system.pattern
    opt.optimize(40)
    assert opt.problem is p
    assert opt.chi2() == pytest.approx(ref.chi2(), rel=1e-9)
    assert opt.active_robust_chi2() == opt.chi2()
    np.testing.assert_allclose(opt.estimates_of(VertexPointXYZ), ref.estimates_of(VertexPointXYZ),
                               atol=1e-7)
    es[:3].set_robust_kernel(RobustKernelHuber(1.0))  # a kernel on some edges only
    assert opt.active_robust_chi2() < opt.chi2()


def test_remove_and_add_again(scene) -> None:
    """Outliers removed: the inlier graph's optimum (a new structure); added back: the whole
    graph's. Another set's removal leaves a set valid; a removed set's edges raise."""
    full, _ = build(scene)
    full.optimize(20)
    inl = np.flatnonzero(~scene.outlier)
    ref, _ = build(scene, inl)
    ref.optimize(20)
    opt, es = build(scene)
    bad = es[scene.outlier]
    good = es[~scene.outlier]
    chi_good = good.chi2()
    bad.remove()
    assert len(bad) == 0 and opt.num_edges() == len(inl)
    np.testing.assert_array_equal(good.chi2(), chi_good)
    np.testing.assert_array_equal(good.ids, scene.ids[inl])
    opt.optimize(20)
    assert opt.chi2() == pytest.approx(ref.chi2(), rel=1e-8)
    np.testing.assert_allclose(opt.estimates_of(VertexSE3Expmap),
                               ref.estimates_of(VertexSE3Expmap), atol=1e-7)
    stale = es[scene.outlier]
    with pytest.raises(GraphError, match=r"EdgeSet of EdgeSE3ProjectXYZ: \d+ of these \d+ edges "
                                         "were removed"):
        stale.chi2()
    with pytest.raises(GraphError, match="were removed"):
        stale.set_level(1)
    # The idle point is used by no edge now: it can go, and come back.
    idle = len(scene.poses)
    with pytest.raises(GraphError, match=r"vertices \[\d+\] are still used by \d+ "
                                         "EdgeSE3ProjectXYZ edges"):
        opt.remove_vertices([idle + 1])
    v = opt.vertex(idle)
    opt.remove_vertices([idle])
    assert opt.vertex(idle) is None and v.estimate.shape == (3,)
    opt.add_vertices(VertexPointXYZ, [idle], scene.points[:1], marginalized=True)
    back = opt.add_edges(EdgeSE3ProjectXYZ, scene.ids[scene.outlier], scene.meas[scene.outlier],
                         params=CAMERA, robust_kernel=RobustKernelHuber(np.sqrt(5.991)))
    assert opt.num_edges() == len(scene.ids) and len(back) == int(scene.outlier.sum())
    opt.set_estimates_of(VertexSE3Expmap, scene.poses)
    opt.set_estimates_of(VertexPointXYZ, scene.points[np.argsort(opt.ids_of(VertexPointXYZ))
                                                      .argsort()])
    opt.optimize(20)
    assert opt.chi2() == pytest.approx(full.chi2(), rel=1e-6)


def test_single_edges_levels_and_removal() -> None:
    _, init, edges, meas = pose_graph(5)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, np.arange(5), init, fixed=np.arange(5) == 0)
    objs = [EdgeSE2(list(map(int, e)), z) for e, z in zip(edges, meas, strict=True)]
    for e in objs:
        opt.add_edge(e)
    chi = [e.chi2() for e in objs]
    assert sum(chi) == pytest.approx(opt.chi2(), rel=1e-12)
    objs[1].set_level(2)
    assert objs[1].level() == 2 and objs[0].level() == 0
    assert opt.chi2() == pytest.approx(sum(chi) - chi[1], rel=1e-12)
    opt.remove_edge(objs[0])
    assert opt.num_edges() == len(objs) - 1
    with pytest.raises(ValueError, match="not in an optimizer"):
        objs[0].chi2()
    assert objs[2].chi2() == pytest.approx(chi[2], rel=1e-12)  # its index moved
    with pytest.raises(GraphError, match="is not in this optimizer"):
        opt.remove_edge(objs[0])
    opt.add_edge(objs[0])  # removed objects can be added again
    assert objs[0].chi2() == pytest.approx(chi[0], rel=1e-12)
    for e in objs:
        if 4 in [v if isinstance(v, int) else v.id for v in e.vertices]:
            opt.remove_edge(e)
    v4 = opt.vertex(4)
    assert opt.remove_vertex(v4) and opt.vertex(4) is None and 4 not in opt.vertex_ids()
    np.testing.assert_array_equal(v4.estimate, init[4])
    assert opt.optimize(5).final_chi2 < 1e-6 + opt.chi2()


def test_bad_edits_are_clear_errors(scene) -> None:
    opt, es = build(scene)
    m = len(es)
    for bad in (-1, 1.5, True, "1", np.zeros(m - 1, int), np.full(m, 0.0), np.full((m, 1), 1)):
        with pytest.raises(GraphError, match="EdgeSet of EdgeSE3ProjectXYZ.set_level: levels"):
            es.set_level(bad)
    for bad in (-2, 0.5, None):
        with pytest.raises(GraphError, match="a level must be a non-negative integer"):
            opt.initialize_optimization(bad)
    with pytest.raises(GraphError, match=rf"a mask must have shape \({m},\), got \(3,\)"):
        es[np.ones(3, bool)]
    with pytest.raises(GraphError, match="index out of range"):
        es[[m]]
    with pytest.raises(GraphError, match="select with a"):
        es[[0.5]]
    with pytest.raises(GraphError, match=r"remove\): a mask must have shape"):
        es.remove(np.ones(2, bool))
    with pytest.raises(GraphError, match="robust_kernel must be a RobustKernel or None"):
        es.set_robust_kernel("huber")
    ep = opt.add_edges(EdgeSE3Expmap, [[0, 1]], np.eye(4)[None])
    with pytest.raises(GraphError, match="EdgeSE3Expmap has no depth_positive"):
        ep.is_depth_positive()
    ep.remove()
    with pytest.raises(GraphError, match=r"no vertex with id \[999\]"):
        opt.remove_vertices([999])
    with pytest.raises(GraphError, match="a level must be a non-negative integer"):
        EdgeSE2().set_level(-3)
    es.remove()
    assert len(es) == 0 and opt.num_edges() == 0


def test_a_level_change_reuses_the_problem_and_gives_fresh_results(scene) -> None:
    """No rebuild for levels, kernels or estimates (the same Problem, pattern and solver),
    and chi2 queries are never stale after an edit."""
    opt, es = build(scene)
    opt.optimize(3)
    p, solver = opt.problem, opt.solver
    c0 = opt.chi2()
    es.set_level(scene.outlier.astype(int))
    c1 = opt.chi2()
    assert c1 < c0 and opt.problem is p
    opt.set_estimates_of(VertexSE3Expmap, scene.poses)
    assert opt.chi2() != c1
    opt.initialize_optimization(0)
    opt.optimize(3)
    assert opt.problem is p and opt.solver is solver
    es[:1].remove()  # removing edges rebuilds
    opt.optimize(1)
    assert opt.problem is not p


class EdgeWithDepth(EdgeSE3ProjectXYZ):
    """The projection edge with a depth test (types22 adds g2o's to the projection types)."""

    @classmethod
    def depth_positive(cls, x, measurement, ctx):
        return transform_points(x[0], x[1])[:, 2] > 0.0


def test_is_depth_positive_gathers_the_estimates_of_the_set(scene) -> None:
    opt = SparseOptimizer()
    c = len(scene.poses)
    opt.add_vertices(VertexSE3Expmap, np.arange(c), scene.poses, fixed=scene.fixed)
    pts = scene.points.copy()
    pts[::7, 2] *= -1.0  # behind every camera
    opt.add_vertices(VertexPointXYZ, c + np.arange(len(pts)), pts, marginalized=True)
    es = opt.add_edges(EdgeWithDepth, scene.ids, scene.meas, params=CAMERA)
    behind = (scene.ids[:, 1] - c) % 7 == 0
    np.testing.assert_array_equal(es.is_depth_positive(), ~behind)
    np.testing.assert_array_equal(es[behind].is_depth_positive(), False)
    # One edge at a time (g2o's isDepthPositive): the same answers, from one group evaluation.
    objs = [EdgeWithDepth(list(map(int, ids)), z, params=CAMERA)
            for ids, z in zip(scene.ids[:20], scene.meas[:20], strict=True)]
    for e in objs:
        opt.add_edge(e)
    assert [e.is_depth_positive() for e in objs] == (~behind[:20]).tolist()


def test_a_kernel_width_changed_in_place_is_seen_by_the_next_query_and_run() -> None:
    """``kernel.set_delta`` after a run (g2o: the edge holds the kernel's pointer): the robust
    chi2 queried and the next run use the new width, not values cached by the last trial step
    at the same estimates."""
    truth, init, edges, meas = pose_graph(20, seed=1, noise=(0.3, 0.1))

    def make(delta: float, est: np.ndarray) -> tuple[SparseOptimizer, RobustKernelHuber]:
        opt = SparseOptimizer()
        opt.add_vertices(VertexSE2, np.arange(20), est, fixed=np.arange(20) == 0)
        k = RobustKernelHuber(delta)
        opt.add_edges(EdgeSE2, edges, meas, robust_kernel=k)
        return opt, k

    opt, k = make(0.5, init)
    opt.optimize(2)
    est = opt.estimates_of(VertexSE2).copy()
    k.set_delta(0.05)
    ref, _ = make(0.05, est)
    assert opt.active_robust_chi2() == pytest.approx(ref.active_robust_chi2(), rel=1e-12)
    opt.initialize_optimization()  # λ from the τ rule again, as in a fresh optimizer
    opt.optimize(1)
    ref.optimize(1)
    np.testing.assert_allclose(opt.estimates_of(VertexSE2), ref.estimates_of(VertexSE2),
                               rtol=0, atol=1e-12)


def test_equal_kernels_are_merged_and_a_width_changed_on_one_is_not_lost() -> None:
    """Equal kernel objects share one slot (one robustify per value); a width set afterwards
    on one of them would reach the other's edges: a clear error instead, and setting the
    changed kernel on its edges again gives the run with each edge's own width."""
    truth, init, edges, meas = pose_graph(20, seed=1, noise=(0.3, 0.1))
    half = np.arange(len(edges)) < len(edges) // 2

    def make(da: float, db: float, objects: bool = False):
        opt = SparseOptimizer()
        opt.add_vertices(VertexSE2, np.arange(20), init, fixed=np.arange(20) == 0)
        a, b = RobustKernelHuber(da), RobustKernelHuber(db)
        if objects:  # one object per edge, g2o style: filed by value
            for e, z, h in zip(edges, meas, half, strict=True):
                opt.add_edge(EdgeSE2(list(map(int, e)), z, robust_kernel=RobustKernelHuber(
                    da if h else db)))
            return opt, None, None, None
        opt.add_edges(EdgeSE2, edges[half], meas[half], robust_kernel=a)
        sb = opt.add_edges(EdgeSE2, edges[~half], meas[~half], robust_kernel=b)
        return opt, a, b, sb

    ref, *_ = make(0.5, 0.05)
    expected = ref.active_robust_chi2()
    opt, a, b, sb = make(0.5, 0.5)
    assert len(sb.group.kernels) == 1  # merged
    b.set_delta(0.05)
    with pytest.raises(GraphError, match="were equal when their edges were added and now differ"):
        opt.active_robust_chi2()
    sb.set_robust_kernel(b)  # the remedy
    assert opt.active_robust_chi2() == pytest.approx(expected, rel=1e-12)
    a.set_delta(0.7)  # one object on its own edges only: fine, and seen
    ref2, *_ = make(0.7, 0.05)
    assert opt.active_robust_chi2() == pytest.approx(ref2.active_robust_chi2(), rel=1e-12)
    objs, *_ = make(0.5, 0.5, objects=True)
    objs.optimize(1)
    objs.edges()[-1].robust_kernel.set_delta(0.05)
    with pytest.raises(GraphError, match="now differ"):
        objs.optimize(1)


def test_values_of_an_added_edge_that_cannot_change_raise_instead_of_being_ignored() -> None:
    """g2o lets ``setMeasurement`` follow ``addEdge``; here the measurement, information and
    vertices of an edge in the arrays are structure: changing them is a clear error (remove
    the edge and add it again), not a setter whose value the optimizer never sees."""
    opt = SparseOptimizer()
    opt.add_vertices(VertexSE2, [0, 1], [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], fixed=[True, False])
    e = EdgeSE2([0, 1], np.array([1.0, 0.0, 0.0]))
    opt.add_edge(e)
    e.set_measurement(np.array([1.5, 0.0, 0.0]))  # still buffered: taken at the flush
    opt.optimize(1)
    np.testing.assert_array_equal(e.measurement, [1.5, 0.0, 0.0])
    for call in (lambda: e.set_measurement(np.array([2.0, 0.0, 0.0])),
                 lambda: e.set_information(np.eye(3) * 2.0), lambda: e.set_vertex(1, 0)):
        with pytest.raises(GraphError, match=r"EdgeSE2\(vertices=\[0, 1\]\).*remove_edge"):
            call()
    np.testing.assert_array_equal(e.measurement, [1.5, 0.0, 0.0])
    opt.remove_edge(e)
    e.set_measurement(np.array([2.0, 0.0, 0.0]))  # a removed edge is a free object again
    opt.add_edge(e)
    opt.initialize_optimization()
    opt.optimize(5)
    np.testing.assert_allclose(opt.vertex(1).estimate, [2.0, 0.0, 0.0], atol=1e-9)


def test_every_optimize_call_starts_lambda_from_its_rule(scene) -> None:
    """g2o (λ from computeLambdaInit at iteration 0 of every optimize) and Ceres (every Solve)
    start each run's damping afresh: two runs in a row equal two runs with an
    initialize_optimization between them, and the second run's first λ is τ·max diag(H)."""
    runs = []
    for reinit in (False, True):
        opt, _ = build(scene)
        opt.optimize(2)
        if reinit:
            opt.initialize_optimization()
        res = opt.optimize(3)
        runs.append((res.info[0].lam, _estimates(opt, np.unique(scene.ids[:, 1]))))
    assert runs[0][0] == runs[1][0]
    for a, b in zip(runs[0][1], runs[1][1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_whole_groups_set_reads_and_edits_its_arrays_whole(scene) -> None:
    """A set of every edge of its group (``add_edges``' or ``edge_sets()``') is read and edited
    without an index; a set as long as the group but with an edge twice (indexing) is not
    taken for the whole group. Both give the indexed set's numbers; dropping the one kernel
    leaves a broadcast kernel index and no kernel."""
    opt, es = build(scene)
    g = es.group
    m = len(es)
    assert m == g.size and es._whole(es._rows())
    twice = es[np.r_[0, np.arange(m - 1)]]  # edge 0 twice, the last edge missing
    assert len(twice) == m and not twice._whole(twice._rows())
    levels = (np.arange(m) % 7 == 0).astype(int)
    twice.set_level(np.r_[5, levels[:-1]])  # edge 0 gets 5, then its own level
    assert g.levels[-1] == 0 and g.levels[0] == levels[0]
    es.set_level(levels)
    np.testing.assert_array_equal(es.levels(), levels)
    np.testing.assert_array_equal(twice.levels(), np.r_[levels[0], levels[:-1]])
    np.testing.assert_allclose(es.chi2(), _chi2_by_hand(scene, opt), rtol=1e-12)
    np.testing.assert_array_equal(twice.chi2(), es.chi2()[np.r_[0, np.arange(m - 1)]])
    out = es.chi2()
    out[:] = -1.0  # a copy: the cached values stay
    assert (es.chi2() >= 0).all()
    twice.set_robust_kernel(None)  # all but the last edge
    assert len(g.kernels) == 1 and g.kernel_of(m - 1) is not None
    (opt.edge_sets()[0]).set_robust_kernel(None)
    assert g.kernels == [] and g.kernel_index.strides == (0,) and g.kernel_of(m - 1) is None
    assert opt.chi2() == pytest.approx(float(_chi2_by_hand(scene, opt)[levels == 0].sum()),
                                       rel=1e-12)
