"""Random valid inputs of every built-in edge type, for the autodiff-vs-analytic test.

``SAMPLES[name](rng, m)`` returns ``(x, measurement, params, data)``: per vertex position the
``(m, *estimate_shape)`` estimates, the ``(m, *measurement_shape)`` measurements, the group's
``params`` and per-edge ``data`` — what :func:`graphopt.check_jacobians` takes.

Adding a type (tests/test_autodiff.py fails naming any edge type exported by
``graphopt.types`` that has no sample here) is one function::

    @sample("EdgeMyType")
    def _my_type(rng, m):
        x0 = ...                       # (m, *estimate_shape) valid estimates
        z = rng.normal(size=(m, 2))    # (m, *measurement_shape)
        return [x0, ...], z, None, None
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from graphopt.lie import se3_exp, so3_exp

Sample = tuple[list[np.ndarray], np.ndarray, Any, dict[str, np.ndarray] | None]
SAMPLES: dict[str, Callable[[np.random.Generator, int], Sample]] = {}


def sample(name: str) -> Callable[[Callable[..., Sample]], Callable[..., Sample]]:
    """Register ``fn(rng, m)`` as the sample of the edge type ``name``."""
    def deco(fn: Callable[..., Sample]) -> Callable[..., Sample]:
        SAMPLES[name] = fn
        return fn
    return deco


def se2(rng: np.random.Generator, m: int) -> np.ndarray:
    x = rng.normal(0.0, 3.0, (m, 3))
    x[:, 2] = rng.uniform(-np.pi, np.pi, m)
    return x


def se3_compact(rng: np.random.Generator, m: int) -> np.ndarray:
    """``(m, 3, 4)`` ``[R | t]`` (VertexSE3's estimate)."""
    T = np.empty((m, 3, 4))
    T[:, :, :3] = so3_exp(rng.normal(0.0, 1.0, (m, 3)))
    T[:, :, 3] = rng.normal(0.0, 3.0, (m, 3))
    return T


def pose(rng: np.random.Generator, m: int, scale: float = 0.3) -> np.ndarray:
    """``(m, 4, 4)`` transforms (VertexSE3Expmap's estimate)."""
    return se3_exp(rng.normal(0.0, scale, (m, 6)))


def in_front(rng: np.random.Generator, T: np.ndarray) -> np.ndarray:
    """World points 4–8 units in front of the cameras ``T_cw``."""
    m = len(T)
    pc = np.c_[rng.normal(0, 0.5, (m, 2)), rng.uniform(4, 8, m)]
    R, t = T[:, :3, :3], T[:, :3, 3]
    return np.einsum("mji,mj->mi", R, pc - t)


@sample("EdgeBALProjection")
def _bal(rng: np.random.Generator, m: int) -> Sample:
    cams = np.c_[rng.normal(0, 0.5, (m, 3)), rng.normal(0, 1, (m, 3)), rng.uniform(400, 1500, m),
                 rng.normal(0, 0.1, m), rng.normal(0, 0.01, m)]
    d = np.c_[rng.normal(0, 0.3, (m, 2)), -np.ones(m)] * rng.uniform(5, 15, m)[:, None]
    X = np.einsum("mji,mj->mi", so3_exp(cams[:, :3]), d - cams[:, 3:6])
    return [cams, X], rng.normal(0, 200, (m, 2)), None, None


def _pinhole(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import CameraParameters

    T = pose(rng, m)
    return [T, in_front(rng, T)], rng.normal(300, 50, (m, 2)), \
        CameraParameters(500, 510, 320, 240), None


SAMPLES["EdgeSE3ProjectXYZ"] = _pinhole
SAMPLES["EdgeProjectXYZ2UV"] = _pinhole


@sample("EdgeInverseDepthProjection")
def _inverse_depth(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import CameraParameters

    Ta, T = pose(rng, m, 0.1), pose(rng, m, 0.1)
    ip = np.c_[rng.normal(0, 0.3, (m, 2)), rng.uniform(0.1, 0.3, m)]
    return [Ta, T, ip], rng.normal(300, 50, (m, 2)), CameraParameters(450, 450, 320, 240), None


def _photometric(kind: int) -> Callable[[np.random.Generator, int], Sample]:
    def fn(rng: np.random.Generator, m: int) -> Sample:
        from graphopt.types import PhotometricParams

        h, w = 120, 160
        yy, xx = np.mgrid[0:h, 0:w].astype(float)
        images = np.stack([100 + 50 * np.sin(xx / 7 + k) * np.cos(yy / 9 - k) + 0.02 * xx * yy
                           for k in range(2)])
        prm = PhotometricParams(images, 100.0, 110.0, 80.0, 60.0, patch=4,
                                gradient="interpolated", dtype="float64")
        Tj, Ta = pose(rng, m, 0.05), pose(rng, m, 0.05)
        p = np.c_[rng.normal(size=(m, 2)) * 0.5, 3 + rng.random(m)]
        q = np.c_[rng.normal(size=(m, 2)) * 0.3, 1 / (3 + rng.random(m))]
        x = [[Tj, p], [Ta, Tj, q], [Ta, q]][kind]
        meas = rng.random((m, 16)) * 200
        return x, meas, prm, {"image": rng.integers(0, 2, m)}
    return fn


SAMPLES["EdgePhotometricPatch"] = _photometric(0)
SAMPLES["EdgePhotometricPatchInverseDepth"] = _photometric(1)
SAMPLES["EdgePhotometricPatchInverseDepthHost"] = _photometric(2)


@sample("EdgeSE2")
def _se2_edge(rng: np.random.Generator, m: int) -> Sample:
    return [se2(rng, m), se2(rng, m)], se2(rng, m) * 0.3, None, None


@sample("EdgeSE2PointXY")
def _se2_point(rng: np.random.Generator, m: int) -> Sample:
    return [se2(rng, m), rng.normal(0, 3, (m, 2))], rng.normal(0, 3, (m, 2)), None, None


@sample("EdgeSE2Prior")
def _se2_prior(rng: np.random.Generator, m: int) -> Sample:
    return [se2(rng, m)], se2(rng, m), None, None


@sample("EdgeSE3")
def _se3_edge(rng: np.random.Generator, m: int) -> Sample:
    return [se3_compact(rng, m), se3_compact(rng, m)], se3_compact(rng, m), None, None


@sample("EdgeSE3PointXYZ")
def _se3_point(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import ParameterSE3Offset

    off = ParameterSE3Offset(se3_compact(rng, 1)[0], id=0)
    return [se3_compact(rng, m), rng.normal(0, 3, (m, 3))], rng.normal(0, 3, (m, 3)), off, None


@sample("EdgeSE3Prior")
def _se3_prior(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import ParameterSE3Offset

    off = ParameterSE3Offset(se3_compact(rng, 1)[0], id=0)
    return [se3_compact(rng, m)], se3_compact(rng, m), off, None



# --- g2o's sensor, sclam, sba and icp types (g2otypes23) -------------------------------------

def _t(name: str) -> Any:
    import graphopt.types as types

    return getattr(types, name)


def unit_quaternions(rng: np.random.Generator, m: int) -> np.ndarray:
    q = rng.normal(size=(m, 4))
    return q / np.linalg.norm(q, axis=1)[:, None]


def sba_cams(rng: np.random.Generator, m: int) -> np.ndarray:
    """VertexCam estimates ``[t, q, fx, fy, cx, cy, baseline]``."""
    return np.c_[rng.normal(0, 2, (m, 3)), unit_quaternions(rng, m),
                 np.tile([500.0, 510.0, 320.0, 240.0, 0.1], (m, 1))]


def front(rng: np.random.Generator, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points in front of cameras whose pose in the world is ``(R, t)``."""
    pc = np.c_[rng.normal(0, 1, (len(R), 2)), rng.uniform(3, 8, len(R))]
    return np.einsum("nij,nj->ni", R, pc) + t


def _plain(fn: Callable[[np.random.Generator, int], tuple[list[np.ndarray], np.ndarray]]
           ) -> Callable[[np.random.Generator, int], Sample]:
    return lambda rng, m: (*fn(rng, m), None, None)


SAMPLES.update({
    "EdgePointXY": _plain(lambda r, m: ([r.normal(0, 5, (m, 2)), r.normal(0, 5, (m, 2))],
                                       r.normal(size=(m, 2)))),
    "EdgePointXYZ": _plain(lambda r, m: ([r.normal(0, 5, (m, 3)), r.normal(0, 5, (m, 3))],
                                        r.normal(size=(m, 3)))),
    "EdgeXYPrior": _plain(lambda r, m: ([r.normal(0, 5, (m, 2))], r.normal(size=(m, 2)))),
    "EdgeXYZPrior": _plain(lambda r, m: ([r.normal(0, 5, (m, 3))], r.normal(size=(m, 3)))),
    "EdgeSE2XYPrior": _plain(lambda r, m: ([se2(r, m)], r.normal(size=(m, 2)))),
    "EdgeSE3XYZPrior": _plain(lambda r, m: ([se3_compact(r, m)], r.normal(size=(m, 3)))),
    "EdgeSE2PointXYBearing": _plain(lambda r, m: ([se2(r, m), r.normal(0, 5, (m, 2))],
                                                 r.uniform(-0.3, 0.3, (m, 1)))),
    "EdgeSE2PointXYCalib": _plain(lambda r, m: ([se2(r, m), r.normal(0, 5, (m, 2)),
                                               se2(r, m) * 0.1], r.normal(size=(m, 2)))),
    "EdgeSE2TwoPointsXY": _plain(lambda r, m: ([se2(r, m), r.normal(0, 5, (m, 2)),
                                              r.normal(0, 5, (m, 2))], r.normal(size=(m, 4)))),
    "EdgeSE2SensorCalib": _plain(lambda r, m: ([se2(r, m), se2(r, m), 0.3 * se2(r, m)],
                                              0.1 * se2(r, m))),
    "EdgeSE2OdomDifferentialCalib": _plain(lambda r, m: (
        [se2(r, m), se2(r, m), r.uniform(0.5, 1.5, (m, 3))], r.normal(0, 0.5, (m, 3)))),
    "EdgeVVGicp": _plain(lambda r, m: ([se3_compact(r, m), se3_compact(r, m)],
                                      r.normal(size=(m, 2, 3)))),
})


@sample("EdgeSE2LotsOfXY")
def _se2_lots(rng: np.random.Generator, m: int) -> Any:
    p = rng.normal(0, 5, (m, 2))
    return ([se2(rng, m), p, rng.normal(0, 5, (m, 2)), p + 1], rng.normal(size=(m, 6)), None,
            None, _t("EdgeSE2LotsOfXY").of(3))


@sample("EdgeSE3LotsOfXYZ")
def _se3_lots(rng: np.random.Generator, m: int) -> Any:
    p = rng.normal(0, 5, (m, 3))
    return ([se3_compact(rng, m), p, rng.normal(0, 5, (m, 3)), 2 * p],
            rng.normal(size=(m, 9)), None, None, _t("EdgeSE3LotsOfXYZ").of(3))


@sample("EdgeSE2Offset")
def _se2_offset(rng: np.random.Generator, m: int) -> Sample:
    P = _t("ParameterSE2Offset")
    return ([se2(rng, m), se2(rng, m)], 0.1 * se2(rng, m),
            (P([0.3, -0.2, 0.4]), P([-1.0, 0.5, -2.0])), None)


@sample("EdgeSE2PointXYOffset")
def _se2_point_offset(rng: np.random.Generator, m: int) -> Sample:
    return ([se2(rng, m), rng.normal(0, 5, (m, 2))], rng.normal(size=(m, 2)),
            _t("ParameterSE2Offset")([0.3, -0.2, 0.4]), None)


@sample("EdgeSE3Offset")
def _se3_offset(rng: np.random.Generator, m: int) -> Sample:
    P = _t("ParameterSE3Offset")
    return ([se3_compact(rng, m), se3_compact(rng, m)], se3_compact(rng, m),
            (P(se3_compact(rng, 1)[0]), P(se3_compact(rng, 1)[0])), None)


def _se3_camera(rng: np.random.Generator, m: int) -> Sample:
    cam = _t("ParameterCamera")(se3_compact(rng, 1)[0], fx=500, fy=510, cx=320, cy=240)
    X = se3_compact(rng, m)
    # points in front of the sensor (pose X, offset) so that depths are positive
    Rs = np.einsum("mij,jk->mik", X[:, :, :3], cam.offset[:, :3])
    ts = np.einsum("mij,j->mi", X[:, :, :3], cam.offset[:, 3]) + X[:, :, 3]
    return [X, front(rng, Rs, ts)], rng.normal(size=(m, 3)), cam, None


SAMPLES["EdgeSE3PointXYZDepth"] = _se3_camera
SAMPLES["EdgeSE3PointXYZDisparity"] = _se3_camera


def _sba_projection(dim: int) -> Callable[[np.random.Generator, int], Sample]:
    def fn(rng: np.random.Generator, m: int) -> Sample:
        from graphopt.lie import quat_to_rot

        c = sba_cams(rng, m)
        return [c, front(rng, quat_to_rot(c[:, 3:7]), c[:, :3])], \
            rng.normal(0, 100, (m, dim)), None, None
    return fn


SAMPLES["EdgeProjectP2MC"] = _sba_projection(2)
SAMPLES["EdgeProjectP2SC"] = _sba_projection(3)
SAMPLES["EdgeSBACam"] = _plain(lambda r, m: ([sba_cams(r, m), sba_cams(r, m)], np.c_[
    r.normal(size=(m, 3)), unit_quaternions(r, m)]))
SAMPLES["EdgeSBAScale"] = _plain(lambda r, m: ([sba_cams(r, m), sba_cams(r, m)],
                                              r.uniform(1, 3, (m, 1))))


def _expmap_front(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    from graphopt.lie import transform_inverse

    T = se3_exp(rng.normal(0, 0.3, (m, 6)))
    Tinv = transform_inverse(T)
    return T, front(rng, Tinv[:, :3, :3], Tinv[:, :3, 3])


@sample("EdgeProjectXYZ2UVU")
def _xyz2uvu(rng: np.random.Generator, m: int) -> Sample:
    T, pw = _expmap_front(rng, m)
    return [T, pw], rng.normal(size=(m, 3)), \
        _t("SBACameraParameters").from_g2o(500, (320, 240), 0.1), None


@sample("EdgeProjectPSI2UV")
def _psi2uv(rng: np.random.Generator, m: int) -> Sample:
    T, _ = _expmap_front(rng, m)
    psi = np.c_[rng.normal(0, 0.3, (m, 2)), rng.uniform(0.1, 0.5, m)]
    return [T, T[::-1].copy(), psi], rng.normal(size=(m, 2)), \
        _t("SBACameraParameters").from_g2o(500, (320, 240), 0.1), None


@sample("EdgeVVGicpPlaneToPlane")
def _gicp_plane(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types.icp import gicp_covariance

    n = rng.normal(size=(m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    data = {"cov0": gicp_covariance(n, 0.01), "cov1": gicp_covariance(n[::-1], 0.01)}
    return [se3_compact(rng, m), se3_compact(rng, m)], rng.normal(size=(m, 2, 3)), None, data


@sample("EdgeXyzVsc")
def _xyz_vsc(rng: np.random.Generator, m: int) -> Sample:
    X = se3_compact(rng, m)
    return [X, front(rng, X[:, :, :3], X[:, :, 3])], rng.normal(size=(m, 3)), \
        _t("SCamParameters")(500, 510, 320, 240, 0.1), None

def _stereo_cam() -> Any:
    from graphopt.types import StereoCameraParameters

    return StereoCameraParameters(500, 510, 320, 240, 40)


@sample("EdgeSE3ProjectXYZOnlyPose")
def _only_pose(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import CameraParameters

    T = pose(rng, m)
    return [T], rng.normal(300, 50, (m, 2)), CameraParameters(500, 510, 320, 240), \
        {"Xw": in_front(rng, T)}


@sample("EdgeStereoSE3ProjectXYZOnlyPose")
def _stereo_only_pose(rng: np.random.Generator, m: int) -> Sample:
    T = pose(rng, m)
    return [T], rng.normal(300, 50, (m, 3)), _stereo_cam(), {"Xw": in_front(rng, T)}


@sample("EdgeStereoSE3ProjectXYZ")
def _stereo(rng: np.random.Generator, m: int) -> Sample:
    T = pose(rng, m)
    return [T, in_front(rng, T)], rng.normal(300, 50, (m, 3)), _stereo_cam(), None


@sample("EdgeSE3Expmap")
def _se3_expmap(rng: np.random.Generator, m: int) -> Sample:
    return [pose(rng, m), pose(rng, m)], pose(rng, m), None, None


def _sim3(rng: np.random.Generator, m: int) -> np.ndarray:
    from graphopt.types.sim3_lie import sim3_exp

    return sim3_exp(np.c_[rng.normal(0.0, 0.3, (m, 6)), rng.normal(0.0, 0.3, m)])


@sample("EdgeSim3")
def _edge_sim3(rng: np.random.Generator, m: int) -> Sample:
    return [_sim3(rng, m), _sim3(rng, m)], _sim3(rng, m), None, None


def _sim3_projection(rng: np.random.Generator, m: int) -> Sample:
    from graphopt.types import CameraParameters

    S = _sim3(rng, m) * np.array([1.0, 1.0, 1.0, 0.0])[None, None, :]   # near the identity
    S[:, :3, 3] *= 0.1
    S[:, 3, 3] = 1.0
    X = np.c_[rng.normal(0, 0.5, (m, 2)), rng.uniform(4, 8, m)]
    return [X, S], rng.normal(300, 50, (m, 2)), CameraParameters(500, 510, 320, 240), None


SAMPLES["EdgeSim3ProjectXYZ"] = _sim3_projection
SAMPLES["EdgeInverseSim3ProjectXYZ"] = _sim3_projection


#: Types whose analytic Jacobians are not the exact derivative of their error, by design: the
#: test compares automatic differentiation with central differences instead.
APPROXIMATE = {
    "EdgeVVGicpPlaneToPlane": "g2o's Jacobians hold the whitener (cov0 + R cov1 Rᵀ)^-1/2 "
                              "constant, though R depends on the poses",
}

#: Types whose error does not run on jets yet, with the reason (the test expects them to fail
#: and reports it when one starts to pass).
PENDING: dict[str, str] = {}
