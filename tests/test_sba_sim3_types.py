"""ORB-SLAM's g2o types (``sba_pose``, ``sim3``): chi2 against g2o's (recorded from g2opy
2.3.0 by ``benchmarks/g2o_sba_sim3_reference.py`` on the inputs of ``sba_sim3_cases.py``),
analytic Jacobians against numeric ones, the Sim(3) maps, the fix-scale flag and
``depth_positive``."""

from __future__ import annotations

import numpy as np
import pytest
import sba_sim3_cases as C

from graphopt import SparseOptimizer
from graphopt.edge import EdgeContext
from graphopt.lie import se3_exp
from graphopt.numeric import numeric_jacobians
from graphopt.types import (
    CameraParameters,
    EdgeInverseDepthProjection,
    EdgeInverseSim3ProjectXYZ,
    EdgeSE3Expmap,
    EdgeSE3ProjectXYZ,
    EdgeSE3ProjectXYZOnlyPose,
    EdgeSim3,
    EdgeSim3ProjectXYZ,
    EdgeStereoSE3ProjectXYZ,
    EdgeStereoSE3ProjectXYZOnlyPose,
    StereoCameraParameters,
    VertexSE3Expmap,
    VertexSim3Expmap,
    sim3_matrix,
)
from graphopt.types.sim3_lie import (
    log_left_jacobian,
    se3quat_log,
    sim3_exp,
    sim3_log,
    sim3_parts,
    sim3_product,
)

# g2opy 2.3.0's per-edge chi2 (see the module docstring).
G2O_CHI2: dict[str, list[float]] = {
    'EdgeSE3ProjectXYZ': [
        5.0, 12.479804824686045, 9.705346176111458,
        5.375856267527612, 15.384119521615375, 6.701914884350637,
        4.758062041891153, 11.284231439461047,
    ],
    'EdgeSE3ProjectXYZOnlyPose': [
        5.0, 12.479804824686045, 9.705346176111458,
        5.375856267527612, 15.384119521615375, 6.701914884350637,
        4.758062041891153, 11.284231439461047,
    ],
    'EdgeStereoSE3ProjectXYZ': [
        7.4, 22.871972405227865, 16.55149507095617,
        10.762728530811735, 19.35896420465854, 8.241299222667301,
        4.755933212189826, 25.871193845247888,
    ],
    'EdgeStereoSE3ProjectXYZOnlyPose': [
        7.4, 22.871972405227865, 16.55149507095617,
        10.762728530811735, 19.35896420465854, 8.241299222667301,
        4.755933212189826, 25.871193845247888,
    ],
    'EdgeSE3Expmap': [
        1.2578893330966876, 0.5778433635647189, 2.5685172686691287,
        5.300786922698302, 8.586062361839655, 11.21240726548496,
        17.33533203154754, 25.09608487859704,
    ],
    'EdgeSim3': [
        1.8115512305799315, 1.5953950709963816, 2.2601135971427095,
        5.12794170537229, 9.424122149827001, 11.727627612033306,
        14.237887939450733, 28.092765015887124,
    ],
    'EdgeSim3ProjectXYZ': [
        5891.5022898569205, 9465.778177776618, 8538.005389443533,
        6919.570349221793, 6888.677988645992, 12430.643061340588,
        2192.7349165003234, 3827.957097946158,
    ],
    'EdgeInverseSim3ProjectXYZ': [
        4593.998366347428, 14183.670118655593, 12693.775064319909,
        6405.03673668674, 2800.9253603389234, 8707.879873325563,
        263.55758106381467, 4692.635812892258,
    ],
    'EdgeSE3Expmap near optimum': [
        7.484497344258352e-06, 8.526455067954117e-06, 8.527764003565522e-06,
        1.4414114190125293e-05, 2.6822331875831777e-05, 2.4599488957203413e-05,
        3.837173599988852e-05, 6.192226547458929e-05,
    ],
    'EdgeSim3 near optimum': [
        1.076278975189783e-05, 7.66139352652406e-06, 8.351874580507355e-06,
        1.5134919572010965e-05, 1.5674198714234936e-05, 1.8942784060030855e-05,
        3.076590238331937e-05, 3.64524327294805e-05,
    ],
}

