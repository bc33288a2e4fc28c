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
