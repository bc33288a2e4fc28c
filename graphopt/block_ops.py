"""Small batched linear-algebra kernels and the precomputed segment-sum used for scattering."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """A block or the reduced system is not positive definite."""


class SegmentSum:
    """Sum rows of a ``(n, D)`` array into ``n_targets`` rows, the map fixed at construction.

    Implemented as a product with a constant CSR matrix (a C loop over rows, about 10x faster
    than ``np.add.at``); a one-to-one map degenerates to a gather, or to nothing.

    Args:
        target: ``(n,)`` target row of every input row.
        n_targets: Number of output rows.
    """

    def __init__(self, target: np.ndarray, n_targets: int) -> None:
        target = np.asarray(target, dtype=np.int64)
        self.n_targets = n_targets
        self.identity = len(target) == n_targets and np.array_equal(target, np.arange(n_targets))
        self.perm: np.ndarray | None = None
        self.matrix: sp.csr_matrix | None = None
        if self.identity:
            return
        if len(target) == n_targets and len(np.unique(target)) == n_targets:
            self.perm = np.argsort(target)  # output row t = input row perm[t]
            return
        n = len(target)
        self.matrix = sp.csr_matrix(
            (np.ones(n), (target, np.arange(n))), shape=(n_targets, n)
        )

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """Apply to ``values`` of shape ``(n, ...)``; returns ``(n_targets, ...)``.

        Args:
            values: Per-input-row values.
        """
        if self.identity:
            return values
        if self.perm is not None:
            return values[self.perm]
        assert self.matrix is not None
        flat = values.reshape(len(values), -1)
        return np.asarray(self.matrix @ flat).reshape((self.n_targets, *values.shape[1:]))


def batched_inverse_spd(A: np.ndarray) -> np.ndarray:
    """Inverse of many small symmetric positive definite matrices.

    Closed forms for sizes 1–3 (cofactors; Sylvester's criterion checks definiteness), batched
    Cholesky otherwise.

    Args:
        A: ``(n, d, d)`` symmetric matrices.

    Returns:
        ``(n, d, d)`` inverses.

    Raises:
        NotPositiveDefiniteError: if any block is not positive definite.
    """
    n, d, _ = A.shape
    if n == 0:
        return A.copy()
    if d == 1:
        if np.any(~(A[:, 0, 0] > 0)):
            raise NotPositiveDefiniteError("a 1x1 block is not positive")
        return 1.0 / A
    if d == 2:
        a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 1, 1]
        det = a * c - b * b
        if np.any(~(a > 0)) or np.any(~(det > 0)):
            raise NotPositiveDefiniteError("a 2x2 block is not positive definite")
        inv = np.empty_like(A)
        inv[:, 0, 0], inv[:, 1, 1] = c / det, a / det
        inv[:, 0, 1] = inv[:, 1, 0] = -b / det
        return inv
    if d == 3:
        a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
        a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        m2 = a00 * a11 - a01 * a01
        if np.any(~(a00 > 0)) or np.any(~(m2 > 0)) or np.any(~(det > 0)):
            raise NotPositiveDefiniteError("a 3x3 block is not positive definite")
        inv = np.empty_like(A)
        r = 1.0 / det
        inv[:, 0, 0] = c00 * r
        inv[:, 0, 1] = inv[:, 1, 0] = c01 * r
        inv[:, 0, 2] = inv[:, 2, 0] = c02 * r
        inv[:, 1, 1] = (a00 * a22 - a02 * a02) * r
        inv[:, 1, 2] = inv[:, 2, 1] = (a01 * a02 - a00 * a12) * r
        inv[:, 2, 2] = m2 * r
        return inv
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError as exc:
        raise NotPositiveDefiniteError(f"a {d}x{d} block is not positive definite") from exc
    Linv = np.linalg.inv(L)
    return np.swapaxes(Linv, 1, 2) @ Linv
