"""Assembly of the normal equations, once per linearisation, into the fixed block structure.

Every edge group's Hessian and gradient terms — which edges, which contraction, which target
— are built once by :class:`Assembler`; :meth:`Assembler.assemble` then only computes numbers.
Every scatter-add is a constant-structure sparse product (see ``block_ops.py``); a U term on
diagonal blocks with many edges per block (a camera's observations) may instead be summed by
gathered Gram products when the cost model prefers them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.linear.block_ops import EdgeContraction
from graphopt.linear.gathered_gram import GatheredGram
from graphopt.linear.indexing import unique_ints
from graphopt.linear.jacobian_w import JacobianProducts, JacobianW
from graphopt.linear.schur_config import SchurCostModel
from graphopt.linear.structure import EdgeSums

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex
    from graphopt.storage import EdgeGroup


#: Per edge group, one array per vertex position.
GroupArrays = list[tuple[np.ndarray, ...]]


@dataclass
class Assembly:
    """The numbers of one linearisation.

    Args:
        h_data: Data of the U part in the S pattern (undamped, without Schur terms).
        bu: Right-hand side (``−Jᵀ ρ' Ω e``) of the U part.
        v: Per V class ``(n, d, d)`` blocks.
        bv: Per V class ``(n, d)``.
        wt: Per W class ``(n, dv, du)`` transposed W blocks; ``None`` for a matrix-free
            system, whose W products come from the Jacobians (``wjac``).
        wjac: The W products from the per-edge Jacobians (matrix-free systems only).
    """

    h_data: np.ndarray
    bu: np.ndarray
    v: list[np.ndarray]
    bv: list[np.ndarray]
    wt: list[np.ndarray] | None
    wjac: JacobianProducts | None = None


#: A destination of blocks: indices, or every block of the class in order.
Dest = np.ndarray | slice


@dataclass
class _HTerm:
    """Hessian blocks ``Lᵀ (ρ'ΩR)`` of one edge group's positions into one destination.

    ``left``/``right`` name the positions whose Jacobian (left) and weighted Jacobian (right)
    form the block. ``contraction`` is ``None`` for a U term summed by a Gram.
    """

    left: int
    right: int
    kind: str  # "U", "V" or "W"
    contraction: EdgeContraction | None
    # U: (t, dl·dr) data positions until the assembler's map takes them (then None, as with a
    # Gram); V/W: (t,) blocks
    dest: Dest | None
    dest_t: np.ndarray | None = None  # U off-diagonal: positions of the transposed entries
    span: slice | None = None  # U contraction: its outputs' place in the assembler's buffer
    cls: int = -1  # V class or W class
    mirror: bool = False  # V term with left != right on the same vertex: add the transpose too
    identity: bool = False  # V/W term whose targets are all blocks of its class, in order
    # U term on diagonal blocks summed by gathered Gram products (outputs in ``out``, added to
    # S's data by ``to_h``) instead of the contraction.
    gram: GatheredGram | None = None
    out: np.ndarray | None = None
    to_h: sp.csr_matrix | None = None


@dataclass
class _GTerm:
    """Gradient ``−Jᵀ ρ'Ω e`` of position ``a`` of one edge group into U or a V class."""

    a: int
    kind: str
    sums: EdgeSums | EdgeContraction  # the H term's contraction where there is one
    dest: Dest  # U: (t, d) vector positions; V: (t,) block index
    cls: int = -1
    identity: bool = False  # V term whose targets are all V blocks of its class, in order


@dataclass
class _GroupTerms:
    hterms: list[_HTerm] = field(default_factory=list)
    gterms: list[_GTerm] = field(default_factory=list)
    wterms: list[int] = field(default_factory=list)  # matrix-free: terms of ``Assembler.jw``


def _add_blocks(acc: list[np.ndarray | None], k: int, dest: Dest, blk: np.ndarray,
                whole: bool, shape: tuple[int, ...]) -> None:
    """``acc[k][dest] += blk``, allocating ``acc[k]`` on first use — or taking ``blk`` itself
    when it is the first contribution and covers every block in order (``whole``)."""
    if acc[k] is None:
        if whole:
            acc[k] = blk
            return
        acc[k] = np.zeros(shape)
    acc[k][dest] += blk  # type: ignore[index]


class Assembler:
    """The terms of every edge group, built once, and the per-linearisation assembly.

    A matrix-free index (an implicit Schur solver) gets no W terms: the W blocks are never
    formed, and the assembly keeps the Jacobians their products need instead (``jw``).

    Args:
        index: The block index.
        cost: Decides where gathered Gram products sum U diagonal blocks.

    Attributes:
        jw: The W terms from the Jacobians (``None`` unless the index is matrix-free).
    """

    def __init__(self, index: BlockIndex, cost: SchurCostModel) -> None:
        self.index, self.cost = index, cost
        # Arrays that terms over the same edges share: all edges' indices (by group size),
        # EdgeSums' and contractions' column pointers (by length and width).
        self._all: dict[int, np.ndarray] = {}
        self._pointers: dict[tuple[int, int], np.ndarray] = {}
        self.jw = JacobianW(index) if index.matrix_free else None
        self.terms = [self._group_terms(gi) for gi in range(len(index.groups))]
        self._u_buffer, self._u_layers = self._u_scatter()
        if self.jw is not None:
            self.jw.finish()

    @property
    def u_gram_terms(self) -> int:
        """U terms summed by gathered Gram products rather than by their contraction."""
        return sum(t.gram is not None for gt in self.terms for t in gt.hterms)

    # --- structure ---------------------------------------------------------------------------

    def _group_terms(self, gi: int) -> _GroupTerms:
        ix = self.index
        g, pos = ix.groups[gi], ix.positions[gi]
        nb = max(ix.n_ublocks, 1)
        gt = _GroupTerms()
        ub, vb = ix.blocks_of(gi)
        isu = [u >= 0 for u in ub]
        isv = [v >= 0 for v in vb]
        dims = [ix.stores[s].vtype.dimension for s, _ in pos]
        for a in range(g.k):
            for b in range(a, g.k):
                mask = isu[a] & isu[b]
                if mask.any():
                    gt.hterms.append(self._u_term(g, a, b, self._edges(mask), ub, dims[a]))
                mask = isv[a] & isv[b]
                if mask.any():
                    sel = self._edges(mask)
                    cls = ix.vclass_of_store[pos[a][0]]
                    nvc = len(ix.vclasses[cls].slots)
                    uniq, inv = unique_ints(vb[a][sel], nvc, True)
                    whole = len(uniq) == nvc
                    # The contraction, not EdgeSums: 32 bytes more per edge, half the time on
                    # 3x3 blocks (3M observations: 0.11 s against 0.21 s per linearisation).
                    gt.hterms.append(_HTerm(
                        a, b, "V", self._contraction(g, sel, inv, len(uniq), dims[a]),
                        slice(None) if whole else uniq, cls=cls, mirror=a != b, identity=whole))
        wspecs = []
        for a, b in combinations(range(g.k), 2):
            for ui, vi in ((a, b), (b, a)):
                mask = isu[ui] & isv[vi]
                if mask.any() and self.jw is not None:
                    wspecs.append((vi, ui, self._edges(mask)))
                elif mask.any():
                    sel = self._edges(mask)
                    k = ix.wclass_of[(pos[ui][0], ix.vclass_of_store[pos[vi][0]])]
                    keys = ix.wclasses[k].keys
                    widx = np.searchsorted(keys, vb[vi][sel] * nb + ub[ui][sel])
                    uniq, inv = unique_ints(widx, len(keys), True)
                    # Wᵀ block = J_vᵀ Ω J_u: the V position's Jacobian on the left.
                    con = self._contraction(g, sel, inv, len(uniq), ix.wclasses[k].dv)
                    ident = len(uniq) == len(keys) and len(inv) == len(uniq)
                    del keys, widx
                    gt.hterms.append(_HTerm(vi, ui, "W", con, slice(None) if ident else uniq,
                                            cls=k, identity=ident))
        for a in range(g.k):
            for kind, isx, xb in (("U", isu[a], ub[a]), ("V", isv[a], vb[a])):
                if not isx.any():
                    continue
                sel = self._edges(isx)
                cls = ix.vclass_of_store[pos[a][0]] if kind == "V" else -1
                size = nb if kind == "U" else len(ix.vclasses[cls].slots)
                uniq, inv = unique_ints(xb[sel], size, True)
                whole = kind == "V" and len(uniq) == size
                dest: Dest = (ix.uoffset[uniq][:, None] + np.arange(dims[a]) if kind == "U"
                              else slice(None) if whole else uniq)
                # The (a, a) H term's contraction has these edges and targets: reuse it.
                con = next((t.contraction for t in gt.hterms if t.left == a and t.right == a
                            and t.kind == kind and t.contraction is not None), None)
                gt.gterms.append(_GTerm(a, kind, con or self._sums(g, sel, inv, len(uniq)),
                                        dest, cls, whole))
        for vi, ui, sel in wspecs:
            gt.wterms.append(self._w_term(gi, gt, vi, ui, sel))
        return gt

    def _u_scatter(self) -> tuple[np.ndarray, list[tuple[np.ndarray | None, np.ndarray]]]:
        """One buffer for the outputs of every U contraction, and the gathers that add them,
        transposes included, into ``H_uu``'s data: ``h = buffer[src_0]``, then
        ``h[pos_k] += buffer[src_k]`` for the entries with a ``k``-th contribution.

        Every H entry of a pose graph has one contribution or two (a diagonal block from both
        ends of its edges; a pair of vertices joined in both directions), so the first gather
        covers the whole array and the others a small part of it (w10000, 64k edges: 1.2M
        entries, 0.09M with a second contribution; 2.6 ms against 3.1 for a 0/1 CSR product,
        and no sort to build). Entries without any contribution read a zero past the outputs.
        Each list of destinations below has distinct positions (a term's targets are unique
        blocks), so a list adds at most one contribution per entry, after those of the lists
        before it: the sums keep the terms' order.
        """
        rows, off = [], 0
        for gt in self.terms:
            for t in gt.hterms:
                if t.kind != "U" or t.contraction is None:
                    continue
                assert isinstance(t.dest, np.ndarray)
                d2 = t.dest.shape[-1] // t.contraction.d1
                t.span = slice(off, off + t.contraction.out_size(d2))
                rows.append((t.dest.reshape(-1), off))
                if t.dest_t is not None:
                    rows.append((t.dest_t.reshape(-1), off))
                t.dest = t.dest_t = None  # kept in the gathers
                off = t.span.stop  # a scratch block past the outputs is not gathered
        if not rows:
            return np.zeros(0), []
        nnz = self.index.pattern.nnz
        layers: list[tuple[np.ndarray | None, np.ndarray]] = []
        # intp indices: np.take converts other index types on every call.
        first = np.full(nnz, off, dtype=np.intp)  # `off`: the zero past the outputs
        later: list[list[tuple[np.ndarray, np.ndarray]]] = []  # per layer ≥ 1: (pos, src)
        # Contributions placed so far per entry (at most one per list).
        taken = np.zeros(nnz, dtype=np.int8 if len(rows) < 127 else np.int32)
        for li, (d, o) in enumerate(rows):
            d = d.astype(np.intp, copy=False)  # once, not at every fancy index below
            src = np.arange(o, o + len(d), dtype=np.intp)
            if li == 0:  # nothing placed yet
                first[d] = src
                k = np.zeros(len(d), dtype=taken.dtype)
            else:
                k = taken[d]
                fresh = k == 0
                if fresh.all():
                    first[d] = src
                else:
                    first[d[fresh]] = src[fresh]
                    for level in np.unique(k[~fresh]):
                        at = k == level
                        while len(later) < level:
                            later.append([])
                        later[level - 1].append((d[at], src[at]))
            if li < len(rows) - 1:
                taken[d] = k + 1  # distinct positions: a plain scatter
        layers.append((None, first))
        for parts in later:
            layers.append((np.concatenate([p for p, _ in parts]).astype(np.intp),
                           np.concatenate([q for _, q in parts])))
        buffer = np.zeros(off + 1)  # the last value stays zero
        return buffer, layers

    def _w_term(self, gi: int, gt: _GroupTerms, vi: int, ui: int, sel: np.ndarray) -> int:
        """Add the matrix-free W term of positions ``(vi, ui)``; its sums are the gradient's
        (or the V term's contraction) where those run over the same edges and targets."""
        assert self.jw is not None
        ix = self.index
        g = ix.groups[gi]
        r = g.etype.jacobian_rows()
        ptr = self._pointers.get((g.size * r, 1))
        if ptr is None:
            ptr = self._pointers[g.size * r, 1] = EdgeSums.pointers(g.size, r)
        to_u = to_v = None
        if len(sel) == g.size:
            us = ix.positions[gi][ui][0]
            ub = np.flatnonzero(ix.ustore == us)
            rows = ix.uoffset[ub]
            for t in gt.gterms:
                if not t.sums.all:
                    continue
                if (t.kind == "U" and t.a == ui and isinstance(t.dest, np.ndarray)
                        and t.dest.shape[0] == len(ub) and np.array_equal(t.dest[:, 0], rows)):
                    to_u = t.sums  # targets: the store's U blocks in order
                elif t.kind == "V" and t.a == vi and t.identity:
                    to_v = t.sums
        self.jw.add(gi, vi, ui, sel, g.size, r, ptr, to_u, to_v)
        return len(self.jw.terms) - 1

    def _edges(self, mask: np.ndarray) -> np.ndarray:
        """``flatnonzero(mask)``; one shared array for every term over all of a group's edges."""
        if not mask.all():
            return np.flatnonzero(mask)
        if len(mask) not in self._all:
            self._all[len(mask)] = np.arange(len(mask))
        return self._all[len(mask)]

    def _sums(self, g: EdgeGroup, sel: np.ndarray, target: np.ndarray, n_t: int) -> EdgeSums:
        """Σ over edges ``sel`` of ``Jᵀ · e`` (a gradient) into ``n_t`` targets; sums over all
        edges of a group share their column pointers."""
        r = g.etype.jacobian_rows()
        if len(sel) < g.size:
            return EdgeSums(target, n_t, r, sel, g.size)
        ptr = self._pointers.get((g.size * r, 1))
        if ptr is None:
            ptr = self._pointers[g.size * r, 1] = EdgeSums.pointers(g.size, r)
        return EdgeSums(target, n_t, r, indptr=ptr)

    def _contraction(self, g: EdgeGroup, sel: np.ndarray, target: np.ndarray, n_t: int,
                     d_out: int) -> EdgeContraction:
        """Σ over edges ``sel`` of ``Jᵀ · (ρ'ΩJ)`` blocks with ``d_out`` rows into ``n_t``
        targets. Over all edges, the column pointers depend on the width alone: shared."""
        r = g.etype.jacobian_rows()
        con = EdgeContraction(sel, target, n_t, g.size, r, d_out)
        if con.all:
            con.indptr = self._pointers.setdefault((g.size * r, d_out), con.indptr)
        return con

    def _u_term(self, g: EdgeGroup, a: int, b: int, sel: np.ndarray, ub: list[np.ndarray],
                d: int) -> _HTerm:
        """The U-U term of positions ``(a, b)`` over edges ``sel``."""
        nb = max(self.index.n_ublocks, 1)
        pattern = self.index.pattern
        if a == b:  # diagonal blocks: unique U blocks (a bitmap, not a sort of pair keys)
            br, inv = unique_ints(ub[a][sel], nb, True)
            bc = br
        else:
            uniq, inv = unique_ints(ub[a][sel] * nb + ub[b][sel], nb * nb, True)
            br, bc = uniq // nb, uniq % nb
        gram = self._u_gram(g, sel, inv, len(br), d) if a == b else None
        if gram is not None:  # diagonal blocks: (u, u) per output
            ub_out = br[gram.targets]
            return _HTerm(a, b, "U", None, None, gram=gram, out=np.zeros((gram.n_out, d, d)),
                          to_h=pattern.to_s(ub_out, ub_out))
        con = self._contraction(g, sel, inv, len(br), d)
        pos, post = pattern.dest(br, bc, transposes=a != b)
        return _HTerm(a, b, "U", con, pos, post)

    def _u_gram(self, g: EdgeGroup, sel: np.ndarray, target: np.ndarray, n_t: int, d: int
                ) -> GatheredGram | None:
        """Gathered Gram products for a U term on diagonal blocks, if the cost model prefers
        them to the sparse contraction (many edges per U block: a camera's observations)."""
        cost = self.cost
        if not cost.gram_enabled or len(sel) == 0:
            return None
        r = g.etype.jacobian_rows()
        sparse = cost.sparse_mac * len(sel) * r * d * d
        # gram_seconds below without padding, one output per target and one chunk: a lower
        # bound that spares planning a hopeless Gram (a local BA's 10 cameras: 0.2 ms).
        if ((2 * cost.gram_gather * r * d + cost.gemm_mac * r * d * d) * len(sel)
                + cost.gemm_output * n_t + cost.gemm_chunk >= sparse):
            return None
        gram = GatheredGram(target, sel, sel, n_t, r, d)
        seconds = cost.gram_seconds(gram, 2 * gram.padded)  # J and ρ'ΩJ (once if equal)
        if seconds >= sparse:
            return None
        gram.build()
        return gram

    # --- numbers -----------------------------------------------------------------------------

    def assemble(self, jacobians: GroupArrays, weighted: GroupArrays,
                 weighted_errors: list[np.ndarray]) -> Assembly:
        """Accumulate ``JᵀΩJ`` and ``−JᵀΩe`` of every edge group into the fixed structure.

        Args:
            jacobians: Per group, per position ``(m, e, d)`` (C-contiguous).
            weighted: Per group, per position ``ρ' Ω J`` ``(m, e, d)`` (C-contiguous).
            weighted_errors: Per group ``ρ' Ω e`` ``(m, e)``.
        """
        ix = self.index
        h: np.ndarray | None = None  # gathered Gram products' part of H_uu, if any
        bu = np.zeros(ix.n)
        # V and W classes are allocated on first use: a first term that covers every block of
        # its class in order is used as it is (no zero fill, no scatter-add).
        v: list[np.ndarray | None] = [None] * len(ix.vclasses)
        bv: list[np.ndarray | None] = [None] * len(ix.vclasses)
        wt: list[np.ndarray | None] = [None] * len(ix.wclasses)
        warrays: list[tuple[np.ndarray, np.ndarray]] = []  # matrix-free: per W term
        for gt, J, WJ, we in zip(self.terms, jacobians, weighted, weighted_errors, strict=True):
            for t in gt.hterms:
                if t.gram is not None:  # diagonal U blocks by gathered Gram products
                    assert t.out is not None and t.to_h is not None
                    ja, wjb = J[t.left], WJ[t.right]
                    m = len(ja)
                    t.gram(np.ascontiguousarray(ja).reshape(m, -1), t.out,
                           None if wjb is ja else np.ascontiguousarray(wjb).reshape(m, -1))
                    gh = t.to_h @ t.out.reshape(-1)
                    h = gh if h is None else h + gh
                    continue
                assert t.contraction is not None
                if t.kind == "U":  # into the buffer, added to h below
                    t.contraction(np.ascontiguousarray(J[t.left]), WJ[t.right],
                                  self._u_buffer[t.span])
                    continue
                blk = t.contraction(np.ascontiguousarray(J[t.left]), WJ[t.right])
                if t.kind == "V":
                    if t.mirror:
                        blk = blk + np.swapaxes(blk, 1, 2)
                    c = ix.vclasses[t.cls]
                    _add_blocks(v, t.cls, t.dest, blk, t.identity, (len(c.slots), c.dim, c.dim))
                else:
                    w = ix.wclasses[t.cls]
                    _add_blocks(wt, t.cls, t.dest, blk, t.identity, (len(w.ublock), w.dv, w.du))
            if self.jw is not None:
                for ti in gt.wterms:
                    w = self.jw.terms[ti]
                    jv, wju = J[w.v_pos], WJ[w.u_pos]
                    if w.sel is not None:
                        jv, wju = jv[w.sel], wju[w.sel]
                    warrays.append((np.ascontiguousarray(jv), np.ascontiguousarray(wju)))
            we3 = we[:, :, None]
            for g in gt.gterms:
                gb = g.sums(J[g.a], we3)[:, :, 0]
                np.negative(gb, out=gb)
                if g.kind == "U":
                    bu[g.dest] += gb
                else:
                    c = ix.vclasses[g.cls]
                    _add_blocks(bv, g.cls, g.dest, gb, g.identity, (len(c.slots), c.dim))
        if self._u_layers:
            # The indices are in range by construction: "wrap" skips the bounds check.
            hu = np.take(self._u_buffer, self._u_layers[0][1], mode="wrap")
            for pos, src in self._u_layers[1:]:
                hu[pos] += np.take(self._u_buffer, src, mode="wrap")
            h = hu if h is None else h + hu
        if h is None:
            h = np.zeros(ix.pattern.nnz)
        vfull = [x if x is not None else np.zeros((len(c.slots), c.dim, c.dim))
                 for x, c in zip(v, ix.vclasses, strict=True)]
        bvfull = [x if x is not None else np.zeros((len(c.slots), c.dim))
                  for x, c in zip(bv, ix.vclasses, strict=True)]
        if self.jw is not None:
            return Assembly(h, bu, vfull, bvfull, None, self.jw.bind(warrays))
        wfull = [x if x is not None else np.zeros((len(c.ublock), c.dv, c.du))
                 for x, c in zip(wt, ix.wclasses, strict=True)]
        return Assembly(h, bu, vfull, bvfull, wfull)
