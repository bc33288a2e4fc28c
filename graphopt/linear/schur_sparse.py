"""``W V⁻¹ Wᵀ`` by sparse pair contractions.

With ``Yᵀ = V⁻¹Wᵀ`` per W block, every block ``(u1, u2)`` of ``S`` loses ``Σ Y_w1 W_w2ᵀ`` over
the pairs of W blocks of ``u1`` and ``u2`` that share a V block. The sum is one constant
:class:`~graphopt.linear.block_ops.BlockContraction` (a gather of ``Yᵀ`` rows and one sparse
product); the pairs of a block with itself are an
:class:`~graphopt.linear.block_ops.EdgeContraction` (no gather). This is also the only way to
couple two W classes of one V class (``k1 != k2``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import scipy.sparse as sp

from graphopt.linear.block_ops import BlockContraction, EdgeContraction
from graphopt.linear.indexing import unique_ints
from graphopt.linear.products import w_product
from graphopt.linear.schur_config import SchurCostModel
from graphopt.linear.schur_strategy import SchurPlan, SchurStrategy, VFactors

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex


class SparsePairs(SchurStrategy):
    """``Σ Y_w1 W_w2ᵀ`` over pairs of W blocks of classes ``k1``, ``k2`` that share a V block.

    For a class with itself this is the class's whole share: the pairs ``(w, w)`` and the
    planned ones (both triangles), and ``W V⁻¹ b_v`` in the right-hand side. For two classes
    it is their coupling only (the right-hand side belongs to each class).

    Args:
        index: The block index.
        plan: The classes and their pairs.

    Attributes:
        k2: The second class (``k`` for a class with itself).
    """

    name = "sparse"

    def __init__(self, index: BlockIndex, plan: SparsePlan) -> None:
        super().__init__(index, plan)
        k1, self.k2 = plan.k, plan.k if plan.k2 is None else plan.k2
        w1, w2 = plan.w1, plan.w2
        nb = max(index.n_ublocks, 1)
        c1, c2 = index.wclasses[k1], index.wclasses[self.k2]
        # Terms (contraction of Yᵀ of k1 with Wᵀ of k2, its sum into S's data).
        self._terms: list[tuple[BlockContraction | EdgeContraction, sp.csr_matrix]] = []
        if plan.k2 is None:  # the pairs (w, w): diagonal blocks, one block with itself
            uniq, inv = unique_ints(c1.ublock, nb, True)
            nw = len(c1.ublock)
            self._terms.append((EdgeContraction(np.arange(nw), inv, len(uniq), nw, c1.dv, c1.du),
                                index.pattern.to_s(uniq, uniq)))
        if len(w1):
            uniq, inv = unique_ints(c1.ublock[w1] * nb + c2.ublock[w2], nb * nb, True)
            # S_t −= Σ Y_w1 W_w2ᵀ = Σ (Yᵀ_w1)ᵀ Wᵀ_w2: A = Yᵀ (dv, du1), B = Wᵀ (dv, du2).
            con = BlockContraction(inv, w1, w2, len(uniq), c1.dv, c1.du, len(c2.ublock))
            self._terms.append((con, index.pattern.to_s(uniq // nb, uniq % nb)))

    def reduce_into(self, s: np.ndarray, rhs: np.ndarray, asm: Assembly,
                    factors: VFactors) -> None:
        """The pair contractions with ``Yᵀ``; ``W (V⁻¹b_v)`` for a class with itself.

        Arguments as in :meth:`SchurStrategy.reduce_into`.
        """
        if self.k2 == self.k:
            wc = self.index.wclasses[self.k]
            y = factors.v_inv_b(wc.vclass)[wc.vblock]
            rhs[wc.rhs_dest] -= w_product(self.index, asm, self.k, y)
        yt = factors.y_transposed(self.k)
        for con, to_s in self._terms:
            s -= to_s @ con(yt, asm.wt[self.k2]).reshape(-1)


@dataclass(frozen=True)
class SparsePlan(SchurPlan):
    """Sparse pairs for W class ``k`` (with itself, or with class ``k2`` of its V class).

    Args:
        k: The W class.
        w1: First W blocks of the pairs sharing a V block (``u(w1) < u(w2)`` for a class
            with itself) ...
        w2: ... and second.
        seconds: Modelled seconds per reduction.
        k2: The second class, or ``None``: ``k`` with itself.
    """

    strategy: ClassVar[type[SchurStrategy]] = SparsePairs
    k: int
    w1: np.ndarray
    w2: np.ndarray
    seconds: float
    k2: int | None = None

    @classmethod
    def plan(cls, index: BlockIndex, k: int, pairs: tuple[np.ndarray, np.ndarray],
             cost: SchurCostModel, k2: int | None = None) -> SparsePlan:
        """Plan W class ``k`` with itself, or its coupling with class ``k2``.

        Args:
            index: The block index.
            k: The W class.
            pairs: The pairs of W blocks sharing a V block (:meth:`BlockIndex.w_pairs`).
            cost: The cost model.
            k2: The second class of a coupling.
        """
        w1, w2 = pairs
        c = index.wclasses[k]
        nw, n_cross, dv, du = len(c.ublock), len(w1), c.dv, c.du
        if k2 is not None:  # the gather of Yᵀ rows and the pairs' product
            du2 = index.wclasses[k2].du
            return cls(k, w1, w2, (cost.gather * n_cross * dv * du
                                   + cost.sparse_mac * n_cross * dv * du * du2), k2)
        seconds = (cost.gather * n_cross * dv * du
                   + cost.sparse_mac * (n_cross + nw) * dv * du * du
                   + cost.sparse_mac * nw * dv * du  # the right-hand side
                   + cost.small_mac * nw * dv * dv * du)  # Yᵀ = V⁻¹Wᵀ
        return cls(k, w1, w2, seconds)
