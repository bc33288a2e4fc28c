"""``LinearSystem``: the facade over the three tiers of the (Schur-reduced) normal equations.

* *structure*, once per graph structure: :class:`~graphopt.linear.structure.BlockIndex`
  (U/V/W blocks, V order, the pattern of ``S``);
* *assembly*, once per linearisation: :class:`~graphopt.linear.assembly.Assembler` and the
  λ-free products of ``products.py``;
* *Schur reduction*, once per λ: :class:`~graphopt.linear.schur.SchurComplement`, one
  strategy per W class — or, for a matrix-free solver, the products of
  :class:`~graphopt.linear.implicit.ImplicitSchur` (``S`` is never formed, nor its pattern).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

import graphopt.linear.products as products
from graphopt.linear.assembly import Assembler, Assembly, GroupArrays
from graphopt.linear.implicit import ImplicitSchur, SchurOperator
from graphopt.linear.schur import SchurComplement
from graphopt.linear.schur_config import SchurConfig
from graphopt.linear.single_block import SingleBlockAssembler
from graphopt.linear.structure import BlockIndex, Positions

if TYPE_CHECKING:
    from graphopt.storage import EdgeGroup, VertexStore

#: The default configuration, shared (frozen): its cost model's checks cost 20 us a build.
_DEFAULT_CONFIG = SchurConfig()


class LinearSystem:
    """Structure, assembly and Schur reduction of the normal equations.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
        config: How ``W V⁻¹ Wᵀ`` is formed (default: the cheapest per W class).
        matrix_free: Whether the solver only needs products with ``S`` (see
            :class:`~graphopt.linear.structure.BlockIndex`): then neither ``S``'s fill nor a
            Schur strategy is built, and :meth:`reduce` hands over a
            :class:`~graphopt.linear.implicit.SchurOperator`. A callable decides from the
            block index.
        u_order: Chooses the U blocks' numbering (see
            :class:`~graphopt.linear.structure.BlockIndex`; a linear solver's ``block_order``).

    Attributes:
        index: The block index (U/V/W blocks, numbering, pattern).
        assembler: The edge groups' terms.
        reduction: The Schur strategies (``None`` when matrix-free).
        implicit: The implicit products (``None`` unless matrix-free).
        matrix_free: Whether the system is matrix-free.
        n: Size of the reduced system.
        udims: ``(n_ublocks,)`` dimension of every U block.
        pattern: The reduced matrix's CSC pattern (both triangles); ``H_uu``'s when
            matrix-free.
        schur: Whether there is anything to eliminate (a V class).

    Raises:
        GraphError: if an edge joins two different marginalised vertices.
        ValueError: if a forced dense strategy exceeds its limit.
    """

    def __init__(self, stores: list[VertexStore], groups: list[EdgeGroup], positions: Positions,
                 config: SchurConfig | None = None,
                 matrix_free: bool | Callable[[BlockIndex], bool] = False,
                 u_order: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None
                 ) -> None:
        self.config = config if config is not None else _DEFAULT_CONFIG
        self.index = BlockIndex(stores, groups, positions, self.config.cost.spectral_max,
                                matrix_free, u_order)
        self.matrix_free = self.index.matrix_free
        # One free vertex, nothing to eliminate: dense products (single_block.py).
        self.assembler: Assembler | SingleBlockAssembler = (
            SingleBlockAssembler.of(self.index) or Assembler(self.index, self.config.cost))
        self.reduction = None if self.matrix_free else SchurComplement(self.index, self.config)
        self.implicit = ImplicitSchur(self.index) if self.matrix_free else None
        self.n = self.index.n
        self.udims = self.index.udims
        self.pattern = self.index.pattern.csc
        self.schur = bool(self.index.vclasses)
        self._identity: tuple[np.ndarray, list[np.ndarray]] | None = None

    def assemble(self, jacobians: GroupArrays, weighted: GroupArrays,
                 weighted_errors: list[np.ndarray]) -> Assembly:
        """The numbers of one linearisation (:meth:`Assembler.assemble`).

        Args:
            jacobians: The Jacobians, per group and position.
            weighted: ``ρ'ΩJ``, per group and position.
            weighted_errors: ``ρ'Ωe``, per group.
        """
        return self.assembler.assemble(jacobians, weighted, weighted_errors)

    @staticmethod
    def is_finite(asm: Assembly) -> bool:
        """See :func:`~graphopt.linear.products.is_finite`.

        Args:
            asm: The assembled system.
        """
        return products.is_finite(asm)

    def damping(self, asm: Assembly, diagonal: bool) -> tuple[np.ndarray, list[np.ndarray]]:
        """See :func:`~graphopt.linear.products.damping`.

        Args:
            asm: The assembled system.
            diagonal: ``diag(H)`` (clipped) instead of the identity.
        """
        if diagonal:
            return products.damping(self.index, asm, True)
        if self._identity is None:  # the identity: the same arrays every time (read-only)
            du, dv = products.damping(self.index, asm, False)
            for a in (du, *dv):
                a.flags.writeable = False
            self._identity = du, dv
        return self._identity[0], list(self._identity[1])

    def max_diagonal(self, asm: Assembly) -> float:
        """See :func:`~graphopt.linear.products.max_diagonal`.

        Args:
            asm: The assembled system.
        """
        return products.max_diagonal(self.index, asm)

    def reduce(self, asm: Assembly, lam: float,
               damp: tuple[np.ndarray, list[np.ndarray]] | None = None
               ) -> tuple[np.ndarray | SchurOperator, np.ndarray, list[np.ndarray]]:
        """See :meth:`SchurComplement.reduce`: ``(s_data, rhs, vinv)``; when matrix-free,
        ``S`` is a :class:`~graphopt.linear.implicit.SchurOperator` instead of its data.

        Args:
            asm: The assembled system.
            lam: Levenberg damping (0 for none).
            damp: The diagonal ``D`` from :meth:`damping` (``None``: the identity).

        Raises:
            NotPositiveDefiniteError: if a V block is not positive definite.
        """
        if self.implicit is not None:
            op = self.implicit.operator(asm, lam, damp)
            return op, op.rhs, op.vinv
        assert self.reduction is not None
        return self.reduction.reduce(asm, lam, damp)

    def back_substitute(self, asm: Assembly, du: np.ndarray, vinv: list[np.ndarray]
                        ) -> list[np.ndarray]:
        """See :func:`~graphopt.linear.products.back_substitute`.

        Args:
            asm: The assembled system.
            du: Solution of the reduced system.
            vinv: Inverted damped V blocks per class.
        """
        return products.back_substitute(self.index, asm, du, vinv)

    def hessian_product(self, asm: Assembly, xu: np.ndarray, xv: list[np.ndarray]
                        ) -> tuple[np.ndarray, list[np.ndarray]]:
        """See :func:`~graphopt.linear.products.hessian_product`.

        Args:
            asm: The assembled system.
            xu: U part of the vector.
            xv: V parts per class.
        """
        return products.hessian_product(self.index, asm, xu, xv)

    def wt_product(self, asm: Assembly, k: int, xu: np.ndarray) -> np.ndarray:
        """See :func:`~graphopt.linear.products.wt_product`.

        Args:
            asm: The assembled system.
            k: The W class.
            xu: A vector over the U part.
        """
        return products.wt_product(self.index, asm, k, xu)

    def y_transposed(self, asm: Assembly, vinv: list[np.ndarray]) -> list[np.ndarray]:
        """``Yᵀ = V⁻¹ Wᵀ`` per W class, ``(n, dv, du)`` each (for marginal covariances).

        Args:
            asm: The assembled system.
            vinv: Inverted V blocks per class (from :meth:`reduce`).
        """
        return [products.class_y_transposed(self.index, asm, vinv, k)
                for k in range(len(self.index.wclasses))]
