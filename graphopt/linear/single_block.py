"""Assembly of a system with one free vertex and nothing to eliminate: a few dense products.

A motion-only BA (one pose, its map points fixed), ORB-SLAM's ``OptimizeSim3`` (one Sim(3),
fixed points) or a pose tracked against a fixed map: ``H`` is one ``d × d`` block and every
edge term is ``J_aᵀ ρ'Ω J_b`` on it. :class:`~graphopt.linear.assembly.Assembler`'s sparse
contractions and scatter maps would cost more to build than such a problem takes to solve
(a 100-match motion-only BA: about 120 µs of set-up per ``initialize_optimization`` and 14 µs
an iteration); here a term is one ``(m·r, d)ᵀ × (m·r, d)`` product.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graphopt.linear.assembly import Assembly, GroupArrays

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex

#: Per edge group: the ``(left, right, edges)`` Hessian terms (``left <= right``) and the
#: ``(position, edges)`` gradient terms; ``edges`` ``None`` means all of the group's.
_Terms = tuple[list[tuple[int, int, np.ndarray | None]], list[tuple[int, np.ndarray | None]]]


class SingleBlockAssembler:
    """The assembler of a block index with one U block, no V class and a formed ``S``.

    Use :meth:`of`, which returns ``None`` for any other index.

    Args:
        index: The block index.
        terms: Per group, its terms (see :meth:`of`).

    Attributes:
        jw: Always ``None`` (the system is not matrix-free).
        u_gram_terms: Always 0 (no gathered Gram products).
    """

    jw = None
    u_gram_terms = 0

    def __init__(self, index: BlockIndex, terms: list[_Terms]) -> None:
        self.index = index
        self.terms = terms
        self.d = int(index.n)

    @classmethod
    def of(cls, index: BlockIndex) -> SingleBlockAssembler | None:
        """The single-block assembler of ``index``, or ``None`` if it has more than one U
        block, a V class, or is matrix-free.

        Args:
            index: The block index.
        """
        if index.n_ublocks != 1 or index.vclasses or index.matrix_free:
            return None
        d = int(index.n)
        csc = index.pattern.csc
        if csc.nnz != d * d:  # the one block's pattern is full: data in column-major order
            return None
        terms: list[_Terms] = []
        for gi, g in enumerate(index.groups):
            ub, _ = index.blocks_of(gi)
            on = [u >= 0 for u in ub]
            sel = [None if o.all() else np.flatnonzero(o) for o in on]
            hterms = [(a, b, None if sel[a] is None and sel[b] is None
                       else np.flatnonzero(on[a] & on[b]))
                      for a in range(g.k) for b in range(a, g.k) if (on[a] & on[b]).any()]
            gterms = [(a, sel[a]) for a in range(g.k) if on[a].any()]
            terms.append((hterms, gterms))
        return cls(index, terms)

    def assemble(self, jacobians: GroupArrays, weighted: GroupArrays,
                 weighted_errors: list[np.ndarray]) -> Assembly:
        """``JᵀΩJ`` and ``−JᵀΩe`` of every edge group into the one block (see
        :meth:`Assembler.assemble <graphopt.linear.assembly.Assembler.assemble>`).

        Args:
            jacobians: Per group, per position ``(m, e, d)`` (C-contiguous).
            weighted: Per group, per position ``ρ' Ω J`` ``(m, e, d)`` (C-contiguous).
            weighted_errors: Per group ``ρ' Ω e`` ``(m, e)``.
        """
        d = self.d
        ht: np.ndarray | None = None  # Hᵀ: its C order is H's column-major data
        bu: np.ndarray | None = None
        for (hterms, gterms), J, WJ, we in zip(self.terms, jacobians, weighted,
                                               weighted_errors, strict=True):
            for a, b, sel in hterms:
                ja, wjb = J[a], WJ[b]
                if sel is not None:
                    ja, wjb = ja[sel], wjb[sel]
                blk = wjb.reshape(-1, d).T @ ja.reshape(-1, d)  # (J_aᵀ ρ'Ω J_b)ᵀ
                if a != b:  # both positions on the one vertex: the term and its transpose
                    blk += blk.T
                ht = blk if ht is None else ht + blk
            for a, sel in gterms:
                ja, wa = J[a], we
                if sel is not None:
                    ja, wa = ja[sel], wa[sel]
                gb = wa.reshape(-1) @ ja.reshape(-1, d)
                bu = gb if bu is None else bu + gb
        h = np.zeros(d * d) if ht is None else ht.reshape(-1)
        bu = np.zeros(d) if bu is None else np.negative(bu, out=bu)
        return Assembly(h, bu, [], [], [])
