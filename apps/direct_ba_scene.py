"""A synthetic textured room for direct bundle adjustment, with ground truth.

:func:`synthetic_scene` renders the room from known poses (:func:`render`, a ray cast onto four
textured planes), samples points with patches on high-gradient pixels of the first frame and
perturbs poses and points deterministically. ``graphopt-direct-ba`` uses it without DATA_DIR.
"""

from __future__ import annotations

import numpy as np

from graphopt.io.directba import DEFAULT_INTRINSICS, DirectBAData
from graphopt.lie import make_transform, se3_exp, transform_inverse

__all__ = ["render", "synthetic_scene"]


def _texture(rng: np.random.Generator, size: int = 800, cells: int = 36) -> np.ndarray:
    """A smooth random texture in [20, 235]: upsampled value noise plus a little detail."""
    import cv2

    coarse = rng.random((cells, cells)).astype(np.float32)
    big = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)
    fine = cv2.resize(rng.random((cells * 3, cells * 3)).astype(np.float32), (size, size),
                      interpolation=cv2.INTER_CUBIC)
    tex = cv2.GaussianBlur(0.75 * big + 0.25 * fine, (0, 0), size / cells / 4)
    tex = (tex - tex.min()) / max(float(np.ptp(tex)), 1e-9)
    return 20.0 + 215.0 * tex.astype(np.float64)


