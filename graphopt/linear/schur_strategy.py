"""The interface of the Schur strategies, and the per-λ factors of the V blocks they share.

A strategy forms one W class's share of ``W V⁻¹ Wᵀ`` and of ``W V⁻¹ b_v``. It is planned
(with its modelled cost) and built once from the block index; per λ, :meth:`reduce_into`
subtracts both shares from the reduced matrix's data and right-hand side.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from graphopt.linear.block_ops import batched_cholesky_inverses
from graphopt.linear.products import class_y_transposed

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex


class VFactors:
    """The damped V blocks ``V + λD = LLᵀ`` of one λ, and products of them shared by W classes
    (each computed on first use).

    Args:
        index: The block index.
        asm: The assembled system.
        vdamp: Per V class, ``(n, d)`` added to the diagonals, or ``None``.

    Attributes:
        linv: Per V class, ``(n, d, d)`` lower-triangular ``L⁻¹``.
        vinv: Per V class, ``(n, d, d)`` ``(V + λD)⁻¹``.

    Raises:
        NotPositiveDefiniteError: if a V block is not positive definite.
    """

    def __init__(self, index: BlockIndex, asm: Assembly,
                 vdamp: list[np.ndarray | None]) -> None:
        self.index, self.asm = index, asm
        self.linv: list[np.ndarray] = []
        self.vinv: list[np.ndarray] = []
        for vb, d in zip(asm.v, vdamp, strict=True):
            li, vi = batched_cholesky_inverses(vb, d)
            self.linv.append(li)
            self.vinv.append(vi)
        self._lb: dict[int, np.ndarray] = {}
        self._vb: dict[int, np.ndarray] = {}
        self._yt: dict[int, np.ndarray] = {}

    def l_inv_b(self, vc: int) -> np.ndarray:
        """``L⁻¹ b_v`` of V class ``vc``, ``(n, d)``.

        Args:
            vc: The V class.
        """
        return self._times_bv(self._lb, self.linv, vc)

    def v_inv_b(self, vc: int) -> np.ndarray:
        """``V⁻¹ b_v`` of V class ``vc``, ``(n, d)``.

        Args:
            vc: The V class.
        """
        return self._times_bv(self._vb, self.vinv, vc)

    def _times_bv(self, cache: dict[int, np.ndarray], blocks: list[np.ndarray], vc: int
                  ) -> np.ndarray:
        if vc not in cache:
            cache[vc] = np.einsum("nij,nj->ni", blocks[vc], self.asm.bv[vc])
        return cache[vc]

    def y_transposed(self, k: int) -> np.ndarray:
        """``Yᵀ = V⁻¹ Wᵀ`` of W class ``k``, ``(n, dv, du)``.

        Args:
            k: The W class.
        """
        if k not in self._yt:
            self._yt[k] = class_y_transposed(self.index, self.asm, self.vinv, k)
        return self._yt[k]


class SchurStrategy(ABC):
    """One way to subtract a W class's share of the Schur complement, built from the block
    index and its plan (``Strategy(index, plan)``).

    Attributes:
        name: ``"sparse"``, ``"dense"`` or ``"gram"``.
        k: The W class (for the sparse pairs of two classes: the first).
    """

    name: ClassVar[str]

    def __init__(self, index: BlockIndex, plan: SchurPlan) -> None:
        """Build the strategy's index arrays (subclasses).

        Args:
            index: The block index.
            plan: Its plan.
        """
        self.index, self.k = index, plan.k

    @abstractmethod
    def reduce_into(self, s: np.ndarray, rhs: np.ndarray, asm: Assembly,
                    factors: VFactors) -> None:
        """``s −= share of W V⁻¹ Wᵀ`` (in ``S``'s data) and ``rhs −= share of W V⁻¹ b_v``.

        Args:
            s: Data of ``S`` (updated).
            rhs: Reduced right-hand side (updated).
            asm: The assembled system.
            factors: The damped V blocks' factors.
        """


class SchurPlan:
    """A strategy planned for one W class: its modelled cost, before anything is built.

    Attributes:
        k: The W class.
        seconds: Modelled seconds per reduction.
        strategy: The strategy class the plan builds.
    """

    k: int
    seconds: float
    strategy: ClassVar[type[SchurStrategy]]

    def build(self, index: BlockIndex) -> SchurStrategy:
        """The strategy with its index arrays.

        Args:
            index: The block index.
        """
        return self.strategy(index, self)
