"""Products with the W blocks computed from the per-edge Jacobians, the W blocks never formed.

For a matrix-free (implicit Schur) system, every W term of an edge group — the edges linking
position ``u`` (a U block) to position ``v`` (a V block) — keeps the edge Jacobians ``J_v``
``(q, r, d_v)`` and ``ρ'ΩJ_u`` ``(q, r, d_u)`` instead of the summed blocks
``Wᵀ_w = Σ_{e ∈ w} J_v,eᵀ ρ'Ω J_u,e``. Then, per edge,

* ``Wᵀx``: ``t_e = ρ'ΩJ_u,e x_u(e)`` (a BSR product whose data is the ``ρ'ΩJ_u`` array as it
  is, one ``(r, d_u)`` block per block row), then ``y_v = Σ_e J_v,eᵀ t_e`` (an
  :class:`~graphopt.linear.structure.EdgeSums` or the V term's contraction);
* ``Wz``: ``s_e = J_v,e z_v(e)`` (BSR over ``J_v``), then ``Σ_e (ρ'ΩJ_u,e)ᵀ s_e`` per U block;

``r·(d_u + d_v)`` multiply-adds each way per edge (24 for BAL) against ``d_u·d_v`` (27) per W
block. Repeated pairs (two edges on the same U and V blocks, in one or several terms) sum
correctly in these products; only the Schur-Jacobi diagonal ``Σ_w W_w V⁻¹ W_wᵀ`` needs the
pairs' sums, which :meth:`JacobianProducts.schur_diagonal` forms for the repeated pairs only.
The index kept per edge is its U and V block (``int32``) and the sums' index, shared with the
gradient's sums and the V term's contraction where they are the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.linear.block_ops import EdgeContraction
from graphopt.linear.structure import EdgeSums

try:  # SciPy's BSR kernel; it accumulates into a given output array.
    from scipy.sparse._sparsetools import bsr_matvec as _bsr_matvec
except ImportError:  # pragma: no cover - private module: the public product below
    _bsr_matvec = None

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex

#: Edges per chunk of the Schur-Jacobi sums and of :meth:`JacobianProducts.class_wt`.
CHUNK = 8192


def _bsr_product(n_rows: int, n_cols: int, r: int, c: int, indptr: np.ndarray,
                 cols: np.ndarray, data: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``A x`` for a BSR matrix of one ``(r, c)`` block per block row (``data`` as it is)."""
    x = np.ascontiguousarray(x, dtype=float).reshape(-1)
    if _bsr_matvec is not None and cols.dtype == indptr.dtype:
        out = np.zeros(n_rows * r)
        _bsr_matvec(n_rows, n_cols, r, c, indptr, cols, data.reshape(-1), x, out)
        return out
    a = sp.bsr_matrix((data, cols, indptr), shape=(n_rows * r, n_cols * c))  # pragma: no cover
    return a @ x  # pragma: no cover


@dataclass
class WTerm:
    """The edges of one group linking position ``u_pos`` (U) to ``v_pos`` (V).

    Args:
        group: The edge group.
        v_pos: Position of the V vertex.
        u_pos: Position of the U vertex.
        wclass: The W class.
        sel: The group's edges of the term, or ``None`` for all of them.
        ucol: ``(q,)`` U block of every edge within the class's store (``int32`` where it fits).
        vrow: ``(q,)`` V block of every edge within the V class (same type).
        indptr: ``arange(q + 1)``: one block per row of the BSR products (shared).
        to_u: ``Σ_e Aᵀ_e B_e`` into the store's U blocks (target ``ucol``).
        to_v: The same into the V class's blocks (target ``vrow``).
        repeated: Sorted edges (within the term) whose pair has other edges.
    """

    group: int
    v_pos: int
    u_pos: int
    wclass: int
    sel: np.ndarray | None
    ucol: np.ndarray
    vrow: np.ndarray
    indptr: np.ndarray
    to_u: EdgeSums | EdgeContraction
    to_v: EdgeSums | EdgeContraction
    repeated: np.ndarray | None = None


