"""Synthetic scenes with known truth for ORB-SLAM's four back-end procedures
(``benchmarks/bench_slam_backend.py``, ``docs/slam_backend.md``), generated deterministically
from a seed.

Cameras: 640×480 pixels, ``fx = fy = 500``, ``cx = 320``, ``cy = 240``, stereo ``bf = 40``
(a 8 cm baseline). Keypoints carry an ORB octave ``0…7``; a measurement's noise is
``σ = 1.2^octave`` pixels and its information ``I/σ²`` (ORB-SLAM's ``invSigma2``).
Outliers (10 %) are moved by 15–40 σ in a random direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphopt.lie import make_transform, se3_exp, so3_exp, transform_inverse, transform_points
from graphopt.types import CameraParameters, StereoCameraParameters

FX = FY = 500.0
CX, CY = 320.0, 240.0
BF = 40.0
WIDTH, HEIGHT = 640, 480
CAM = CameraParameters(FX, FY, CX, CY)
STEREO = StereoCameraParameters(FX, FY, CX, CY, BF)
OUTLIERS = 0.10


def _octaves(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    """``(σ (m,), invSigma2 (m,))`` of random ORB octaves."""
    sigma = 1.2 ** rng.integers(0, 8, m)
    return sigma, 1.0 / sigma**2


def _project(T: np.ndarray, X: np.ndarray, stereo: bool) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(m, 2|3)`` and depths of world points ``X`` seen from poses ``T`` ``(m, 4, 4)``."""
    P = transform_points(T, X)
    u = FX * P[:, 0] / P[:, 2] + CX
    v = FY * P[:, 1] / P[:, 2] + CY
    cols = [u, v, u - BF / P[:, 2]] if stereo else [u, v]
    return np.stack(cols, axis=1), P[:, 2]


