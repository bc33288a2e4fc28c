"""The fast paths of the first ``initialize_optimization`` against their general twins: slots of
consecutive ids by a subtraction (graphopt.g2o's banks and the graph's resolve), the vertex-id
check by a set, one kernel for a batch handed to ``add_edges``, a whole batch's kernels and
levels written as one broadcast, the information tests of a finalised group, ``Xw`` joined as
bytes, and one validated estimate not validated again — each giving the same arrays or errors
as the path it short-cuts."""

from __future__ import annotations

import numpy as np
import pytest
from custom_types import EdgeSE2, VertexSE2, pose_graph

import graphopt.g2o as g2o
import graphopt.g2o.filing as filing
from graphopt import GraphError, RobustKernelHuber, SparseOptimizer
from graphopt.edge_group import EdgeGroup
from graphopt.g2o.vertices import Bank

FX, FY, CX, CY = 500.0, 480.0, 320.0, 240.0


def _bank(ids: list[int]) -> Bank:
    recs = []
    for i in ids:
        v = g2o.VertexPointXYZ()
        v.set_id(i)
        recs.append(v)
    return Bank(VertexSE2, recs, np.zeros((len(ids), 3)))


@pytest.mark.parametrize("ids", [[7, 8, 9, 10, 11], [7], [7, 8], [7, 9, 8, 11, 10], [11, 3, 5], []])
def test_bank_slots_of_consecutive_and_other_ids(ids: list[int]) -> None:
    """(graphopt.linear.indexing.IdLookup, which the graph's resolve uses too.)"""
    bank = _bank(ids)
    where = {v: s for s, v in enumerate(ids)}
    probe = np.array([*ids[::-1], min(ids, default=7) - 1, max(ids, default=7) + 1, -3, 6, 12,
                      2**40])
    slots, ok = bank.slots_of(probe)
    expected_ok = np.array([int(p) in where for p in probe])
    np.testing.assert_array_equal(ok, expected_ok)
    np.testing.assert_array_equal(slots[ok], [where[int(p)] for p in probe[ok]])


def _two_stores(consecutive: bool) -> tuple[SparseOptimizer, np.ndarray]:
    _, init, edges, meas = pose_graph(8)
    ids = np.arange(8) + 100 if consecutive else np.array([100, 103, 101, 107, 102, 104, 106, 105])
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, ids, init, fixed=np.arange(8) == 0)
    return opt, ids[edges]


@pytest.mark.parametrize("consecutive", [True, False])
def test_resolve_slots_by_subtraction_match_the_search(consecutive: bool) -> None:
    opt, vids = _two_stores(consecutive)
    _, _, _, meas = pose_graph(8)
    opt.add_edges(EdgeSE2, vids, meas)
    stores, _, positions = opt.graph.resolve()
    for a in range(2):
        si, slots = positions[0][a]
        np.testing.assert_array_equal(stores[si].ids[slots], vids[:, a])


def test_resolve_still_names_a_vertex_of_another_type() -> None:
    """Consecutive ids (the subtraction path): a vertex of another store at a position is the
    graph's error naming both types, not a wrong slot."""

    class OtherSE2(VertexSE2):
        pass

    class LooseSE2(EdgeSE2):
        vertex_types = (VertexSE2, VertexSE2)

    _, init, edges, meas = pose_graph(8)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, np.arange(4), init[:4])
    opt.add_vertices(OtherSE2, np.arange(4, 8), init[4:])
    keep = (edges < 4).all(axis=1)
    opt.add_edges(LooseSE2, np.vstack([edges[keep], [[0, 5]]]),
                  np.vstack([meas[keep], meas[:1]]))
    with pytest.raises(GraphError, match=r"position 1 mixes vertex types \(VertexSE2 and "
                                         r"OtherSE2, vertex 5\)"):
        opt.graph.resolve()