@dataclass
class _Repeated:
    """The repeated pairs of one W class: their edges sorted by pair.

    Args:
        term: ``(p,)`` term of every edge.
        edge: ``(p,)`` edge within its term.
        start: ``(n_pairs,)`` first of every pair's edges.
        ucol: ``(n_pairs,)`` U block (within the store) of every pair.
        vrow: ``(n_pairs,)`` V block of every pair.
    """

    term: np.ndarray
    edge: np.ndarray
    start: np.ndarray
    ucol: np.ndarray
    vrow: np.ndarray


class JacobianW:
    """The W terms of every edge group, built once (matrix-free systems only).

    Args:
        index: The block index.

    Attributes:
        terms: The W terms, in the order of :meth:`add`.
        n_u: Per W class, U blocks of its store.
        ub0: Per W class, the store's first global U block.
    """

    def __init__(self, index: BlockIndex) -> None:
        self.index = index
        self.terms: list[WTerm] = []
        self.n_u: list[int] = []
        self.ub0: list[int] = []
        for wc in index.wclasses:
            ub = np.flatnonzero(index.ustore == wc.ustore)  # a store's U blocks are contiguous
            self.ub0.append(int(ub[0]))
            self.n_u.append(len(ub))
        self._repeated: list[_Repeated | None] = []

    def add(self, gi: int, v_pos: int, u_pos: int, sel: np.ndarray, m: int, r: int,
            indptr: np.ndarray, to_u: EdgeSums | EdgeContraction | None = None,
            to_v: EdgeSums | EdgeContraction | None = None) -> WTerm:
        """Add the W term of positions ``(v_pos, u_pos)`` of group ``gi`` over edges ``sel``.

        Args:
            gi: The group.
            v_pos: Position of the V vertices.
            u_pos: Position of the U vertices.
            sel: Sorted edges of the term.
            m: Edges of the group.
            r: Jacobian rows.
            indptr: ``arange(m·r + 1)`` (prefixes are used; shared).
            to_u: Sums over all ``m`` edges into the store's U blocks in order, to share.
            to_v: Sums over all ``m`` edges into the V class's blocks in order, to share.
        """
        ix = self.index
        (us, uslots), (vs, vslots) = ix.positions[gi][u_pos], ix.positions[gi][v_pos]
        k = ix.wclass_of[(us, ix.vclass_of_store[vs])]
        ucol = ix.ublock[us][uslots[sel]] - self.ub0[k]
        vrow = ix.vblock[vs][vslots[sel]]
        q = len(sel)
        n_v = len(ix.vclasses[ix.vclass_of_store[vs]].slots)
        idx_t = indptr.dtype if max(self.n_u[k], n_v, q + 1) < 2**31 else np.int64
        ucol, vrow = ucol.astype(idx_t), vrow.astype(idx_t)
        whole = q == m
        ptr = indptr[:q + 1] if indptr.dtype == idx_t else np.arange(q + 1, dtype=idx_t)
        # Sums over the term's rows share the pointers when their index type matches.
        sums_t = np.int32 if max(self.n_u[k], n_v, q * r) < 2**31 else np.int64
        sptr = indptr[:q * r + 1] if indptr.dtype == sums_t else None
        term = WTerm(gi, v_pos, u_pos, k, None if whole else sel, ucol, vrow, ptr,
                     to_u if whole and to_u is not None
                     else EdgeSums(ucol, self.n_u[k], r, indptr=sptr),
                     to_v if whole and to_v is not None else EdgeSums(vrow, n_v, r, indptr=sptr))
        self.terms.append(term)
        return term

    def finish(self) -> None:
        """Find the repeated pairs of every W class (after the last :meth:`add`)."""
        ix = self.index
        for k, wc in enumerate(ix.wclasses):
            own = [ti for ti, t in enumerate(self.terms) if t.wclass == k]
            nb = max(ix.n_ublocks, 1)
            keys = wc.keys
            widx = [np.searchsorted(keys, self.terms[ti].vrow.astype(np.int64) * nb
                                    + self.terms[ti].ucol + self.ub0[k]) for ti in own]
            count = np.zeros(len(keys), dtype=np.int64)
            for w in widx:
                count += np.bincount(w, minlength=len(keys))
            parts = []
            for ti, w in zip(own, widx, strict=True):
                rep = np.flatnonzero(count[w] > 1)
                self.terms[ti].repeated = rep if len(rep) else None
                if len(rep):
                    parts.append((np.full(len(rep), ti), rep, w[rep]))
            if not parts:
                self._repeated.append(None)
                continue
            term, edge, w = (np.concatenate(p) for p in zip(*parts, strict=True))
            order = np.argsort(w, kind="stable")
            term, edge, w = term[order], edge[order], w[order]
            start = np.flatnonzero(np.r_[True, w[1:] != w[:-1]])
            tf, ef = term[start], edge[start]
            pu = np.empty(len(start), dtype=np.int64)
            pv = np.empty(len(start), dtype=np.int64)
            for ti in np.unique(tf).tolist():  # a loop over terms, not pairs
                at = tf == ti
                pu[at] = self.terms[ti].ucol[ef[at]]
                pv[at] = self.terms[ti].vrow[ef[at]]
            self._repeated.append(_Repeated(term, edge, start, pu, pv))

    def bind(self, arrays: list[tuple[np.ndarray, np.ndarray]]) -> JacobianProducts:
        """The products of one assembly.

        Args:
            arrays: Per term, ``(J_v (q, r, d_v), ρ'ΩJ_u (q, r, d_u))``, C-contiguous.
        """
        return JacobianProducts(self, arrays)


