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


def group_terms(on: list[np.ndarray]) -> _Terms:
    """One group's Hessian and gradient terms on the one block.

    Args:
        on: Per vertex position, ``(m,)`` whether the edge's vertex there is the free one.
    """
    k = len(on)
    if k == 1 and len(on[0]) and on[0].all():  # unary edges, all on the block (no selection)
        return [(0, 0, None)], [(0, None)]
    sel = [None if o.all() else np.flatnonzero(o) for o in on]
    hterms = [(a, b, None if sel[a] is None and sel[b] is None else np.flatnonzero(on[a] & on[b]))
              for a in range(k) for b in range(a, k) if (on[a] & on[b]).any()]
    return hterms, [(a, sel[a]) for a in range(k) if on[a].any()]


class SingleBlockAssembler:
    """The assembler of a block index with one U block, no V class and a formed ``S``.

    Use :meth:`of`, which returns ``None`` for any other index.

    Args:
        d: The block's dimension.
        terms: Per group, its terms (:func:`group_terms`).

    Attributes:
        jw: Always ``None`` (the system is not matrix-free).
        u_gram_terms: Always 0 (no gathered Gram products).
    """

    jw = None
    u_gram_terms = 0

    def __init__(self, d: int, terms: list[_Terms]) -> None:
        self.terms = terms
        self.d = d

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
        return cls(d, [group_terms([u >= 0 for u in index.blocks_of(gi)[0]])
                       for gi in range(len(index.groups))])

    def assemble(self, jacobians: GroupArrays, weighted: GroupArrays,
                 weighted_errors: list[np.ndarray]) -> Assembly:
        """``JᵀΩJ`` and ``−JᵀΩe`` of every edge group into the one block (see
        :meth:`Assembler.assemble <graphopt.linear.assembly.Assembler.assemble>`).

        Args:
            jacobians: Per group, per position ``(m, e, d)`` (C-contiguous).
            weighted: Per group, per position ``ρ' Ω J`` ``(m, e, d)`` (C-contiguous).
            weighted_errors: Per group ``ρ' Ω e`` ``(m, e)``.
        """
        ht: np.ndarray | None = None  # Hᵀ: its C order is H's column-major data
        bu: np.ndarray | None = None
        for gi, (J, WJ, we) in enumerate(zip(jacobians, weighted, weighted_errors, strict=True)):
            ht, bu = self.add_group(gi, J, WJ, we, ht, bu)
        return self.finish(ht, bu)

    def add_group(self, gi: int, J: tuple[np.ndarray, ...], WJ: tuple[np.ndarray, ...],
                  we: np.ndarray, ht: np.ndarray | None, bu: np.ndarray | None
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Add group ``gi``'s terms to ``Hᵀ`` and ``Jᵀρ'Ωe`` (``None``: nothing yet).

        Args:
            gi: Group index.
            J: Its Jacobians per position ``(m, e, d)`` (C-contiguous).
            WJ: ``ρ' Ω J`` per position.
            we: ``ρ' Ω e`` ``(m, e)``.
            ht: ``Hᵀ`` ``(d, d)`` so far.
            bu: ``Jᵀρ'Ωe`` ``(d,)`` so far.
        """
        d = self.d
        hterms, gterms = self.terms[gi]
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
        return ht, bu

    def finish(self, ht: np.ndarray | None, bu: np.ndarray | None) -> Assembly:
        """The assembly of the summed terms (``b = −Jᵀρ'Ωe``).

        Args:
            ht: ``Hᵀ`` ``(d, d)``, or ``None`` for no term.
            bu: ``Jᵀρ'Ωe`` ``(d,)``, or ``None``.
        """
        d = self.d
        h = np.zeros(d * d) if ht is None else ht.reshape(-1)
        bu = np.zeros(d) if bu is None else np.negative(bu, out=bu)
        return Assembly(h, bu, [], [], [])
