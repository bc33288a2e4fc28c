"""Batched 3D rigid-transform helpers in g2o's conventions (``isometry3d_mappings``).

A pose is a ``(n, 3, 4)`` array ``[R | t]`` (the top three rows of g2o's ``Isometry3``
matrix). Quaternions are ``[qx, qy, qz, qw]`` (scalar last), Hamilton, as in g2o's files.

Two of g2o's habits matter for chi2 to agree with g2o's to the last digits:

* g2o (2.3.0, as measured with g2opy) turns a quaternion read from a file into a matrix
  *without normalising it* (Eigen's ``toRotationMatrix`` of the quaternion as written):
  :func:`quat_to_matrix` does the same. A quaternion written with 6 digits is off unit length by
  up to ~1e-6, and normalising it changes ``pose3example``'s chi2 by 7e-6 relative.
* The inverse of a pose is ``[Rᵀ | −Rᵀt]`` (Eigen's isometry inverse), even for such a
  slightly non-orthonormal ``R``.

Rotations back to quaternions follow Eigen's ``Quaternion(Matrix3)`` (Shepperd's method: the
trace branch when the trace is positive, else the largest diagonal element), then normalise.
"""

from __future__ import annotations

import numpy as np

from graphopt.lie import quat_to_rot

__all__ = [
    "compact_quaternion",
    "compose",
    "from_compact_quaternion",
    "inverse",
    "matrix_to_quat",
    "orthonormalize",
    "pose_from_qt",
    "pose_to_qt",
    "quat_to_matrix",
]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Eigen's ``toRotationMatrix`` of quaternions as given (not normalised).

    For ``q = s·q̂`` with ``|q̂| = 1`` that is ``s² R(q̂) + (1 − s²) I``.

    Args:
        q: ``(n, 4)`` quaternions ``[qx, qy, qz, qw]``.

    Returns:
        ``(n, 3, 3)`` matrices (rotations for unit quaternions).
    """
    s2 = np.einsum("ni,ni->n", q, q)
    return s2[:, None, None] * quat_to_rot(q) + (1.0 - s2)[:, None, None] * np.eye(3)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Eigen's ``Quaternion(R)``, normalised (the sign as Eigen's conversion gives it).

    Args:
        R: ``(n, 3, 3)`` rotation matrices.

    Returns:
        ``(n, 4)`` unit quaternions ``[qx, qy, qz, qw]``.
    """
    n = len(R)
    q = np.empty((n, 4), like=R)  # like=: jets stay jets (graphopt.autodiff)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    pos = tr > 0.0
    every = bool(pos.all())
    Rp = R if every else R[pos]
    t = np.sqrt((tr if every else tr[pos]) + 1.0)
    k = 0.5 / t
    qp = np.stack([(Rp[:, 2, 1] - Rp[:, 1, 2]) * k, (Rp[:, 0, 2] - Rp[:, 2, 0]) * k,
                   (Rp[:, 1, 0] - Rp[:, 0, 1]) * k, 0.5 * t], axis=1)
    if every:
        q = qp
    else:
        q[pos] = qp
        diag = np.einsum("nii->ni", R)
        first = np.where(diag[:, 1] > diag[:, 0], 1, 0)
        first = np.where(diag[:, 2] > diag[np.arange(n), first], 2, first)
        for i in range(3):
            sel = np.flatnonzero(~pos & (first == i))
            if not len(sel):
                continue
            j, kk = (i + 1) % 3, (i + 2) % 3
            Rs = R[sel]
            t = np.sqrt(Rs[:, i, i] - Rs[:, j, j] - Rs[:, kk, kk] + 1.0)
            h = 0.5 / t
            q[sel, i] = 0.5 * t
            q[sel, 3] = (Rs[:, kk, j] - Rs[:, j, kk]) * h
            q[sel, j] = (Rs[:, j, i] + Rs[:, i, j]) * h
            q[sel, kk] = (Rs[:, kk, i] + Rs[:, i, kk]) * h
    return q / np.sqrt(np.einsum("ni,ni->n", q, q))[:, None]


