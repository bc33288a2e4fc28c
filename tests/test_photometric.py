"""Photometric patch edges: analytic vs numeric Jacobians, sampling order, inactive edges."""

from __future__ import annotations

import numpy as np
import pytest

from graphopt.edge import EdgeContext
from graphopt.lie import se3_exp
from graphopt.numeric import numeric_jacobians
from graphopt.types.image_sampling import central_gradients
from graphopt.types.photometric import (
    EdgePhotometricPatch,
    EdgePhotometricPatchInverseDepth,
    EdgePhotometricPatchInverseDepthHost,
    PhotometricParams,
    numeric_variant,
    photometric_edge_types,
)

H, W = 120, 160
CAM = (100.0, 110.0, 80.0, 60.0)


def smooth_images(n: int = 3) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    return np.stack(
        [100 + 50 * np.sin(xx / 7 + k) * np.cos(yy / 9 - k) + 0.02 * xx * yy for k in range(n)]
    )


def bilinear_images(n: int = 3) -> np.ndarray:
    """``a x + b y + c xy``: bilinear interpolation and central differences are both exact."""
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    return np.stack([20 + (1.5 + k) * xx + (0.7 - 0.2 * k) * yy + 0.01 * xx * yy for k in range(n)])


def problem(patch: int, m: int = 60, seed: int = 0):
    rng = np.random.default_rng(seed)
    Tj = se3_exp(rng.normal(size=(m, 6)) * 0.05)
    Ta = se3_exp(rng.normal(size=(m, 6)) * 0.05)
    p = np.c_[rng.normal(size=(m, 2)) * 0.5, 3 + rng.random(m)]
    q = np.c_[rng.normal(size=(m, 2)) * 0.3, 1 / (3 + rng.random(m))]
    img = rng.integers(0, 3, m)
    meas = rng.random((m, patch * patch)) * 200
    return Tj, Ta, p, q, img, meas


def full(cls, x, meas, ctx):
    """Error, the full ``(m, P², d)`` Jacobians (``linearize`` hands over the reduced ones) and
    the activity mask."""
    e, g, factors, active = cls.linearize_factored(x, meas, ctx)
    return e, tuple(np.matmul(g, f) for f in factors), active


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def check_all(prm: PhotometricParams, tol: float, seed: int = 0) -> None:
    E, EI, EH = photometric_edge_types(prm.patch)
    Tj, Ta, p, q, img, meas = problem(prm.patch, seed=seed)
    for cls, x in ((E, (Tj, p)), (EI, (Ta, Tj, q)), (EH, (Ta, q))):
        ctx = EdgeContext(prm, {"image": img})
        e, jac, active = full(cls, x, meas, ctx)
        assert active.sum() > 0.6 * len(img)
        assert e.shape == (len(img), prm.patch**2)
        np.testing.assert_array_equal(e, cls.error(x, meas, ctx))
        np.testing.assert_array_equal(active, cls.evaluate(x, meas, ctx).active)
        num = numeric_jacobians(cls, x, meas, ctx)
        for a, b in zip(jac, num, strict=True):
            assert a.shape == b.shape
            assert rel_err(a, b) < tol, (cls.__name__, rel_err(a, b))


@pytest.mark.parametrize("patch", [2, 4, 6, 8])
def test_jacobians_exact_interpolant(patch: int) -> None:
    """With the interpolant's own gradient the analytic Jacobians match to rounding."""
    prm = PhotometricParams(smooth_images(), *CAM, patch=patch, gradient="interpolated",
                            dtype="float64")
    check_all(prm, 1e-6)


@pytest.mark.parametrize("patch", [2, 4, 8])
def test_jacobians_central_on_bilinear_scene(patch: int) -> None:
    """Central-difference gradients are exact on an ``a x + b y + c xy`` image."""
    prm = PhotometricParams(bilinear_images(), *CAM, patch=patch, dtype="float64")
    check_all(prm, 1e-6, seed=1)


def test_jacobians_central_smooth_image_close() -> None:
    """On a smooth image central differences approximate the true gradient to a few percent."""
    prm = PhotometricParams(smooth_images(), *CAM, patch=4, dtype="float64")
    check_all(prm, 0.08, seed=2)


def test_float32_images_match_float64() -> None:
    Tj, _, p, _, img, meas = problem(4)
    out = []
    for dt in ("float32", "float64"):
        prm = PhotometricParams(smooth_images(), *CAM, dtype=dt)
        ctx = EdgeContext(prm, {"image": img})
        out.append(full(EdgePhotometricPatch, (Tj, p), meas, ctx))
    assert rel_err(out[0][0], out[1][0]) < 1e-5
    for a, b in zip(out[0][1], out[1][1], strict=True):
        assert a.dtype == np.float64
        assert rel_err(a, b) < 1e-4


