"""The graph: what add_vertices/add_edges keep, and what a rejected call leaves behind
(graphopt.graph, graphopt.storage)."""

from __future__ import annotations

import numpy as np
import pytest
from custom_types import EdgeSE2, VertexSE2, pose_graph

from graphopt import GraphError, SparseOptimizer


def test_rejected_add_edges_leaves_no_group_behind() -> None:
    _, init, edges, meas = pose_graph(6)
    results = []
    for reject_first in (True, False):
        opt = SparseOptimizer("lm", "dense")
        opt.add_vertices(VertexSE2, np.arange(6), init, fixed=np.arange(6) == 0)
        if reject_first:
            with pytest.raises(GraphError, match="vertex 99 .* does not exist"):
                opt.add_edges(EdgeSE2, [[0, 99]], meas[:1])
            assert opt.edge_groups() == [] and opt.num_edges() == 0
        opt.add_edges(EdgeSE2, edges, meas)
        results.append(opt.optimize(10))
    assert results[0].final_chi2 == results[1].final_chi2
    assert results[0].final_chi2 < 0.1 * results[0].initial_chi2


def test_adding_zero_edges_is_a_no_op() -> None:
    _, init, edges, meas = pose_graph(6)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, np.arange(6), init, fixed=np.arange(6) == 0)
    opt.add_edges(EdgeSE2, np.zeros((0, 2), int), np.zeros((0, 3)))
    assert opt.edge_groups() == []
    opt.add_edges(EdgeSE2, edges, meas)
    opt.add_edges(EdgeSE2, np.zeros((0, 2), int), np.zeros((0, 3)))
    assert [g.size for g in opt.edge_groups()] == [len(edges)]


def test_resolve_maps_ids_to_slots_in_any_order() -> None:
    """Vertices added in shuffled id order: every edge position gets the right slot."""
    _, init, edges, meas = pose_graph(8)
    order = np.random.default_rng(0).permutation(8)
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, order[:5], init[order[:5]])
    opt.add_vertices(VertexSE2, order[5:], init[order[5:]])
    opt.add_edges(EdgeSE2, edges, meas)
    stores, groups, positions = opt.graph.resolve()
    assert len(stores) == 1 and len(groups) == 1
    for a in range(2):
        si, slots = positions[0][a]
        np.testing.assert_array_equal(stores[si].ids[slots], edges[:, a])


def test_measurement_derived_values_reach_the_edges_and_are_checked() -> None:
    """``measurement_derived`` runs once per finalised group; its rows reach ``ctx.measured``
    (sliced with the edges), and a result of the wrong shape names the type."""
    seen: list[np.ndarray] = []

    class Tagged(EdgeSE2):
        @classmethod
        def measurement_derived(cls, measurements):
            return measurements[:, :1] * 10.0

        @classmethod
        def error(cls, x, z, ctx):
            seen.append(ctx.measured)
            return super().error(x, z, ctx)

    truth, init, edges, meas = pose_graph(6)
    opt = SparseOptimizer("gn", "dense")
    opt.add_vertices(VertexSE2, np.arange(6), init, fixed=np.arange(6) == 0)
    opt.add_edges(Tagged, edges, meas)
    opt.compute_active_errors()
    np.testing.assert_array_equal(seen[-1], meas[:, :1] * 10.0)

    class Broken(EdgeSE2):
        @classmethod
        def measurement_derived(cls, measurements):
            return measurements[:2]

    bad = SparseOptimizer("gn", "dense")
    bad.add_vertices(VertexSE2, np.arange(6), init)
    bad.add_edges(Broken, edges, meas)
    with pytest.raises(GraphError, match=r"Broken.measurement_derived returned shape \(2, 3\)"):
        bad.optimize(1)
