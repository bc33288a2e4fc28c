"""Preconditioned conjugate gradients with a block-Jacobi preconditioner."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.block_ops import batched_cholesky_inverses
from graphopt.solvers.base import LinearSolver


@dataclass(frozen=True)
class PCGConfig:
    """Settings of :class:`LinearSolverPCG`.

    Args:
        tolerance: Stop when ``‖r‖ ≤ tolerance · ‖b‖``.
        max_iterations: Iteration cap; ``None`` means the system size.
    """

    tolerance: float = 1e-10
    max_iterations: int | None = None


class LinearSolverPCG(LinearSolver):
    """Conjugate gradients preconditioned by the inverses of the diagonal blocks.

    Args:
        config: Tolerance and iteration cap.
    """

    name = "pcg"

    def __init__(self, config: PCGConfig | None = None) -> None:
        self.config = config or PCGConfig()
        self.last_iterations = 0

    def analyze(self, pattern: sp.csc_matrix, block_sizes: np.ndarray) -> None:
        """Precompute where the diagonal blocks sit in the data array.

        Args:
            pattern: Full symmetric CSC pattern.
            block_sizes: Diagonal block sizes.
        """
        super().analyze(pattern, block_sizes)
        offsets = np.concatenate([[0], np.cumsum(block_sizes)]).astype(np.int64)
        keys = np.repeat(np.arange(pattern.shape[1]), np.diff(pattern.indptr)) * pattern.shape[0]
        keys = keys + pattern.indices
        self._groups = []
        for d in np.unique(block_sizes):
            blocks = np.flatnonzero(block_sizes == d)
            r = offsets[blocks][:, None, None] + np.arange(d)[None, :, None]
            c = offsets[blocks][:, None, None] + np.arange(d)[None, None, :]
            r, c = np.broadcast_arrays(r, c)
            pos = np.searchsorted(keys, c * pattern.shape[0] + r)
            idx = offsets[blocks][:, None] + np.arange(d)
            self._groups.append((int(d), pos, idx))

    def solve(self, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """See :meth:`LinearSolver.solve`.

        Args:
            data: Values in the analysed pattern.
            rhs: Right-hand side ``(n,)`` or ``(n, k)`` (columns solved one by one).
        """
        if rhs.ndim == 2:
            return np.stack([self.solve(data, rhs[:, j]) for j in range(rhs.shape[1])], 1)
        # A symmetric CSC matrix read as CSR is the same matrix; CSR matvec is the faster one.
        p = self.pattern
        A = sp.csr_matrix((data, p.indices, p.indptr), shape=p.shape)
        pre = [(batched_cholesky_inverses(data[pos])[1], idx) for _, pos, idx in self._groups]

        def precondition(r: np.ndarray) -> np.ndarray:
            z = np.empty_like(r)
            for inv, idx in pre:
                z[idx] = np.einsum("nij,nj->ni", inv, r[idx])
            return z

        n = len(rhs)
        cap = self.config.max_iterations or max(n, 1)
        x = np.zeros(n)
        r = rhs.copy()
        bnorm = np.linalg.norm(rhs)
        if bnorm == 0:
            return x
        z = precondition(r)
        pvec = z.copy()
        rz = r @ z
        it = 0
        for it in range(1, cap + 1):  # noqa: B007 - iterations over CG steps, not edges
            q = A @ pvec
            curv = pvec @ q
            if curv <= 0:
                raise NotPositiveDefiniteError("PCG met non-positive curvature")
            alpha = rz / curv
            x += alpha * pvec
            r -= alpha * q
            if np.linalg.norm(r) <= self.config.tolerance * bnorm:
                break
            z = precondition(r)
            rz_new = r @ z
            pvec = z + (rz_new / rz) * pvec
            rz = rz_new
        self.last_iterations = it
        return x
