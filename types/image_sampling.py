"""Images and patch sampling for the photometric edges.

:class:`PhotometricParams` holds a group's images (stacked and flattened for one flat gather),
intrinsics and patch layout; :func:`project_points` maps camera-frame points to pixels with the
activity mask; :func:`sample_patches` interpolates every edge's ``P × P`` patch (and its image
gradients) bilinearly, and :func:`patch_residuals` turns the same samples into the errors and
the per-edge Gauss–Newton terms block by block. Because a patch's offsets are integers, all its
pixels share the fractional part of the projection: one ``(P+1) × (P+1)`` window and four
weights per edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "GRADIENTS",
    "CHUNK",
    "MIN_DEPTH",
    "PhotometricParams",
    "central_gradients",
    "patch_residuals",
    "project_points",
    "safe_points",
    "sample_patches",
]

#: Depths at or below this (in the camera frame) make an edge inactive (behind the camera).
MIN_DEPTH = 1e-6

#: Image gradient models of :attr:`PhotometricParams.gradient`.
GRADIENTS = ("central", "interpolated")

#: Edges per block of :func:`patch_residuals`: a block's temporaries (window slice,
#: interpolated grid, gradients, errors: ≈ 1 kB per edge) stay in a 2 MB L2 / the L3 cache.
CHUNK = 8192


def central_gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image gradients by central differences, ``(I(x+1) − I(x−1)) / 2``.

    The outermost rows/columns use one-sided differences; they are never sampled by an active
    edge anyway (the margin keeps projections at least 4 px inside).

    Args:
        image: ``(H, W)`` image.

    Returns:
        ``(gx, gy)``: derivatives along columns (u) and rows (v), each ``(H, W)``.
    """
    gy, gx = np.gradient(np.asarray(image, dtype=np.float64))
    return gx, gy


@dataclass
class PhotometricParams:
    """Images, intrinsics and patch layout shared by a group of photometric edges.

    Args:
        images: ``(n, H, W)`` greyscale images (any real dtype; stored flattened as ``dtype``).
        fx: Focal length along u, pixels.
        fy: Focal length along v, pixels.
        cx: Principal point u.
        cy: Principal point v.
        patch: Patch side ``P`` (even: 2, 4, 6, 8).
        margin: An edge is active only while ``margin <= u <= W − margin`` and likewise for v.
            ``None`` (default) uses the task's 4 px, widened to ``P/2 + 2`` for large patches so
            that the interpolation and gradient stencil never leave the image.
        gradient: ``"central"`` (precomputed central-difference gradient images, bilinearly
            interpolated — the task's choice) or ``"interpolated"`` (the exact derivative of the
            bilinear interpolant; what a numeric Jacobian sees).
        dtype: Floating type of the stored images and of the interpolation. ``"float32"``
            (default) halves the memory traffic of the gathers, which dominate the cost; the
            geometry (projection, Jacobians of the projection) is always float64, and errors and
            Jacobians are returned as float64. Use ``"float64"`` to compare against numeric
            Jacobians with tiny steps.
    """

    images: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    patch: int = 4
    margin: float | None = None
    gradient: str = "central"
    dtype: str = "float32"
    # Derived in __post_init__.
    height: int = field(init=False)
    width: int = field(init=False)
    flat: np.ndarray = field(init=False, repr=False)
    window: np.ndarray = field(init=False, repr=False)
    window_ext: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        imgs = np.asarray(self.images, dtype=np.float64)
        if imgs.ndim == 2:
            imgs = imgs[None]
        if imgs.ndim != 3:
            raise ValueError(f"images must be (n, H, W), got shape {imgs.shape}")
        if self.patch < 2 or self.patch % 2:
            raise ValueError(f"patch size must be even and >= 2, got {self.patch}")
        if self.gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {GRADIENTS}, got {self.gradient!r}")
        half = self.patch // 2
        # The central-difference sampler reads P/2 + 1 pixels left/up of floor(u) and P/2 + 1
        # right/down of it, so the projection must stay P/2 + 2 px inside (the task's 4 for P=4).
        need = half + 2
        if self.margin is None:
            self.margin = float(max(4, need))
        if self.margin < need:
            raise ValueError(
                f"margin {self.margin} too small for a {self.patch}x{self.patch} patch "
                f"(needs {need})"
            )
        self.images = imgs
        _, self.height, self.width = imgs.shape
        self.flat = np.ascontiguousarray(imgs.reshape(-1), dtype=np.dtype(self.dtype))
        # Window of (P+1)² pixels around floor(u, v), laid out [wx, wy] so that reshaping the
        # interpolated (P, P) block row-major gives k = P·(dx + P/2) + (dy + P/2).
        w = np.arange(-half, half + 1)
        self.window = (w[:, None] + w[None, :] * self.width).ravel().astype(np.int64)
        # One more pixel on every side, for central differences of the interpolated image.
        w = np.arange(-half - 1, half + 2)
        self.window_ext = (w[:, None] + w[None, :] * self.width).ravel().astype(np.int64)

    @property
    def dimension(self) -> int:
        """Error dimension ``P²``."""
        return self.patch * self.patch

    @property
    def camera(self) -> np.ndarray:
        """``[fx, fy, cx, cy]``."""
        return np.array([self.fx, self.fy, self.cx, self.cy])


