"""The dense linear algebra and the state of a problem with one free vertex: ``H + λD``
solved by LAPACK's Cholesky, the step applied to that vertex alone, the trial's state kept by
reference (a step replaces the store's array, so keeping it is keeping the state).
"""

from __future__ import annotations

import math
import time

import numpy as np

from graphopt.linear import Assembly
from graphopt.numeric import checked_oplus
from graphopt.problem import Step, Timing
from graphopt.solvers.small_dense import damped_solve
from graphopt.storage import VertexStore

__all__ = ["OneVertexOps"]


class OneVertexOps:
    """:class:`~graphopt.problem.Problem`'s linear algebra and state operations for
    :class:`~graphopt.single_vertex.SingleVertexProblem` (a mixin: the problem sets the
    attributes below).

    Attributes:
        stores: The vertex stores.
        d: The free vertex's dimension.
        timing: The problem's timings.
    """

    stores: list[VertexStore]
    d: int
    timing: Timing
    _store: int          # the free vertex's store
    _slot: int           # and slot
    _diag: np.ndarray    # H's diagonal positions in its column-major data
    _ones: np.ndarray    # D = I
    _pushed: np.ndarray | None

    # --- the linear algebra ------------------------------------------------------------------

    def damping(self, asm: Assembly, diagonal: bool) -> Step:
        """See :meth:`Problem.damping`.

        Args:
            asm: The assembly.
            diagonal: Marquardt's scaling instead of the identity.
        """
        if diagonal:
            return np.clip(asm.h_data[self._diag], 1e-6, 1e32), []
        return self._ones, []

    def max_diagonal(self, asm: Assembly) -> float:
        """See :meth:`Problem.max_diagonal`.

        Args:
            asm: The assembly.
        """
        return float(asm.h_data[self._diag].max())

    def solve(self, asm: Assembly, lam: float, damping: Step | None = None) -> Step:
        """See :meth:`Problem.solve`: LAPACK's Cholesky of ``H + λD`` (``D``: ``damping``, the
        identity if ``None``), held to the dense solver's rank rule
        (:func:`~graphopt.solvers.small_dense.damped_solve`).

        Args:
            asm: The assembly.
            lam: Damping λ (0 for none).
            damping: ``D`` from :meth:`damping`.
        """
        t0 = time.perf_counter()
        du = damped_solve(asm.h_data, asm.bu, self._diag, lam,
                          self._ones if damping is None else damping[0])
        self.timing.solve += time.perf_counter() - t0
        return du, []

    def hessian_product(self, asm: Assembly, step: Step) -> Step:
        """See :meth:`Problem.hessian_product`.

        Args:
            asm: The assembly.
            step: A vector in the step layout.
        """
        d = self.d
        return asm.h_data.reshape(d, d).T @ step[0], []

    # --- the state ---------------------------------------------------------------------------

    @staticmethod
    def max_abs(step: Step) -> float:
        """See :meth:`Problem.max_abs` (in floats: the gradient test's ``b``, finite here).

        Args:
            step: A vector in the step layout.
        """
        return max(map(abs, step[0].tolist()), default=0.0)

    def state_norm(self) -> float:
        """See :meth:`Problem.state_norm`."""
        est = self.stores[self._store].estimates
        x = est if len(est) == 1 else est[self._slot:self._slot + 1]
        return math.sqrt(float(np.vdot(x, x)))

    def push(self) -> None:
        """See :meth:`Problem.push` (the one store with the free vertex)."""
        self._pushed = self.stores[self._store].estimates

    def pop(self) -> None:
        """See :meth:`Problem.pop`."""
        self.stores[self._store].estimates = self._pushed

    def apply(self, step: Step) -> None:
        """``x ← x ⊞ Δ`` on the free vertex (``oplus`` gets a copy; see
        :meth:`Problem.apply`).

        Args:
            step: ``(Δ (d,), [])``.

        Raises:
            GraphError: ``oplus`` returned the wrong shape (naming the vertex type).
        """
        st = self.stores[self._store]
        est = st.estimates
        delta = step[0].reshape(1, -1)
        if len(est) == 1:
            st.estimates = checked_oplus(st.vtype, est.copy(), delta)
            return
        new = est.copy()
        k = self._slot
        new[k:k + 1] = checked_oplus(st.vtype, est[k:k + 1].copy(), delta)
        st.estimates = new
