"""The g2o types added for the g2o API (``slam3d_sensors``, ``slam2d_sensors``, ``sba_cam``,
``sba_expmap``, ``icp``): chi2 equal to g2o's own (g2opy 2.3.0, recorded by
``benchmarks/g2o_types_reference.py`` in ``tests/data``), analytic Jacobians against numeric
ones, and a few solves through the optimizer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_slam_types import _assert_jacobians, _se2, _se3

from graphopt import SparseOptimizer
from graphopt.edge import EdgeContext
from graphopt.lie import quat_to_rot, se3_exp, transform_inverse
from graphopt.numeric import numeric_jacobians
from graphopt.types import (
    EdgePointXY,
    EdgePointXYZ,
    EdgeProjectP2MC,
    EdgeProjectP2SC,
    EdgeProjectPSI2UV,
    EdgeProjectXYZ2UV,
    EdgeProjectXYZ2UVU,
    EdgeSBACam,
    EdgeSBAScale,
    EdgeSE2LotsOfXY,
    EdgeSE2OdomDifferentialCalib,
    EdgeSE2Offset,
    EdgeSE2PointXYBearing,
    EdgeSE2PointXYCalib,
    EdgeSE2PointXYOffset,
    EdgeSE2SensorCalib,
    EdgeSE2TwoPointsXY,
    EdgeSE2XYPrior,
    EdgeSE3LotsOfXYZ,
    EdgeSE3Offset,
    EdgeSE3PointXYZDepth,
    EdgeSE3PointXYZDisparity,
    EdgeSE3ProjectXYZ,
    EdgeSE3XYZPrior,
    EdgeVVGicp,
    EdgeVVGicpPlaneToPlane,
    EdgeXYPrior,
    EdgeXYZPrior,
    EdgeXyzVsc,
    ParameterCamera,
    ParameterSE2Offset,
    ParameterSE3Offset,
    SBACameraParameters,
    SCamParameters,
    VertexCam,
    VertexIntrinsics,
    VertexPointXY,
    VertexPointXYZ,
    VertexSE2,
    VertexSE3,
)
from graphopt.types.icp import gicp_covariance, gicp_normal_frame

REFERENCE = Path(__file__).parent / "data" / "g2o_types_reference.json"
RECORD = json.loads(REFERENCE.read_text())
CASES = RECORD["cases"]
TYPES: dict[str, Any] = {
    "EdgeSE3LotsOfXYZ": EdgeSE3LotsOfXYZ.of(3),
    "EdgeSE2LotsOfXY": EdgeSE2LotsOfXY.of(3),
    **{t.__name__: t for t in (
        EdgePointXY, EdgePointXYZ, EdgeProjectP2MC, EdgeProjectP2SC, EdgeProjectPSI2UV,
        EdgeProjectXYZ2UVU, EdgeSBACam, EdgeSBAScale, EdgeSE2Offset, EdgeSE2PointXYBearing,
        EdgeSE2PointXYCalib, EdgeSE2PointXYOffset, EdgeSE2TwoPointsXY, EdgeSE2XYPrior,
        EdgeSE2SensorCalib, EdgeSE2OdomDifferentialCalib,
        EdgeSE3Offset, EdgeSE3PointXYZDepth, EdgeSE3PointXYZDisparity, EdgeSE3XYZPrior,
        EdgeVVGicp, EdgeVVGicpPlaneToPlane, EdgeXYPrior, EdgeXyzVsc, EdgeXYZPrior,
        # graphopt's own, recorded for the API layer: g2o's numbers through SBACameraParameters
        EdgeProjectXYZ2UV, EdgeSE3ProjectXYZ)},
}


def _context(case: dict[str, Any]) -> EdgeContext:
    """graphopt's params and data for a recorded case."""
    spec, params = case["params"], None
    kind = spec and spec["kind"]
    if kind == "se3_offsets":
        params = tuple(ParameterSE3Offset(np.array(o)) for o in spec["offsets"])
    elif kind == "se3_offset":
        params = ParameterSE3Offset(np.array(spec["offset"]))
    elif kind == "camera":
        params = ParameterCamera(np.array(spec["offset"]), 0, *spec["K"])
    elif kind == "se2_offsets":
        offsets = tuple(ParameterSE2Offset(np.array(o)) for o in spec["offsets"])
        params = offsets if case["type"] == "EdgeSE2Offset" else offsets[0]
    elif kind == "sba_camera":
        params = SBACameraParameters.from_g2o(spec["f"], spec["pp"], spec["baseline"])
    elif kind == "scam":
        params = SCamParameters(*spec["K"])
    data = {}
    if case["type"] == "EdgeVVGicpPlaneToPlane":
        n = np.array(case["data"]["normals"])
        data = {"cov0": gicp_covariance(n[:, 0], 0.01), "cov1": gicp_covariance(n[:, 1], 0.01)}
    return EdgeContext(params, data)