CAM = CameraParameters(C.FX, C.FY, C.CX, C.CY)
STEREO = StereoCameraParameters(C.FX, C.FY, C.CX, C.CY, C.BF)
CAM_SIM3 = CameraParameters(C.F_SIM3, C.F_SIM3, C.CX, C.CY)


def _rep(a: np.ndarray) -> np.ndarray:
    return np.repeat(a[None], C.M, axis=0)


def _cases() -> dict[str, tuple]:
    """Per name: ``(type, x, measurement, ctx, information)`` of the recorded inputs."""
    X, T = C.points(), _rep(C.pose())
    Ti, Tj, Tij = C.pose_pairs()
    Si, Sj, Sji = C.sim3_pairs()
    S, zs = C.sim3_projection()
    Ei, Ej, Ez = C.near_optimum(False)
    Fi, Fj, Fz = C.near_optimum(True)
    return {
        "EdgeSE3ProjectXYZ": (EdgeSE3ProjectXYZ, (T, X), C.pixels(), EdgeContext(CAM), C.INFO2),
        "EdgeSE3ProjectXYZOnlyPose": (EdgeSE3ProjectXYZOnlyPose, (T,), C.pixels(),
                                      EdgeContext(CAM, {"Xw": X}), C.INFO2),
        "EdgeStereoSE3ProjectXYZ": (EdgeStereoSE3ProjectXYZ, (T, X), C.stereo(),
                                    EdgeContext(STEREO), C.INFO3),
        "EdgeStereoSE3ProjectXYZOnlyPose": (EdgeStereoSE3ProjectXYZOnlyPose, (T,), C.stereo(),
                                            EdgeContext(STEREO, {"Xw": X}), C.INFO3),
        "EdgeSE3Expmap": (EdgeSE3Expmap, (Ti, Tj), Tij, EdgeContext(), np.eye(6)),
        "EdgeSim3": (EdgeSim3, (Si, Sj), Sji, EdgeContext(), C.INFO7),
        "EdgeSim3ProjectXYZ": (EdgeSim3ProjectXYZ, (X, _rep(S)), zs, EdgeContext(CAM_SIM3),
                               C.INFO2),
        "EdgeInverseSim3ProjectXYZ": (EdgeInverseSim3ProjectXYZ, (X, _rep(S)), zs,
                                      EdgeContext(CAM_SIM3), C.INFO2),
        "EdgeSE3Expmap near optimum": (EdgeSE3Expmap, (Ei, Ej), Ez, EdgeContext(), np.eye(6)),
        "EdgeSim3 near optimum": (EdgeSim3, (Fi, Fj), Fz, EdgeContext(), C.INFO7),
    }


@pytest.mark.parametrize("name", sorted(G2O_CHI2))
def test_chi2_equals_g2o(name: str) -> None:
    etype, x, z, ctx, info = _cases()[name]
    e = etype.error(x, z, ctx)
    chi2 = np.einsum("ni,ij,nj->n", e, info, e)
    np.testing.assert_allclose(chi2, G2O_CHI2[name], rtol=1e-9)


@pytest.mark.parametrize("name", [n for n in sorted(G2O_CHI2) if "near" not in n])
def test_analytic_jacobians_match_numeric(name: str) -> None:
    etype, x, z, ctx, _ = _cases()[name]
    lin = etype.linearize(x, z, ctx)
    np.testing.assert_allclose(lin.error, etype.error(x, z, ctx), rtol=1e-12, atol=1e-12)
    for ja, jn in zip(lin.jacobians, numeric_jacobians(etype, x, z, ctx), strict=True):
        scale = np.abs(jn).max()
        np.testing.assert_allclose(ja, jn, rtol=0, atol=2e-7 * scale)


