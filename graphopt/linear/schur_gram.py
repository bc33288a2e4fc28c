"""``W V⁻¹ Wᵀ`` and ``W V⁻¹ b_v`` of a W class through ``Z = L⁻¹Wᵀ`` (``V = LLᵀ``) and
gathered Gram products.

``Z`` is formed for every W block by one constant-structure CSR product (the entries of
``L⁻¹`` times the W array as it is) into a reused buffer. Every block of ``S`` is then a sum of
``Z_aᵀ Z_b`` over the W blocks ``a``, ``b`` of its two U blocks that share a V block (a U
block with itself on the diagonal), computed per block of ``S`` by
:class:`~graphopt.linear.gathered_gram.GatheredGram`; the right-hand side takes
``Z_wᵀ L⁻¹b_v`` per W block. This suits few U blocks with many W blocks each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from graphopt.linear.block_ops import csr_product_into
from graphopt.linear.gathered_gram import GatheredGram
from graphopt.linear.indexing import unique_ints
from graphopt.linear.schur_config import SchurCostModel
from graphopt.linear.schur_strategy import SchurPlan, SchurStrategy, VFactors

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex


class GramProducts(SchurStrategy):
    """The Gram products of one W class, with their CSR structures and buffers.

    Args:
        index: The block index.
        plan: The planned Gram.
    """

    name = "gram"

    def __init__(self, index: BlockIndex, plan: GramPlan) -> None:
        super().__init__(index, plan)
        self.gram = plan.gram
        self.gram.build()  # (planned: built once chosen)
        c = index.wclasses[self.k]
        nb = max(index.n_ublocks, 1)
        dv, du, nw = c.dv, c.du, len(c.ublock)
        # CSR rows (W block, row i of Z) → entries j ≤ i of L⁻¹ times rows (W block, j) of Wᵀ.
        ti, tj = np.tril_indices(dv)
        out_row = (np.arange(nw)[:, None] * dv + ti).ravel()
        idx_t = np.int32 if nw * dv < 2**31 else np.int64
        self._indptr = np.searchsorted(out_row, np.arange(nw * dv + 1)).astype(idx_t)
        self._indices = (np.arange(nw)[:, None] * dv + tj).ravel().astype(idx_t)
        self._lidx = (c.vblock[:, None] * dv * dv + ti * dv + tj).ravel()  # into L⁻¹
        self._z = np.zeros(nw * dv * du)  # Z, one block after the other
        self._results = np.zeros((plan.gram.n_out, du, du))
        tk = plan.keys[plan.gram.targets]
        self._to_s = index.pattern.to_s(tk // nb, tk % nb)  # both triangles
        # Σ_w Z_wᵀ (L⁻¹b_v)[v_w] per U block is one product of a CSC matrix (rows: U blocks of
        # the class; column (w, i) holds entry i of L⁻¹b_v of w's V block) with Z as it is.
        _, inv = unique_ints(c.ublock, nb, True)
        self._rhs_indptr = np.arange(nw * dv + 1, dtype=idx_t)
        self._rhs_indices = np.repeat(inv, dv).astype(idx_t)
        self._rhs_lidx = (c.vblock[:, None] * dv + np.arange(dv)).ravel()  # into L⁻¹b_v

    def reduce_into(self, s: np.ndarray, rhs: np.ndarray, asm: Assembly,
                    factors: VFactors) -> None:
        """``Z = L⁻¹Wᵀ``, the Gram products ``Z_aᵀZ_b`` into S and ``Z_wᵀ L⁻¹b_v``.

        Arguments as in :meth:`SchurStrategy.reduce_into`.
        """
        wc = self.index.wclasses[self.k]
        dv, du, nw = wc.dv, wc.du, len(wc.ublock)
        lvals = np.take(factors.linv[wc.vclass].reshape(-1), self._lidx)
        wflat = np.ascontiguousarray(asm.wt[self.k]).reshape(-1)
        csr_product_into(nw * dv, nw * dv, du, self._indptr, self._indices, lvals, wflat,
                         self._z)  # Z = L⁻¹Wᵀ
        self.gram(self._z.reshape(nw, dv * du), self._results)
        s -= self._to_s @ self._results.reshape(-1)
        n_u = len(wc.rhs_dest)
        zl = np.empty(n_u * du)
        csr_product_into(n_u, nw * dv, du, self._rhs_indptr, self._rhs_indices,
                         np.take(factors.l_inv_b(wc.vclass), self._rhs_lidx), self._z, zl,
                         csc=True)
        rhs[wc.rhs_dest] -= zl.reshape(n_u, du)  # Σ_w Z_wᵀ L⁻¹b_v per U block


@dataclass(frozen=True)
class GramPlan(SchurPlan):
    """Gram products for W class ``k``.

    Args:
        k: The W class.
        gram: Sums ``Z_aᵀ Z_b`` per block of ``S`` (diagonal pairs ``(w, w)`` first).
        keys: ``u1 · n_ublocks + u2`` of every target of ``gram``.
        seconds: Modelled seconds per reduction.
    """

    strategy: ClassVar[type[SchurStrategy]] = GramProducts
    k: int
    gram: GatheredGram
    keys: np.ndarray
    seconds: float

    @classmethod
    def plan(cls, index: BlockIndex, k: int, pairs: tuple[np.ndarray, np.ndarray],
             cost: SchurCostModel, beat: float = math.inf) -> GramPlan | None:
        """The Gram of W class ``k`` and its modelled cost; ``None`` when even a lower bound
        of that cost is not below ``beat`` (nothing is built then).

        Args:
            index: The block index.
            k: The W class.
            pairs: Its pairs of W blocks sharing a V block (:meth:`BlockIndex.w_pairs`).
            cost: The cost model.
            beat: The cost to beat.
        """
        w1, w2 = pairs
        c = index.wclasses[k]
        nw, dv, du = len(c.ublock), c.dv, c.du
        # Without padding or overheads: a lower bound that spares building a hopeless Gram.
        bound = (cost.z * nw * dv * du
                 + cost.gram_gather * (nw + 2 * len(w1)) * dv * du
                 + cost.gemm_mac * (nw + len(w1)) * dv * du * du)
        if not nw or bound >= beat:
            return None
        nb = max(index.n_ublocks, 1)
        w = np.arange(nw)
        keys = np.concatenate([c.ublock * (nb + 1), c.ublock[w1] * nb + c.ublock[w2]])
        uniq, inv = unique_ints(keys, nb * nb, True)
        gram = GatheredGram(inv, np.concatenate([w, w1]), np.concatenate([w, w2]), len(uniq),
                            dv, du)
        seconds = cost.z * nw * dv * du + cost.gram_seconds(gram, gram.gathered)
        return cls(k, gram, uniq, seconds)