def compact_quaternion(R: np.ndarray) -> np.ndarray:
    """g2o's ``toCompactQuaternion``: the unit quaternion of ``R`` with ``qw ≥ 0``.

    Args:
        R: ``(n, 3, 3)`` rotation matrices.

    Returns:
        ``(n, 4)`` ``[qx, qy, qz, qw]`` with ``qw ≥ 0``; g2o's error uses ``[:, :3]``.
    """
    q = matrix_to_quat(R)
    neg = q[:, 3] < 0.0
    if neg.any():
        q[neg] *= -1.0
    return q


def from_compact_quaternion(v: np.ndarray) -> np.ndarray:
    """g2o's ``fromCompactQuaternion``: the rotation of ``(√(1 − |v|²), v)``; the identity
    where ``|v| > 1``.

    Args:
        v: ``(n, 3)`` quaternion vector parts.

    Returns:
        ``(n, 3, 3)`` rotation matrices.
    """
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    w2 = 1.0 - (x * x + y * y + z * z)
    bad = w2 < 0.0
    w = np.sqrt(np.where(bad, 1.0, w2))
    if bad.any():
        x, y, z = (np.where(bad, 0.0, c) for c in (x, y, z))
    R = np.empty((len(v), 3, 3), like=v)
    R[:, 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[:, 0, 1] = 2.0 * (x * y - z * w)
    R[:, 0, 2] = 2.0 * (x * z + y * w)
    R[:, 1, 0] = 2.0 * (x * y + z * w)
    R[:, 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[:, 1, 2] = 2.0 * (y * z - x * w)
    R[:, 2, 0] = 2.0 * (x * z - y * w)
    R[:, 2, 1] = 2.0 * (y * z + x * w)
    R[:, 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def pose_from_qt(v: np.ndarray) -> np.ndarray:
    """g2o's ``fromVectorQT``: ``[x y z qx qy qz qw]`` → ``[R | t]`` (quaternion as written).

    Args:
        v: ``(n, 7)`` poses.

    Returns:
        ``(n, 3, 4)`` poses.
    """
    T = np.empty((len(v), 3, 4), like=v)
    T[:, :, :3] = quat_to_matrix(v[:, 3:7])
    T[:, :, 3] = v[:, :3]
    return T


def pose_to_qt(T: np.ndarray) -> np.ndarray:
    """g2o's ``toVectorQT``: ``[R | t]`` → ``[x y z qx qy qz qw]`` (quaternion normalised).

    Args:
        T: ``(n, 3, 4)`` poses.

    Returns:
        ``(n, 7)`` poses.
    """
    return np.concatenate([T[:, :, 3], matrix_to_quat(T[:, :, :3])], axis=1)


def inverse(T: np.ndarray) -> np.ndarray:
    """``[Rᵀ | −Rᵀt]`` (Eigen's isometry inverse).

    Args:
        T: ``(n, 3, 4)`` poses.
    """
    out = np.empty_like(T)
    Rt = np.swapaxes(T[:, :, :3], 1, 2)
    out[:, :, :3] = Rt
    out[:, :, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :, 3])
    return out


def compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A·B`` for ``[R | t]`` poses: ``[R_A R_B | R_A t_B + t_A]``.

    Args:
        A: ``(n, 3, 4)`` poses.
        B: ``(n, 3, 4)`` poses.
    """
    out = A[:, :, :3] @ B
    out[:, :, 3] += A[:, :, 3]
    return out


def orthonormalize(R: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """g2o's ``approximateNearestOrthogonalMatrix``, ``R − ½ R (RᵀR − I)``, applied to the
    matrices whose deviation ``max |RᵀR − I|`` exceeds ``tolerance``.

    One first-order step: a deviation ``ε`` shrinks to ``O(ε²)``; an orthonormal ``R`` is
    unchanged up to rounding.

    Args:
        R: ``(n, 3, 3)`` nearly orthonormal matrices.
        tolerance: Leave matrices within it alone (``0``: correct every matrix).

    Returns:
        ``(n, 3, 3)`` matrices (``R`` itself when none is corrected).
    """
    E = np.swapaxes(R, 1, 2) @ R
    E[:, [0, 1, 2], [0, 1, 2]] -= 1.0
    if tolerance <= 0.0:
        return R - 0.5 * (R @ E)
    sel = np.flatnonzero(np.abs(E).max(axis=(1, 2)) > tolerance)
    if not len(sel):
        return R
    out = R.copy()
    out[sel] -= 0.5 * (R[sel] @ E[sel])
    return out