def _motion_only(n: int, kernel: bool = True) -> tuple[g2o.SparseOptimizer, list]:
    opt = g2o.SparseOptimizer()
    opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(g2o.BlockSolverSE3(
        g2o.LinearSolverDenseSE3())))
    v = g2o.VertexSE3Expmap()
    v.set_id(0)
    v.set_estimate(g2o.SE3Quat(np.eye(3), np.array([0.05, -0.02, 0.1])))
    opt.add_vertex(v)
    rng = np.random.default_rng(1)
    edges = []
    for _ in range(n):
        X = rng.random(3) + [0.0, 0.0, 4.0]
        e = g2o.EdgeSE3ProjectXYZOnlyPose()
        e.set_vertex(0, v)
        e.set_measurement(np.array([FX * X[0] / X[2] + CX, FY * X[1] / X[2] + CY]) + 1.0)
        e.set_information(np.identity(2))
        if kernel:
            e.set_robust_kernel(g2o.RobustKernelHuber(2.0))
        e.fx, e.fy, e.cx, e.cy = FX, FY, CX, CY
        e.Xw = X
        opt.add_edge(e)
        edges.append(e)
    return opt, edges


@pytest.mark.parametrize("n", [5, 600])
def test_a_missing_vertex_is_named_by_the_set_and_the_isin_check(n: int) -> None:
    """(5 edges: the set of ids; 600 two-vertex edges, 1,200 ids: ``np.isin``.)"""
    assert (n * 2 > filing._SET_CHECK) == (n == 600)
    opt = g2o.SparseOptimizer()
    cam = g2o.VertexSE3Expmap()
    cam.set_id(0)
    cam.set_estimate(g2o.SE3Quat())
    opt.add_vertex(cam)
    for j in range(n):
        p = g2o.VertexPointXYZ()
        p.set_id(1 + j)
        p.set_estimate(np.array([0.0, 0.0, 5.0]))
        e = g2o.EdgeSE3ProjectXYZ()
        e.set_vertex(0, p)
        e.set_vertex(1, cam)
        e.set_measurement(np.array([CX, CY]))
        e.fx, e.fy, e.cx, e.cy = FX, FY, CX, CY
        if j != n - 2:  # that point is never added; its edge still is
            opt.add_vertex(p)
        opt.add_edge(e)
    with pytest.raises(GraphError, match=rf"EdgeSE3ProjectXYZ on vertices \[{n - 1}, 0\]: vertex "
                                         rf"{n - 1} \(position 0\) was not added"):
        opt.initialize_optimization()


def test_one_kernel_for_all_and_mixed_kernels_reach_the_group() -> None:
    """One Huber width for every edge goes to add_edges as one broadcast slot; a second width
    on some edges takes the per-code pass: the robust chi2 is the sum of the kernels' costs."""
    opt, edges = _motion_only(8)
    opt.initialize_optimization()
    g = opt.core.edge_groups()[0]
    assert g.sole_kernel is not None and g.kernel_index.strides == (0,)
    for e in edges[:3]:
        e.set_robust_kernel(g2o.RobustKernelHuber(0.5))
    opt.initialize_optimization()
    opt.compute_active_errors()
    chi2 = np.array([e.chi2() for e in edges])
    expected = sum(float(RobustKernelHuber(0.5 if i < 3 else 2.0).cost(np.array([c]))[0])
                   for i, c in enumerate(chi2))
    assert opt.active_robust_chi2() == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(g.kernel_index >= 0, True)
    assert len(g.kernels) == 2


