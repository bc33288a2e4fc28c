"""The block structure of the normal equations, built once, and their numeric assembly.

Vertices that are neither fixed nor marginalised are *U* blocks; marginalised ones are *V*
blocks (block-diagonal, eliminated by the Schur complement); *W* blocks couple the two. The
reduced system ``S = U − W V⁻¹ Wᵀ`` lives in one fixed CSC pattern (the U blocks plus the fill
from every pair of U blocks that share a V block). Everything index-related — which edge block
goes where, the pattern, the pairs for ``W V⁻¹ Wᵀ`` — is computed in :meth:`LinearSystem.__init__`;
each iteration only computes numbers. Every scatter-add is a :class:`BlockContraction`: a
constant-structure sparse product (see ``docs/architecture.md``).

W blocks are stored transposed, ``Wᵀ`` of shape ``(dv, du)``, which is the layout every product
below wants.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg.blas as blas
import scipy.sparse as sp

from graphopt.block_ops import (
    BlockContraction,
    EdgeContraction,
    GatheredGram,
    batched_cholesky_inverses,
    csr_product_into,
)
from graphopt.errors import GraphError
from graphopt.storage import EdgeGroup, VertexStore


@dataclass
class _HTerm:
    """Hessian blocks ``Lᵀ Ω R`` of positions (a, b) of one edge group into one destination.

    ``left``/``right`` name the positions whose Jacobian (left) and weighted Jacobian (right)
    form the block.
    """

    left: int
    right: int
    kind: str  # "U", "V" or "W"
    contraction: EdgeContraction
    dest: np.ndarray  # U: (t, dl*dr) data positions; V/W: (t,) block index
    dest_t: np.ndarray | None = None  # U off-diagonal: positions of the transposed entries
    cls: int = -1  # V class or W class index
    mirror: bool = False  # V term with a != b on the same vertex: add the transpose too
    identity: bool = False  # V/W term whose targets are all blocks of its class, in order
    # U term on diagonal blocks with many edges per block: summed by gathered Gram products
    # (outputs in ``out``, added to S's data by ``to_h``) instead of the contraction.
    gram: GatheredGram | None = None
    out: np.ndarray | None = None
    to_h: sp.csr_matrix | None = None


@dataclass
class _GTerm:
    """Gradient ``−Jᵀ ρ'Ω e`` of position ``a`` of one edge group into U or a V class."""

    a: int
    kind: str
    contraction: EdgeContraction
    dest: np.ndarray  # U: (t, d) vector positions; V: (t,) block index
    cls: int = -1
    shared: int = -1  # index of an H term with the same contraction
    identity: bool = False  # V term whose targets are all V blocks of its class, in order


@dataclass
class _GroupTerms:
    hterms: list[_HTerm] = field(default_factory=list)
    gterms: list[_GTerm] = field(default_factory=list)


@dataclass
class VClass:
    """All marginalised vertices of one store."""

    store: int
    dim: int
    slots: np.ndarray  # (n,) store slots, by V block index


@dataclass
class WClass:
    """W blocks between the U vertices of one store and one V class."""

    ustore: int
    vclass: int
    du: int
    dv: int
    ublock: np.ndarray  # (n,) global U block
    vblock: np.ndarray  # (n,) block within the V class
    upos: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # v·nb + u
    rhs: EdgeContraction | None = None  # Σ_w W_w x_v[v_w] into U blocks of this store
    rhs_dest: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    # Wᵀ of the class as a block-sparse (BSR) matrix over the store's U columns: its data is
    # the W array as it is, so ``Wᵀ x`` for every V block is one SciPy product.
    bsr_cols: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bsr_indptr: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    ucols: slice = field(default_factory=lambda: slice(0, 0))  # the store's U entries


@dataclass
class _PairTerm:
    """Products ``Y_w1 W_w2ᵀ`` over pairs of W blocks sharing a V block: the fill of S."""

    k1: int
    k2: int
    contraction: BlockContraction | EdgeContraction
    # Sums the products into S's data (both triangles): one sparse product, no fancy indexing.
    to_s: sp.csr_matrix


@dataclass
class _Panel:
    """A run of consecutive V blocks and the U blocks they meet: one dense ``syrk``.

    With ``V = LLᵀ``, ``M = L⁻¹Wᵀ`` of the panel's W blocks, laid out densely as
    ``(rows·dv, cols·du)`` (zeros where a V block does not meet a U block), is one product of a
    constant-structure CSR matrix holding the entries of ``L⁻¹`` with the W array as it is: the
    small products and their placement happen in one C loop. ``MᵀM`` is the panel's share of
    ``W V⁻¹ Wᵀ`` and ``Mᵀ L⁻¹b_v`` its share of ``W V⁻¹ b_v``.
    """

    v0: int  # first V block of the panel
    w0: int  # W block range of the panel
    w1: int
    rows: int  # V blocks in the panel
    cols: int  # U blocks the panel meets
    indptr: np.ndarray  # CSR rows: (V block, row of L⁻¹, U block) → entries of L⁻¹ ...
    indices: np.ndarray  # ... times rows (W block, i) of the panel's W array
    d0: int  # the panel's range in the term's gathered L⁻¹ entries
    d1: int
    r0: int  # offset of the panel's MᵀM (column-major) in the term's result buffer
    rhs_pos: np.ndarray  # positions in the reduced right-hand side of the panel's U columns


@dataclass
class _DenseSchurTerm:
    """``W V⁻¹ Wᵀ`` of one W class as dense BLAS ``syrk`` products over panels of V blocks.

    V blocks are numbered so that vertices seen by the same U blocks are neighbours (see
    :meth:`LinearSystem._order_v_blocks`), which keeps every panel's ``M`` narrow.
    """

    k: int
    panels: list[_Panel]
    lidx: np.ndarray  # flat index into L⁻¹ of every CSR entry of every panel, in order
    scratch: np.ndarray  # room for the largest panel's M
    results: np.ndarray  # every panel's MᵀM, one after the other
    # Sums the upper-triangle entries of ``results`` into S's pattern: one sparse product
    # instead of a fancy-indexed subtraction per panel.
    to_s: sp.csr_matrix


@dataclass
class _GramSchurTerm:
    """``W V⁻¹ Wᵀ`` and ``W V⁻¹ b_v`` of one W class through ``Z = L⁻¹Wᵀ`` (``V = LLᵀ``).

    ``Z`` is formed for every W block by one constant-structure CSR product (the entries of
    ``L⁻¹`` times the W array as it is) into a reused buffer. Then every
    block of S is a sum of ``Z_aᵀ Z_b`` over the W blocks ``a``, ``b`` of its two U blocks that
    share a V block (a U block with itself on the diagonal), computed per block of S by
    :class:`GatheredGram`; the right-hand side takes ``Z_wᵀ L⁻¹b_v`` per W block.
    """

    k: int
    indptr: np.ndarray  # CSR rows (W block, row i of Z) → entries j ≤ i of L⁻¹ ...
    indices: np.ndarray  # ... times rows (W block, j) of the Wᵀ array
    lidx: np.ndarray  # flat index into L⁻¹ of every CSR entry
    z: np.ndarray  # (nw·dv·du,) Z, one block after the other
    gram: GatheredGram
    results: np.ndarray  # (gram.n_out, du, du)
    # Sums the results into S's pattern (both triangles): one sparse product.
    to_s: sp.csr_matrix
    # ``Σ_w Z_wᵀ (L⁻¹b_v)[v_w]`` per U block is one product of a CSC matrix (rows: U blocks of
    # the class; column (w, i) holds entry i of L⁻¹b_v of w's V block) with Z as it is.
    rhs_indptr: np.ndarray
    rhs_indices: np.ndarray
    rhs_lidx: np.ndarray  # flat index into L⁻¹b_v of every column (w, i)