def test_sim3_jacobians_with_fixed_scale_match_numeric() -> None:
    """A fixed-scale vertex's σ column is zero in both (its ``oplus`` drops σ)."""
    Si, Sj, Sji = C.sim3_pairs()
    Si[::2, 3, 0] = 1.0
    Sj[::2, 3, 0] = 1.0
    S, zs = C.sim3_projection()
    Sp = _rep(S)
    Sp[::2, 3, 0] = 1.0
    for etype, x, z, ctx in [(EdgeSim3, (Si, Sj), Sji, EdgeContext()),
                             (EdgeSim3ProjectXYZ, (C.points(), Sp), zs, EdgeContext(CAM_SIM3)),
                             (EdgeInverseSim3ProjectXYZ, (C.points(), Sp), zs,
                              EdgeContext(CAM_SIM3))]:
        lin = etype.linearize(x, z, ctx)
        for ja, jn in zip(lin.jacobians, numeric_jacobians(etype, x, z, ctx), strict=True):
            np.testing.assert_allclose(ja, jn, rtol=0, atol=2e-7 * np.abs(jn).max())
        js = lin.jacobians[-1]
        assert np.all(js[::2, :, 6] == 0.0)
        # The forward projection's σ column is zero anyway: scaling the camera frame about its
        # centre leaves every image point where it is.
        assert np.any(js[1::2, :, 6] != 0.0) == (etype is not EdgeSim3ProjectXYZ)


def test_sim3_exp_log_round_trip_and_g2o_branches() -> None:
    rng = np.random.default_rng(3)
    xi = rng.normal(0.0, 0.6, (50, 7))
    xi[:10, :3] *= 1e-6          # θ < 1e-5: g2o's small-rotation branch
    xi[10:20, 6] *= 1e-6         # |σ| < 1e-5: C = 1
    xi[20:25, :3] = xi[20:25, :3] / np.linalg.norm(xi[20:25, :3], axis=1)[:, None] * 3.1
    S = sim3_exp(xi)
    np.testing.assert_allclose(sim3_log(S), xi, rtol=0, atol=1e-12)
    R, t, s = sim3_parts(S)
    np.testing.assert_allclose(s, np.exp(xi[:, 6]), rtol=1e-14)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), _eye(50), atol=1e-14)
    # The exact log agrees with g2o's away from the branches, and its derivative with the
    # numeric derivative of the log under left perturbations.
    log, D = log_left_jacobian(S[25:])
    np.testing.assert_allclose(log, xi[25:], atol=1e-12)
    h = 1e-6
    for k in range(7):
        d = np.zeros((25, 7))
        d[:, k] = h
        num = (sim3_log(sim3_product(sim3_exp(d), S[25:]))
               - sim3_log(sim3_product(sim3_exp(-d), S[25:]))) / (2 * h)
        np.testing.assert_allclose(D[:, :, k], num, atol=1e-8)
    T = se3_exp(xi[25:, :6])
    log6, _ = log_left_jacobian(T, scaled=False)
    np.testing.assert_allclose(se3quat_log(T), log6, atol=1e-12)


def _eye(n: int) -> np.ndarray:
    return np.repeat(np.eye(3)[None], n, axis=0)


def test_vertex_sim3_fix_scale_flag() -> None:
    S = sim3_exp(np.array([[0.1, 0.2, -0.1, 1.0, 2.0, 3.0, 0.4]] * 2))
    S[1, 3, 0] = 1.0
    new = VertexSim3Expmap.oplus(S.copy(), np.full((2, 7), 0.1))
    _, _, s = sim3_parts(new)
    assert s[0] == pytest.approx(np.exp(0.5)) and s[1] == pytest.approx(np.exp(0.4))
    assert new[0, 3, 0] == 0.0 and new[1, 3, 0] == 1.0
    assert VertexSim3Expmap.validate(S).all()
    bad = S.copy()
    bad[0, 3, 0] = 0.5
    bad[1, :3, :3] *= np.array([1.0, 1.0, 1.1])
    assert not VertexSim3Expmap.validate(bad).any()
    # Per-object: the flag lives in the estimate and survives set_estimate.
    v = VertexSim3Expmap(7, sim3_matrix(_eye(1), np.zeros((1, 3)), np.ones(1))[0], fix_scale=True)
    opt = SparseOptimizer()
    opt.add_vertex(v)
    assert v.fix_scale() and v.estimate[3, 0] == 1.0
    v.set_estimate(S[0])
    assert v.fix_scale()
    v.set_fix_scale(False)
    assert not v.fix_scale() and v.estimate[3, 0] == 0.0