def test_kernels_and_levels_of_a_whole_batch_are_one_write() -> None:
    """Dropping every kernel (an outlier pass's last rounds) gives the group one broadcast
    ``-1`` and the chi2 of a run that never had kernels; levels set on every edge give the same
    active set as the general path."""
    opt, edges = _motion_only(10)
    plain, plain_edges = _motion_only(10, kernel=False)
    opt.initialize_optimization()
    for e in edges:
        e.set_robust_kernel(None)
    for i, (e, f) in enumerate(zip(edges, plain_edges, strict=True)):
        e.set_level(i % 3 == 0)
        f.set_level(i % 3 == 0)
    for o in (opt, plain):
        o.initialize_optimization(0)
        o.optimize(5)
    g = opt.core.edge_groups()[0]
    assert g.sole_kernel is None and not g.kernels and (g.kernel_index == -1).all()
    np.testing.assert_array_equal(g.levels, [i % 3 == 0 for i in range(10)])
    assert opt.active_robust_chi2() == opt.active_chi2() == plain.active_chi2()


def test_set_kernel_on_every_edge_is_the_index_write() -> None:
    _, init, edges, meas = pose_graph(8)
    groups = []
    for rows in (slice(None), np.arange(len(edges))):
        opt = SparseOptimizer("lm", "dense")
        opt.add_vertices(VertexSE2, np.arange(8), init)
        es = opt.add_edges(EdgeSE2, edges, meas, robust_kernel=RobustKernelHuber(1.0))
        k = RobustKernelHuber(0.1)
        es.group.set_kernel(rows, k)
        groups.append(es.group)
    whole, indexed = groups
    np.testing.assert_array_equal(whole.kernel_index, indexed.kernel_index)
    assert whole.kernel_index.strides == (0,)
    assert [k.delta for k in whole.kernels] == [k.delta for k in indexed.kernels] == [0.1]


@pytest.mark.parametrize("info", [np.eye(3), np.diag([1.0, 4.0, 9.0]), np.diag([1.0, 0.0, 2.0]),
                                  np.array([[2.0, 0.5, 0.0], [0.5, 2.0, 0.0], [0.0, 0.0, 1.0]]),
                                  "per-edge-diagonal", "per-edge"])
def test_finalised_information_flags_match_a_direct_test(info: object) -> None:
    _, init, edges, meas = pose_graph(8)
    m = len(edges)
    if isinstance(info, str) and info == "per-edge-diagonal":
        info = np.stack([np.diag([1.0 + i, 2.0, 3.0]) for i in range(m)])
    elif isinstance(info, str):
        info = np.stack([np.eye(3) + 0.1 * i * (np.ones((3, 3)) - np.eye(3)) / m
                         for i in range(m)])
    g = EdgeGroup(EdgeSE2, None)
    g.append(edges, meas, np.asarray(info), -1, {})
    g.finalize()
    full = np.broadcast_to(g.information, (m, 3, 3))
    diagonal = not np.count_nonzero(full - full * np.eye(3))
    assert g.info_is_identity == (g.information.ndim == 2 and np.array_equal(g.information,
                                                                             np.eye(3)))
    assert (g.info_diagonal is not None) == diagonal
    if diagonal:
        np.testing.assert_array_equal(np.broadcast_to(g.info_diagonal, (m, 3)),
                                      full.diagonal(0, 1, 2))


@pytest.mark.parametrize("form", ["float64", "list", "float32", "column", "view"])
def test_xw_in_any_form_files_to_the_same_points(form: str) -> None:
    opt, edges = _motion_only(4)
    ref = np.array([e.Xw for e in edges])
    for e, x in zip(edges, ref, strict=True):
        e.Xw = {"float64": x.copy(), "list": x.tolist(), "float32": x.astype(np.float32),
                "column": x.reshape(3, 1).copy(),
                "view": np.repeat(x, 2)[::2]}[form]
    opt.initialize_optimization()
    batch = next(iter(opt._batches))
    expected = ref.astype(np.float32).astype(float) if form == "float32" else ref
    np.testing.assert_array_equal(batch.data["Xw"], expected)


def test_xw_of_wrong_sizes_is_not_joined() -> None:
    """Sizes 2 and 4 make as many bytes as two points of 3: the join is refused (an error)."""
    opt, edges = _motion_only(2)
    edges[0].Xw, edges[1].Xw = np.ones(2), np.ones(4)
    with pytest.raises(ValueError):
        opt.initialize_optimization()


