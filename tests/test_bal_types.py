"""BA types: every analytic Jacobian against the numeric one, Lie round trips, BAL projection."""

from __future__ import annotations

import numpy as np
import pytest

from graphopt.edge import EdgeContext
from graphopt.lie import angle_axis_rotate, se3_exp, so3_exp, so3_log
from graphopt.numeric import numeric_jacobians
from graphopt.types.bal import (
    EdgeBALProjection,
    VertexCameraBAL,
    bal_project,
    count_behind_camera,
)
from graphopt.types.projection import (
    CameraParameters,
    EdgeInverseDepthProjection,
    EdgeProjectXYZ2UV,
    EdgeSE3ProjectXYZ,
)
from graphopt.types.vertices import VertexPointXYZ, VertexSE3Expmap


def _bal_inputs(m: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    cams = np.concatenate(
        [
            rng.normal(0, 0.5, (m, 3)),
            rng.normal(0, 1.0, (m, 3)),
            rng.uniform(400, 1500, (m, 1)),
            rng.normal(0, 0.1, (m, 1)),
            rng.normal(0, 0.01, (m, 1)),
        ],
        axis=1,
    )
    cams[:4, :3] = 0.0  # identity rotation (small-angle branch)
    cams[4, :3] = [1e-9, -2e-9, 0.5e-9]
    cams[5, :3] = [0.0, 3.0, 0.0]  # large angle
    X = rng.normal(0, 1.0, (m, 3))
    # Put points in front of their cameras (P_z < 0) at depth 5..15.
    uv_dir = np.column_stack([rng.normal(0, 0.3, (m, 2)), -np.ones(m)])
    depth = rng.uniform(5, 15, m)
    P = uv_dir * depth[:, None]
    X = angle_axis_rotate(-cams[:, :3], P - cams[:, 3:6])
    z = rng.normal(0, 200, (m, 2))
    return cams, X, z


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def test_bal_edge_jacobians_match_numeric() -> None:
    cams, X, z = _bal_inputs()
    ctx = EdgeContext()
    e, (Jc, Jp), *_ = EdgeBALProjection.linearize((cams, X), z, ctx)
    Nc, Np = numeric_jacobians(EdgeBALProjection, (cams, X), z, ctx)
    assert Jc.shape == (len(cams), 2, 9) and Jp.shape == (len(cams), 2, 3)
    np.testing.assert_allclose(e, EdgeBALProjection.error((cams, X), z, ctx))
    # Per-column scale: the f/k columns are orders of magnitude apart.
    for col in range(9):
        scale = np.abs(Nc[:, :, col]).max()
        assert np.abs(Jc[:, :, col] - Nc[:, :, col]).max() <= 1e-5 * scale, col
    assert _rel_err(Jp, Np) < 1e-6
    assert np.array_equal(EdgeBALProjection.jacobians((cams, X), z, ctx)[0], Jc)


def test_bal_edge_jacobians_with_points_behind_camera() -> None:
    cams, X, z = _bal_inputs(seed=3)
    X = angle_axis_rotate(-cams[:, :3], -(angle_axis_rotate(cams[:, :3], X)))  # mirror
    ctx = EdgeContext()
    _, (Jc, Jp), *_ = EdgeBALProjection.linearize((cams, X), z, ctx)
    Nc, Np = numeric_jacobians(EdgeBALProjection, (cams, X), z, ctx)
    assert _rel_err(Jc, Nc) < 1e-5 and _rel_err(Jp, Np) < 1e-5


def test_bal_projection_matches_textbook_formula() -> None:
    cams, X, _ = _bal_inputs(m=50, seed=1)
    R = so3_exp(cams[:, :3])
    P = np.einsum("nij,nj->ni", R, X) + cams[:, 3:6]
    p = -P[:, :2] / P[:, 2:3]
    r2 = (p**2).sum(1)
    expect = (cams[:, 6] * (1 + cams[:, 7] * r2 + cams[:, 8] * r2**2))[:, None] * p
    uv, Pz = bal_project(cams, X)
    np.testing.assert_allclose(uv, expect, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(Pz, P[:, 2])
    np.testing.assert_allclose(angle_axis_rotate(cams[:, :3], X), np.einsum("nij,nj->ni", R, X),
                               atol=1e-12)


def test_count_behind_camera() -> None:
    cams, X, _ = _bal_inputs(m=20, seed=2)
    assert count_behind_camera(cams, X, np.arange(20), np.arange(20)) == 0
    X2 = X.copy()
    X2[:3] = angle_axis_rotate(-cams[:3, :3], -angle_axis_rotate(cams[:3, :3], X[:3])
                               - 2 * cams[:3, 3:6])
    assert count_behind_camera(cams, X2, np.arange(20), np.arange(20)) == 3


def test_camera_oplus_is_left_rotation_update() -> None:
    rng = np.random.default_rng(4)
    cams = rng.normal(size=(30, 9))
    delta = rng.normal(0, 0.2, (30, 9))
    out = VertexCameraBAL.oplus(cams, delta)
    np.testing.assert_allclose(
        so3_exp(out[:, :3]), so3_exp(delta[:, :3]) @ so3_exp(cams[:, :3]), atol=1e-12
    )
    np.testing.assert_allclose(out[:, 3:], cams[:, 3:] + delta[:, 3:])
    # Zero increment is the identity; the input is not modified.
    before = cams.copy()
    np.testing.assert_allclose(VertexCameraBAL.oplus(cams, np.zeros_like(cams)), cams, atol=1e-12)
    assert np.array_equal(cams, before)


@pytest.mark.parametrize("theta", [0.0, 1e-10, 1e-4, 0.5, 2.0, 3.0, np.pi - 1e-6])
def test_so3_exp_log_round_trip(theta: float) -> None:
    rng = np.random.default_rng(5)
    axis = rng.normal(size=(10, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    w = axis * theta
    R = so3_exp(w)
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-9)
    if theta < 3.0:
        np.testing.assert_allclose(so3_log(R), w, atol=1e-9)


def test_se3_oplus_round_trip() -> None:
    rng = np.random.default_rng(6)
    T = se3_exp(rng.normal(0, 0.5, (10, 6)))
    d = rng.normal(0, 0.1, (10, 6))
    T2 = VertexSE3Expmap.oplus(VertexSE3Expmap.oplus(T, d), -d)
    # exp(−δ) exp(δ) = I.
    np.testing.assert_allclose(T2, T, atol=1e-12)
    assert VertexSE3Expmap.validate(T).all()


def _pinhole_inputs(m: int = 200, seed: int = 7):
    rng = np.random.default_rng(seed)
    T = se3_exp(rng.normal(0, 0.3, (m, 6)))
    Ta = se3_exp(rng.normal(0, 0.3, (m, 6)))
    X = rng.normal(size=(m, 3))
    X[:, 2] += 8.0
    ip = np.column_stack([rng.normal(0, 0.3, (m, 2)), rng.uniform(0.05, 0.5, m)])
    z = rng.normal(300, 50, (m, 2))
    return T, Ta, X, ip, z


@pytest.mark.parametrize("edge", [EdgeSE3ProjectXYZ, EdgeProjectXYZ2UV])
@pytest.mark.parametrize(
    "params", [CameraParameters(500, 510, 320, 240), (500, 510, 320, 240),
               {"fx": 500, "fy": 510, "cx": 320, "cy": 240}]
)
def test_pinhole_edge_jacobians_match_numeric(edge, params) -> None:
    T, _, X, _, z = _pinhole_inputs()
    ctx = EdgeContext(params=params)
    e, J, *_ = edge.linearize((T, X), z, ctx)
    N = numeric_jacobians(edge, (T, X), z, ctx)
    np.testing.assert_allclose(e, edge.error((T, X), z, ctx))
    assert [j.shape[1:] for j in J] == [(2, 6), (2, 3)]
    for a, b in zip(J, N, strict=True):
        assert _rel_err(a, b) < 1e-6
    # g2o's sign: error = measurement − projection.
    P = np.einsum("nij,nj->ni", T[:, :3, :3], X) + T[:, :3, 3]
    np.testing.assert_allclose(z[:, 0] - e[:, 0], 500 * P[:, 0] / P[:, 2] + 320)


def test_inverse_depth_edge_jacobians_match_numeric() -> None:
    T, Ta, _, ip, z = _pinhole_inputs()
    ctx = EdgeContext(params=CameraParameters(450, 450, 320, 240))
    x = (Ta, T, ip)
    e, J, *_ = EdgeInverseDepthProjection.linearize(x, z, ctx)
    N = numeric_jacobians(EdgeInverseDepthProjection, x, z, ctx)
    np.testing.assert_allclose(e, EdgeInverseDepthProjection.error(x, z, ctx))
    for a, b in zip(J, N, strict=True):
        assert _rel_err(a, b) < 1e-6
    # Same pixel as the Euclidean edge for the equivalent world point.
    Xa = np.column_stack([ip[:, :2], np.ones(len(ip))]) / ip[:, 2:3]
    Raw = Ta[:, :3, :3]
    Xw = np.einsum("nji,nj->ni", Raw, Xa - Ta[:, :3, 3])
    e2 = EdgeSE3ProjectXYZ.error((T, Xw), z, ctx)
    np.testing.assert_allclose(e, e2, atol=1e-8)


def test_inverse_depth_anchor_observing_itself() -> None:
    T, _, _, ip, z = _pinhole_inputs(m=20)
    ctx = EdgeContext(params=CameraParameters(450, 450, 320, 240))
    _, (Ja, Jo, _), *_ = EdgeInverseDepthProjection.linearize((T, T, ip), z, ctx)
    np.testing.assert_allclose(Ja + Jo, 0.0, atol=1e-9)


def test_projection_params_missing_is_clear() -> None:
    T, _, X, _, z = _pinhole_inputs(m=3)
    with pytest.raises(ValueError, match="CameraParameters"):
        EdgeSE3ProjectXYZ.error((T, X), z, EdgeContext())


def test_bal_edge_blocks_match_single_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    cams, X, z = _bal_inputs(m=1000, seed=8)
    ctx = EdgeContext()
    e1, (Jc1, Jp1), *_ = EdgeBALProjection.linearize((cams, X), z, ctx)
    err1 = EdgeBALProjection.error((cams, X), z, ctx)
    monkeypatch.setattr(EdgeBALProjection, "block_size", 97)  # several blocks, ragged last
    e2, (Jc2, Jp2), *_ = EdgeBALProjection.linearize((cams, X), z, ctx)
    err2 = EdgeBALProjection.error((cams, X), z, ctx)
    for a, b in ((e1, e2), (Jc1, Jc2), (Jp1, Jp2), (err1, err2), (e1, err1)):
        np.testing.assert_array_equal(a, b)


# --- the projection edges inside the optimizer (Schur complement over the points) -------------


def _pinhole_scene(seed: int = 0):
    rng = np.random.default_rng(seed)
    K = CameraParameters(400.0, 400.0, 320.0, 240.0)
    nc, npt = 6, 200
    xi = np.zeros((nc, 6))
    xi[:, 3] = -0.5 * np.arange(nc)  # cameras along x, looking down +z
    T = se3_exp(xi + rng.normal(0, 0.01, (nc, 6)))
    Xw = rng.uniform([-2, -2, 4], [4, 2, 8], (npt, 3))
    P = np.einsum("cij,pj->cpi", T[:, :3, :3], Xw) + T[:, None, :3, 3]
    u = K.fx * P[..., 0] / P[..., 2] + K.cx
    v = K.fy * P[..., 1] / P[..., 2] + K.cy
    seen = (P[..., 2] > 0) & (u > 0) & (u < 640) & (v > 0) & (v < 480)
    cam, pt = np.nonzero(seen)
    uv = np.column_stack([u[cam, pt], v[cam, pt]]) + rng.normal(0, 0.5, (len(cam), 2))
    T0 = VertexSE3Expmap.oplus(T, np.r_[np.zeros((2, 6)), rng.normal(0, 0.01, (nc - 2, 6))])
    return K, T, T0, Xw, cam, pt, uv, rng


def test_inverse_depth_bundle_adjustment_converges() -> None:
    from graphopt import LevenbergConfig, SparseOptimizer
    from graphopt.types.vertices import VertexPointInverseDepth

    K, T, T0, Xw, cam, pt, uv, rng = _pinhole_scene()
    npt = len(Xw)
    first = np.full(npt, len(cam))
    np.minimum.at(first, pt, np.arange(len(cam)))
    anchor = cam[first]  # the first camera that sees each point
    Pa = np.einsum("nij,nj->ni", T[anchor, :3, :3], Xw) + T[anchor, :3, 3]
    ip = np.column_stack([Pa[:, 0] / Pa[:, 2], Pa[:, 1] / Pa[:, 2], 1 / Pa[:, 2]])
    ip *= 1 + rng.normal(0, 0.02, ip.shape)
    opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True))
    opt.add_vertices(VertexSE3Expmap, np.arange(len(T)), T0, fixed=np.arange(len(T)) < 2)
    opt.add_vertices(VertexPointInverseDepth, 100 + np.arange(npt), ip, marginalized=True)
    # Includes edges whose observing camera is the anchor itself.
    opt.add_edges(EdgeInverseDepthProjection, np.column_stack([anchor[pt], cam, 100 + pt]), uv,
                  params=K)
    res = opt.optimize(20)
    assert res.final_chi2 < 1e-2 * res.initial_chi2
    assert res.final_chi2 < 2 * 0.25 * 2 * len(uv)  # about the noise level (σ = 0.5 px)


def test_pinhole_bundle_adjustment_converges() -> None:
    from graphopt import LevenbergConfig, SparseOptimizer

    K, T, T0, Xw, cam, pt, uv, rng = _pinhole_scene(seed=1)
    X0 = Xw + rng.normal(0, 0.05, Xw.shape)
    opt = SparseOptimizer(algorithm=LevenbergConfig(diagonal_damping=True))
    opt.add_vertices(VertexSE3Expmap, np.arange(len(T)), T0, fixed=np.arange(len(T)) < 2)
    opt.add_vertices(VertexPointXYZ, 100 + np.arange(len(Xw)), X0, marginalized=True)
    opt.add_edges(EdgeSE3ProjectXYZ, np.column_stack([cam, 100 + pt]), uv, params=K)
    res = opt.optimize(20)
    assert res.final_chi2 < 1e-2 * res.initial_chi2
    assert res.final_chi2 < 2 * 0.25 * 2 * len(uv)


def test_bal_edge_with_derived_rotations_matches_rodrigues() -> None:
    """The camera's derived rotation matrices give the edge's own Rodrigues results."""
    cams, X, z = _bal_inputs(m=500, seed=9)
    plain = EdgeBALProjection.linearize((cams, X), z, EdgeContext())
    ctx = EdgeContext(derived=(VertexCameraBAL.derived(cams), None))
    shared = EdgeBALProjection.linearize((cams, X), z, ctx)
    for a, b in ((plain[0], shared[0]), *zip(plain[1], shared[1], strict=True)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-9 * np.abs(a).max())
    np.testing.assert_allclose(EdgeBALProjection.error((cams, X), z, ctx), plain[0],
                               rtol=1e-12, atol=1e-9)


def test_bal_camera_uses_the_one_rodrigues() -> None:
    """The camera's rotation is graphopt.lie.so3_exp, bit for bit, at every angle."""
    cams, X, z = _bal_inputs(m=60, seed=11)
    cams[6, :3] = [0.6e-4, 0.0, 0.0]  # just inside the series branch of lie.SMALL_ANGLE2
    R = so3_exp(cams[:, :3])
    np.testing.assert_array_equal(VertexCameraBAL.derived(cams), R.reshape(60, 9))
    np.testing.assert_array_equal(VertexCameraBAL.derived(cams[:4]), np.tile(np.eye(3).ravel(),
                                                                              (4, 1)))
    uv, Pz = bal_project(cams, X)
    P = np.einsum("nij,nj->ni", R, X) + cams[:, 3:6]
    np.testing.assert_allclose(Pz, P[:, 2], rtol=1e-14)
    p = -P[:, :2] / P[:, 2:]
    r2 = (p * p).sum(1)
    d = 1 + cams[:, 7] * r2 + cams[:, 8] * r2 * r2
    np.testing.assert_allclose(uv, cams[:, 6:7] * d[:, None] * p, rtol=1e-12)


def test_reprojection_errors_and_cost() -> None:
    from graphopt.io.bal import BALProblem
    from graphopt.types.bal import bal_cost, reprojection_errors

    cams, _, z = _bal_inputs(m=30, seed=12)
    ci = np.arange(30) % 6  # 6 cameras, 30 points, one observation each
    cams6 = cams[:6]
    P = np.c_[np.zeros((30, 2)), np.full(30, -8.0)]  # on each camera's axis, 8 in front
    Xw = angle_axis_rotate(-cams6[ci, :3], P - cams6[ci, 3:6])  # X = Rᵀ (P − t)
    problem = BALProblem(cams6, Xw, ci, np.arange(30), z)
    r, Pz = reprojection_errors(problem)
    uv, Pz_ref = bal_project(cams6[ci], Xw)
    np.testing.assert_array_equal(r, uv - z)
    np.testing.assert_allclose(Pz, -8.0, rtol=1e-12)  # every point 8 units in front
    np.testing.assert_array_equal(Pz, Pz_ref)
    np.testing.assert_allclose(uv, 0.0, atol=1e-9)  # on the optical axis: the image centre
    assert bal_cost(problem) == pytest.approx(0.5 * float((z * z).sum()), rel=1e-12)
    moved = Xw + 1.0
    r2, _ = reprojection_errors(problem, points=moved)
    np.testing.assert_array_equal(r2, bal_project(cams6[ci], moved)[0] - z)
    r3, _ = reprojection_errors(problem, cameras=cams6 * 1.0, points=Xw)
    np.testing.assert_array_equal(r3, r)