def project_points(
    pc: np.ndarray, prm: PhotometricParams, extra_ok: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates, inverse depth and the activity mask of camera-frame points.

    Inactive projections are moved to a safe pixel so that later gathers stay in bounds and no
    NaN or inf is ever produced.

    Args:
        pc: ``(m, 3)`` points in their camera's frame.
        prm: Intrinsics, image size and margin.
        extra_ok: Optional ``(m,)`` mask of edges that are active for other reasons.

    Returns:
        ``(u, v, iz, ok)``, each ``(m,)``: pixel coordinates, ``1/z`` (0 where inactive) and
        the activity mask (in front by :data:`MIN_DEPTH`, inside the margin, ``extra_ok``).
    """
    z = pc[:, 2]
    ok = z > MIN_DEPTH
    if extra_ok is not None:
        ok &= extra_ok
    iz = 1.0 / np.where(ok, z, 1.0)
    mg = prm.margin
    # Far-off or non-finite projections may overflow; they fail the margin test below.
    with np.errstate(over="ignore", invalid="ignore"):
        u = prm.fx * pc[:, 0] * iz + prm.cx
        v = prm.fy * pc[:, 1] * iz + prm.cy
        ok &= (u >= mg) & (u <= prm.width - mg) & (v >= mg) & (v <= prm.height - mg)
    if not ok.all():
        u = np.where(ok, u, mg)
        v = np.where(ok, v, mg)
        iz = np.where(ok, iz, 0.0)
    return u, v, iz, ok


def safe_points(pc: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Replace the camera points of inactive edges by ``[0, 0, 1]`` (finite Jacobian inputs).

    Args:
        pc: ``(m, 3)`` camera-frame points.
        ok: ``(m,)`` activity mask.
    """
    if ok.all():
        return pc
    return np.where(ok[:, None], pc, np.array([0.0, 0.0, 1.0]))


def _gather(
    prm: PhotometricParams, base: np.ndarray, window: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """``flat[window[i] + base]`` as ``(len(window), m)``: one ``np.take`` per window offset.

    Each take reuses the same ``(m,)`` indices on a shifted view of the images, which is about
    twice as fast as one take with a ``(len(window), m)`` index array (no index array to build,
    and short cache-resident index rows). Indices stay inside the images (active edges by the
    margin, inactive ones at the safe pixel), so ``mode="wrap"`` never wraps; it only skips
    the buffered bounds check of ``mode="raise"``.
    """
    lo = int(window.min())
    start = base + lo
    if out is None:
        out = np.empty((len(window), len(base)), dtype=prm.flat.dtype)
    for i, off in enumerate((window - lo).tolist()):
        np.take(prm.flat[off:], start, out=out[i], mode="wrap")
    return out


def _corners(
    u: np.ndarray, v: np.ndarray, image: np.ndarray, prm: PhotometricParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat index of ``floor(u, v)`` ``(m,)``, the fractional parts ``(2, m)`` ``[a, b]`` and
    the bilinear weights ``(4, m)`` of the corners ``00, 10, 01, 11`` — one set per edge,
    since a patch's offsets are integers (both in the sampling dtype)."""
    u0 = np.floor(u)
    v0 = np.floor(v)
    base = (image.astype(np.int64) * prm.height + v0.astype(np.int64)) * prm.width
    base += u0.astype(np.int64)
    ab = np.empty((2, len(u)), dtype=prm.flat.dtype, like=u)  # like=: jets stay jets
    np.subtract(u, u0, out=ab[0], casting="same_kind")
    np.subtract(v, v0, out=ab[1], casting="same_kind")
    a, b = ab
    ia, ib = 1.0 - a, 1.0 - b
    return base, ab, np.stack([ia * ib, a * ib, ia * b, a * b])


def _window(prm: PhotometricParams, base: np.ndarray, ext: bool, out: np.ndarray | None = None
            ) -> np.ndarray:
    """Raw pixel windows ``(n, n, m)`` ``[wx, wy, edge]`` around ``base`` (``n = P + 3`` with
    ``ext``, for central differences, else ``P + 1``)."""
    n = prm.patch + 3 if ext else prm.patch + 1
    win = _gather(prm, base, prm.window_ext if ext else prm.window, out)
    return win.reshape(n, n, -1)


def _interpolate(win: np.ndarray, w: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
    """Bilinear samples of ``win`` ``(n, n, c)`` on the ``(n−1)²`` grid into ``out``
    (``tmp``: scratch of the same shape, so that no term allocates)."""
    k = win.shape[0] - 1
    np.multiply(w[0], win[:k, :k], out=out)
    out += np.multiply(w[1], win[1:, :k], out=tmp)
    out += np.multiply(w[2], win[:k, 1:], out=tmp)
    out += np.multiply(w[3], win[1:, 1:], out=tmp)


def _gradients(
    val: np.ndarray, win: np.ndarray, ab: np.ndarray, central: bool, out: np.ndarray
) -> None:
    """Image gradients ``[gu, gv]`` into the float64 ``out`` ``(2, P, P, c)``.

    Central: differences of the interpolated ``(P+2)²`` grid ``val`` — bilinear interpolation
    commutes with integer shifts, so this equals interpolating precomputed central-difference
    gradient images, with one gather instead of three. The differences are taken in the
    sampling dtype and halved exactly in float64. Otherwise: the exact derivative of the
    bilinear interpolant from the raw window ``win`` ``(P+1, P+1, c)``.
    """
    if central:
        f = val.dtype
        np.subtract(val[2:, 1:-1], val[:-2, 1:-1], out=out[0], dtype=f)
        np.subtract(val[1:-1, 2:], val[1:-1, :-2], out=out[1], dtype=f)
        out *= 0.5
        return
    a, b = ab
    k = win.shape[0] - 1
    c00, c10, c01, c11 = win[:k, :k], win[1:, :k], win[:k, 1:], win[1:, 1:]
    out[0] = (1.0 - b) * (c10 - c00) + b * (c11 - c01)
    out[1] = (1.0 - a) * (c01 - c00) + a * (c11 - c10)


def sample_patches(
    u: np.ndarray, v: np.ndarray, image: np.ndarray, prm: PhotometricParams, grad: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Bilinear patch samples (and gradients) for all edges, pixel-major.

    Arrays are laid out ``(P², m)`` (pixel first) so that every arithmetic operation runs over
    long contiguous rows; the caller transposes once at the end.

    With ``gradient="central"`` the image is interpolated on a ``(P+2)²`` grid (one pixel of
    extra border) and the gradients are central differences of that grid: bilinear
    interpolation commutes with integer shifts, so this equals bilinearly interpolating
    precomputed central-difference gradient images — with one gather instead of three.

    Args:
        u: ``(m,)`` pixel columns of the patch centres (inside the margin).
        v: ``(m,)`` pixel rows.
        image: ``(m,)`` image index of every edge.
        prm: Images and patch layout.
        grad: Also return the image gradients.

    Returns:
        ``(I, gu, gv)``, each ``(P², m)`` in k order (``I`` in the sampling dtype, the gradients
        float64); ``gu, gv`` are ``None`` unless asked.
    """
    p, m = prm.patch, len(u)
    ext = grad and prm.gradient == "central"
    base, ab, w = _corners(u, v, image, prm)
    win = _window(prm, base, ext)
    k = win.shape[0] - 1
    val = np.empty((k, k, m), dtype=win.dtype)
    _interpolate(win, w, val, np.empty_like(val))
    if not grad:
        return val.reshape(p * p, m), None, None
    g = np.empty((2, p, p, m))
    _gradients(val, win, ab, ext, g)
    patch = val[1:-1, 1:-1] if ext else val
    gu, gv = g.reshape(2, p * p, m)
    return patch.reshape(p * p, m), gu, gv


def _samples_generic(u: np.ndarray, v: np.ndarray, image: np.ndarray,
                     prm: PhotometricParams) -> np.ndarray:
    """Bilinear samples ``(P², m)`` in k order by plain array operations (no ``out=``
    buffers), for array-likes that are not ndarrays: jets (graphopt.autodiff) carry the
    derivative of the interpolant through the weights."""
    p = prm.patch
    base, _, w = _corners(u, v, image, prm)
    win = _window(prm, base, False)
    val = w[0] * win[:p, :p] + w[1] * win[1:, :p] + w[2] * win[:p, 1:] + w[3] * win[1:, 1:]
    return val.reshape(p * p, len(base))


def patch_residuals(
    u: np.ndarray, v: np.ndarray, image: np.ndarray, meas: np.ndarray, prm: PhotometricParams,
    grad: bool,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Patch errors ``C − I`` and, with ``grad``, the Gauss–Newton terms of every patch.

    The same samples as :func:`sample_patches`, consumed block by block of :data:`CHUNK` edges
    while they are in cache: interpolation, gradients and their products over ``P²`` pixels
    stream through several arrays of ``(P+2)² × m`` values, which from memory cost more than
    the arithmetic.

    Args:
        u: ``(m,)`` pixel columns of the patch centres (inside the margin).
        v: ``(m,)`` pixel rows.
        image: ``(m,)`` image index of every edge.
        meas: ``(m, P²)`` reference patches ``C``.
        prm: Images and patch layout.
        grad: Also return the Gauss–Newton terms.

    Returns:
        ``e (m, P²)`` (float64; inactive edges are not zeroed) and, with ``grad``, ``(5, m)``
        ``[Σ gu², Σ gu gv, Σ gv², Σ gu e, Σ gv e]`` over the pixels of each patch (else
        ``None``).
    """
    p, m = prm.patch, len(u)
    if type(u) is not np.ndarray and not grad:
        return meas - _samples_generic(u, v, image, prm).T, None
    ext = grad and prm.gradient == "central"
    base, ab, w = _corners(u, v, image, prm)
    n = p + 3 if ext else p + 1
    k = n - 1
    c = min(CHUNK, m)
    raw = np.empty((n * n, c), dtype=prm.flat.dtype)
    val = np.empty((k, k, c), dtype=prm.flat.dtype)
    tmp = np.empty_like(val)
    ep = np.empty((p, p, c))
    g = np.empty((2, p, p, c if grad else 0))
    e = np.empty((m, p * p))
    terms = np.empty((5, m)) if grad else None
    for lo in range(0, m, c):
        sl = slice(lo, min(lo + c, m))
        nb = sl.stop - lo
        vb, eb = val[..., :nb], ep[..., :nb]
        win = _window(prm, base[sl], ext, raw[:, :nb])
        _interpolate(win, w[:, sl], vb, tmp[..., :nb])
        patch = vb[1:-1, 1:-1] if ext else vb
        if terms is None:  # C − I straight into e
            np.subtract(meas[sl].reshape(nb, p, p), patch.transpose(2, 0, 1),
                        out=e[sl].reshape(nb, p, p))
            continue
        # C − I pixel-major for the products below (meas read column-wise: its block is cache
        # resident), then one transposed write of the block into e.
        np.subtract(meas[sl].T.reshape(p, p, nb), patch, out=eb)
        ef = eb.reshape(p * p, nb)
        e[sl] = ef.T
        gb = g[..., :nb]
        _gradients(vb, win, ab[:, sl], ext, gb)
        gu, gv = gb.reshape(2, p * p, nb)
        for i, (x, y) in enumerate(((gu, gu), (gu, gv), (gv, gv), (gu, ef), (gv, ef))):
            np.einsum("km,km->m", x, y, out=terms[i, sl])
    return e, terms