def test_a_validated_pose_is_not_validated_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pose checked at filing, set again each round (a motion-only BA's reset), skips the
    check; another valid value is checked once; an invalid one is still refused, naming it."""
    opt, _ = _motion_only(3)
    start = opt.vertex(0).estimate()
    opt.initialize_optimization()
    st = opt.core.graph.stores[g2o.vertices.core_type("VertexSE3Expmap")]
    calls = []
    original = st.vtype.validate
    monkeypatch.setattr(st.vtype, "validate", classmethod(
        lambda cls, est: calls.append(len(est)) or original(est)))
    opt.vertex(0).set_estimate(start)
    assert calls == []
    moved = g2o.SE3Quat(start.rotation().matrix(), start.translation() + 1.0)
    opt.vertex(0).set_estimate(moved)
    opt.vertex(0).set_estimate(moved)
    assert calls == [1]
    bad = g2o.Isometry3d(np.diag([1.0, 1.0, 2.0]), np.zeros(3))
    with pytest.raises(GraphError, match=r"vertex 0 \(VertexSE3Expmap\): invalid estimate"):
        opt.vertex(0).set_estimate(bad)


def test_a_store_owns_its_first_chunk() -> None:
    """The first add_vertices of a store is taken without a concatenation: the caller's arrays
    stay the caller's."""
    _, init, _, _ = pose_graph(5)
    ids, fixed = np.arange(5), np.zeros(5, bool)
    est = init.copy()
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, ids, est, fixed=fixed)
    ids += 10
    est += 1.0
    fixed[:] = True
    st = opt.graph.stores[VertexSE2]
    np.testing.assert_array_equal(st.ids, np.arange(5))
    np.testing.assert_array_equal(st.estimates, init)
    assert not st.fixed.any() and len(st) == 5


def test_vertices_of_the_wrong_type_are_still_named() -> None:
    """The graph skips its per-id check when the batch's banks vouch for the ids; a bank of
    another type than the edge type's position (the vertices swapped) is still refused."""
    opt = g2o.SparseOptimizer()
    cam, p = g2o.VertexSE3Expmap(), g2o.VertexPointXYZ()
    cam.set_id(0)
    cam.set_estimate(g2o.SE3Quat())
    p.set_id(1)
    p.set_estimate(np.array([0.0, 0.0, 5.0]))
    opt.add_vertex(cam)
    opt.add_vertex(p)
    e = g2o.EdgeSE3ProjectXYZ()
    e.set_vertex(0, cam)  # g2o's order is (point, pose)
    e.set_vertex(1, p)
    e.set_measurement(np.array([CX, CY]))
    opt.add_edge(e)
    with pytest.raises(GraphError, match=r"vertex 1 is a VertexPointXYZ, position 0 needs a "
                                         r"VertexSE3Expmap"):
        opt.initialize_optimization()


@pytest.mark.parametrize("cls", [g2o.EdgeSE3ProjectXYZOnlyPose, g2o.EdgeProjectXYZ2UV])
def test_batches_by_shared_key_and_by_keys(cls: type) -> None:
    """One key for every edge (compared attribute by attribute) and several keys (one tuple
    per edge) bucket as a direct grouping by ``_params_key`` does, in the order added."""
    for split in (False, True):
        recs = [cls() for _ in range(7)]
        for i, e in enumerate(recs):
            if split and i % 3 == 1:
                if cls is g2o.EdgeProjectXYZ2UV:
                    e.set_parameter_id(0, 4)
                else:
                    e.fx = 900.0
        buckets = filing.bucket_edges(recs)
        expected: dict = {}
        for e in recs:
            expected.setdefault((cls, e._params_key()), []).append(e)
        assert list(buckets) == list(expected) and len(buckets) == 1 + split
        for k, v in expected.items():
            assert buckets[k] == v