def test_sampling_order_and_central_gradient_images() -> None:
    """Patch order k = P(dx+P/2) + (dy+P/2); gradients equal interpolated np.gradient images."""
    imgs = smooth_images(1)
    prm = PhotometricParams(imgs, *CAM, patch=4, dtype="float64")
    # A camera-frame point that projects to (u, v) = (50.25, 40.5).
    u, v = 50.25, 40.5
    z = 2.0
    pt = np.array([[(u - CAM[2]) / CAM[0] * z, (v - CAM[3]) / CAM[1] * z, z]])
    T = np.eye(4)[None]
    ctx = EdgeContext(prm, {"image": np.array([0])})
    e, (jp, _), _ = full(EdgePhotometricPatch, (T, pt), np.zeros((1, 16)), ctx)

    def bil(img: np.ndarray, x: float, y: float) -> float:
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        a, b = x - x0, y - y0
        return ((1 - a) * (1 - b) * img[y0, x0] + a * (1 - b) * img[y0, x0 + 1]
                + (1 - a) * b * img[y0 + 1, x0] + a * b * img[y0 + 1, x0 + 1])

    gx, gy = central_gradients(imgs[0])
    for dx in range(-2, 2):
        for dy in range(-2, 2):
            k = 4 * (dx + 2) + (dy + 2)
            assert -e[0, k] == pytest.approx(bil(imgs[0], u + dx, v + dy), rel=1e-12)
    # The translation-x column of the pose Jacobian is −g_u fx/z.
    expect = np.array([-bil(gx, u + dx, v + dy) * CAM[0] / z
                       for dx in range(-2, 2) for dy in range(-2, 2)])
    np.testing.assert_allclose(jp[0, :, 3], expect, rtol=1e-10)
    expect_v = np.array([-bil(gy, u + dx, v + dy) * CAM[1] / z
                         for dx in range(-2, 2) for dy in range(-2, 2)])
    np.testing.assert_allclose(jp[0, :, 4], expect_v, rtol=1e-10)


def test_inactive_edges_zero_and_finite() -> None:
    """Outside the margin, behind the camera, at the camera centre or ρ ≤ 0: zero, no NaN."""
    prm = PhotometricParams(smooth_images(1), *CAM)
    fx, fy, cx, cy = CAM
    z = 2.0

    def at(u: float, v: float, depth: float = z) -> list[float]:
        return [(u - cx) / fx * depth, (v - cy) / fy * depth, depth]

    pts = np.array([
        at(4.0, 4.0),            # exactly on the margin: active
        at(W - 4.0, H - 4.0),    # the other corner of the margin: active
        at(3.99, 50.0),          # just outside (left)
        at(50.0, H - 3.99),      # just outside (bottom)
        [0.1, 0.1, -2.0],        # behind the camera
        [0.0, 0.0, 0.0],         # at the centre
        at(1e9, 50.0),           # far outside
        [1e300, 1e300, 1e-300],  # overflowing projection
        [np.nan, 0.0, 2.0],      # non-finite estimate
    ])
    m = len(pts)
    T = np.repeat(np.eye(4)[None], m, axis=0)
    ctx = EdgeContext(prm, {"image": np.zeros(m, dtype=int)})
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        e, (jp, jx), active = full(EdgePhotometricPatch, (T, pts), np.full((m, 16), 7.0), ctx)
    np.testing.assert_array_equal(active, [True, True] + [False] * (m - 2))
    for arr in (e, jp, jx):
        assert np.isfinite(arr).all()
        assert not arr[2:].any()
    assert np.abs(jp[:2]).sum() > 0

    # Inverse depth: ρ ≤ 0 is inactive; the host edge too.
    q = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [10.0, 0.0, 0.5]])
    Ts = np.repeat(np.eye(4)[None], 4, axis=0)
    img = np.zeros(4, dtype=int)
    for cls, x in ((EdgePhotometricPatchInverseDepth, (Ts, Ts, q)),
                   (EdgePhotometricPatchInverseDepthHost, (Ts, q))):
        ctx = EdgeContext(prm, {"image": img})
        with np.errstate(all="raise"):
            e, jac, active = full(cls, x, np.zeros((4, 16)), ctx)
        np.testing.assert_array_equal(active, [True, False, False, False])
        for arr in (e, *jac):
            assert np.isfinite(arr).all() and not arr[1:].any()