def test_mixed_fix_scale_store_optimizes() -> None:
    """One store, three vertices, scales free except vertex 2's: a Sim3 chain pulls every
    vertex towards scale 2; vertex 0 is fixed, vertex 2 keeps its scale."""
    n = 3
    I3 = _eye(n)
    est = sim3_matrix(I3, np.zeros((n, 3)), np.ones(n), fix_scale=[0, 0, 1])
    opt = SparseOptimizer(algorithm="lm")
    opt.add_vertices(VertexSim3Expmap, np.arange(n), est, fixed=[True, False, False])
    Z = sim3_matrix(I3[:2], np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.full(2, 2.0))
    opt.add_edges(EdgeSim3, np.array([[0, 1], [1, 2]]), Z)
    opt.initialize_optimization()
    opt.optimize(20)
    _, t, s = sim3_parts(np.stack([opt.vertex(i).estimate for i in range(n)]))
    assert s[2] == 1.0 and s[1] != 1.0
    assert opt.vertex(2).estimate[3, 0] == 1.0 and opt.vertex(1).estimate[3, 0] == 0.0


def test_depth_positive() -> None:
    X, T = C.points(), _rep(C.pose())
    X = X.copy()
    X[::3, 2] *= -1.0
    want = (X @ C.pose()[:3, :3].T + C.pose()[:3, 3])[:, 2] > 0
    assert not want.all() and want.any()
    ctx = EdgeContext(STEREO, {"Xw": X})
    for etype, x in [(EdgeSE3ProjectXYZ, (T, X)), (EdgeStereoSE3ProjectXYZ, (T, X)),
                     (EdgeSE3ProjectXYZOnlyPose, (T,)), (EdgeStereoSE3ProjectXYZOnlyPose, (T,))]:
        np.testing.assert_array_equal(etype.depth_positive(x, None, ctx), want)
    S = sim3_matrix(_eye(C.M), np.zeros((C.M, 3)), np.full(C.M, 2.0))
    for etype in (EdgeSim3ProjectXYZ, EdgeInverseSim3ProjectXYZ):
        np.testing.assert_array_equal(etype.depth_positive((X, S), None, ctx), X[:, 2] > 0)
    # Inverse depth: in front of the anchor by construction; behind a camera facing back.
    anchor, back = _rep(np.eye(4)), _rep(np.diag([-1.0, 1.0, -1.0, 1.0]))
    back[1::2] = anchor[1::2]
    ip = np.stack([X[:, 0], X[:, 1], np.full(C.M, 0.2)], axis=1)
    got = EdgeInverseDepthProjection.depth_positive((anchor, back, ip), None, ctx)
    np.testing.assert_array_equal(got, np.arange(C.M) % 2 == 1)


def test_only_pose_edges_need_world_points() -> None:
    from graphopt.errors import GraphError
    with pytest.raises(GraphError, match="EdgeSE3ProjectXYZOnlyPose needs data"):
        EdgeSE3ProjectXYZOnlyPose.error((_rep(C.pose()),), C.pixels(), EdgeContext(CAM))
    # Intrinsics without a baseline, or none: a GraphError naming the type, from the optimizer.
    opt = SparseOptimizer()
    opt.add_vertices(VertexSE3Expmap, [0], C.pose()[None])
    opt.add_edges(EdgeStereoSE3ProjectXYZOnlyPose, np.zeros((C.M, 1), int), C.stereo(),
                  params=CAM, data={"Xw": C.points()})
    with pytest.raises(GraphError, match="EdgeStereoSE3ProjectXYZOnlyPose needs params="
                                         "StereoCameraParameters"):
        opt.optimize(1)
    with pytest.raises(GraphError, match="EdgeSim3ProjectXYZ needs params=CameraParameters"):
        EdgeSim3ProjectXYZ.error((C.points(), _rep(np.eye(4))), C.pixels(), EdgeContext())