def _bilinear(tex: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Sample a texture at continuous (s, t) texel coordinates (clamped at the border)."""
    h, w = tex.shape
    s = np.clip(s, 0.0, w - 1.0)
    t = np.clip(t, 0.0, h - 1.0)
    s0 = np.minimum(np.floor(s), w - 2)
    t0 = np.minimum(np.floor(t), h - 2)
    a, b = s - s0, t - t0
    i0 = s0.astype(np.int64)
    j0 = t0.astype(np.int64)
    i1, j1 = i0 + 1, j0 + 1
    return ((1 - a) * (1 - b) * tex[j0, i0] + a * (1 - b) * tex[j0, i1]
            + (1 - a) * b * tex[j1, i0] + a * b * tex[j1, i1])


#: Scene planes ``n·X = d`` (world frame, y down, cameras looking along +z) with the in-plane axes
#: used for texture coordinates.
_PLANES = (
    (np.array([0.0, 0.0, 1.0]), 6.0, 0, 1),  # back wall z = 6
    (np.array([0.0, 1.0, 0.0]), 1.5, 0, 2),  # floor y = 1.5
    (np.array([1.0, 0.0, 0.0]), -3.5, 2, 1),  # left wall x = -3.5
    (np.array([1.0, 0.0, 0.0]), 3.5, 2, 1),  # right wall x = 3.5
)


#: Texture coordinates are centred here so that one texture spans a whole wall.
_ROOM_CENTRE = np.array([0.0, 0.0, 3.0])


def render(
    pose: np.ndarray,
    intrinsics: tuple[float, float, float, float],
    size: tuple[int, int],
    textures: list[np.ndarray],
    texel: float = 0.015,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the synthetic room from one pose.

    Args:
        pose: ``(4, 4)`` ``T_cw``.
        intrinsics: ``(fx, fy, cx, cy)``.
        size: ``(width, height)``.
        textures: One texture per plane of the room.
        texel: Metres per texel; a texture covers the room without repeating (no seams).

    Returns:
        ``(image, depth)``, both ``(H, W)`` float64 (depth = camera z of the hit).
    """
    fx, fy, cx, cy = intrinsics
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays_c = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    Twc = transform_inverse(pose[None])[0]
    origin = Twc[:3, 3]
    rays_w = rays_c @ Twc[:3, :3].T
    best = np.full(len(rays_w), np.inf)
    image = np.zeros(len(rays_w))
    for (normal, d, ax_s, ax_t), tex in zip(_PLANES, textures, strict=True):
        denom = rays_w @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (d - origin @ normal) / denom
        hit = (lam > 0) & (lam < best)
        pts = origin + lam[hit, None] * rays_w[hit]
        st = (pts - _ROOM_CENTRE) / texel + 0.5 * (len(tex) - 1)  # textures are square
        image[hit] = _bilinear(tex, st[:, ax_s], st[:, ax_t])
        best[hit] = lam[hit]
    # rays_c has z = 1, so the ray parameter is the camera depth.
    return image.reshape(h, w), best.reshape(h, w)


def synthetic_scene(
    n_frames: int = 5,
    n_points: int = 1500,
    size: tuple[int, int] = (640, 480),
    intrinsics: tuple[float, float, float, float] = DEFAULT_INTRINSICS,
    patch: int = 4,
    rot_noise_deg: float = 1.0,
    trans_noise: float = 0.03,
    point_noise: float = 0.02,
    seed: int = 0,
    image_noise: float = 0.0,
    outlier_fraction: float = 0.0,
) -> DirectBAData:
    """A textured room seen by a camera moving sideways, with perturbed initial values.

    Points are sampled on high-gradient pixels of the first frame (integer pixel positions, a
    minimum spacing), back-projected with the true depth; their patches are the first image's
    intensities around the pixel. Initial poses (all but the first, which fixes the gauge) are
    perturbed by a random rotation of ``rot_noise_deg`` degrees and a translation of
    ``trans_noise`` metres (fixed magnitudes, random directions); points by isotropic Gaussian
    noise of ``point_noise`` metres per axis.

    Args:
        n_frames: Number of cameras.
        n_points: Maximum number of points.
        size: Image ``(width, height)``.
        intrinsics: ``(fx, fy, cx, cy)``.
        patch: Patch side.
        rot_noise_deg: Rotation perturbation per pose (degrees).
        trans_noise: Translation perturbation per pose (metres).
        point_noise: Standard deviation of the point perturbation per axis (metres).
        seed: Seed of everything random (texture, sampling, perturbation).
        image_noise: Standard deviation of Gaussian noise added to every rendered image
            (intensity units), after the reference patches are taken from the clean first image.
        outlier_fraction: Fraction of points whose reference patch is replaced by the patch of
            another, random point (gross photometric outliers).

    Returns:
        The problem, with ``true_poses``/``true_points`` and ``hosts`` (all 0).
    """
    rng = np.random.default_rng(seed)
    textures = [_texture(rng) for _ in _PLANES]
    # Camera centres on a gentle arc, looking roughly along +z, slightly yawing.
    true = []
    for i in range(n_frames):
        s = i / max(n_frames - 1, 1) - 0.5
        centre = np.array([1.2 * s, -0.05 * s, 0.4 * s * s])
        yaw = np.deg2rad(-6.0 * s)
        Rwc = se3_exp(np.array([[0.0, yaw, 0.0, 0, 0, 0]]))[0, :3, :3]
        Twc = make_transform(Rwc[None], centre[None])
        true.append(transform_inverse(Twc)[0])
    true_poses = np.stack(true)
    rendered = [render(T, intrinsics, size, textures) for T in true_poses]
    images = np.stack([r[0] for r in rendered])
    depth0 = rendered[0][1]

    # Candidate pixels: strong central-difference gradient, away from the border, thinned by a
    # grid so that patches do not all pile up on one edge.
    gy, gx = np.gradient(images[0])
    mag = np.hypot(gx, gy)
    w, h = size
    border = max(8, patch)
    cell = 6
    cand_u, cand_v = [], []
    for v0 in range(border, h - border - cell, cell):
        for u0 in range(border, w - border - cell, cell):
            blk = mag[v0 : v0 + cell, u0 : u0 + cell]
            j = int(np.argmax(blk))
            if blk.flat[j] > 2.0:
                cand_v.append(v0 + j // cell)
                cand_u.append(u0 + j % cell)
    cu, cv = np.array(cand_u), np.array(cand_v)
    if len(cu) > n_points:
        pick = np.sort(rng.choice(len(cu), n_points, replace=False))
        cu, cv = cu[pick], cv[pick]
    fx, fy, cx, cy = intrinsics
    z = depth0[cv, cu]
    pc = np.stack([(cu - cx) / fx * z, (cv - cy) / fy * z, z], axis=1)
    Twc0 = transform_inverse(true_poses[:1])[0]
    true_points = pc @ Twc0[:3, :3].T + Twc0[:3, 3]
    half = patch // 2
    d = np.arange(-half, half)
    # k = P (dx + P/2) + (dy + P/2): dx (column) outer, dy (row) inner.
    patches = images[0][cv[:, None, None] + d[None, None, :], cu[:, None, None] + d[None, :, None]]
    patches = patches.reshape(len(cu), patch * patch)
    # A separate stream, so that noise and outliers leave the perturbation of a seed unchanged.
    rng_noise = np.random.default_rng([seed, 1])
    n_out = int(round(outlier_fraction * len(cu)))
    outliers = (np.sort(rng_noise.choice(len(cu), n_out, replace=False)) if n_out
                else np.zeros(0, dtype=np.int64))
    if n_out:
        patches[outliers] = patches[rng_noise.integers(0, len(cu), n_out)]
    if image_noise > 0:
        images = images + rng_noise.normal(scale=image_noise, size=images.shape)

    # Deterministic perturbation: fixed magnitudes, random directions.
    def unit(n: int) -> np.ndarray:
        x = rng.normal(size=(n, 3))
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    xi = np.zeros((n_frames, 6))
    xi[1:, :3] = unit(n_frames - 1) * np.deg2rad(rot_noise_deg)
    xi[1:, 3:] = unit(n_frames - 1) * trans_noise
    poses = se3_exp(xi) @ true_poses
    points = true_points + rng.normal(scale=point_noise, size=true_points.shape)
    return DirectBAData(
        poses=poses,
        points=points,
        patches=patches,
        images=images,
        intrinsics=tuple(float(v) for v in intrinsics),  # type: ignore[arg-type]
        true_poses=true_poses,
        true_points=true_points,
        hosts=np.zeros(len(points), dtype=np.int64),
        source="synthetic",
        extra={"seed": seed, "rot_noise_deg": rot_noise_deg, "trans_noise": trans_noise,
               "point_noise": point_noise, "image_noise": image_noise, "outliers": outliers},
    )