def test_inverse_depth_matches_xyz() -> None:
    """The same geometry in both parametrisations gives the same errors."""
    prm = PhotometricParams(smooth_images(), *CAM, dtype="float64")
    Tj, Ta, _, q, img, meas = problem(4)
    pa = np.c_[q[:, :2], np.ones(len(q))] / q[:, 2:3]
    Twa = np.linalg.inv(Ta)
    pw = np.einsum("mij,mj->mi", Twa[:, :3, :3], pa) + Twa[:, :3, 3]
    ctx = EdgeContext(prm, {"image": img})
    e1, _, _, a1 = EdgePhotometricPatch.evaluate((Tj, pw), meas, ctx)
    e2, _, _, a2 = EdgePhotometricPatchInverseDepth.evaluate((Ta, Tj, q), meas, ctx)
    np.testing.assert_array_equal(a1, a2)
    assert a1.sum() > 0.6 * len(img)
    np.testing.assert_allclose(e1, e2, atol=1e-8)


def test_types_and_params_validation() -> None:
    E6 = photometric_edge_types(6)[0]
    assert E6.dimension == 36 and E6.patch == 6 and photometric_edge_types(6)[0] is E6
    assert photometric_edge_types(4)[0] is EdgePhotometricPatch
    with pytest.raises(ValueError):
        photometric_edge_types(3)
    with pytest.raises(ValueError):
        PhotometricParams(smooth_images(1), *CAM, patch=5)
    with pytest.raises(ValueError):
        PhotometricParams(smooth_images(1), *CAM, patch=8, margin=4)
    assert PhotometricParams(smooth_images(1), *CAM, patch=8).margin == 6
    assert PhotometricParams(smooth_images(1), *CAM).margin == 4
    prm = PhotometricParams(smooth_images(1), *CAM, patch=6)
    with pytest.raises(ValueError, match="4x4"):
        EdgePhotometricPatch.error((np.eye(4)[None], np.ones((1, 3))), np.zeros((1, 16)),
                                   EdgeContext(prm, {"image": np.zeros(1, int)}))
    num = numeric_variant(EdgePhotometricPatch)
    assert not num.has_analytic_jacobians() and EdgePhotometricPatch.has_analytic_jacobians()


def test_factored_jacobians() -> None:
    """``J_i = G @ F_i`` and ``J_iᵀ J_j = F_iᵀ (GᵀG) F_j`` for all three edge types."""
    prm = PhotometricParams(smooth_images(), *CAM, dtype="float64")
    Tj, Ta, p, q, img, meas = problem(4)
    for cls, x in ((EdgePhotometricPatch, (Tj, p)),
                   (EdgePhotometricPatchInverseDepth, (Ta, Tj, q)),
                   (EdgePhotometricPatchInverseDepthHost, (Ta, q))):
        ctx = EdgeContext(prm, {"image": img})
        e, jac, _ = full(cls, x, meas, ctx)
        e2, G, factors, _ = cls.linearize_factored(x, meas, ctx)
        np.testing.assert_array_equal(e, e2)
        assert G.shape == (len(img), 16, 2) and len(factors) == len(jac)
        for J, F in zip(jac, factors, strict=True):
            np.testing.assert_allclose(np.matmul(G, F), J, rtol=1e-12, atol=1e-12)
        GtG = np.matmul(np.swapaxes(G, 1, 2), G)
        JtJ = np.matmul(np.swapaxes(jac[-1], 1, 2), jac[0])
        FtF = np.swapaxes(factors[-1], 1, 2) @ GtG @ factors[0]
        np.testing.assert_allclose(FtF, JtJ, rtol=1e-9, atol=1e-9 * np.abs(JtJ).max())


def test_reduced_linearisation_preserves_normal_equations() -> None:
    """``linearize`` returns 2-row Jacobians with the full ``JᵀJ`` and ``Jᵀe``."""
    prm = PhotometricParams(smooth_images(), *CAM, dtype="float64")
    Tj, Ta, p, q, img, meas = problem(4)
    for cls, x in ((EdgePhotometricPatch, (Tj, p)),
                   (EdgePhotometricPatchInverseDepth, (Ta, Tj, q)),
                   (EdgePhotometricPatchInverseDepthHost, (Ta, q))):
        assert cls.linearization_rows == 2
        e, jac, active = full(cls, x, meas, EdgeContext(prm, {"image": img}))
        e2, red, e_lin, active2 = cls.linearize(x, meas, EdgeContext(prm, {"image": img}))
        np.testing.assert_array_equal(active, active2)
        np.testing.assert_array_equal(e, e2)
        assert e_lin.shape == (len(img), 2)
        for a in range(len(jac)):
            gj = np.einsum("mni,mn->mi", jac[a], e)
            gr = np.einsum("mki,mk->mi", red[a], e_lin)
            np.testing.assert_allclose(gr, gj, rtol=1e-9, atol=1e-9 * np.abs(gj).max())
            for b in range(len(jac)):
                hj = np.swapaxes(jac[a], 1, 2) @ jac[b]
                hr = np.swapaxes(red[a], 1, 2) @ red[b]
                np.testing.assert_allclose(hr, hj, rtol=1e-9, atol=1e-9 * np.abs(hj).max())


