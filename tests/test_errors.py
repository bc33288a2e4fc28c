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
    opt.add_edge(e)  # objects are checked in bulk, when the optimizer next needs its arrays
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 42\]: vertex 42 "):
        opt.initialize_optimization()
    assert opt.edges() == [] and opt.num_edges() == 0  # the culprit is not added
    opt.add_vertices(VertexSE2, [42], np.zeros((1, 3)))
    opt.add_edge(e)  # and can be added again
    assert opt.num_edges() == 1
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
    good = EdgeSE2([1, 0], np.zeros(3))
    opt.add_edge(good)
    opt.add_edge(EdgeSE2([0, 1], np.zeros(4)))
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 1\]: measurement has shape "
                                         r"\(4,\), expected \(3,\)"):
        opt.optimize(1)
    assert opt.edges() == [good] and opt.num_edges() == 1  # the others stay
    opt.add_edge(EdgeSE2([0, 1], ["a", 0, 0]))
    with pytest.raises(GraphError, match=r"\[0, 1\]: measurement is not numeric"):
        opt.chi2()


def test_wrong_information_shape_and_values() -> None:
    opt = two_poses()
    ids = np.array([[0, 1]])
    with pytest.raises(GraphError, match=r"information has shape \(2, 2\), expected \(3, 3\)"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.eye(2))
    opt.add_edge(EdgeSE2([0, 1], np.zeros(3), information=np.eye(2)))
    with pytest.raises(GraphError, match=r"information has shape \(2, 2\), expected \(3, 3\)"):
        opt.initialize_optimization()
    for bad, what in ((np.diag([1.0, -1.0, 1.0]), "positive semi"), (np.diag([np.inf, 1, 1]),
                                                                     "non-finite")):
        opt.add_edge(EdgeSE2([1, 0], np.zeros(3)))
        opt.add_edge(EdgeSE2([0, 1], np.zeros(3), information=bad))
        with pytest.raises(GraphError, match=rf"EdgeSE2 on vertices \[0, 1\]: .*{what}"):
            opt.initialize_optimization()
    asym = np.eye(3)
    asym[0, 1] = 0.5
    with pytest.raises(GraphError, match=r"EdgeSE2 on vertices \[0, 1\]: information matrix is "
                                         "not symmetric"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=asym)
    with pytest.raises(GraphError, match=r"EdgeSE2 \(one matrix for all 2 edges\): information "
                                         "matrix is not symmetric"):
        opt.add_edges(EdgeSE2, np.array([[0, 1], [1, 0]]), np.zeros((2, 3)), information=asym)
    with pytest.raises(GraphError, match="not positive semi-definite"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.diag([1.0, -1.0, 1.0]))
    with pytest.raises(GraphError, match="non-finite information"):
        opt.add_edges(EdgeSE2, ids, np.zeros((1, 3)), information=np.diag([1.0, np.nan, 1.0]))
    # Per-edge matrices: the message names the first edge whose own matrix is bad.
    three = np.array([[0, 1], [1, 0], [0, 1]])
    for bad, what in ((asym, "not symmetric"), (np.diag([1.0, -1.0, 1.0]), "positive semi"),
                      (np.diag([np.inf, 1.0, 1.0]), "non-finite")):
        infos = np.stack([np.eye(3), bad, np.eye(3)])
        with pytest.raises(GraphError, match=rf"EdgeSE2 on vertices \[1, 0\]: .*{what}"):
            opt.add_edges(EdgeSE2, three, np.zeros((3, 3)), information=infos)


def test_non_finite_values() -> None:
    opt = two_poses()
    bad = np.zeros((2, 3))
    bad[1, 2] = np.nan
    with pytest.raises(GraphError, match=r"vertex 11 \(VertexSE2\): invalid estimate"):
        opt.add_vertices(VertexSE2, [10, 11], bad)
    opt.add_vertex(VertexSE2(21, [0, 0, 0]))
    opt.add_vertex(VertexSE2(20, [np.inf, 0, 0]))
    with pytest.raises(GraphError, match=r"vertex 20 \(VertexSE2\): invalid estimate"):
        opt.initialize_optimization()
    assert opt.vertex(20) is None and opt.vertex(21) is not None
    opt.add_vertex(VertexSE2(22, [0, 0]))
    with pytest.raises(GraphError, match=r"vertex 22 \(VertexSE2\): estimate has shape \(2,\), "
                                         r"expected \(3,\)"):
        opt.vertex_ids()
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
    opt.add_vertices(VertexPositive, [0, 7], [[4.0], [-1.0]])
    opt.add_edges(EdgeSqrt, np.array([[0], [7], [7]]), [[2.0], [2.0], [1.0]])
    with pytest.raises(FloatingPointError, match=r"initial chi2 is not finite: EdgeSqrt on "
                                                 r"vertices \[7\] \(and 1 more edges"):
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


