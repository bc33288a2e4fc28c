"""A synthetic BAL-like scene with known ground truth, and the errors of an estimate against it.

``graphopt-bal`` without an input file optimises :func:`synthetic_scene`'s problem and reports
:func:`ground_truth_errors` (after :func:`similarity_align`, since bundle adjustment fixes the
scene only up to a similarity).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from graphopt.apps.bal_preprocess import perturb
from graphopt.io.bal import BALProblem
from graphopt.lie import angle_axis_rotate, so3_exp, so3_log
from graphopt.types.bal import bal_project

__all__ = ["SyntheticScene", "ground_truth_errors", "similarity_align", "synthetic_scene"]


@dataclass
class SyntheticScene:
    """A synthetic BAL problem with its ground truth.

    Args:
        problem: The problem to solve (perturbed initial estimates, noisy observations).
        truth: The same problem at the true cameras and points (noise-free parameters).
        pixel_sigma: Std-dev of the observation noise in pixels.
    """

    problem: BALProblem
    truth: BALProblem
    pixel_sigma: float


def synthetic_scene(
    num_cameras: int = 16,
    num_points: int = 3000,
    *,
    pixel_sigma: float = 0.5,
    rotation_sigma: float = 0.005,
    translation_sigma: float = 0.05,
    point_sigma: float = 0.05,
    focal: float = 800.0,
    half_width: float = 400.0,
    seed: int = 0,
) -> SyntheticScene:
    """Generate a BAL-like scene: a camera moving along a street, filming a facade.

    Cameras stand 2 units apart on the x axis (with small random offsets and rotations), looking
    down −z (BAL's convention) at points spread on a 2-unit-deep facade 10 units away, with a
    focal length near ``focal`` and mild radial distortion. A point is observed by every camera
    that sees it in front and within ``±half_width`` pixels, which gives BAL-like tracks of a few
    observations per point (the Schur complement's cost depends on track length); points seen
    fewer than twice are dropped. Observations get ``N(0, pixel_sigma²)`` noise; the initial
    estimate is the truth perturbed with :func:`perturb`.

    Args:
        num_cameras: Number of cameras (>= 2).
        num_points: Number of points drawn (some may be dropped if seen fewer than twice).
        pixel_sigma: Observation noise (pixels).
        rotation_sigma: Initial rotation noise (radians).
        translation_sigma: Initial translation noise (scene units).
        point_sigma: Initial point noise (scene units).
        focal: Nominal focal length (pixels).
        half_width: Half image size (pixels); projections outside are not observed.
        seed: Random seed (the scene is a deterministic function of the arguments).

    Returns:
        The scene.
    """
    if num_cameras < 2 or num_points < 1:
        raise ValueError("synthetic_scene: need at least 2 cameras and 1 point")
    rng = np.random.default_rng(seed)
    spacing, distance = 2.0, 10.0
    length = spacing * (num_cameras - 1)
    reach = distance * half_width / focal  # half the facade width one camera sees
    pts = rng.uniform(
        [-reach, -0.8 * reach, -distance - 1.0], [length + reach, 0.8 * reach, -distance + 1.0],
        (num_points, 3),
    )
    centers = np.column_stack([
        spacing * np.arange(num_cameras) + rng.normal(0, 0.1, num_cameras),
        rng.normal(0, 0.2, num_cameras),
        rng.normal(0, 0.2, num_cameras),
    ])
    cams = np.zeros((num_cameras, 9))
    cams[:, :3] = rng.normal(0, 0.05, (num_cameras, 3))  # R_cw close to I: looking down −z
    cams[:, 3:6] = -angle_axis_rotate(cams[:, :3], centers)
    cams[:, 6] = focal * rng.uniform(0.9, 1.1, num_cameras)
    cams[:, 7] = rng.normal(0.0, 0.05, num_cameras)
    cams[:, 8] = rng.normal(0.0, 0.005, num_cameras)

    ci, pi = np.meshgrid(np.arange(num_cameras), np.arange(num_points), indexing="ij")
    ci, pi = ci.ravel(), pi.ravel()
    uv, pz = bal_project(cams[ci], pts[pi])
    visible = (pz < 0) & (np.abs(uv) < half_width).all(axis=1)
    ci, pi, uv = ci[visible], pi[visible], uv[visible]
    keep = np.bincount(pi, minlength=num_points) >= 2
    remap = np.cumsum(keep) - 1
    sel = keep[pi]
    ci, pi, uv = ci[sel], remap[pi[sel]], uv[sel]
    order = np.lexsort((ci, pi))  # BAL files list observations by point
    ci, pi, uv = ci[order], pi[order], uv[order]
    pts = pts[keep]

    truth = BALProblem(cams, pts, ci.astype(np.int64), pi.astype(np.int64), uv.copy())
    noisy = truth.copy()
    noisy.observations = uv + rng.normal(0.0, pixel_sigma, uv.shape)
    problem = perturb(noisy, rotation_sigma, translation_sigma, point_sigma, seed=seed + 1)
    return SyntheticScene(problem=problem, truth=truth, pixel_sigma=pixel_sigma)


def similarity_align(
    source: np.ndarray, target: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's similarity ``(s, R, t)`` minimising ``Σ‖s R source_i + t − target_i‖²``.

    Bundle adjustment fixes the scene only up to a similarity (gauge freedom), so estimates are
    compared with ground truth after this alignment.

    Args:
        source: ``(n, 3)`` points.
        target: ``(n, 3)`` corresponding points.

    Returns:
        ``(scale, R (3, 3), t (3,))``.
    """
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(source)
    s = float(np.trace(np.diag(S) @ D) / var_s)
    return s, R, mu_t - s * R @ mu_s


def ground_truth_errors(estimate: BALProblem, truth: BALProblem) -> dict[str, Any]:
    """Errors of an estimate against ground truth after a similarity alignment of the points.

    Args:
        estimate: The estimated problem.
        truth: The ground truth (same cameras, points and observations).

    Returns:
        ``point_rms`` and ``camera_center_rms`` (scene units, after alignment),
        ``rotation_deg_rms`` and ``focal_rel_rms``.
    """
    s, R, t = similarity_align(estimate.points, truth.points)
    pts = s * estimate.points @ R.T + t
    cen = s * estimate.camera_centers() @ R.T + t
    R_est = so3_exp(estimate.cameras[:, :3]) @ R.T  # R_cw of the aligned camera
    dR = so3_log(R_est @ np.swapaxes(so3_exp(truth.cameras[:, :3]), 1, 2))
    rms = lambda a: float(np.sqrt(np.mean(np.sum(a * a, axis=-1))))  # noqa: E731
    return {
        "point_rms": rms(pts - truth.points),
        "camera_center_rms": rms(cen - truth.camera_centers()),
        "rotation_deg_rms": float(np.degrees(rms(dR))),
        "focal_rel_rms": float(
            np.sqrt(np.mean((estimate.cameras[:, 6] / truth.cameras[:, 6] - 1.0) ** 2))
        ),
    }
