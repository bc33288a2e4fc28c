"""Preconditioned conjugate gradients with a block-Jacobi preconditioner.

On a singular system PCG does not stop as the direct solvers do (:mod:`graphopt.solvers.rank`):
a consistent one (the right-hand side in the range of ``A``, as every Gauss–Newton system is)
is solved: from ``x = 0`` the iterates stay in ``M⁻¹ range(A)`` (``M`` the block diagonal), so
the step is the solution of least ``M``-norm, with no component along the null space in that
metric. A singular diagonal block (an unobserved direction of a vertex) gets its
pseudo-inverse. What cannot be solved raises instead of returning NaN: a right-hand side
with a component in a singular block's null space, or a search direction of negligible
curvature (``pᵀAp ≤ τ · pᵀ diag(A) p``) while the residual is still large, is inconsistent
(:class:`SingularSystemError`); negative curvature is indefinite
(:class:`NotPositiveDefiniteError`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError, SingularSystemError
from graphopt.linear.block_ops import batched_cholesky_inverses
from graphopt.solvers.base import LinearSolver
from graphopt.solvers.rank import SINGULAR_TOLERANCE


@dataclass(frozen=True)
class PCGConfig:
    """Settings of :class:`LinearSolverPCG`.

    Args:
        tolerance: Stop when ``‖r‖ ≤ tolerance · ‖b‖``.
        max_iterations: Iteration cap; ``None`` means the system size.
    """

    tolerance: float = 1e-10
    max_iterations: int | None = None


def _block_inverses(blocks: np.ndarray, rhs: np.ndarray, limit: float) -> np.ndarray:
    """Inverses of the diagonal blocks; pseudo-inverses where a block is singular.

    Args:
        blocks: ``(m, d, d)`` diagonal blocks of ``A``.
        rhs: ``(m, d)``: the right-hand side's rows of each block.
        limit: Largest norm of the right-hand side's part in the blocks' null spaces (that part
            is never reduced: a PSD matrix has zero rows along a null direction of a block).

    Raises:
        SingularSystemError: if that part is larger (the system is inconsistent).
        NotPositiveDefiniteError: if a block is indefinite or not finite.
    """
    try:
        return batched_cholesky_inverses(blocks)[1]
    except NotPositiveDefiniteError:
        if not np.all(np.isfinite(blocks)):
            raise
    w, v = np.linalg.eigh(blocks)
    tol = SINGULAR_TOLERANCE * np.abs(w).max(axis=1, initial=0.0)[:, None]
    if np.any(w < -tol):
        raise NotPositiveDefiniteError("PCG: a diagonal block is not positive semi-definite")
    keep = w > tol
    inv = np.einsum("mij,mj,mkj->mik", v, np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0), v)
    null = np.einsum("mij,mj,mkj,mk->mi", v, (~keep).astype(float), v, rhs)
    if np.linalg.norm(null) > limit:
        raise SingularSystemError("PCG: the system is singular and inconsistent (the right-hand "
                                  "side has a component in the null space of a diagonal block)")
    return inv


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
        bnorm = float(np.linalg.norm(rhs))
        limit = self.config.tolerance * bnorm
        pre = [(_block_inverses(data[pos], rhs[idx], limit), idx) for _, pos, idx in self._groups]
        diag = data[self.diag_pos]

        def precondition(r: np.ndarray) -> np.ndarray:
            z = np.empty_like(r)
            for inv, idx in pre:
                z[idx] = np.einsum("nij,nj->ni", inv, r[idx])
            return z

        n = len(rhs)
        cap = self.config.max_iterations or max(n, 1)
        x = np.zeros(n)
        r = rhs.copy()
        if bnorm == 0:
            return x
        z = precondition(r)
        pvec = z.copy()
        rz = r @ z
        it = 0
        for it in range(1, cap + 1):  # noqa: B007 - iterations over CG steps, not edges
            q = A @ pvec
            curv = pvec @ q
            size = SINGULAR_TOLERANCE * (pvec @ (diag * pvec))
            if not curv > size:
                if not curv >= -size:  # negative or NaN
                    raise NotPositiveDefiniteError("PCG met negative (or NaN) curvature: the "
                                                   "system is not positive semi-definite")
                raise SingularSystemError(
                    "PCG met a direction of negligible curvature with the residual at "
                    f"{np.linalg.norm(r) / bnorm:.2g} of the right-hand side: the system is "
                    "singular and inconsistent")
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
        if not np.all(np.isfinite(x)):
            raise NotPositiveDefiniteError("PCG produced non-finite values")
        return x