def _observe(rng: np.random.Generator, clean: np.ndarray, sigma: np.ndarray,
             out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Noisy measurements and the outlier mask (10 % unless given, moved 15–40 σ)."""
    m, d = clean.shape
    z = clean + rng.normal(0.0, 1.0, (m, d)) * sigma[:, None]
    out = rng.random(m) < OUTLIERS if out is None else out
    k = int(out.sum())
    direction = rng.normal(size=(k, d))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    z[out] += direction * (rng.uniform(15.0, 40.0, k) * sigma[out])[:, None]
    return z, out


def _perturb(rng: np.random.Generator, T: np.ndarray, rot: float, trans: float) -> np.ndarray:
    xi = np.concatenate([rng.normal(0.0, rot, (len(T), 3)),
                         rng.normal(0.0, trans, (len(T), 3))], axis=1)
    return se3_exp(xi) @ T


def _backproject(rng: np.random.Generator, T: np.ndarray, m: int, zmin: float, zmax: float
                 ) -> np.ndarray:
    """``m`` world points seen inside the image of each pose ``T`` ``(m, 4, 4)``."""
    u = rng.uniform(10.0, WIDTH - 10.0, m)
    v = rng.uniform(10.0, HEIGHT - 10.0, m)
    z = rng.uniform(zmin, zmax, m)
    Pc = np.stack([(u - CX) / FX * z, (v - CY) / FY * z, z], axis=1)
    return transform_points(transform_inverse(T), Pc)


@dataclass
class MotionOnlyScene:
    """One frame's matches: ``T_true``/``T_init`` ``(4, 4)``, ``Xw`` ``(m, 3)``, ``z``
    ``(m, 2|3)``, ``inv_sigma2`` ``(m,)``, the true ``outlier`` mask."""

    T_true: np.ndarray
    T_init: np.ndarray
    Xw: np.ndarray
    z: np.ndarray
    inv_sigma2: np.ndarray
    outlier: np.ndarray


def motion_only(m: int, stereo: bool = False, seed: int = 0) -> MotionOnlyScene:
    """A frame with ``m`` matches to map points 1–12 m away (stereo: 1–6 m, the close points
    ORB-SLAM triangulates from the stereo pair); the initial pose is the truth moved by
    ~0.02 rad and ~5 cm (a constant-velocity prediction).

    Args:
        m: Matches.
        stereo: Measurements ``(u, v, u_r)``.
        seed: Random seed.
    """
    rng = np.random.default_rng(seed)
    T = se3_exp(np.concatenate([rng.normal(0.0, 0.3, (1, 3)), rng.normal(0.0, 2.0, (1, 3))], 1))
    X = _backproject(rng, np.repeat(T, m, 0), m, 1.0, 6.0 if stereo else 12.0)
    clean, _ = _project(np.repeat(T, m, 0), X, stereo)
    sigma, inv2 = _octaves(rng, m)
    z, out = _observe(rng, clean, sigma)
    return MotionOnlyScene(T[0], _perturb(rng, T, 0.012, 0.03)[0], X, z, inv2, out)


@dataclass
class LocalBAScene:
    """A local window: poses ``T_true``/``T_init`` ``(n, 4, 4)`` (the first ``n_fixed`` fixed,
    at the truth), points ``X_true``/``X_init`` ``(p, 3)``, observations ``kf``/``pt`` ``(o,)``
    with measurements ``z`` ``(o, 2)``, ``inv_sigma2`` and the true ``outlier`` mask."""

    T_true: np.ndarray
    T_init: np.ndarray
    fixed: np.ndarray
    X_true: np.ndarray
    X_init: np.ndarray
    kf: np.ndarray
    pt: np.ndarray
    z: np.ndarray
    inv_sigma2: np.ndarray
    outlier: np.ndarray


def local_ba(n_free: int, n_fixed: int, points: int, observations: int,
             seed: int = 0) -> LocalBAScene:
    """Keyframes 25 cm apart along a gently curving path, looking forward-left at points
    4–14 m away; every point seen by ``observations / points`` keyframes that see it in the
    image. Free keyframes start ~0.5° and ~2 cm off, points ~5 cm off.

    Args:
        n_free: Keyframes optimised.
        n_fixed: Keyframes held fixed (the oldest of the path).
        points: Map points.
        observations: Observations (a multiple of ``points``).
        seed: Random seed.
    """
    rng = np.random.default_rng(seed)
    n = n_free + n_fixed
    per = observations // points
    yaw = np.linspace(-0.15, 0.15, n)
    R = so3_exp(np.stack([np.zeros(n), yaw, np.zeros(n)], 1))
    centres = np.stack([0.25 * np.arange(n), 0.05 * np.sin(np.arange(n)), np.zeros(n)], 1)
    T = make_transform(R, -np.einsum("nij,nj->ni", R, centres))
    X = np.zeros((0, 3))
    vis = np.zeros((0, n), bool)
    while len(X) < points:
        cand = _backproject(rng, T[rng.integers(0, n, 4 * points)], 4 * points, 4.0, 14.0)
        pix, depth = _project(np.repeat(T, len(cand), 0), np.tile(cand, (n, 1)), False)
        pix, depth = pix.reshape(n, -1, 2), depth.reshape(n, -1)
        inside = ((depth > 0.5) & (pix[..., 0] > 0) & (pix[..., 0] < WIDTH)
                  & (pix[..., 1] > 0) & (pix[..., 1] < HEIGHT)).T
        keep = inside.sum(1) >= per
        X, vis = np.concatenate([X, cand[keep]]), np.concatenate([vis, inside[keep]])
    X, vis = X[:points], vis[:points]
    # Each point's observers: `per` of the keyframes that see it, chosen at random.
    key = np.where(vis, rng.random(vis.shape), 2.0)
    kf = np.argsort(key, axis=1)[:, :per].reshape(-1)
    pt = np.repeat(np.arange(points), per)
    order = np.lexsort((kf, pt))
    kf, pt = kf[order], pt[order]
    clean, _ = _project(T[kf], X[pt], False)
    sigma, inv2 = _octaves(rng, len(kf))
    z, out = _observe(rng, clean, sigma)
    fixed = np.arange(n) < n_fixed
    T0 = T.copy()
    T0[~fixed] = _perturb(rng, T[~fixed], 0.008, 0.02)
    X0 = X + rng.normal(0.0, 0.05, X.shape)
    return LocalBAScene(T, T0, fixed, X, X0, kf, pt, z, inv2, out)


@dataclass
class Sim3Scene:
    """Matched map points of two keyframes: ``S12_true``/``S12_init`` ``(4, 4)`` (camera 2 to
    camera 1), points ``P1c``/``P2c`` ``(m, 3)`` in each camera's frame (each map's own scale),
    pixels ``z1``/``z2`` ``(m, 2)`` and ``inv_sigma2_1``/``_2``, the true ``outlier`` mask."""

    S12_true: np.ndarray
    S12_init: np.ndarray
    P1c: np.ndarray
    P2c: np.ndarray
    z1: np.ndarray
    z2: np.ndarray
    inv_sigma2_1: np.ndarray
    inv_sigma2_2: np.ndarray
    outlier: np.ndarray


def sim3(m: int = 100, seed: int = 0, scale: float = 1.25) -> Sim3Scene:
    """Two keyframes 30 cm apart, their maps differing by ``scale`` (monocular drift); the map
    points carry 5 mm of noise, the initial ``S12`` (from RANSAC) is ~1°, 5 cm and 3 % off.

    Args:
        m: Matches.
        seed: Random seed.
        scale: ``s`` of the true ``S12``.
    """
    from graphopt.types.sim3_lie import sim3_exp, sim3_inverse, sim3_matrix, sim3_product

    rng = np.random.default_rng(seed)
    R12 = so3_exp(rng.normal(0.0, 0.1, (1, 3)))
    S12 = sim3_matrix(R12, np.array([[0.3, 0.05, 0.02]]), np.array([scale]))
    P1 = _backproject(rng, np.repeat(np.eye(4)[None], m, 0), m, 3.0, 10.0)
    P2 = _apply(sim3_inverse(S12)[0], P1)
    sig1, inv1 = _octaves(rng, m)
    sig2, inv2 = _octaves(rng, m)
    out = rng.random(m) < OUTLIERS                 # a wrong match: both pixels moved
    z1, _ = _observe(rng, _pixels(P1), sig1, out)
    z2, _ = _observe(rng, _pixels(P2), sig2, out)
    noise = np.array([[0.02, 0.02, 0.02, 0.05, 0.05, 0.05, 0.03]]) * rng.normal(size=(1, 7))
    S0 = sim3_product(sim3_exp(noise), S12)
    return Sim3Scene(S12[0], S0[0], P1 + rng.normal(0, 0.005, P1.shape),
                     P2 + rng.normal(0, 0.005 / scale, P2.shape), z1, z2, inv1, inv2, out)


def _apply(S: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X @ S[:3, :3].T + S[:3, 3]


def _pixels(P: np.ndarray) -> np.ndarray:
    return np.stack([FX * P[:, 0] / P[:, 2] + CX, FY * P[:, 1] / P[:, 2] + CY], axis=1)


@dataclass
class EssentialGraphScene:
    """A loop of keyframes: true similarities ``S_true`` and drifted, loop-corrected initial
    ones ``S_init`` ``(n, 4, 4)`` (``S_kw``), edges ``ij`` ``(e, 2)`` with measurements
    ``S_ji`` ``(e, 4, 4)`` (spanning tree, covisibility, loop), the fixed ``loop_kf``."""

    S_true: np.ndarray
    S_init: np.ndarray
    ij: np.ndarray
    S_ji: np.ndarray
    loop_kf: int


def essential_graph(n: int, seed: int = 0) -> EssentialGraphScene:
    """A circle of ``n`` keyframes (radius ``n/40`` m) walked by monocular odometry whose
    map scale drifts by −25 % over the loop (and 0.1°, 0.5 % noise per step); the spanning
    tree links consecutive keyframes, covisibility each keyframe to the 2nd and 3rd before
    it, and loop closing keyframes ``n−1, n−2`` to ``0, 1`` (the measurements from the
    corrected poses, as ORB-SLAM builds them). The current keyframe and its two neighbours
    start at their loop-corrected Sim3; keyframe 0 (the loop keyframe) is fixed.

    Args:
        n: Keyframes.
        seed: Random seed.
    """
    from graphopt.types.sim3_lie import sim3_inverse, sim3_matrix, sim3_product

    rng = np.random.default_rng(seed)
    radius = n / 40.0
    a = 2.0 * np.pi * np.arange(n) / n
    centres = np.stack([radius * np.sin(a), np.zeros(n), radius * (1.0 - np.cos(a))], 1)
    Rwc = so3_exp(np.stack([np.zeros(n), a, np.zeros(n)], 1))   # facing along the circle
    R = np.swapaxes(Rwc, 1, 2)
    T = make_transform(R, -np.einsum("nij,nj->ni", R, centres))
    # Odometry: true relative motions with noise and a slowly drifting scale.
    local_scale = np.exp(np.log(0.75) * np.arange(n) / (n - 1))
    rel = T[1:] @ transform_inverse(T[:-1])
    noise = se3_exp(np.concatenate([rng.normal(0, 0.0017, (n - 1, 3)),
                                    np.zeros((n - 1, 3))], 1))
    rel = noise @ rel
    rel[:, :3, 3] *= (local_scale[1:] * (1.0 + rng.normal(0.0, 0.005, n - 1)))[:, None]
    D = np.empty((n, 4, 4))
    D[0] = T[0]
    for k in range(1, n):                      # composing odometry is sequential by nature
        D[k] = rel[k - 1] @ D[k - 1]
    S_drift = sim3_matrix(D[:, :3, :3], D[:, :3, 3], np.ones(n))
    # The loop-corrected pose of keyframe k: the truth in its local map scale.
    target = sim3_matrix(R, T[:, :3, 3] * local_scale[:, None], local_scale)
    S0 = S_drift.copy()
    S0[-3:] = target[-3:]
    pairs = [(k - 1, k) for k in range(1, n)] + [(k - d, k) for d in (2, 3) for k in range(d, n)]
    ij = np.array(pairs)
    S_ji = sim3_product(S_drift[ij[:, 1]], sim3_inverse(S_drift[ij[:, 0]]))
    loop = np.array([(0, n - 1), (1, n - 1), (0, n - 2), (1, n - 2)])
    S_loop = sim3_product(target[loop[:, 1]], sim3_inverse(target[loop[:, 0]]))
    S_true = sim3_matrix(R, T[:, :3, 3], np.ones(n))
    return EssentialGraphScene(S_true, S0, np.concatenate([ij, loop]),
                               np.concatenate([S_ji, S_loop]), 0)


def centres(S: np.ndarray) -> np.ndarray:
    """Camera centres ``−Rᵀt/s`` ``(n, 3)`` of similarities (or rigid poses) ``S_kw``.

    Args:
        S: ``(n, 4, 4)``.
    """
    sR, t = S[:, :3, :3], S[:, :3, 3]
    return -np.linalg.solve(sR, t[:, :, None])[:, :, 0]


def pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Rotation (degrees) and camera-centre (metres) error of one pose.

    Args:
        T: ``(4, 4)``.
        T_true: ``(4, 4)``.
    """
    from graphopt.lie import so3_log

    dR = T[:3, :3] @ T_true[:3, :3].T
    rot = float(np.degrees(np.linalg.norm(so3_log(dR[None])[0])))
    return rot, float(np.linalg.norm(centres(T[None])[0] - centres(T_true[None])[0]))
