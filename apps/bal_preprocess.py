"""Ceres-style preparation of a BAL problem (as ``examples/bal_problem.cc``): :func:`normalize`
centres and scales the scene, :func:`perturb` adds deterministic Gaussian noise.

Both keep the problem's observations and return a modified copy; ``graphopt-bal`` applies them
for ``--normalize`` and ``--perturb``, and the synthetic scene (:mod:`graphopt.apps.bal_scene`)
perturbs its ground truth with :func:`perturb`.
"""

from __future__ import annotations

import numpy as np

from graphopt.io.bal import BALProblem
from graphopt.lie import so3_exp

__all__ = ["normalize", "perturb"]

def _upper_median(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """``std::nth_element`` at ``n/2`` (Ceres' Median): the upper median for even ``n``."""
    n = x.shape[axis]
    return np.take(np.partition(x, n // 2, axis=axis), n // 2, axis=axis)


def normalize(problem: BALProblem) -> BALProblem:
    """Centre and scale a problem as Ceres' bundle_adjuster does.

    Points are translated by their coordinate-wise median and scaled so that the median of
    ``‖X − median‖₁`` becomes 100; camera centres get the same similarity; rotations are kept.

    Args:
        problem: The problem (not modified).

    Returns:
        A normalised copy.
    """
    out = problem.copy()
    median = _upper_median(out.points, axis=0)
    mad = float(_upper_median(np.abs(out.points - median).sum(axis=1)))
    if not np.isfinite(mad) or mad <= 0:
        raise ValueError("normalize: the points have zero spread")
    scale = 100.0 / mad
    out.points = scale * (out.points - median)
    R = so3_exp(out.cameras[:, :3])
    centers = out.camera_centers()
    centers = scale * (centers - median)
    out.cameras[:, 3:6] = -np.einsum("nij,nj->ni", R, centers)
    return out


def perturb(
    problem: BALProblem,
    rotation_sigma: float,
    translation_sigma: float,
    point_sigma: float,
    seed: int = 0,
) -> BALProblem:
    """Add Gaussian noise as Ceres' bundle_adjuster does, deterministically for a seed.

    Points get ``N(0, point_sigma²)`` per coordinate; each camera's angle-axis gets
    ``N(0, rotation_sigma²)`` per component with the camera *centre* held fixed, then its
    translation ``t`` gets ``N(0, translation_sigma²)`` per component. Draw order: all points,
    then per camera rotation then translation (as a single vectorised draw each).

    Args:
        problem: The problem (not modified).
        rotation_sigma: Std-dev of the angle-axis noise (radians); 0 disables.
        translation_sigma: Std-dev of the translation noise; 0 disables.
        point_sigma: Std-dev of the point noise; 0 disables.
        seed: Random seed.

    Returns:
        A perturbed copy.
    """
    sig = (rotation_sigma, translation_sigma, point_sigma)
    if any((not np.isfinite(s)) or s < 0 for s in sig):
        raise ValueError(f"perturb: sigmas must be finite and >= 0, got {sig}")
    rng = np.random.default_rng(seed)
    out = problem.copy()
    if point_sigma > 0:
        out.points = out.points + rng.normal(0.0, point_sigma, out.points.shape)
    if rotation_sigma > 0:
        centers = out.camera_centers()
        out.cameras[:, :3] += rng.normal(0.0, rotation_sigma, (out.num_cameras, 3))
        R = so3_exp(out.cameras[:, :3])
        out.cameras[:, 3:6] = -np.einsum("nij,nj->ni", R, centers)
    if translation_sigma > 0:
        out.cameras[:, 3:6] += rng.normal(0.0, translation_sigma, (out.num_cameras, 3))
    return out