@dataclass
class Assembly:
    """The numbers of one linearisation.

    Args:
        h_data: Data of the U part in the S pattern (undamped, without Schur terms).
        bu: Right-hand side (``−Jᵀ ρ' Ω e``) of the U part.
        v: Per V class ``(n, d, d)`` blocks.
        bv: Per V class ``(n, d)``.
        wt: Per W class ``(n, dv, du)`` transposed W blocks.
    """

    h_data: np.ndarray
    bu: np.ndarray
    v: list[np.ndarray]
    bv: list[np.ndarray]
    wt: list[np.ndarray]


def _add_blocks(acc: list[np.ndarray | None], k: int, dest: np.ndarray, blk: np.ndarray,
                whole: bool, shape: tuple[int, ...]) -> None:
    """``acc[k][dest] += blk``, allocating ``acc[k]`` on first use — or taking ``blk`` itself
    when it is the first contribution and covers every block in order (``whole``)."""
    if acc[k] is None:
        if whole:
            acc[k] = blk
            return
        acc[k] = np.zeros(shape)
    acc[k][dest] += blk  # type: ignore[index]


def _unique(x: np.ndarray, size: int, return_inverse: bool = False
            ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``np.unique`` for non-negative integers below ``size``: a bitmap and a cumulative sum
    (linear time) when ``size`` is small against ``len(x)``, NumPy's sort otherwise."""
    x = np.asarray(x, dtype=np.int64)
    if size > 16 * len(x) + 65536:
        return np.unique(x, return_inverse=return_inverse)
    present = np.zeros(size, dtype=bool)
    present[x] = True
    uniq = np.flatnonzero(present)
    if not return_inverse:
        return uniq
    rank = np.cumsum(present, dtype=np.int64) - 1
    return uniq, rank[x]


class LinearSystem:
    """Structure and assembly of the (Schur-reduced) normal equations.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
    """

    def __init__(
        self,
        stores: list[VertexStore],
        groups: list[EdgeGroup],
        positions: list[list[tuple[int, np.ndarray]]],
        config: object = None,
    ) -> None:
        self.index = self
        self.stores = stores
        self.groups = groups
        self.positions = positions
        self._index_vertices()
        self._order_v_blocks()
        self._build_terms()
        self._build_pattern()

    # --- structure ---------------------------------------------------------------------------

    def _index_vertices(self) -> None:
        self.ublock: list[np.ndarray] = []
        self.vblock: list[np.ndarray] = []
        self.vclass_of_store: list[int] = []
        self.vclasses: list[VClass] = []
        udims, ustore_of = [], []
        nu = 0
        for si, st in enumerate(self.stores):
            active = ~st.fixed
            umask = active & ~st.marginalized
            vmask = active & st.marginalized
            nuh = int(umask.sum())
            ub = np.full(len(st), -1, dtype=np.int64)
            ub[umask] = nu + np.arange(nuh)
            nu += nuh
            self.ublock.append(ub)
            udims.append(np.full(nuh, st.vtype.dimension, dtype=np.int64))
            ustore_of.append(np.full(nuh, si, dtype=np.int64))
            vb = np.full(len(st), -1, dtype=np.int64)
            if vmask.any():
                vb[vmask] = np.arange(int(vmask.sum()))
                self.vclass_of_store.append(len(self.vclasses))
                self.vclasses.append(VClass(si, st.vtype.dimension, np.flatnonzero(vmask)))
            else:
                self.vclass_of_store.append(-1)
            self.vblock.append(vb)
        self.n_ublocks = nu
        self.udims = np.concatenate(udims) if udims else np.zeros(0, dtype=np.int64)
        self.ustore = np.concatenate(ustore_of) if ustore_of else np.zeros(0, dtype=np.int64)
        self.uoffset = np.concatenate([[0], np.cumsum(self.udims)]).astype(np.int64)
        self.n = int(self.uoffset[-1])
        self.schur = bool(self.vclasses)

    def _order_v_blocks(self) -> None:
        """Number every V class's blocks so that vertices seen by the same U blocks are
        neighbours, which keeps dense panels narrow and lets vertices with identical U sets
        share a panel.

        U blocks are first put in a 1-D order that follows their co-visibility (the Fiedler
        vector of the co-visibility graph for up to ``SPECTRAL_MAX`` U blocks). V blocks are
        then sorted by the last and first U block they meet in that order, and by a hash of
        their whole U set (identical sets become runs).
        """
        nb = max(self.n_ublocks, 1)
        rng = np.random.default_rng(0x5EED)
        tag = rng.integers(0, 2**62, size=nb, dtype=np.int64)  # per U block, for set hashes
        for vc in self.vclasses:
            nv = len(vc.slots)
            v, u = self._v_u_incidence(vc)
            lo = np.full(nv, self.n_ublocks, dtype=np.int64)
            hi = np.full(nv, -1, dtype=np.int64)
            h = np.zeros(nv, dtype=np.int64)
            if len(v):
                rank = self._u_rank(v, u, nv)
                ru = rank[u]
                first = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
                lo[v[first]] = np.minimum.reduceat(ru, first)
                hi[v[first]] = np.maximum.reduceat(ru, first)
                with np.errstate(over="ignore"):
                    h[v[first]] = np.add.reduceat(tag[u], first)  # wraps: a set hash
            order = np.lexsort((h, lo, hi))  # new block b is old block order[b]
            new_id = np.empty(nv, dtype=np.int64)
            new_id[order] = np.arange(nv)
            vb = self.vblock[vc.store]
            vb[vb >= 0] = new_id[vb[vb >= 0]]
            vc.slots = vc.slots[order]

    def _v_u_incidence(self, vc: VClass) -> tuple[np.ndarray, np.ndarray]:
        """Unique (V block, U block) pairs linked by an edge, sorted by V then U block."""
        nb = max(self.n_ublocks, 1)
        keys = []
        for pos in self.positions:  # groups and positions: structure, not numbers
            for vi, (sv, slots_v) in enumerate(pos):
                if sv != vc.store:
                    continue
                vb = self.vblock[sv][slots_v]
                for ui, (su, slots_u) in enumerate(pos):
                    ub = self.ublock[su][slots_u]
                    ok = (vb >= 0) & (ub >= 0) & (ui != vi)
                    keys.append(vb[ok] * nb + ub[ok])
        if not keys:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = _unique(np.concatenate(keys), len(vc.slots) * nb)
        return k // nb, k % nb

    #: Largest number of U blocks ordered by the co-visibility graph's Fiedler vector.
    SPECTRAL_MAX = 600

    def _u_rank(self, v: np.ndarray, u: np.ndarray, nv: int) -> np.ndarray:
        """Position of every U block in a 1-D order that keeps co-visible U blocks close."""
        nb = self.n_ublocks
        if nb < 3 or nb > self.SPECTRAL_MAX:
            return np.arange(nb)
        inc = sp.csr_matrix((np.ones(len(v)), (v, u)), shape=(nv, nb))
        c = (inc.T @ inc).toarray()
        np.fill_diagonal(c, 0.0)
        lap = np.diag(c.sum(axis=1)) - c
        _, vec = np.linalg.eigh(lap)
        order = np.argsort(vec[:, 1], kind="stable")
        rank = np.empty(nb, dtype=np.int64)
        rank[order] = np.arange(nb)
        return rank

    def _contraction(self, g: EdgeGroup, left: int, right: int, sel: np.ndarray,
                     target: np.ndarray, n_t: int, d_out: int) -> EdgeContraction:
        """Σ over edges ``sel`` of ``J_leftᵀ · (ρ'ΩJ)_right`` into ``n_t`` targets."""
        return EdgeContraction(sel, target, n_t, g.size, g.etype.jacobian_rows(), d_out)

    def _u_gram(self, g: EdgeGroup, sel: np.ndarray, target: np.ndarray, n_t: int, d: int
                ) -> GatheredGram | None:
        """Gathered Gram products for a U term on diagonal blocks, if the cost model prefers
        them to the sparse contraction (many edges per U block: a camera's observations)."""
        if not self.GRAM_ENABLED or len(sel) == 0:
            return None
        r = g.etype.jacobian_rows()
        sparse = self.COST_SPARSE_MAC * len(sel) * r * d * d
        # Lower bound (one gather, no padding or overheads): spares building a hopeless Gram.
        if (self.COST_GRAM_GATHER * r * d + self.COST_GEMM_MAC * r * d * d) * len(sel) >= sparse:
            return None
        gram = GatheredGram(target, sel, sel, n_t, r, d)
        cost = self._gram_cost(gram, 2 * gram.padded)  # J and ρ'ΩJ (once if equal)
        return gram if cost < sparse else None

    def _gram_cost(self, gram: GatheredGram, gathered: int) -> float:
        """Modelled seconds of one call of ``gram`` that gathers ``gathered`` blocks."""
        r, d = gram.r, gram.d
        return (self.COST_GRAM_GATHER * gathered * r * d
                + self.COST_GEMM_MAC * gram.padded * r * d * d
                + self.COST_GEMM_OUTPUT * gram.n_out
                + self.COST_GEMM_CHUNK * len(gram.chunks))

    def _build_terms(self) -> None:
        self.wclasses: list[WClass] = []
        wkey: dict[tuple[int, int], int] = {}
        w_pairs: list[list[np.ndarray]] = []
        self.terms: list[_GroupTerms] = []
        ublock_pairs: list[np.ndarray] = []
        pending_w: list[tuple[_GroupTerms, EdgeGroup, int, int, int, np.ndarray, np.ndarray,
                              np.ndarray]] = []
        nb = max(self.n_ublocks, 1)

        for gi, g in enumerate(self.groups):
            gt = _GroupTerms()
            pos = self.positions[gi]
            ub = [self.ublock[s][slots] for s, slots in pos]
            vb = [self.vblock[s][slots] for s, slots in pos]
            isu = [u >= 0 for u in ub]
            isv = [v >= 0 for v in vb]
            dims = [self.stores[s].vtype.dimension for s, _ in pos]
            for a in range(g.k):
                for b in range(a, g.k):
                    mask = isu[a] & isu[b]
                    if mask.any():
                        sel = np.flatnonzero(mask)
                        pa, pb = ub[a][sel], ub[b][sel]
                        ublock_pairs.append(np.stack([pa, pb], 1))
                        if a != b:
                            ublock_pairs.append(np.stack([pb, pa], 1))
                        uniq, inv = _unique(pa * nb + pb, nb * nb, True)
                        gt.hterms.append(_HTerm(
                            a, b, "U", self._contraction(g, a, b, sel, inv, len(uniq), dims[a]),
                            np.stack([uniq // nb, uniq % nb], 1),
                            gram=self._u_gram(g, sel, inv, len(uniq), dims[a]) if a == b
                            else None))
                    mask = isv[a] & isv[b]
                    if mask.any():
                        if a != b and (pos[a][0] != pos[b][0]
                                       or np.any(vb[a][mask] != vb[b][mask])):
                            raise GraphError(
                                f"{g.etype.__name__}: an edge connects two different "
                                "marginalised vertices; the Schur complement needs marginalised "
                                "vertices that are independent given the others"
                            )
                        sel = np.flatnonzero(mask)
                        nvc = len(self.vclasses[self.vclass_of_store[pos[a][0]]].slots)
                        uniq, inv = _unique(vb[a][sel], nvc, True)
                        gt.hterms.append(_HTerm(
                            a, b, "V", self._contraction(g, a, b, sel, inv, len(uniq), dims[a]),
                            uniq, cls=self.vclass_of_store[pos[a][0]], mirror=a != b,
                            identity=len(uniq) == nvc))
                    if a == b:
                        continue
                    for ui, vi in ((a, b), (b, a)):
                        mask = isu[ui] & isv[vi]
                        if not mask.any():
                            continue
                        sel = np.flatnonzero(mask)
                        key = (pos[ui][0], self.vclass_of_store[pos[vi][0]])
                        if key not in wkey:
                            wkey[key] = len(self.wclasses)
                            self.wclasses.append(WClass(
                                key[0], key[1], self.stores[key[0]].vtype.dimension,
                                self.vclasses[key[1]].dim, np.zeros(0), np.zeros(0)))
                            w_pairs.append([])
                        k = wkey[key]
                        w_pairs[k].append(np.stack([ub[ui][sel], vb[vi][sel]], 1))
                        pending_w.append((gt, g, vi, ui, k, sel, ub[ui][sel], vb[vi][sel]))
            for a in range(g.k):
                for kind, isx, xb in (("U", isu[a], ub[a]), ("V", isv[a], vb[a])):
                    if not isx.any():
                        continue
                    sel = np.flatnonzero(isx)
                    cls = self.vclass_of_store[pos[a][0]] if kind == "V" else -1
                    size = nb if kind == "U" else len(self.vclasses[cls].slots)
                    uniq, inv = _unique(xb[sel], size, True)
                    shared = next((i for i, t in enumerate(gt.hterms)
                                   if t.left == a and t.right == a and t.kind == kind), -1)
                    con = (gt.hterms[shared].contraction if shared >= 0 else
                           self._contraction(g, a, a, sel, inv, len(uniq), dims[a]))
                    gt.gterms.append(_GTerm(a, kind, con, uniq, cls, shared,
                                            kind == "V" and len(uniq) == size))
            self.terms.append(gt)

        # Unique W blocks per class, ordered by V block, then each W term's edges onto them.
        for k, wc in enumerate(self.wclasses):
            allp = np.concatenate(w_pairs[k])
            keys = _unique(allp[:, 1] * nb + allp[:, 0], len(self.vclasses[wc.vclass].slots) * nb)
            wc.vblock, wc.ublock = keys // nb, keys % nb
            wc.upos = (self.uoffset[wc.ublock][:, None] + np.arange(wc.du)).astype(np.int64)
            # rhs: Σ_w Y_w b_v = Σ_w (Wᵀ_w)ᵀ (V⁻¹ b_v)[v_w] per U block: Wᵀ used in place.
            uu, inv = _unique(wc.ublock, nb, True)
            wc.rhs = EdgeContraction(np.arange(len(keys)), inv, len(uu), len(keys), wc.dv, wc.du)
            wc.rhs_dest = self.uoffset[uu][:, None] + np.arange(wc.du)
            wc.keys = keys
            ub_store = np.flatnonzero(self.ustore == wc.ustore)  # contiguous U blocks
            wc.bsr_cols = wc.ublock - ub_store[0]
            n_vc = len(self.vclasses[wc.vclass].slots)
            wc.bsr_indptr = np.searchsorted(wc.vblock, np.arange(n_vc + 1))
            wc.ucols = slice(int(self.uoffset[ub_store[0]]), int(self.uoffset[ub_store[-1] + 1]))
        for gt, g, vi, ui, k, sel, ubs, vbs in pending_w:
            keys = self.wclasses[k].keys
            widx = np.searchsorted(keys, vbs * nb + ubs)
            uniq, inv = _unique(widx, len(keys), True)
            # Wᵀ block = J_vᵀ Ω J_u: the V position's Jacobian on the left.
            con = self._contraction(g, vi, ui, sel, inv, len(uniq), self.wclasses[k].dv)
            ident = len(uniq) == len(keys) and len(inv) == len(uniq)
            gt.hterms.append(_HTerm(vi, ui, "W", con, uniq, cls=k, identity=ident))

        # Pairs of W blocks sharing a V block: the fill of the reduced system.
        self._pairs: list[tuple[int, int, np.ndarray, np.ndarray | None]] = []
        self._dense_pairs: list[tuple[int, list[tuple[int, int, int, int, np.ndarray]]]] = []
        self._gram_pairs: list[tuple[int, GatheredGram, np.ndarray]] = []
        for k1, c1 in enumerate(self.wclasses):
            for k2 in range(k1, len(self.wclasses)):
                c2 = self.wclasses[k2]
                if c1.vclass != c2.vclass:
                    continue
                w1, w2 = self._pairs_sharing_v(c1.vblock, c2.vblock)
                if k1 == k2:
                    # The cross pairs keep u1 < u2 (S is symmetric); each block with itself,
                    # (w, w), is summed without a gather (EdgeContraction).
                    keep = c1.ublock[w1] < c2.ublock[w2]
                    w1, w2 = w1[keep], w2[keep]
                u1, u2 = c1.ublock[w1], c2.ublock[w2]
                ublock_pairs.append(np.stack([u1, u2], 1))
                ublock_pairs.append(np.stack([u2, u1], 1))
                if k1 == k2:
                    path = self._schur_path(c1, w1, w2)
                    if isinstance(path, list):
                        self._dense_pairs.append((k1, path))
                        continue
                    if path is not None:
                        self._gram_pairs.append((k1, *path))
                        continue
                    self._pairs.append((k1, k1, np.arange(len(c1.ublock)), None))
                if len(w1):
                    self._pairs.append((k1, k2, w1, w2))
        diag = np.arange(self.n_ublocks)
        ublock_pairs.append(np.stack([diag, diag], 1))
        bp = np.concatenate(ublock_pairs)
        self._block_pairs = _unique(bp[:, 1] * nb + bp[:, 0], nb * nb)

    #: Costs (seconds per unit, fitted on this project's 2-core machine) behind the choice
    #: among the three ways to form ``W V⁻¹ Wᵀ`` (sparse pair contractions, dense panels,
    #: gathered Gram products): a value gathered (in whole rows) by ``np.take``, a multiply-add
    #: in SciPy's sparse product, in NumPy's loops for small matrices (``V⁻¹Wᵀ``), in BLAS
    #: ``syrk`` on wide panels and in the batched ``(d, n) × (n, d)`` products of a Gram; a
    #: value of ``L⁻¹Wᵀ`` formed and placed in a panel, an element of a panel (zeroed, read
    #: again for the right-hand side), an element of a panel's ``n × n`` product, one panel;
    #: a value of ``Z = L⁻¹Wᵀ`` formed for a Gram (and read again for the right-hand side), a
    #: value gathered into a Gram's chunk, one output block and one chunk of a Gram.
    COST_GATHER, COST_SPARSE_MAC, COST_SMALL_MAC, COST_BLAS_MAC = 0.6e-9, 0.4e-9, 0.7e-9, 3.2e-11
    COST_PLACE, COST_AREA, COST_DENSE_ELEMENT, COST_PANEL = 2.4e-9, 0.8e-9, 4.2e-9, 3e-5
    COST_GEMM_MAC, COST_Z, COST_GRAM_GATHER = 1.35e-10, 3.0e-9, 0.8e-9
    COST_GEMM_OUTPUT, COST_GEMM_CHUNK = 5e-7, 5e-6
    #: ``syrk`` on ``n`` columns runs at about ``n / (n + BLAS_HALF)`` of its peak rate.
    BLAS_HALF = 45
    #: Most rows of a panel's dense matrix (about 1.6 MB for 100 columns: it stays in cache).
    PANEL_ROWS = 2048
    #: Largest total number of elements of a class's panels (their work grows with it).
    DENSE_LIMIT = 64_000_000

    def _panel_cost(self, rows: int, n: int, placed: int) -> float:
        """Modelled seconds of one panel: ``rows × n`` matrix, ``placed`` values of it formed."""
        syrk = self.COST_BLAS_MAC * rows * n * (n + self.BLAS_HALF) / 2
        return (self.COST_PANEL + syrk + self.COST_PLACE * placed + self.COST_AREA * rows * n
                + self.COST_DENSE_ELEMENT * n * n)

    def _schur_path(self, c: WClass, w1: np.ndarray, w2: np.ndarray
                    ) -> list[tuple[int, int, int, int, np.ndarray]] | tuple[
                        GatheredGram, np.ndarray] | None:
        """The cheapest way (by the cost model) to form ``W V⁻¹ Wᵀ`` of W class ``c``:
        dense panels (their list), a gathered Gram (it and its targets' keys) or the sparse
        pair contractions (``None``).

        Args:
            c: A W class.
            w1: Its pairs of W blocks that share a V block, ``u(w1) < u(w2)``: first ...
            w2: ... and second blocks.
        """
        nw, n_cross = len(c.ublock), len(w1)
        dv, du = c.dv, c.du
        sparse = (self.COST_GATHER * n_cross * dv * du
                  + self.COST_SPARSE_MAC * (n_cross + nw) * dv * du * du
                  + self.COST_SPARSE_MAC * nw * dv * du  # the right-hand side
                  + self.COST_SMALL_MAC * nw * dv * dv * du)  # Yᵀ = V⁻¹Wᵀ
        best: tuple[float, list[tuple[int, int, int, int, np.ndarray]] | tuple[
            GatheredGram, np.ndarray] | None] = (sparse, None)
        dense = self._dense_panels(c)
        if dense is not None and dense[1] < best[0]:
            best = (dense[1], dense[0])
        # Without padding or overheads: a lower bound that spares building a hopeless Gram.
        gram_bound = (self.COST_Z * nw * dv * du
                      + self.COST_GRAM_GATHER * (nw + 2 * n_cross) * dv * du
                      + self.COST_GEMM_MAC * (nw + n_cross) * dv * du * du)
        if nw and self.GRAM_ENABLED and gram_bound < best[0]:
            nb = max(self.n_ublocks, 1)
            w = np.arange(nw)
            keys = np.concatenate([c.ublock * (nb + 1), c.ublock[w1] * nb + c.ublock[w2]])
            uniq, inv = _unique(keys, nb * nb, True)
            gram = GatheredGram(inv, np.concatenate([w, w1]), np.concatenate([w, w2]),
                                len(uniq), dv, du)
            cost = self.COST_Z * nw * dv * du + self._gram_cost(gram, gram.gathered)
            if cost < best[0]:
                best = (cost, (gram, uniq))
        return best[1]

    #: Whether the gathered Gram products are considered (tests switch paths off).
    GRAM_ENABLED = True

    def _dense_panels(self, c: WClass
                      ) -> tuple[list[tuple[int, int, int, int, np.ndarray]], float] | None:
        """Panels ``(v0, v1, w0, w1, local U indices)`` for dense ``syrk`` products of this W
        class and their modelled cost, or ``None`` if there are none or they would be too large.

        V blocks come in runs with identical U sets (see :meth:`_order_v_blocks`). A greedy
        scan merges the next run into the current panel while that is cheaper than starting a
        new one (fewer, larger BLAS calls against wider panels, but more zeros in them).
        """
        n_v = len(self.vclasses[c.vclass].slots)
        nw = len(c.ublock)
        if nw == 0:
            return None
        uu = _unique(c.ublock, max(self.n_ublocks, 1))
        lu = np.searchsorted(uu, c.ublock)
        dv, du = c.dv, c.du
        wstart = np.searchsorted(c.vblock, np.arange(n_v + 1))
        # Runs of V blocks with the same U set: a block continues the run of its predecessor
        # when both meet as many U blocks and the same ones (lists are sorted; compare each
        # W block with its counterpart in the previous V block).
        cnt = np.diff(wstart)
        eq = np.zeros(n_v, dtype=bool)
        eq[1:] = cnt[1:] == cnt[:-1]
        w = np.flatnonzero(eq[c.vblock])
        prev = w - cnt[c.vblock[w] - 1]
        eq[c.vblock[w[lu[w] != lu[prev]]]] = False
        run_start = np.flatnonzero(~eq)
        run_end = np.r_[run_start[1:], n_v]
        max_rows = max(1, self.PANEL_ROWS // dv)
        lul = lu.tolist()
        ws = wstart.tolist()
        closed: list[tuple[int, int, int, float]] = []  # panels: v0, v1, U mask, cost
        cur: tuple[int, int, int, float] | None = None  # the open panel
        for r0, r1 in zip(run_start.tolist(), run_end.tolist(), strict=True):  # runs, not vertices
            mask = 0
            for x in lul[ws[r0]:ws[r0 + 1]]:
                mask |= 1 << x
            nset = mask.bit_count()
            if nset == 0:
                continue  # V blocks that meet no U block of this class
            for a in range(r0, r1, max_rows):  # split runs longer than a panel
                b = min(r1, a + max_rows)
                alone = self._panel_cost((b - a) * dv, nset * du, (ws[b] - ws[a]) * dv * du)
                if cur is not None:
                    v0, _, cmask, ccost = cur
                    um = cmask | mask
                    merged = self._panel_cost((b - v0) * dv, um.bit_count() * du,
                                              (ws[b] - ws[v0]) * dv * du)
                    if b - v0 <= max_rows and merged < ccost + alone:
                        cur = (v0, b, um, merged)
                        continue
                    closed.append(cur)
                cur = (a, b, mask, alone)
        if cur is not None:
            closed.append(cur)
        dense = sum(p[3] for p in closed)
        elements = sum((v1 - v0) * dv * m.bit_count() * du for v0, v1, m, _ in closed)
        if elements > self.DENSE_LIMIT:
            return None
        return [self._panel_spec(p, ws) for p in closed], dense

    @staticmethod
    def _panel_spec(cur: tuple[int, int, int, float], ws: list[int]
                    ) -> tuple[int, int, int, int, np.ndarray]:
        v0, v1, mask, _ = cur
        cams = np.array([i for i in range(mask.bit_length()) if mask >> i & 1], dtype=np.int64)
        return v0, v1, ws[v0], ws[v1], cams

    @staticmethod
    def _pairs_sharing_v(v1: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All index pairs (i, j) with ``v1[i] == v2[j]`` (both sorted by v), vectorised."""
        nv = int(max(v1.max(initial=-1), v2.max(initial=-1))) + 1
        c1 = np.bincount(v1, minlength=nv)
        c2 = np.bincount(v2, minlength=nv)
        s1 = np.concatenate([[0], np.cumsum(c1)[:-1]])
        s2 = np.concatenate([[0], np.cumsum(c2)[:-1]])
        per = c1 * c2
        vv = np.repeat(np.arange(nv), per)
        k = np.arange(int(per.sum())) - np.repeat(np.cumsum(per) - per, per)
        c2v = np.maximum(c2[vv], 1)
        return s1[vv] + k // c2v, s2[vv] + k % c2v

    def _block_entries(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scalar (row, col) of every entry of blocks (r, c), row-major within a block."""
        if len(r) == 0:
            return np.zeros((0, 0), np.int64), np.zeros((0, 0), np.int64)
        d1, d2 = int(self.udims[r[0]]), int(self.udims[c[0]])
        rows = self.uoffset[r][:, None, None] + np.arange(d1)[None, :, None]
        cols = self.uoffset[c][:, None, None] + np.arange(d2)[None, None, :]
        rows, cols = np.broadcast_arrays(rows, cols)
        return rows.reshape(len(r), -1), cols.reshape(len(r), -1)

    def _dest(self, br: np.ndarray, bc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Data positions of blocks (br, bc) and of their transposes, entry-aligned."""
        r, c = self._block_entries(br, bc)
        d1, d2 = int(self.udims[br[0]]), int(self.udims[bc[0]])
        pos = self._positions(r, c)
        post = self._positions(c.reshape(-1, d1, d2), r.reshape(-1, d1, d2))
        return pos, post.reshape(len(br), -1)

    def _to_s(self, tu1: np.ndarray, tu2: np.ndarray) -> sp.csr_matrix:
        """The constant sparse matrix that sums result blocks ``(tu1, tu2)`` (row-major, one
        after the other) into S's data: both triangles for ``tu1 != tu2``."""
        pos, post = self._dest(tu1, tu2)
        off = tu1 != tu2
        src = np.arange(pos.size).reshape(pos.shape)
        rows = np.concatenate([pos.ravel(), post[off].ravel()])
        cols = np.concatenate([src.ravel(), src[off].ravel()])
        return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.nnz, pos.size))

    #: Largest ``n²`` for which pattern positions are looked up in a dense table.
    POSMAP_MAX = 4_000_000

    def _positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Data positions of entries (rows, cols) in the CSC pattern."""
        k = cols.astype(np.int64) * self.n + rows
        if self._posmap is not None:
            return self._posmap[k]
        return np.searchsorted(self._keys, k)

    def _build_pattern(self) -> None:
        n, nb = self.n, max(self.n_ublocks, 1)
        bc, br = self._block_pairs // nb, self._block_pairs % nb
        rows_l, cols_l = [], []
        for d1 in np.unique(self.udims):
            for d2 in np.unique(self.udims):
                sel = (self.udims[br] == d1) & (self.udims[bc] == d2)
                if sel.any():
                    r, c = self._block_entries(br[sel], bc[sel])
                    rows_l.append(r.ravel())
                    cols_l.append(c.ravel())
        rows = np.concatenate(rows_l) if rows_l else np.zeros(0, np.int64)
        cols = np.concatenate(cols_l) if cols_l else np.zeros(0, np.int64)
        keys = np.unique(cols.astype(np.int64) * n + rows)
        self._keys = keys
        # Small systems: a dense (col, row) → position table is faster than binary searches.
        self._posmap: np.ndarray | None = None
        if n * n <= self.POSMAP_MAX:
            self._posmap = np.full(n * n, -1, dtype=np.int64)
            self._posmap[keys] = np.arange(len(keys))
        indices = (keys % max(n, 1)).astype(np.int32)
        indptr = np.searchsorted(keys // max(n, 1), np.arange(n + 1)).astype(np.int32)
        self.pattern = sp.csc_matrix((np.zeros(len(keys)), indices, indptr), shape=(n, n))
        self.nnz = len(keys)
        diag = np.arange(n)
        self.diag_pos = self._positions(diag, diag)

        for gt in self.terms:
            for t in gt.hterms:
                if t.kind == "U":
                    if t.gram is not None:  # diagonal blocks: (u, u) per output
                        ub_out = t.dest[t.gram.targets, 0]
                        t.to_h = self._to_s(ub_out, ub_out)
                        t.out = np.zeros((t.gram.n_out, t.gram.d, t.gram.d))
                    pos, post = self._dest(t.dest[:, 0], t.dest[:, 1])
                    t.dest, t.dest_t = pos, (post if t.left != t.right else None)
            for gterm in gt.gterms:
                if gterm.kind == "U":
                    d = int(self.udims[gterm.dest[0]])
                    gterm.dest = self.uoffset[gterm.dest][:, None] + np.arange(d)
        self.pair_terms: list[_PairTerm] = []
        for k1, k2, w1, w2 in self._pairs:
            c1, c2 = self.wclasses[k1], self.wclasses[k2]
            if w2 is None:  # self pairs (w, w): diagonal blocks
                uniq, inv = _unique(c1.ublock, nb, True)
                con: BlockContraction | EdgeContraction = EdgeContraction(
                    w1, inv, len(uniq), len(w1), c1.dv, c1.du)
                tu1 = tu2 = uniq
            else:
                uniq, inv = _unique(c1.ublock[w1] * nb + c2.ublock[w2], nb * nb, True)
                tu1, tu2 = uniq // nb, uniq % nb
                # S_t −= Σ Y_w1 W_w2ᵀ = Σ (Yᵀ_w1)ᵀ Wᵀ_w2: A = Yᵀ (dv, du1), B = Wᵀ (dv, du2).
                con = BlockContraction(inv, w1, w2, len(uniq), c1.dv, c1.du, len(c2.ublock))
            self.pair_terms.append(_PairTerm(k1, k2, con, self._to_s(tu1, tu2)))
        del self._pairs
        self.gram_terms: list[_GramSchurTerm] = []
        for k, gram, keys in self._gram_pairs:
            c = self.wclasses[k]
            dv, du, nw = c.dv, c.du, len(c.ublock)
            ti, tj = np.tril_indices(dv)
            out_row = (np.arange(nw)[:, None] * dv + ti).ravel()
            idx_t = np.int32 if nw * dv < 2**31 else np.int64
            indptr = np.searchsorted(out_row, np.arange(nw * dv + 1)).astype(idx_t)
            indices = (np.arange(nw)[:, None] * dv + tj).ravel().astype(idx_t)
            lidx = (c.vblock[:, None] * dv * dv + ti * dv + tj).ravel()
            tk = keys[gram.targets]
            _, inv = _unique(c.ublock, nb, True)
            self.gram_terms.append(_GramSchurTerm(
                k, indptr, indices, lidx, np.zeros(nw * dv * du), gram,
                np.zeros((gram.n_out, du, du)), self._to_s(tk // nb, tk % nb),
                np.arange(nw * dv + 1, dtype=idx_t), np.repeat(inv, dv).astype(idx_t),
                (c.vblock[:, None] * dv + np.arange(dv)).ravel()))
        del self._gram_pairs
        self.dense_terms: list[_DenseSchurTerm] = []
        nb = max(self.n_ublocks, 1)
        for k, panel_specs in self._dense_pairs:
            c = self.wclasses[k]
            dv, du = c.dv, c.du
            uu = _unique(c.ublock, nb)
            lu = np.searchsorted(uu, c.ublock)
            di, dj = np.arange(du)[:, None], np.arange(du)[None, :]
            # L⁻¹ is lower triangular: row i of a V block's Z = L⁻¹Wᵀ takes entries j ≤ i.
            ti, tj = np.tril_indices(dv)
            panels, lidx, d0, largest, r0 = [], [], 0, 0, 0
            to_rows, to_cols = [], []
            for v0, v1, w0, w1, cams in panel_specs:  # panels, not vertices
                nc = len(cams)
                n = nc * du  # columns of M
                la, lb = np.divmod(np.arange(nc * nc), nc)
                ga, gb = uu[cams[la]], uu[cams[lb]]
                # Keep the block pairs present in S (others have no common V block at all).
                present = np.isin(gb * nb + ga, self._block_pairs)
                la, lb, ga, gb = la[present], lb[present], ga[present], gb[present]
                dest, _ = self._dest(ga, gb)
                i = la[:, None, None] * du + di
                j = lb[:, None, None] * du + dj
                src = np.maximum(i, j) * n + np.minimum(i, j)  # upper triangle, column-major
                # CSR of the panel's Z: output row (V block r, i, U block c) of du values is
                # Σ_j L⁻¹[r][i, j] · (row j of the W block (r, c)); each output row has at most
                # one W block, so rows are ordered by (r, i, c) and entries by j.
                w = np.arange(w0, w1)
                r = c.vblock[w] - v0
                lc = np.searchsorted(cams, lu[w])
                out_row = ((r[:, None] * dv + ti) * nc + lc[:, None]).ravel()
                order = np.argsort(out_row, kind="stable")
                n_out = (v1 - v0) * dv * nc
                indptr = np.searchsorted(out_row[order], np.arange(n_out + 1))
                indices = ((w - w0)[:, None] * dv + tj).ravel()[order]
                lidx.append((c.vblock[w][:, None] * dv * dv + ti * dv + tj).ravel()[order])
                idx_t = np.int32 if max(n_out, (w1 - w0) * dv) < 2**31 else np.int64
                rhs_pos = (self.uoffset[uu[cams]][:, None] + np.arange(du)).reshape(-1)
                panels.append(_Panel(v0, w0, w1, v1 - v0, nc, indptr.astype(idx_t),
                                     indices.astype(idx_t), d0, d0 + len(indices), r0,
                                     rhs_pos))
                to_rows.append(dest.reshape(-1))
                to_cols.append(r0 + src.reshape(-1))
                d0 += len(indices)
                r0 += n * n
                largest = max(largest, n_out * du)
            scratch = np.zeros(largest)
            scratch.fill(0.0)  # touch the pages here, not in the first iteration
            rows = np.concatenate(to_rows) if to_rows else np.zeros(0, np.int64)
            cols = np.concatenate(to_cols) if to_cols else np.zeros(0, np.int64)
            to_s = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.nnz, r0))
            self.dense_terms.append(_DenseSchurTerm(
                k, panels, np.concatenate(lidx) if lidx else np.zeros(0, np.int64), scratch,
                np.zeros(r0), to_s))
        del self._dense_pairs

    # --- numbers -----------------------------------------------------------------------------

    def assemble(
        self,
        jacobians: list[tuple[np.ndarray, ...]],
        weighted: list[tuple[np.ndarray, ...]],
        weighted_errors: list[np.ndarray],
    ) -> Assembly:
        """Accumulate ``JᵀΩJ`` and ``−JᵀΩe`` of every edge group into the fixed structure.

        Args:
            jacobians: Per group, per position ``(m, e, d)`` (C-contiguous).
            weighted: Per group, per position ``ρ' Ω J`` ``(m, e, d)`` (C-contiguous).
            weighted_errors: Per group ``ρ' Ω e`` ``(m, e)``.
        """
        h = np.zeros(self.nnz)
        bu = np.zeros(self.n)
        # V and W classes are allocated on first use: a first term that covers every block of
        # its class in order is used as it is (no zero fill, no scatter-add).
        v: list[np.ndarray | None] = [None] * len(self.vclasses)
        bv: list[np.ndarray | None] = [None] * len(self.vclasses)
        wt: list[np.ndarray | None] = [None] * len(self.wclasses)
        for gt, J, WJ, we in zip(self.terms, jacobians, weighted, weighted_errors, strict=True):
            mats: list[sp.csc_matrix | None] = []
            for t in gt.hterms:
                if t.gram is not None:  # diagonal U blocks by gathered Gram products
                    assert t.out is not None and t.to_h is not None
                    ja, wjb = J[t.left], WJ[t.right]
                    m = len(ja)
                    t.gram(np.ascontiguousarray(ja).reshape(m, -1), t.out,
                           None if wjb is ja else np.ascontiguousarray(wjb).reshape(m, -1))
                    h += t.to_h @ t.out.reshape(-1)
                    mats.append(None)
                    continue
                M = t.contraction.matrix(np.ascontiguousarray(J[t.left]))
                mats.append(M)
                blk = t.contraction.apply(M, WJ[t.right])
                if t.kind == "U":
                    flat = blk.reshape(len(blk), -1)
                    h[t.dest] += flat
                    if t.dest_t is not None:
                        h[t.dest_t] += flat
                elif t.kind == "V":
                    if t.mirror:
                        blk = blk + np.swapaxes(blk, 1, 2)
                    c = self.vclasses[t.cls]
                    _add_blocks(v, t.cls, t.dest, blk, t.identity, (len(c.slots), c.dim, c.dim))
                else:
                    c = self.wclasses[t.cls]
                    _add_blocks(wt, t.cls, t.dest, blk, t.identity, (len(c.ublock), c.dv, c.du))
            we3 = we[:, :, None]
            for g in gt.gterms:
                M = mats[g.shared] if g.shared >= 0 else None
                if M is None:
                    M = g.contraction.matrix(np.ascontiguousarray(J[g.a]))
                gb = -g.contraction.apply(M, we3)[:, :, 0]
                if g.kind == "U":
                    bu[g.dest] += gb
                else:
                    c = self.vclasses[g.cls]
                    _add_blocks(bv, g.cls, g.dest, gb, g.identity, (len(c.slots), c.dim))
        vfull = [x if x is not None else np.zeros((len(c.slots), c.dim, c.dim))
                 for x, c in zip(v, self.vclasses, strict=True)]
        bvfull = [x if x is not None else np.zeros((len(c.slots), c.dim))
                  for x, c in zip(bv, self.vclasses, strict=True)]
        wfull = [w if w is not None else np.zeros((len(c.ublock), c.dv, c.du))
                 for w, c in zip(wt, self.wclasses, strict=True)]
        return Assembly(h, bu, vfull, bvfull, wfull)

    @staticmethod
    def is_finite(asm: Assembly) -> bool:
        """Whether the U part, the V blocks and both right-hand sides are finite.

        Args:
            asm: The assembled system.
        """
        total = asm.h_data.sum() + asm.bu.sum()
        total += sum(float(v.sum()) for v in asm.v) + sum(float(b.sum()) for b in asm.bv)
        return bool(np.isfinite(total))

    def damping(self, asm: Assembly, diagonal: bool) -> tuple[np.ndarray, list[np.ndarray]]:
        """The damping matrix ``D`` (a diagonal) as ``(u part, [v parts])``.

        Args:
            asm: The assembled system.
            diagonal: ``False``: the identity (g2o's LM). ``True``: ``diag(H)`` clipped to
                ``[1e-6, 1e32]`` (Marquardt's scaling, as Ceres does).
        """
        if not diagonal:
            return np.ones(self.n), [np.ones(b.shape) for b in asm.bv]
        du = np.clip(asm.h_data[self.diag_pos], 1e-6, 1e32)
        return du, [np.clip(np.einsum("nii->ni", v), 1e-6, 1e32) for v in asm.v]

    def reduce(
        self, asm: Assembly, lam: float, damp: tuple[np.ndarray, list[np.ndarray]] | None = None
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """Damp by ``λ D`` and eliminate the V blocks.

        Args:
            asm: The assembled system.
            lam: Levenberg damping (0 for none).
            diagonal: Damp with ``λ·diag(H)`` (see :meth:`damping`) instead of ``λ I``.

        Returns:
            ``(s_data, rhs, vinv, yt)``: the reduced matrix's data, its right-hand side, the
            inverted (damped) V blocks per class, and ``Yᵀ = V⁻¹ Wᵀ`` for the W classes whose
            sparse pair products needed it (``None`` for the others).

        Raises:
            NotPositiveDefiniteError: if a V block is not positive definite.
        """
        s = asm.h_data.copy()
        vdamp: list[np.ndarray | None] = [None] * len(asm.v)
        if lam:
            du, dv = damp if damp is not None else self.damping(asm, False)
            s[self.diag_pos] += lam * du
            vdamp = [lam * d for d in dv]
        linv, vinv = [], []  # L⁻¹ and V⁻¹ of the damped V blocks (V + λD = LLᵀ)
        for vb, d in zip(asm.v, vdamp, strict=True):
            li, vi = batched_cholesky_inverses(vb, d)
            linv.append(li)
            vinv.append(vi)
        rhs = asm.bu.copy()
        # Dense and Gram terms compute their share of the right-hand side themselves.
        own_rhs = {t.k for t in self.dense_terms} | {t.k for t in self.gram_terms}
        vb_rhs: dict[int, np.ndarray] = {}  # V⁻¹ b_v per V class, when a sparse class needs it
        for k, wc in enumerate(self.wclasses):
            if k in own_rhs:
                continue
            if wc.vclass not in vb_rhs:
                vb_rhs[wc.vclass] = np.einsum("nij,nj->ni", vinv[wc.vclass], asm.bv[wc.vclass])
            assert wc.rhs is not None
            y = vb_rhs[wc.vclass][wc.vblock]
            rhs[wc.rhs_dest] -= wc.rhs(asm.wt[k], y[:, :, None])[:, :, 0]
        yt = self.y_transposed(asm, vinv, only={pt.k1 for pt in self.pair_terms})
        lb: dict[int, np.ndarray] = {}  # L⁻¹ b_v per V class, computed on first use

        def l_inv_b(vc: int) -> np.ndarray:
            if vc not in lb:
                lb[vc] = np.einsum("nij,nj->ni", linv[vc], asm.bv[vc])
            return lb[vc]

        for dt in self.dense_terms:
            wc = self.wclasses[dt.k]
            dv, du = wc.dv, wc.du
            x = l_inv_b(wc.vclass)
            lvals = np.take(linv[wc.vclass].reshape(-1), dt.lidx)
            wflat = np.ascontiguousarray(asm.wt[dt.k]).reshape(-1)
            for p in dt.panels:  # cache-sized tiles of V blocks with similar U sets
                n_out, n = p.rows * dv * p.cols, p.cols * du
                m = dt.scratch[:n_out * du]
                csr_product_into(n_out, (p.w1 - p.w0) * dv, du, p.indptr, p.indices,
                                 lvals[p.d0:p.d1], wflat[p.w0 * dv * du:p.w1 * dv * du], m)
                m2 = m.reshape(p.rows * dv, n)  # Z = L⁻¹Wᵀ, dense over the panel
                c = dt.results[p.r0:p.r0 + n * n].reshape(n, n, order="F")
                blas.dsyrk(1.0, m2.T, trans=0, c=c, overwrite_c=1)  # m2ᵀ m2, upper triangle
                rhs[p.rhs_pos] -= m2.T @ x[p.v0:p.v0 + p.rows].reshape(-1)
            s -= dt.to_s @ dt.results
        for gt in self.gram_terms:
            wc = self.wclasses[gt.k]
            dv, du, nw = wc.dv, wc.du, len(wc.ublock)
            lvals = np.take(linv[wc.vclass].reshape(-1), gt.lidx)
            wflat = np.ascontiguousarray(asm.wt[gt.k]).reshape(-1)
            csr_product_into(nw * dv, nw * dv, du, gt.indptr, gt.indices, lvals, wflat,
                             gt.z)  # Z = L⁻¹Wᵀ
            gt.gram(gt.z.reshape(nw, dv * du), gt.results)
            s -= gt.to_s @ gt.results.reshape(-1)
            n_u = len(wc.rhs_dest)
            zl = np.empty(n_u * du)
            csr_product_into(n_u, nw * dv, du, gt.rhs_indptr, gt.rhs_indices,
                             np.take(l_inv_b(wc.vclass), gt.rhs_lidx), gt.z, zl, csc=True)
            rhs[wc.rhs_dest] -= zl.reshape(n_u, du)  # Σ_w Z_wᵀ L⁻¹b_v per U block
        for pt in self.pair_terms:
            s -= pt.to_s @ pt.contraction(yt[pt.k1], asm.wt[pt.k2]).reshape(-1)
        return s, rhs, vinv

    def y_transposed(self, asm: Assembly, vinv: list[np.ndarray],
                     only: set[int] | None = None) -> list[np.ndarray | None]:
        """``Yᵀ = V⁻¹ Wᵀ`` per W class (``None`` for classes not in ``only``).

        Args:
            asm: The assembled system.
            vinv: Inverted V blocks per class.
            only: Classes to compute; all when ``None``.
        """
        return [np.matmul(vinv[wc.vclass][wc.vblock], asm.wt[k])
                if only is None or k in only else None
                for k, wc in enumerate(self.wclasses)]

    def back_substitute(
        self, asm: Assembly, du: np.ndarray, vinv: list[np.ndarray]
    ) -> list[np.ndarray]:
        """``Δv = V⁻¹ (b_v − Wᵀ Δu)`` per V class.

        Args:
            asm: The assembled system.
            du: Solution of the reduced system.
            vinv: Inverted damped V blocks per class.
        """
        r = [b.copy() for b in asm.bv]
        for k, wc in enumerate(self.wclasses):
            r[wc.vclass] -= self.wt_product(asm, k, du)
        return [np.matmul(vi, ri[:, :, None])[:, :, 0] for vi, ri in zip(vinv, r, strict=True)]

    def wt_product(self, asm: Assembly, k: int, xu: np.ndarray) -> np.ndarray:
        """``Σ_w Wᵀ_w x_u[u_w]`` per V block of W class ``k``, as ``(n_v, dv)``.

        Args:
            asm: The assembled system.
            k: W class.
            xu: A vector over the U part.
        """
        wc = self.wclasses[k]
        n_v = len(wc.bsr_indptr) - 1
        n_u = (wc.ucols.stop - wc.ucols.start) // wc.du
        m = sp.bsr_matrix((asm.wt[k], wc.bsr_cols, wc.bsr_indptr),
                          shape=(n_v * wc.dv, n_u * wc.du))
        return (m @ xu[wc.ucols]).reshape(n_v, wc.dv)

    def hessian_product(self, asm: Assembly, xu: np.ndarray, xv: list[np.ndarray]
                        ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The undamped full Hessian times a vector ``[xu, xv]``.

        Args:
            asm: The assembled system.
            xu: U part of the vector.
            xv: V parts per class.
        """
        hu = self.csc(asm.h_data) @ xu
        hv = [np.matmul(vb, x[:, :, None])[:, :, 0] for vb, x in zip(asm.v, xv, strict=True)]
        for k, wc in enumerate(self.wclasses):
            assert wc.rhs is not None
            hu[wc.rhs_dest] += wc.rhs(asm.wt[k], xv[wc.vclass][wc.vblock][:, :, None])[:, :, 0]
            hv[wc.vclass] += self.wt_product(asm, k, xu)
        return hu, hv

    def csc(self, data: np.ndarray) -> sp.csc_matrix:
        """The reduced matrix with the given data in the fixed pattern.

        Args:
            data: ``(nnz,)`` values.
        """
        p = self.pattern
        return sp.csc_matrix((data, p.indices, p.indptr), shape=p.shape)

    def max_diagonal(self, asm: Assembly) -> float:
        """Largest diagonal entry of the full (undamped) Hessian (for LM's initial λ).

        Args:
            asm: The assembled system.
        """
        vals = [asm.h_data[self.diag_pos]] + [np.einsum("nii->ni", vb).ravel() for vb in asm.v]
        vals = [x for x in vals if x.size]
        return float(max(x.max() for x in vals)) if vals else 0.0