@pytest.mark.parametrize("case", CASES, ids=[c["type"] for c in CASES])
def test_chi2_equals_g2os(case: dict[str, Any]) -> None:
    etype = TYPES[case["type"]]
    x = [np.array(a) for a in case["x"]]
    z = np.array(case["z"]).reshape(-1, *etype.get_measurement_shape())
    info = np.array(case["information"])
    ctx = _context(case)
    e = etype.error(x, z, ctx)
    chi2 = np.einsum("mi,mij,mj->m", e, info, e)
    np.testing.assert_allclose(chi2, case["chi2"], rtol=1e-6)
    assert etype.linearize(x, z, ctx).error.shape == e.shape


def test_every_type_has_a_reference() -> None:
    assert sorted(TYPES) == sorted(c["type"] for c in CASES)


def test_camera_update_is_sbacams() -> None:
    """VertexCam.oplus against g2o's SBACam::update (translation in the world frame,
    rotation right-multiplied); the intrinsics stay."""
    rec = RECORD["camera_updates"]
    cams, deltas, g2o = (np.array(rec[k]) for k in ("cameras", "deltas", "result"))
    out = VertexCam.oplus(cams, deltas)
    np.testing.assert_allclose(out[:, :3], g2o[:, :3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(quat_to_rot(out[:, 3:7]), quat_to_rot(g2o[:, 3:7]), atol=1e-14)
    np.testing.assert_array_equal(out[:, 7:], cams[:, 7:])
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:7], axis=1), 1.0, atol=1e-15)
    v = VertexIntrinsics.oplus(np.array([[500.0, 510.0, 320.0, 240.0, 0.1]]),
                               np.array([[1.0, 2.0, 3.0, 4.0]]))
    np.testing.assert_array_equal(v, [[501.0, 512.0, 323.0, 244.0, 0.1]])


# --- Jacobians ---------------------------------------------------------------------------