@pytest.mark.parametrize("gradient", ["central", "interpolated"])
def test_project_and_sample_on_a_linear_image(gradient: str) -> None:
    """Bilinear sampling reproduces a linear image exactly, gradients included."""
    from graphopt.types.image_sampling import project_points, safe_points, sample_patches

    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    images = np.stack([2.0 * xx - 0.5 * yy + 7.0, -1.0 * xx + 3.0 * yy])
    prm = PhotometricParams(images, *CAM, patch=4, gradient=gradient, dtype="float64")
    fx, fy, cx, cy = CAM
    pc = np.array([[0.1, -0.05, 2.0],    # inside
                   [0.0, 0.0, -1.0],     # behind the camera
                   [10.0, 0.0, 1.0],     # far outside the image
                   [0.2, 0.1, 1.5]])     # inside
    u, v, iz, ok = project_points(pc, prm)
    assert ok.tolist() == [True, False, False, True]
    np.testing.assert_allclose(u[ok], fx * pc[ok, 0] / pc[ok, 2] + cx, rtol=1e-14)
    np.testing.assert_allclose(v[ok], fy * pc[ok, 1] / pc[ok, 2] + cy, rtol=1e-14)
    np.testing.assert_allclose(iz, [0.5, 0.0, 0.0, 1 / 1.5], rtol=1e-14)
    assert (u[~ok] == prm.margin).all() and (v[~ok] == prm.margin).all()  # safe pixel
    np.testing.assert_array_equal(safe_points(pc, ok)[~ok], [[0, 0, 1.0], [0, 0, 1.0]])
    image = np.array([0, 0, 1, 1])
    val, gu, gv = sample_patches(u, v, image, prm, grad=True)
    d = np.arange(-2, 2)
    dx, dy = np.repeat(d, 4), np.tile(d, 4)  # k = P (dx + P/2) + (dy + P/2)
    for e in np.flatnonzero(ok):
        a, b, c = (2.0, -0.5, 7.0) if image[e] == 0 else (-1.0, 3.0, 0.0)
        np.testing.assert_allclose(val[:, e], a * (u[e] + dx) + b * (v[e] + dy) + c, rtol=1e-12)
        np.testing.assert_allclose(gu[:, e], a, rtol=1e-12)
        np.testing.assert_allclose(gv[:, e], b, rtol=1e-12)
    only, none_u, none_v = sample_patches(u, v, image, prm, grad=False)
    assert none_u is None and none_v is None
    np.testing.assert_array_equal(only, val)


@pytest.mark.parametrize("gradient", ["central", "interpolated"])
def test_patch_residuals_blocks_match_sample_patches(gradient: str, monkeypatch) -> None:
    """The block-wise errors and Gauss–Newton terms equal those from :func:`sample_patches`,
    whatever the block size (here 7 edges: several blocks and a partial last one)."""
    from graphopt.types import image_sampling
    from graphopt.types.image_sampling import patch_residuals, project_points, sample_patches

    prm = PhotometricParams(smooth_images(), *CAM, gradient=gradient)
    Tj, _, p, _, img, meas = problem(4, m=40)
    pc = np.einsum("mij,mj->mi", Tj[:, :3, :3], p) + Tj[:, :3, 3]
    u, v, _, ok = project_points(pc, prm)
    assert ok.sum() > 20
    val, gu, gv = sample_patches(u, v, img, prm, grad=True)
    e = meas - val.T
    want = [np.einsum("km,km->m", a, b) for a, b in ((gu, gu), (gu, gv), (gv, gv))]
    want += [np.einsum("km,mk->m", gu, e), np.einsum("km,mk->m", gv, e)]
    monkeypatch.setattr(image_sampling, "CHUNK", 7)
    for grad in (True, False):
        e2, terms = patch_residuals(u, v, img, meas, prm, grad)
        np.testing.assert_array_equal(e2, e)
        if grad:
            np.testing.assert_allclose(terms, np.array(want), rtol=1e-12, atol=1e-9)
        else:
            assert terms is None
