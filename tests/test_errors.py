"""Bad input gives a clear exception naming the id and type; results never contain NaN."""

from __future__ import annotations

import numpy as np
import pytest
from custom_types import EdgeCurve, EdgeSE2, VertexCurve, VertexSE2

from graphopt import BaseEdge, GraphError, SparseOptimizer, VertexVector


def two_poses() -> SparseOptimizer:
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexSE2, [0, 1], np.zeros((2, 3)))
    return opt


def test_duplicate_vertex_id_bulk() -> None:
    opt = two_poses()
    with pytest.raises(GraphError, match=r"duplicate vertex id 1 \(VertexSE2\)"):
        opt.add_vertices(VertexSE2, [1, 2], np.zeros((2, 3)))
    with pytest.raises(GraphError, match=r"duplicate vertex id 7 \(VertexSE2\)"):
        opt.add_vertices(VertexSE2, [7, 7], np.zeros((2, 3)))


def test_duplicate_vertex_id_across_types_and_objects() -> None:
    opt = two_poses()
    with pytest.raises(GraphError, match=r"duplicate vertex id 0 \(VertexCurve\)"):
        opt.add_vertex(VertexCurve(0, np.zeros(3)))
    many = np.arange(100, 300)
    opt.add_vertices(VertexCurve, many, np.zeros((200, 3)))
    with pytest.raises(GraphError, match=r"duplicate vertex id 150 \(VertexCurve\)"):
        opt.add_vertices(VertexCurve, np.arange(150, 350), np.zeros((200, 3)))


def test_edge_with_missing_vertex() -> None:
    opt = two_poses()
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 99\]: vertex 99 "
                                         r"\(position 1\) does not exist"):
        opt.add_edges(EdgeSE2, np.array([[0, 1], [0, 99]]), np.zeros((2, 3)))
    e = EdgeSE2(vertices=[0, 42], measurement=np.zeros(3))
    with pytest.raises(GraphError, match="vertex 42"):
        opt.add_edge(e)
    big = np.zeros((100, 2), dtype=int)
    big[57] = [1, 1234]
    with pytest.raises(GraphError, match="vertex 1234"):
        opt.add_edges(EdgeSE2, big, np.zeros((100, 3)))


def test_edge_with_vertex_of_wrong_type() -> None:
    opt = two_poses()
    opt.add_vertices(VertexCurve, [5], np.zeros((1, 3)))
    with pytest.raises(GraphError, match="vertex 5 is a VertexCurve, position 1 needs a VertexSE2"):
        opt.add_edges(EdgeSE2, np.array([[0, 5]]), np.zeros((1, 3)))


def test_wrong_measurement_shape() -> None:
    opt = two_poses()
    with pytest.raises(GraphError, match=r"EdgeSE2.*measurement has shape \(2, 2\), expected "
                                         r"\(2, 3\)"):
        opt.add_edges(EdgeSE2, np.array([[0, 1], [1, 0]]), np.zeros((2, 2)))
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 1\]: measurement has shape "
                                         r"\(4,\), expected \(3,\)"):
        opt.add_edge(EdgeSE2([0, 1], np.zeros(4)))