def test_edge_set_depth_positive_and_chi2_per_edge() -> None:
    """Through the optimizer's ``EdgeSet``: the recorded chi2 and g2o's ``isDepthPositive``."""
    X = C.points().copy()
    opt = SparseOptimizer()
    opt.add_vertices(VertexSE3Expmap, [0], C.pose()[None])
    es = opt.add_edges(EdgeSE3ProjectXYZOnlyPose, np.zeros((C.M, 1), int), C.pixels(),
                       information=C.INFO2, params=CAM, data={"Xw": X})
    np.testing.assert_allclose(es.chi2(), G2O_CHI2["EdgeSE3ProjectXYZOnlyPose"], rtol=1e-9)
    assert es.is_depth_positive().all()
    opt.vertex(0).set_estimate(C.pose() @ np.diag([-1.0, 1.0, -1.0, 1.0]))   # facing away
    assert not es.is_depth_positive().any()


def test_pose_jacobian_in_chunks_equals_one_product() -> None:
    """Above 2,048 edges the monomial product runs in chunks (one BLAS thread each)."""
    from graphopt.types.projection import pose_jacobian

    rng = np.random.default_rng(5)
    iz, uv = rng.uniform(0.1, 1.0, 4500), rng.normal(0.0, 0.5, (4500, 2))
    for bf in (None, C.BF):
        big = pose_jacobian(iz, uv, CAM, bf)
        for lo in (0, 2000, 4400):
            small = pose_jacobian(iz[lo:lo + 100], uv[lo:lo + 100], CAM, bf)
            np.testing.assert_allclose(big[lo:lo + 100], small, rtol=1e-13, atol=1e-9)


def test_projection_of_few_edges_has_the_bits_of_the_columnwise_one() -> None:
    """Up to 256 edges the errors are formed on whole (m, 2) arrays, above column by column:
    the same operations per element, the same bits (mono and stereo)."""
    from graphopt.types import pinhole, projection

    rng = np.random.default_rng(7)
    P = np.column_stack([rng.normal(0, 1, 600), rng.normal(0, 1, 600), rng.uniform(2, 9, 600)])
    z = rng.uniform(0, 640, (600, 3))
    assert 100 <= pinhole._ROWWISE_EDGES < 600
    for bf, zz in ((None, z[:, :2]), (C.BF, z)):
        whole = projection.normalised_projection(P, zz, CAM, bf)   # column by column
        few = projection.normalised_projection(P[:100], zz[:100], CAM, bf)
        for a, b in zip(whole, few, strict=True):
            assert np.array_equal(a[:100], b)


def test_projection_base_is_the_projection_and_the_monomials() -> None:
    """A pose-only edge's linearisation writes ``iz`` and ``uv`` into the Jacobian's monomial
    base: the same errors, ``iz``, ``uv`` and pose Jacobian, bit for bit, at either size."""
    from graphopt.types import projection

    rng = np.random.default_rng(8)
    P = np.column_stack([rng.normal(0, 1, 600), rng.normal(0, 1, 600), rng.uniform(2, 9, 600)])
    z = rng.uniform(0, 640, (600, 3))
    for m in (100, 600):
        for bf, zz in ((None, z[:m, :2]), (C.BF, z[:m])):
            e, iz, uv = projection.normalised_projection(P[:m], zz, CAM, bf)
            e2, a = projection.projection_base(P[:m], zz, CAM, bf)
            assert np.array_equal(e, e2) and np.array_equal(iz, a[2])
            assert np.array_equal(uv, a[:2].T) and np.all(a[3] == 1.0)
            assert np.array_equal(projection.pose_jacobian(iz, uv, CAM, bf),
                                  projection.monomial_pose_jacobian(a, CAM, bf))