def _front(rng: np.random.Generator, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points in front of cameras whose pose in the world is ``(R, t)``."""
    pc = np.column_stack([rng.normal(0, 1, (len(R), 2)), rng.uniform(3, 8, len(R))])
    return np.einsum("nij,nj->ni", R, pc) + t


def test_slam3d_jacobians() -> None:
    rng = np.random.default_rng(5)
    m = 40
    xi, xj, z = _se3(rng, m), _se3(rng, m), _se3(rng, m)
    P1, P2 = ParameterSE3Offset(_se3(rng, 5)[4]), ParameterSE3Offset(_se3(rng, 6)[5])
    _assert_jacobians(EdgeSE3Offset, (xi, xj), z, EdgeContext((P1, P2)))
    _assert_jacobians(EdgeSE3Offset, (xi, xj), z)
    p, q = rng.normal(0, 5, (m, 3)), rng.normal(0, 5, (m, 3))
    _assert_jacobians(EdgePointXYZ, (p, q), z[:, :, 3])
    _assert_jacobians(EdgeXYZPrior, (p,), z[:, :, 3])
    _assert_jacobians(EdgeSE3XYZPrior, (xi,), z[:, :, 3])
    cam = ParameterCamera(_se3(rng, 5)[4], fx=500, fy=510, cx=320, cy=240)
    for etype in (EdgeSE3PointXYZDepth, EdgeSE3PointXYZDisparity):
        _assert_jacobians(etype, (xi, p), q, EdgeContext(cam))
    lots = EdgeSE3LotsOfXYZ.of(3)
    assert lots is EdgeSE3LotsOfXYZ.of(3) and lots.dimension == 9
    _assert_jacobians(lots, (xi, p, q, 2 * p), rng.normal(size=(m, 9)))


def test_slam2d_jacobians() -> None:
    rng = np.random.default_rng(6)
    m = 40
    xi, xj, z = _se2(rng, m), _se2(rng, m), _se2(rng, m)
    p, q = rng.normal(0, 5, (m, 2)), rng.normal(0, 5, (m, 2))
    offsets = ParameterSE2Offset([0.3, -0.2, 0.4]), ParameterSE2Offset([-1.0, 0.5, -2.0])
    _assert_jacobians(EdgeSE2Offset, (xi, xj), 0.1 * z, EdgeContext(offsets))
    _assert_jacobians(EdgePointXY, (p, q), z[:, :2])
    _assert_jacobians(EdgeXYPrior, (p,), z[:, :2])
    _assert_jacobians(EdgeSE2XYPrior, (xi,), z[:, :2])
    _assert_jacobians(EdgeSE2PointXYBearing, (xi, p), 0.1 * z[:, 2:])
    _assert_jacobians(EdgeSE2PointXYOffset, (xi, p), z[:, :2], EdgeContext(offsets[0]))
    _assert_jacobians(EdgeSE2PointXYCalib, (xi, p, xj), z[:, :2])
    _assert_jacobians(EdgeSE2TwoPointsXY, (xi, p, q), rng.normal(size=(m, 4)))
    _assert_jacobians(EdgeSE2LotsOfXY.of(3), (xi, p, q, p + 1), rng.normal(size=(m, 6)))
    _assert_jacobians(EdgeSE2SensorCalib, (xi, xj, 0.3 * z), 0.1 * z)


def _cams(rng: np.random.Generator, m: int) -> np.ndarray:
    q = rng.normal(size=(m, 4))
    return np.column_stack([rng.normal(0, 2, (m, 3)), q / np.linalg.norm(q, axis=1)[:, None],
                            np.tile([500.0, 510.0, 320.0, 240.0, 0.1], (m, 1))])


def test_sba_jacobians() -> None:
    rng = np.random.default_rng(7)
    m = 40
    ci, cj = _cams(rng, m), _cams(rng, m)
    p = _front(rng, quat_to_rot(ci[:, 3:7]), ci[:, :3])
    _assert_jacobians(EdgeProjectP2MC, (ci, p), rng.normal(0, 100, (m, 2)))
    _assert_jacobians(EdgeProjectP2SC, (ci, p), rng.normal(0, 100, (m, 3)))
    # The cameras' rotations from VertexCam.derived give the same linearisation.
    cached = EdgeProjectP2SC.linearize((ci, p), np.zeros((m, 3)),
                                       EdgeContext(derived=(VertexCam.derived(ci), None)))
    plain = EdgeProjectP2SC.linearize((ci, p), np.zeros((m, 3)), EdgeContext())
    np.testing.assert_allclose(cached.jacobians[0], plain.jacobians[0], rtol=1e-12, atol=1e-9)
    z = np.column_stack([rng.normal(size=(m, 3)), _cams(rng, m)[:, 3:7]])
    _assert_jacobians(EdgeSBACam, (ci, cj), z)
    _assert_jacobians(EdgeSBAScale, (ci, cj), rng.uniform(1, 3, (m, 1)))
    T = se3_exp(rng.normal(0, 0.3, (m, 6)))
    Tinv = transform_inverse(T)
    pw = _front(rng, Tinv[:, :3, :3], Tinv[:, :3, 3])
    cam = SBACameraParameters.from_g2o(500, (320, 240), 0.1)
    _assert_jacobians(EdgeProjectXYZ2UVU, (T, pw), rng.normal(size=(m, 3)), EdgeContext(cam))
    psi = np.column_stack([rng.normal(0, 0.3, (m, 2)), rng.uniform(0.1, 0.5, m)])
    _assert_jacobians(EdgeProjectPSI2UV, (T, T[::-1], psi), rng.normal(size=(m, 2)),
                      EdgeContext(cam))


def test_icp_jacobians_and_whitening() -> None:
    rng = np.random.default_rng(8)
    m = 40
    x0, x1 = _se3(rng, m), _se3(rng, m)
    z = rng.normal(size=(m, 2, 3))
    _assert_jacobians(EdgeVVGicp, (x0, x1), z)
    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[0] = [0.0, 1.0, 0.0]  # the x-axis branch of g2o's makeRot
    R = gicp_normal_frame(n)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(R[:, 2], n, atol=1e-15)
    ctx = EdgeContext(data={"cov0": gicp_covariance(n, 0.01),
                            "cov1": gicp_covariance(n[::-1], 0.01)})
    lin = EdgeVVGicpPlaneToPlane.linearize((x0, x1), z, ctx)
    # e_wᵀe_w = eᵀ(cov0 + R cov1 Rᵀ)⁻¹e, and the Jacobians are Lᵀ times the plain ones.
    Rrel = np.swapaxes(x0[:, :, :3], 1, 2) @ x1[:, :, :3]
    C = ctx.data["cov0"] + Rrel @ ctx.data["cov1"] @ np.swapaxes(Rrel, 1, 2)
    e = EdgeVVGicp.error((x0, x1), z, ctx)
    np.testing.assert_allclose(np.einsum("mi,mi->m", lin.error, lin.error),
                               np.einsum("mi,mij,mj->m", e, np.linalg.inv(C), e), rtol=1e-10)
    W = EdgeVVGicpPlaneToPlane._whitener(Rrel, ctx)
    for a, b in zip(lin.jacobians, numeric_jacobians(EdgeVVGicp, (x0, x1), z, ctx), strict=True):
        np.testing.assert_allclose(a, W @ b, atol=1e-6 * max(1.0, np.abs(b).max()))
    X = _se3(rng, m)
    p = _front(rng, X[:, :, :3], X[:, :, 3])
    _assert_jacobians(EdgeXyzVsc, (X, p), rng.normal(size=(m, 3)),
                      EdgeContext(SCamParameters(500, 510, 320, 240, 0.1)))


# --- through the optimizer -----------------------------------------------------------------


def test_gicp_aligns_two_scans() -> None:
    """g2o's gicp_demo in small: two poses, the first fixed, point-to-plane correspondences
    (information ``prec0(0.01)``) of a noiseless scene; the second pose is recovered."""
    rng = np.random.default_rng(9)
    truth = np.eye(3, 4)
    truth[:, :3] = quat_to_rot(np.array([[0.02, -0.03, 0.05, 1.0]]))[0]
    truth[:, 3] = [0.3, -0.1, 0.2]
    pts = rng.uniform(-3, 3, (200, 3))
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # pos1 in frame 1: X1⁻¹ p with X0 = I
    pos1 = (pts - truth[:, 3]) @ truth[:, :3]
    opt = SparseOptimizer()
    opt.add_vertices(VertexSE3, [0, 1], np.stack([np.eye(3, 4), np.eye(3, 4)]),
                     fixed=[True, False])
    info = np.stack([R.T @ np.diag([0.01, 0.01, 1.0]) @ R for R in gicp_normal_frame(normals)])
    opt.add_edges(EdgeVVGicp, np.tile([0, 1], (200, 1)), np.stack([pts, pos1], axis=1), info)
    opt.initialize_optimization()
    opt.optimize(20)
    np.testing.assert_allclose(opt.vertex(1).estimate, truth, atol=1e-8)


def test_offsets_and_priors_solve_a_small_graph() -> None:
    """A 2D and a 3D graph of the new edge types whose measurements come from a known truth:
    the optimum is the truth (chi2 ≈ 0) from a perturbed start."""
    rng = np.random.default_rng(10)
    poses = np.column_stack([np.arange(4.0), np.sin(np.arange(4.0)), 0.3 * np.arange(4.0)])
    lm = rng.normal(0, 3, (3, 2))
    off = ParameterSE2Offset([0.2, -0.1, 0.3])
    opt = SparseOptimizer()
    start = poses + rng.normal(0, 0.05, (4, 3))
    start[0] = poses[0]
    opt.add_vertices(VertexSE2, range(4), start, fixed=[True, False, False, False])
    opt.add_vertices(VertexPointXY, [10, 11, 12], lm + rng.normal(0, 0.1, (3, 2)))
    pairs = np.array([[0, 1], [1, 2], [2, 3], [0, 2]])
    pair_params = (off, off)
    z = EdgeSE2Offset.error((poses[pairs[:, 0]], poses[pairs[:, 1]]), np.zeros((4, 3)),
                            EdgeContext(pair_params))
    # measurement Z with error 0: Z = t2v((Xi P)⁻¹ (Xj P)); error(Z=0) is that relative pose
    opt.add_edges(EdgeSE2Offset, pairs, z, params=pair_params)
    obs = np.array([[i, 10 + j] for i in range(4) for j in range(3)])
    d = lm[obs[:, 1] - 10] - poses[obs[:, 0], :2]
    bearing = np.arctan2(d[:, 1], d[:, 0]) - poses[obs[:, 0], 2]
    opt.add_edges(EdgeSE2PointXYBearing, obs, bearing[:, None], 100.0 * np.eye(1))
    opt.add_edges(EdgeXYPrior, [[10]], lm[:1])
    opt.add_edges(EdgeSE2XYPrior, [[3]], poses[3:, :2])
    opt.initialize_optimization()
    opt.optimize(30)
    np.testing.assert_allclose(opt.vertex(2).estimate, poses[2], atol=1e-6)
    np.testing.assert_allclose(opt.vertex(12).estimate, lm[2], atol=1e-6)

    X = _se3(rng, 8)[4:7]
    pts = rng.normal(0, 3, (2, 3))
    opt = SparseOptimizer()
    opt.add_vertices(VertexSE3, [0, 1, 2], X, fixed=[True, False, False])
    opt.add_vertices(VertexPointXYZ, [5, 6], pts + 0.05)
    P = (ParameterSE3Offset(_se3(rng, 5)[4]), ParameterSE3Offset(_se3(rng, 6)[5]))
    A = np.einsum("nij,jk->nik", X[:, :, :3], P[0].offset)
    A[:, :, 3] += X[:, :, 3]
    B = np.einsum("nij,jk->nik", X[:, :, :3], P[1].offset)
    B[:, :, 3] += X[:, :, 3]
    Z = np.einsum("nji,njk->nik", A[[0, 1]][:, :, :3], B[[1, 2]])  # (A_i)⁻¹ B_j
    Z[:, :, 3] -= np.einsum("nji,nj->ni", A[[0, 1]][:, :, :3], A[[0, 1]][:, :, 3])
    opt.add_edges(EdgeSE3Offset, [[0, 1], [1, 2]], Z, params=P)
    opt.add_edges(EdgePointXYZ, [[5, 6]], (pts[1] - pts[0])[None])
    opt.add_edges(EdgeXYZPrior, [[5]], pts[:1])
    lots = EdgeSE3LotsOfXYZ.of(2)
    local = np.einsum("ji,kj->ki", X[2, :, :3], pts - X[2, :, 3]).reshape(1, 6)
    opt.add_edges(lots, [[2, 5, 6]], local)
    opt.initialize_optimization()
    opt.optimize(30)
    np.testing.assert_allclose(opt.vertex(2).estimate, X[2], atol=1e-6)
    np.testing.assert_allclose(opt.vertex(6).estimate, pts[1], atol=1e-6)