def test_wrong_information_shape_and_values() -> None:
    opt = two_poses()
    ids = np.array([[0, 1]])
    with pytest.raises(GraphError, match=r"information has shape \(2, 2\), expected \(3, 3\)"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.eye(2))
    with pytest.raises(GraphError, match=r"information has shape \(2, 2\), expected \(3, 3\)"):
        opt.add_edge(EdgeSE2([0, 1], np.zeros(3), information=np.eye(2)))
    asym = np.eye(3)
    asym[0, 1] = 0.5
    with pytest.raises(GraphError, match="not symmetric"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=asym)
    with pytest.raises(GraphError, match="not positive semi-definite"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(GraphError, match="non-finite information"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.diag([1.0, np.nan, 1.0]))


def test_non_finite_values() -> None:
    opt = two_poses()
    bad = np.zeros((2, 3))
    bad[1, 2] = np.nan
    with pytest.raises(GraphError, match=r"vertex 11 \(VertexSE2\): invalid estimate"):
        opt.add_vertices(VertexSE2, [10, 11], bad)
    with pytest.raises(GraphError, match=r"vertex 20 \(VertexSE2\): invalid estimate"):
        opt.add_vertex(VertexSE2(20, [np.inf, 0, 0]))
    with pytest.raises(GraphError, match="non-finite measurement"):
        opt.add_edges(EdgeSE2, np.array([[0, 1]]), np.array([[0, np.inf, 0]]))
    with pytest.raises(GraphError, match=r"vertex 0 \(VertexSE2\): invalid estimate"):
        opt.vertex(0).set_estimate([0, np.nan, 0])
    with pytest.raises(GraphError, match=r"vertex 0 \(VertexSE2\): estimate has shape \(2,\)"):
        opt.vertex(0).set_estimate([0, 0])


def test_wrong_estimate_shapes_and_ids() -> None:
    opt = SparseOptimizer()
    with pytest.raises(GraphError, match=r"VertexSE2: estimates have shape \(2, 2\), expected "
                                         r"\(2, 3\)"):
        opt.add_vertices(VertexSE2, [0, 1], np.zeros((2, 2)))
    with pytest.raises(GraphError, match="ids must be a 1-D integer array"):
        opt.add_vertices(VertexSE2, [0.5, 1.5], np.zeros((2, 3)))
    with pytest.raises(GraphError, match="has no estimate"):
        opt.add_vertex(VertexSE2(3))
    with pytest.raises(ValueError, match="iterations must be a non-negative integer"):
        opt.optimize(-1)


def test_edge_vertex_count_and_missing_measurement() -> None:
    with pytest.raises(ValueError, match="EdgeSE2 takes 2 vertices, got 1"):
        EdgeSE2([0])
    opt = two_poses()
    with pytest.raises(GraphError, match="vertex 1 is not set"):
        e = EdgeSE2()
        e.set_vertex(0, 0)
        opt.add_edge(e)
    with pytest.raises(GraphError, match="no measurement set"):
        opt.add_edge(EdgeSE2([0, 1]))


class VertexPositive(VertexVector):
    dimension = 1


class EdgeSqrt(BaseEdge):
    """e = sqrt(x) − z: NaN for x < 0, which a too-long step reaches."""

    dimension = 1
    vertex_types = (VertexPositive,)

    @classmethod
    def error(cls, x, z, ctx):
        with np.errstate(invalid="ignore"):
            return np.sqrt(x[0]) - z

    @classmethod
    def jacobians(cls, x, z, ctx):
        return (0.5 / np.sqrt(x[0])[:, :, None],)


def test_steps_into_nan_are_rejected_and_results_stay_finite() -> None:
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexPositive, [0], [[4.0]])
    opt.add_edges(EdgeSqrt, np.zeros((1, 1), int), [[0.1]])  # the first full step is x = −3.6
    res = opt.optimize(50)
    x = opt.vertex(0).estimate
    assert np.isfinite(x).all() and np.isfinite(res.chi2_history).all()
    assert x[0] == pytest.approx(0.01, rel=1e-6)
    assert max(res.trials) > 1  # at least one step left the domain and was rejected


def test_non_finite_initial_error_is_reported() -> None:
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexPositive, [0], [[-1.0]])
    opt.add_edges(EdgeSqrt, np.zeros((1, 1), int), [[2.0]])
    with pytest.raises(FloatingPointError, match="initial chi2 is not finite"):
        opt.optimize(3)


def test_non_finite_jacobian_names_the_edge() -> None:
    class EdgeBadJac(EdgeCurve):
        @classmethod
        def jacobians(cls, x, measurement, ctx):
            (j,) = EdgeCurve.jacobians(x, measurement, ctx)
            j[3] = np.nan
            return (j,)

    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexCurve, [7], [[0.0, 0.0, 0.0]])
    opt.add_edges(EdgeBadJac, np.full((5, 1), 7), np.ones((5, 2)))
    with pytest.raises(FloatingPointError, match=r"EdgeBadJac on vertices \[7\]: non-finite"):
        opt.optimize(1)