def test_one_vertex_oplus_equals_the_batched_one() -> None:
    """A single Sim3 vertex is updated in Python floats; g2o's branches as the batched path."""
    S = sim3_exp(np.array([[0.1, 0.2, -0.1, 1.0, 2.0, 3.0, 0.4]]))
    for d in ([0.01, -0.02, 0.03, 0.1, 0.2, -0.1, 0.05], [1e-7, 0, 0, 0.1, 0.2, -0.1, 0.05],
              [0.01, -0.02, 0.03, 0.1, 0.2, -0.1, 1e-7], [1e-7, 0, 0, 0.1, 0.2, -0.1, 1e-7],
              [2.5, -1.0, 0.3, 0.1, 0.2, -0.1, -0.3]):
        for flag in (0.0, 1.0):
            Sf = S.copy()
            Sf[:, 3, 0] = flag
            one = VertexSim3Expmap.oplus(Sf, np.array([d]))
            two = VertexSim3Expmap.oplus(np.repeat(Sf, 2, 0), np.array([d, d]))
            np.testing.assert_allclose(one[0], two[0], rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", ["EdgeSE3ProjectXYZOnlyPose", "EdgeStereoSE3ProjectXYZOnlyPose",
                                  "EdgeSim3ProjectXYZ", "EdgeInverseSim3ProjectXYZ"])
def test_one_vertex_broadcast_over_the_edges_equals_its_copies(name: str) -> None:
    """The linearizer hands a vertex that every edge shares as a read-only stride-0 view; the
    types that take a faster product for it give the copies' errors and Jacobians, and the
    recorded g2o chi2."""
    etype, x, z, ctx, info = _cases()[name]
    pos = len(x) - 1  # the pose or the Sim(3)
    for fixed_scale in ([False, True] if "Sim3" in name else [False]):
        shared = x[pos][:1].copy()
        if fixed_scale:
            shared[0, 3, 0] = 1.0
        _check_shared(etype, x, z, ctx, info, name, pos, shared)


def _check_shared(etype, x, z, ctx, info, name, pos, shared) -> None:
    copies = [*x[:pos], np.repeat(shared, C.M, axis=0)]
    view = [*x[:pos], np.broadcast_to(shared, copies[pos].shape)]
    assert view[pos].strides[0] == 0
    a, b = etype.linearize(tuple(copies), z, ctx), etype.linearize(tuple(view), z, ctx)
    np.testing.assert_allclose(b.error, a.error, rtol=1e-13, atol=1e-12)
    for ja, jb in zip(a.jacobians, b.jacobians, strict=True):
        np.testing.assert_allclose(jb, ja, rtol=1e-13, atol=1e-12 * np.abs(ja).max())
    np.testing.assert_allclose(etype.error(tuple(view), z, ctx), a.error, rtol=1e-13,
                               atol=1e-12)
    if np.array_equal(copies[pos], x[pos]):
        e = b.error
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", e, info, e), G2O_CHI2[name],
                                   rtol=1e-9)


def test_one_pose_validation_equals_the_batched_one() -> None:
    """One pose is checked in Python floats (a motion-only BA resets it every round): the same
    verdicts as the batched check, at each test's threshold and past it."""
    rng = np.random.default_rng(9)
    for T in se3_exp(rng.normal(size=(20, 6))):
        cases = [T]
        for i, j, d in [(0, 0, 1e-5), (1, 2, 2e-7), (3, 0, 1e-11), (3, 3, 1e-13),
                        (2, 1, np.nan), (0, 3, np.inf)]:
            U = T.copy()
            U[i, j] += d
            cases.append(U)
        U = T.copy()
        U[:3, 0] *= -1.0  # a reflection
        cases.append(U)
        verdicts = [bool(VertexSE3Expmap.validate(c[None])[0]) for c in cases]
        batched = VertexSE3Expmap.validate(np.stack(cases + [T]))[:-1]
        assert verdicts == batched.tolist()
        assert verdicts == [True, False, True, False, True, False, False, False]