# --- misuse of the edge and vertex interfaces (issue 13 §2) ---------------------------------


class VertexPoint2(VertexVector):
    dimension = 2


class EdgeSquare2(BaseEdge):
    """Unary, nonlinear: e = x² − z (element-wise); analytic Jacobian diag(2x)."""

    dimension = 2
    vertex_types = (VertexPoint2,)

    @classmethod
    def error(cls, x, z, ctx):
        return x[0] ** 2 - z

    @classmethod
    def jacobians(cls, x, z, ctx):
        return (2.0 * x[0][:, :, None] * np.eye(2),)


class EdgeSquare2Numeric(BaseEdge):
    dimension = 2
    vertex_types = (VertexPoint2,)
    error = EdgeSquare2.error
    differentiation = "numeric"


class EdgeDiff2(BaseEdge):
    """Binary: e = x1 − x0 − z."""

    dimension = 2
    vertex_types = (VertexPoint2, VertexPoint2)

    @classmethod
    def error(cls, x, z, ctx):
        return x[1] - x[0] - z

    @classmethod
    def jacobians(cls, x, z, ctx):
        eye = np.broadcast_to(np.eye(2), (len(z), 2, 2))
        return (-eye.copy(), eye.copy())


def points(opt: SparseOptimizer | None = None, vtype=VertexPoint2, n: int = 4) -> SparseOptimizer:
    opt = opt or SparseOptimizer("lm", "dense")
    opt.add_vertices(vtype, np.arange(n), np.arange(1.0, 2 * n + 1).reshape(n, 2))
    return opt


def square_edges(opt: SparseOptimizer, etype: type[BaseEdge]) -> None:
    opt.add_edges(etype, np.arange(4)[:, None], np.full((4, 2), 2.0))


@pytest.mark.parametrize(("result", "got"), [
    (lambda e: e[:, 0], r"shape \(4,\)"),  # (m,) for a 2-D error
    (lambda e: None, "a NoneType"),
    (lambda e: np.hstack([e, e[:, :1]]), r"shape \(4, 3\)"),
    (lambda e: e[:, :1].tolist(), "a list"),
])
def test_error_of_the_wrong_shape_names_the_type(result, got) -> None:
    class EdgeBadError(EdgeSquare2):
        @classmethod
        def error(cls, x, z, ctx):
            return result(EdgeSquare2.error(x, z, ctx))

    opt = points()
    square_edges(opt, EdgeBadError)
    # A small group of an analytic type linearises first (linearizer.TRIAL_LINEARIZE_EDGES).
    with pytest.raises(GraphError, match=rf"EdgeBadError.(evaluate|linearize) returned an error "
                                         rf"of {got}, "
                                         r"expected \(4, 2\) \(4 edges of the group, the first "
                                         r"on vertices \[0\]\)"):
        opt.optimize(3)


def test_error_of_dimension_one_as_a_vector() -> None:
    class EdgeFlat(EdgeSqrt):
        @classmethod
        def error(cls, x, z, ctx):
            return EdgeSqrt.error(x, z, ctx)[:, 0]  # (m,), not (m, 1)

    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexPositive, [3, 4, 5], [[4.0], [4.0], [4.0]])
    opt.add_edges(EdgeFlat, np.array([[4], [5], [3]]), np.full((3, 1), 0.5))
    with pytest.raises(GraphError, match=r"EdgeFlat.(evaluate|linearize) returned an error of "
                                         r"shape \(3,\), "
                                         r"expected \(3, 1\) \(3 edges of the group, the first "
                                         r"on vertices \[4\]\)"):
        opt.optimize(3)


def test_error_as_a_list_of_the_right_shape_is_accepted() -> None:
    class EdgeList(EdgeSquare2):
        @classmethod
        def error(cls, x, z, ctx):
            return EdgeSquare2.error(x, z, ctx).tolist()

    results = []
    for etype in (EdgeSquare2, EdgeList):
        opt = points()
        square_edges(opt, etype)
        opt.optimize(20)
        results.append(np.array([opt.vertex(i).estimate for i in range(4)]))
    np.testing.assert_allclose(results[1], results[0])
    np.testing.assert_allclose(results[0], np.sqrt(2.0), rtol=1e-6)