class JacobianProducts:
    """``Wᵀx``, ``Wz`` and the Schur-Jacobi sums of one assembly, from its Jacobians.

    Args:
        structure: The W terms.
        arrays: Per term, ``(J_v, ρ'ΩJ_u)``.
    """

    def __init__(self, structure: JacobianW, arrays: list[tuple[np.ndarray, np.ndarray]]
                 ) -> None:
        self.structure, self.arrays = structure, arrays

    def _vdims(self) -> list[tuple[int, int]]:
        return [(len(c.slots), c.dim) for c in self.structure.index.vclasses]

    def wt_product(self, xu: np.ndarray, wclass: int | None = None) -> list[np.ndarray]:
        """``Wᵀ xu`` per V class, ``(n_v, d_v)`` each.

        Args:
            xu: ``(n,)`` a vector over the U part.
            wclass: Only this W class's terms (``None``: all).
        """
        st = self.structure
        ix = st.index
        y = [np.zeros(s) for s in self._vdims()]
        for t, (jv, wju) in zip(st.terms, self.arrays, strict=True):
            if wclass is not None and t.wclass != wclass:
                continue
            wc = ix.wclasses[t.wclass]
            q, r, du = wju.shape
            tv = _bsr_product(q, st.n_u[t.wclass], r, du, t.indptr, t.ucol, wju, xu[wc.ucols])
            y[wc.vclass] += t.to_v(jv, tv.reshape(q, r, 1)).reshape(y[wc.vclass].shape)
        return y

    def w_product(self, z: list[np.ndarray], out: np.ndarray, sign: float = 1.0) -> None:
        """``out += sign · W z`` (``z`` per V class, ``(n_v, d_v)``).

        Args:
            z: Per V class, a vector over its blocks.
            out: ``(n,)`` a vector over the U part (updated).
            sign: ``1`` or ``−1``.
        """
        st = self.structure
        ix = st.index
        for t, (jv, wju) in zip(st.terms, self.arrays, strict=True):
            wc = ix.wclasses[t.wclass]
            q, r, dv = jv.shape
            n_v = len(ix.vclasses[wc.vclass].slots)
            s = _bsr_product(q, n_v, r, dv, t.indptr, t.vrow, jv, z[wc.vclass])
            part = t.to_u(wju, s.reshape(q, r, 1)).reshape(-1)
            if sign < 0:
                out[wc.ucols] -= part
            else:
                out[wc.ucols] += part

    @staticmethod
    def _edge_wt(jv: np.ndarray, wju: np.ndarray) -> np.ndarray:
        """Per-edge ``Wᵀ_e = J_vᵀ ρ'ΩJ_u``, ``(q, d_v, d_u)``."""
        return np.matmul(np.swapaxes(jv, 1, 2), wju)

    def schur_diagonal(self, vinv: list[np.ndarray]) -> list[np.ndarray]:
        """``Σ_w W_w V⁻¹ W_wᵀ`` per U block of every W class's store, ``(n_u, d_u, d_u)``.

        Per chunk of edges of a term, the edges' own ``Wᵀ_e`` (those of repeated pairs left
        out), ``Wᵀ_eᵀ V⁻¹ Wᵀ_e``, summed into their U blocks by a 0/1 sparse product; then the
        repeated pairs, their edges' ``Wᵀ_e`` summed per pair first.

        Args:
            vinv: Per V class, the inverted damped V blocks.
        """
        st = self.structure
        ix = st.index
        acc = [np.zeros((st.n_u[k], wc.du * wc.du)) for k, wc in enumerate(ix.wclasses)]
        for t, (jv, wju) in zip(st.terms, self.arrays, strict=True):
            vi = vinv[ix.wclasses[t.wclass].vclass]
            for c0 in range(0, len(jv), CHUNK):
                c1 = min(c0 + CHUNK, len(jv))
                wte = self._edge_wt(jv[c0:c1], wju[c0:c1])
                if t.repeated is not None:
                    rep = t.repeated[(t.repeated >= c0) & (t.repeated < c1)]
                    wte[rep - c0] = 0.0
                self._add_wvw(acc[t.wclass], wte, vi, t.vrow[c0:c1], t.ucol[c0:c1])
        for k, rp in enumerate(st._repeated):
            if rp is None:
                continue
            wc = ix.wclasses[k]
            wte = np.empty((len(rp.term), wc.dv, wc.du))
            for ti in np.unique(rp.term):
                at = np.flatnonzero(rp.term == ti)
                jv, wju = self.arrays[ti]
                wte[at] = self._edge_wt(jv[rp.edge[at]], wju[rp.edge[at]])
            pairs = np.add.reduceat(wte, rp.start, axis=0)
            self._add_wvw(acc[k], pairs, vinv[wc.vclass], rp.vrow, rp.ucol)
        return [a.reshape(len(a), wc.du, wc.du) for a, wc in zip(acc, ix.wclasses, strict=True)]

    @staticmethod
    def _add_wvw(acc: np.ndarray, wt: np.ndarray, vinv: np.ndarray, vrow: np.ndarray,
                 ucol: np.ndarray) -> None:
        """``acc[ucol] += Wᵀᵀ V⁻¹[vrow] Wᵀ`` for a batch of blocks ``wt`` ``(c, d_v, d_u)``."""
        c = len(wt)
        yt = np.matmul(np.take(vinv, vrow, axis=0), wt)
        blocks = np.matmul(np.swapaxes(wt, 1, 2), yt).reshape(c, -1)
        scatter = sp.csr_matrix((np.ones(c), (ucol, np.arange(c))), shape=(len(acc), c))
        acc += scatter @ blocks

    def class_wt(self, k: int) -> np.ndarray:
        """The W blocks of class ``k`` formed explicitly, ``(n_w, d_v, d_u)`` (for marginal
        covariances, which need ``V⁻¹Wᵀ`` per block).

        Args:
            k: The W class.
        """
        st = self.structure
        ix = st.index
        wc = ix.wclasses[k]
        keys = wc.keys
        nb = max(ix.n_ublocks, 1)
        out = np.zeros((len(keys), wc.dv, wc.du))
        for t, (jv, wju) in zip(st.terms, self.arrays, strict=True):
            if t.wclass != k:
                continue
            for c0 in range(0, len(jv), CHUNK):
                c1 = min(c0 + CHUNK, len(jv))
                w = np.searchsorted(keys, t.vrow[c0:c1].astype(np.int64) * nb
                                    + t.ucol[c0:c1] + st.ub0[k])
                np.add.at(out, w, self._edge_wt(jv[c0:c1], wju[c0:c1]))
        return out
