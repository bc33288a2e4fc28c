"""The Schur reduction per λ: damp, factorise the V blocks, and let every W class's strategy
subtract its share of ``W V⁻¹ Wᵀ`` and ``W V⁻¹ b_v``.

The strategy of each W class is chosen once, here: forced by :class:`SchurConfig`, or the
cheapest by its :class:`SchurCostModel` (sparse pairs, unless dense panels or, then, Gram
products are modelled strictly cheaper).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graphopt.linear.products import damping
from graphopt.linear.schur_config import SchurConfig
from graphopt.linear.schur_dense import DensePlan
from graphopt.linear.schur_gram import GramPlan
from graphopt.linear.schur_sparse import SparsePairs, SparsePlan
from graphopt.linear.schur_strategy import SchurPlan, SchurStrategy, VFactors

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex


class SchurComplement:
    """The strategies of every W class, and :meth:`reduce`.

    Args:
        index: The block index.
        config: Strategy choice and cost model.

    Attributes:
        strategies: Per W class, its strategy.
        couplings: Sparse pairs between two W classes of one V class.

    Raises:
        ValueError: if a forced dense strategy exceeds ``config.cost.dense_limit``.
    """

    def __init__(self, index: BlockIndex, config: SchurConfig) -> None:
        self.index, self.config = index, config
        strategies: list[SchurStrategy] = []
        self.couplings: list[SparsePairs] = []
        by_pair: list[SchurStrategy] = []  # sparse pairs, by class pair
        for k1, c1 in enumerate(index.wclasses):
            strategies.append(self._plan(k1, index.w_pairs(k1, k1)).build(index))
            if strategies[-1].name == "sparse":
                by_pair.append(strategies[-1])
            for k2 in range(k1 + 1, len(index.wclasses)):
                if index.wclasses[k2].vclass == c1.vclass:
                    pairs = index.w_pairs(k1, k2)
                    if len(pairs[0]):
                        plan = SparsePlan.plan(index, k1, pairs, config.cost, k2)
                        self.couplings.append(SparsePairs(index, plan))
                        by_pair.append(self.couplings[-1])
        self.strategies = tuple(strategies)
        # Where W classes share entries of S, this order (dense, Gram, then sparse pairs)
        # keeps the floating-point order of their sums fixed.
        self._order = [*(t for t in strategies if t.name == "dense"),
                       *(t for t in strategies if t.name == "gram"), *by_pair]

    def _plan(self, k: int, pairs: tuple[np.ndarray, np.ndarray]) -> SchurPlan:
        """The plan for W class ``k`` (``pairs`` of W blocks sharing a V block)."""
        ix, strategy, cost = self.index, self.config.strategy, self.config.cost
        if strategy == "gram":
            plan = GramPlan.plan(ix, k, pairs, cost)
            assert plan is not None  # a W class has W blocks
            return plan
        dense = DensePlan.plan(ix, k, cost) if strategy in ("auto", "dense") else None
        if strategy == "dense":
            assert dense is not None
            if dense.elements > cost.dense_limit:
                raise ValueError(
                    f"Schur strategy 'dense': W class {k}'s panels hold {dense.elements} "
                    f"elements, over SchurCostModel.dense_limit ({cost.dense_limit}); raise "
                    "the limit or use another strategy")
            return dense
        best: SchurPlan = SparsePlan.plan(ix, k, pairs, cost)
        if strategy == "sparse":
            return best
        if (dense is not None and dense.elements <= cost.dense_limit
                and dense.seconds < best.seconds):
            best = dense
        if cost.gram_enabled:
            gram = GramPlan.plan(ix, k, pairs, cost, beat=best.seconds)
            if gram is not None and gram.seconds < best.seconds:
                best = gram
        return best

    def reduce(self, asm: Assembly, lam: float,
               damp: tuple[np.ndarray, list[np.ndarray]] | None = None
               ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """Damp by ``λ D`` and eliminate the V blocks.

        Args:
            asm: The assembled system.
            lam: Levenberg damping (0 for none).
            damp: The diagonal ``D`` as ``(u part, [v parts])``, computed once per assembly by
                :func:`~graphopt.linear.products.damping`; ``None`` for the identity.

        Returns:
            ``(s_data, rhs, vinv)``: the reduced matrix's data, its right-hand side and the
            inverted (damped) V blocks per class.

        Raises:
            NotPositiveDefiniteError: if a V block is not positive definite.
        """
        s = asm.h_data.copy()
        vdamp: list[np.ndarray | None] = [None] * len(asm.v)
        if lam:
            du, dv = damp if damp is not None else damping(self.index, asm, False)
            s[self.index.pattern.diag_pos] += lam * du
            vdamp = [lam * d for d in dv]
        factors = VFactors(self.index, asm, vdamp)
        rhs = asm.bu.copy()
        for t in self._order:
            t.reduce_into(s, rhs, asm, factors)
        return s, rhs, factors.vinv