def test_linearize_with_an_error_of_the_wrong_shape() -> None:
    class EdgeBadLinearize(EdgeSquare2):
        @classmethod
        def linearize(cls, x, z, ctx):
            lin = super().linearize(x, z, ctx)
            return lin._replace(error=lin.error[:, :1])

    opt = points()
    square_edges(opt, EdgeBadLinearize)
    with pytest.raises(GraphError, match=r"EdgeBadLinearize.linearize returned an error of shape "
                                         r"\(4, 1\), expected \(4, 2\) \(4 edges .* \[0\]\)"):
        opt.optimize(3)


def test_numeric_differences_check_the_error_shape() -> None:
    from graphopt.edge import EdgeContext
    from graphopt.numeric import numeric_jacobians

    class EdgeFlatNumeric(EdgeSquare2Numeric):
        @classmethod
        def error(cls, x, z, ctx):
            return EdgeSquare2.error(x, z, ctx)[:, 0]

    x = (np.ones((3, 2)),)
    with pytest.raises(GraphError, match=r"EdgeFlatNumeric.error returned shape \(3,\), "
                                         r"expected \(3, 2\)"):
        numeric_jacobians(EdgeFlatNumeric, x, np.zeros((3, 2)), EdgeContext())


def test_jacobian_of_the_wrong_shape_names_the_type_and_position() -> None:
    class EdgeWideJac(EdgeSquare2):
        @classmethod
        def jacobians(cls, x, z, ctx):
            return (np.zeros((len(z), 2, 3)),)  # (m, 2, 3) for a 2-D vertex

    opt = points()
    square_edges(opt, EdgeWideJac)
    with pytest.raises(GraphError, match=r"EdgeWideJac.linearize returned a Jacobian of shape "
                                         r"\(4, 2, 3\) for position 0 \(VertexPoint2\), expected "
                                         r"\(4, 2, 2\) \(4 edges of the group, the first on "
                                         r"vertices \[0\]\)"):
        opt.optimize(3)


@pytest.mark.parametrize(("jacobians", "got"), [
    (lambda j: j[1], "a ndarray"),  # one array for a binary edge
    (lambda j: (j[1],), "1 Jacobians"),
])
def test_jacobians_of_a_binary_edge_must_be_one_per_position(jacobians, got) -> None:
    class EdgeOneJac(EdgeDiff2):
        @classmethod
        def jacobians(cls, x, z, ctx):
            return jacobians(EdgeDiff2.jacobians(x, z, ctx))

    opt = points()
    opt.add_edges(EdgeOneJac, np.array([[2, 3], [0, 1]]), np.zeros((2, 2)))
    with pytest.raises(GraphError, match=rf"EdgeOneJac.linearize returned {got}, expected a tuple "
                                         r"of 2 \(one per vertex position\) \(2 edges of the "
                                         r"group, the first on vertices \[2, 3\]\)"):
        opt.optimize(3)


class VertexTruncating(VertexVector):
    """oplus returns (n, 1) for a 2-D vertex: numpy would broadcast it into the estimates."""

    dimension = 2

    @staticmethod
    def oplus(estimates, deltas):
        return estimates[:, :1] + deltas[:, :1]


class VertexMutating(VertexVector):
    """oplus updates its input in place (against the contract) and returns it."""

    dimension = 2

    @staticmethod
    def oplus(estimates, deltas):
        estimates += deltas
        return estimates


class VertexNaN(VertexVector):
    dimension = 2

    @staticmethod
    def oplus(estimates, deltas):
        return np.full_like(estimates, np.nan)


def unary_on(vtype, analytic: bool) -> type[BaseEdge]:
    base = EdgeSquare2 if analytic else EdgeSquare2Numeric
    return type(f"{base.__name__}On{vtype.__name__}", (base,), {"vertex_types": (vtype,)})


@pytest.mark.parametrize("analytic", [True, False])
def test_oplus_of_the_wrong_shape_names_the_vertex_type(analytic: bool) -> None:
    opt = points(vtype=VertexTruncating)
    before = np.array([opt.vertex(i).estimate for i in range(4)])
    square_edges(opt, unary_on(VertexTruncating, analytic))
    with pytest.raises(GraphError, match=r"VertexTruncating.oplus returned shape \(4, 1\), "
                                         r"expected \(4, 2\)"):
        opt.optimize(3)
    np.testing.assert_array_equal([opt.vertex(i).estimate for i in range(4)], before)


