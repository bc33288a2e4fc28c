"""Deterministic inputs (closed-form numbers, no random generator) for the SBA/Sim3 types' chi2
checks: shared by ``tests/test_sba_sim3_types.py`` and ``benchmarks/g2o_sba_sim3_reference.py``,
which computes g2opy's chi2 of the same edges."""

from __future__ import annotations

import numpy as np

from graphopt.lie import se3_exp
from graphopt.types.sim3_lie import sim3_exp

M = 8                                    # edges per type
FX, FY, CX, CY, BF = 500.0, 505.0, 320.0, 240.0, 40.0
F_SIM3 = 450.0                           # fx = fy for the Sim3 projections (see the script)
INFO2 = np.array([[1.2, 0.1], [0.1, 0.8]])
INFO3 = np.array([[1.2, 0.1, 0.0], [0.1, 0.8, 0.05], [0.0, 0.05, 0.9]])
_K = np.arange(M, dtype=float)


def points() -> np.ndarray:
    """``(M, 3)`` world points about 4–8 m in front of the pose."""
    return np.stack([1.5 * np.sin(_K), np.cos(1.3 * _K), 4.0 + 0.5 * _K], axis=1)


def pose() -> np.ndarray:
    """One ``(4, 4)`` camera pose ``T_cw`` near the identity."""
    return se3_exp(np.array([[0.05, -0.08, 0.03, 0.2, -0.1, 0.15]]))[0]


def pixels() -> np.ndarray:
    """``(M, 2)`` pixel measurements, a few pixels off the projections."""
    P = (pose()[:3, :3] @ points().T).T + pose()[:3, 3]
    u = FX * P[:, 0] / P[:, 2] + CX + 3.0 * np.sin(2.0 * _K)
    v = FY * P[:, 1] / P[:, 2] + CY + 2.5 * np.cos(3.0 * _K)
    return np.stack([u, v], axis=1)


def stereo() -> np.ndarray:
    """``(M, 3)`` stereo measurements ``(u, v, u_r)``."""
    P = (pose()[:3, :3] @ points().T).T + pose()[:3, 3]
    z = pixels()
    ur = z[:, 0] - BF / P[:, 2] + 1.5 * np.cos(_K)
    return np.concatenate([z, ur[:, None]], axis=1)


def pose_pairs() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(T_i, T_j, T_ij)`` ``(M, 4, 4)`` each: relative poses with errors of 0.05–0.6 rad."""
    xi = np.stack([0.3 * np.sin(_K + 1), 0.2 * np.cos(_K), 0.4 * np.sin(2 * _K), _K * 0.3,
                   -0.2 * _K, 1.0 + 0.1 * _K], axis=1)
    xj = np.stack([0.3 * np.cos(_K), -0.25 * np.sin(_K), 0.2 * np.cos(3 * _K), 1.0 - _K * 0.2,
                   0.3 * _K, 0.5 * np.sin(_K)], axis=1)
    xm = np.stack([0.05 + 0.07 * _K, 0.1 * np.cos(_K), -0.06 * _K, 0.5 * np.sin(_K),
                   0.4 * np.ones(M), -0.3 * np.cos(_K)], axis=1)
    return se3_exp(xi), se3_exp(xj), se3_exp(xm)


def sim3_pairs() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(S_i, S_j, S_ji)`` ``(M, 4, 4)`` similarities with scales 0.5–2."""
    xi = np.stack([0.3 * np.sin(_K + 1), 0.2 * np.cos(_K), 0.4 * np.sin(2 * _K), _K * 0.3,
                   -0.2 * _K, 1.0 + 0.1 * _K, 0.3 * np.sin(_K)], axis=1)
    xj = np.stack([0.3 * np.cos(_K), -0.25 * np.sin(_K), 0.2 * np.cos(3 * _K), 1.0 - _K * 0.2,
                   0.3 * _K, 0.5 * np.sin(_K), -0.2 * np.cos(2 * _K)], axis=1)
    xm = np.stack([0.05 + 0.07 * _K, 0.1 * np.cos(_K), -0.06 * _K, 0.5 * np.sin(_K),
                   0.4 * np.ones(M), -0.3 * np.cos(_K), 0.1 + 0.05 * _K], axis=1)
    return sim3_exp(xi), sim3_exp(xj), sim3_exp(xm)


def sim3_projection() -> tuple[np.ndarray, np.ndarray]:
    """``(S (4, 4), pixels (M, 2))`` for the Sim3 projections, ``S`` with scale 1.3."""
    S = sim3_exp(np.array([[0.04, -0.05, 0.02, 0.1, 0.2, -0.1, np.log(1.3)]]))[0]
    z = np.stack([CX + 40.0 * np.sin(_K), CY + 30.0 * np.cos(2.0 * _K)], axis=1)
    return S, z


INFO7 = np.diag([2.0, 1.5, 1.0, 0.5, 0.8, 1.2, 3.0]) + 0.05


def near_optimum(scaled: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(X_i, X_j, Z)`` whose errors are tiny (rotation ~1e-3 rad, ``|σ| < 1e-5``): where
    g2o's logs take their limit branches. ``scaled``: Sim3 (else SE3) inputs."""
    Xi, Xj, _ = sim3_pairs() if scaled else pose_pairs()
    eps = np.stack([1e-3 * np.sin(_K), 2e-3 * np.cos(_K), 5e-4 * np.ones(M), 1e-3 * _K,
                    -2e-3 * np.ones(M), 1e-3 * np.cos(_K), 4e-6 * np.sin(_K + 0.5)], axis=1)
    if scaled:
        from graphopt.types.sim3_lie import sim3_inverse, sim3_product
        Z = sim3_product(sim3_product(sim3_exp(eps), Xj), sim3_inverse(Xi))
    else:
        Z = se3_exp(eps[:, :6]) @ Xj @ np.linalg.inv(Xi)
    return Xi, Xj, Z
