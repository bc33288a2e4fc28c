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
from typing import TYPE_CHECKING

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


@dataclass(frozen=True)
class SparsePlan(SchurPlan):
    """Sparse pairs for W class ``k``.

    Args:
        k: The W class.
        w1: First W blocks of its pairs sharing a V block (``u(w1) < u(w2)``) ...
        w2: ... and second.
        seconds: Modelled seconds per reduction.
    """

    k: int
    w1: np.ndarray
    w2: np.ndarray
    seconds: float

    @classmethod
    def plan(cls, index: BlockIndex, k: int, w1: np.ndarray, w2: np.ndarray,
             cost: SchurCostModel) -> SparsePlan:
        """Plan W class ``k``.

        Args:
            index: The block index.
            k: The W class.
            w1: Its pairs sharing a V block (:meth:`BlockIndex.w_pairs`): first ...
            w2: ... and second blocks.
            cost: The cost model.
        """
        c = index.wclasses[k]
        return cls(k, w1, w2, cost.sparse_seconds(len(c.ublock), len(w1), c.dv, c.du))

    def build(self, index: BlockIndex) -> SparsePairs:
        """See :meth:`SchurPlan.build`.

        Args:
            index: The block index.
        """
        return SparsePairs(index, self.k, self.k, self.w1, self.w2)


class SparsePairs(SchurStrategy):
    """``Σ Y_w1 W_w2ᵀ`` over pairs of W blocks of classes ``k1``, ``k2`` that share a V block.

    For a class with itself (``k1 == k2``) this is the class's whole share: the pairs
    ``(w, w)`` and the given ones (both triangles), and ``W V⁻¹ b_v`` in the right-hand side.
    For two classes it is their coupling only (the right-hand side belongs to each class).

    Args:
        index: The block index.
        k1: A W class.
        k2: A W class of the same V class (``k1 <= k2``).
        w1: Blocks of ``k1`` ...
        w2: ... and of ``k2`` that share a V block (``u(w1) < u(w2)`` when ``k1 == k2``).

    Attributes:
        k2: The second class.
    """

    name = "sparse"

    def __init__(self, index: BlockIndex, k1: int, k2: int, w1: np.ndarray,
                 w2: np.ndarray) -> None:
        self.k, self.k2 = k1, k2
        self.index = index
        nb = max(index.n_ublocks, 1)
        c1, c2 = index.wclasses[k1], index.wclasses[k2]
        # Terms (contraction of Yᵀ of k1 with Wᵀ of k2, its sum into S's data).
        self._terms: list[tuple[BlockContraction | EdgeContraction, sp.csr_matrix]] = []
        if k1 == k2:  # the pairs (w, w): diagonal blocks, one block with itself
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
        """See :meth:`SchurStrategy.reduce_into`.

        Args:
            s: Data of ``S`` (updated).
            rhs: Reduced right-hand side (updated).
            asm: The assembled system.
            factors: The damped V blocks' factors.
        """
        k1, k2 = self.k, self.k2
        if k1 == k2:
            wc = self.index.wclasses[k1]
            y = factors.v_inv_b(wc.vclass)[wc.vblock]
            rhs[wc.rhs_dest] -= w_product(self.index, asm, k1, y)
        yt = factors.y_transposed(k1)
        for con, to_s in self._terms:
            s -= to_s @ con(yt, asm.wt[k2]).reshape(-1)