def test_mutating_oplus_gives_the_right_numeric_jacobian_and_answer() -> None:
    analytic = points()
    square_edges(analytic, EdgeSquare2)
    mutating = points(vtype=VertexMutating)
    square_edges(mutating, unary_on(VertexMutating, analytic=False))
    jac = []
    for opt in (analytic, mutating):
        opt.initialize_optimization()
        lin, _ = opt.problem.linearizer.linearize()
        jac.append(lin.jacobians[0][0])
    np.testing.assert_allclose(jac[1], jac[0], rtol=1e-6, atol=1e-8)
    # The estimates are untouched by the differences and by the steps' oplus.
    np.testing.assert_array_equal([mutating.vertex(i).estimate for i in range(4)],
                                  np.arange(1.0, 9.0).reshape(4, 2))
    res = [opt.optimize(20) for opt in (analytic, mutating)]
    assert res[1].iterations == res[0].iterations
    np.testing.assert_allclose([mutating.vertex(i).estimate for i in range(4)],
                               [analytic.vertex(i).estimate for i in range(4)], rtol=1e-6)


def test_oplus_returning_nan_names_the_vertex_type() -> None:
    opt = points(vtype=VertexNaN)
    square_edges(opt, unary_on(VertexNaN, analytic=True))
    with pytest.raises(GraphError, match=r"VertexNaN.oplus returned non-finite estimates for a "
                                         r"finite step \(vertices \[0, 1, 2, 3\]\)"):
        opt.optimize(3)
    np.testing.assert_array_equal([opt.vertex(i).estimate for i in range(4)],
                                  np.arange(1.0, 9.0).reshape(4, 2))


def test_gauss_newton_keeps_the_last_finite_estimate() -> None:
    opt = SparseOptimizer("gn", "dense")
    opt.add_vertices(VertexPositive, [0], [[4.0]])
    opt.add_edges(EdgeSqrt, np.zeros((1, 1), int), [[0.1]])  # the GN step goes to x = −3.6
    res = opt.optimize(5)
    assert opt.vertex(0).estimate.tolist() == [4.0]
    assert res.info[0].failed and len(res.info) == 1
    assert res.final_chi2 == pytest.approx(1.9**2)
    # From where a step stays in the domain, GN goes on to the minimum.
    opt.vertex(0).set_estimate([0.02])
    res = opt.optimize(20)
    assert np.isfinite(res.chi2_history).all()
    assert opt.vertex(0).estimate[0] == pytest.approx(0.01, rel=1e-6)


def test_non_numeric_information_and_flags_of_the_wrong_length_are_graph_errors() -> None:
    opt = two_poses()
    with pytest.raises(GraphError, match="EdgeSE2: information is not numeric"):
        opt.add_edges(EdgeSE2, np.array([[0, 1]]), np.zeros((1, 3)), information="x")
    with pytest.raises(GraphError, match=r"VertexSE2: fixed must be one flag or 2 of them, got "
                                         r"shape \(3,\)"):
        opt.add_vertices(VertexSE2, [5, 6], np.zeros((2, 3)), fixed=[True, False, True])
    with pytest.raises(GraphError, match=r"VertexSE2: marginalized must be one flag or 2"):
        opt.add_vertices(VertexSE2, [5, 6], np.zeros((2, 3)), marginalized=[[True, False]])
    assert opt.vertex(5) is None  # nothing added


class EdgeSquare2InPlace(EdgeSquare2):
    """Writes into its gathered input (allowed: the input is its own copy)."""

    @classmethod
    def error(cls, x, z, ctx):
        x0 = x[0]
        x0 *= 1.0
        return x0 ** 2 - z


@pytest.mark.parametrize("etype", [EdgeSquare2, EdgeSquare2InPlace,
                                   unary_on(VertexMutating, False)])
def test_edges_sharing_one_vertex_may_write_into_their_inputs(etype) -> None:
    """Edges that all have the same vertex get it as a read-only broadcast; a type that writes
    into it (or a numeric Jacobian through a mutating oplus) gets copies instead, and the
    same answer: x² = mean(z) in each coordinate."""
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(etype.vertex_types[0], [0], np.full((1, 2), 3.0))
    z = np.full((6, 2), 2.0) + 0.1 * np.arange(6)[:, None]
    opt.add_edges(etype, np.zeros((6, 1), dtype=int), z)
    res = opt.optimize(20)
    np.testing.assert_allclose(opt.vertex(0).estimate, [1.5, 1.5], rtol=1e-9)
    assert res.final_chi2 == pytest.approx(float(np.sum((2.25 - z) ** 2)), rel=1e-9)
