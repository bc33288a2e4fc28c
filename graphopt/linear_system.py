"""The block structure of the normal equations, built once, and their numeric assembly.

Vertices that are neither fixed nor marginalised are *U* blocks; marginalised ones are *V*
blocks (block-diagonal, eliminated by the Schur complement); *W* blocks couple the two. The
reduced system ``S = U − W V⁻¹ Wᵀ`` lives in one fixed CSC pattern (the U blocks plus the fill
from every pair of U blocks that share a V block). Everything index-related — which edge block
goes where, the pattern, the pairs for ``W V⁻¹ Wᵀ`` — is computed in :meth:`LinearSystem.__init__`;
each iteration only computes numbers (see ``docs/architecture.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from graphopt.block_ops import SegmentSum, batched_inverse_spd
from graphopt.graph import EdgeGroup, GraphError, VertexStore


@dataclass
class _HTerm:
    """One Hessian block term: positions ``(a, b)`` of an edge group, one destination kind."""

    a: int
    b: int
    kind: str  # "U", "V" or "W"
    sel: np.ndarray | None  # edge subset, None for all edges
    transpose: bool  # block value is J_bᵀ Ω J_a (for W terms with the V vertex at position a)
    reduce: SegmentSum
    dest: np.ndarray  # U: (t, da*db) data positions; V/W: (t,) block index
    dest_t: np.ndarray | None = None  # U off-diagonal: positions of the transposed entries
    cls: int = -1  # V class or W class index
    mirror: bool = False  # V term with a != b on the same vertex: add the transpose too


@dataclass
class _GTerm:
    """One gradient term: position ``a`` of an edge group into U or a V class."""

    a: int
    kind: str
    sel: np.ndarray | None
    reduce: SegmentSum
    dest: np.ndarray  # U: (t, d) vector positions; V: (t,) block index
    cls: int = -1


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
    to_u: SegmentSum | None = None
    to_v: SegmentSum | None = None


@dataclass
class _PairTerm:
    """Pairs of W blocks (same V block) whose products fill ``W V⁻¹ Wᵀ``."""

    k1: int
    k2: int
    w1: np.ndarray
    w2: np.ndarray
    reduce: SegmentSum
    dest: np.ndarray  # (t, d1*d2) positions in S data
    dest_t: np.ndarray | None  # transposed positions for off-diagonal targets (None if none)
    offdiag: np.ndarray | None  # (t,) bool, which targets are off-diagonal


@dataclass
class Assembly:
    """The numbers of one linearisation.

    Args:
        h_data: Data of the U part in the S pattern (undamped, without Schur terms).
        bu: Right-hand side (``−Jᵀ ρ' Ω e``) of the U part.
        v: Per V class ``(n, d, d)`` blocks.
        bv: Per V class ``(n, d)``.
        w: Per W class ``(n, du, dv)`` blocks.
    """

    h_data: np.ndarray
    bu: np.ndarray
    v: list[np.ndarray]
    bv: list[np.ndarray]
    w: list[np.ndarray]


def _positions(keys_sorted: np.ndarray, rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """Data positions of entries (rows, cols) in a CSC pattern given its sorted col*n+row keys."""
    return np.searchsorted(keys_sorted, cols.astype(np.int64) * n + rows)


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
    ) -> None:
        self.stores = stores
        self.groups = groups
        self.positions = positions
        self._index_vertices()
        self._build_terms()
        self._build_pattern()

    # --- structure ---------------------------------------------------------------------------

    def _index_vertices(self) -> None:
        self.ublock: list[np.ndarray] = []
        self.vblock: list[np.ndarray] = []
        self.vclass_of_store: list[int] = []
        self.vclasses: list[VClass] = []
        ustart, udims, ustore_of = [], [], []
        nu = 0
        for si, st in enumerate(self.stores):
            active = ~st.fixed
            umask = active & ~st.marginalized
            vmask = active & st.marginalized
            ub = np.full(len(st), -1, dtype=np.int64)
            ub[umask] = nu + np.arange(int(umask.sum()))
            nu += int(umask.sum())
            self.ublock.append(ub)
            udims.append(np.full(int(umask.sum()), st.vtype.dimension))
            ustore_of.append(np.full(int(umask.sum()), si))
            ustart.append(np.flatnonzero(umask))
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
        self.uslot = np.concatenate(ustart) if ustart else np.zeros(0, dtype=np.int64)
        self.uoffset = np.concatenate([[0], np.cumsum(self.udims)]).astype(np.int64)
        self.n = int(self.uoffset[-1])
        self.schur = bool(self.vclasses)

    def _build_terms(self) -> None:
        self.wclasses: list[WClass] = []
        wkey: dict[tuple[int, int], int] = {}
        w_pairs: list[list[np.ndarray]] = []  # per W class: list of (ublock, vblock) arrays
        self.terms: list[_GroupTerms] = []
        ublock_pairs: list[np.ndarray] = []  # (n, 2) U block pairs that need a pattern block
        pending_w: list[tuple[_GroupTerms, int, int, int, np.ndarray | None, bool, np.ndarray,
                              np.ndarray]] = []

        for gi, g in enumerate(self.groups):
            gt = _GroupTerms()
            pos = self.positions[gi]
            ub = [self.ublock[s][slots] for s, slots in pos]
            vb = [self.vblock[s][slots] for s, slots in pos]
            isu = [u >= 0 for u in ub]
            isv = [v >= 0 for v in vb]
            for a in range(g.k):
                for b in range(a, g.k):
                    # U-U
                    mask = isu[a] & isu[b]
                    if mask.any():
                        sel = None if mask.all() else np.flatnonzero(mask)
                        pa, pb = ub[a][mask], ub[b][mask]
                        ublock_pairs.append(np.stack([pa, pb], 1))
                        if a != b:
                            ublock_pairs.append(np.stack([pb, pa], 1))
                        key = pa * self.n_ublocks + pb
                        uniq, inv = np.unique(key, return_inverse=True)
                        gt.hterms.append(
                            _HTerm(a, b, "U", sel, False, SegmentSum(inv, len(uniq)),
                                   np.stack([uniq // self.n_ublocks, uniq % self.n_ublocks], 1))
                        )
                    # V-V
                    mask = isv[a] & isv[b]
                    if mask.any():
                        if a != b and np.any(vb[a][mask] != vb[b][mask]) or (
                            a != b and pos[a][0] != pos[b][0]
                        ):
                            raise GraphError(
                                f"{g.etype.__name__}: an edge connects two different "
                                "marginalised vertices; the Schur complement needs marginalised "
                                "vertices to be independent given the others"
                            )
                        sel = None if mask.all() else np.flatnonzero(mask)
                        tv = vb[a][mask]
                        uniq, inv = np.unique(tv, return_inverse=True)
                        gt.hterms.append(
                            _HTerm(a, b, "V", sel, False, SegmentSum(inv, len(uniq)), uniq,
                                   cls=self.vclass_of_store[pos[a][0]], mirror=a != b)
                        )
                    # U-V and V-U
                    for ui, vi, tr in ((a, b, False), (b, a, True)):
                        if a == b:
                            continue
                        mask = isu[ui] & isv[vi]
                        if not mask.any():
                            continue
                        sel = None if mask.all() else np.flatnonzero(mask)
                        key = (pos[ui][0], self.vclass_of_store[pos[vi][0]])
                        if key not in wkey:
                            wkey[key] = len(self.wclasses)
                            st_u = self.stores[key[0]]
                            self.wclasses.append(
                                WClass(key[0], key[1], st_u.vtype.dimension,
                                       self.vclasses[key[1]].dim, np.zeros(0), np.zeros(0))
                            )
                            w_pairs.append([])
                        k = wkey[key]
                        w_pairs[k].append(np.stack([ub[ui][mask], vb[vi][mask]], 1))
                        pending_w.append((gt, a, b, k, sel, tr, ub[ui][mask], vb[vi][mask]))
            for a in range(g.k):
                if isu[a].any():
                    sel = None if isu[a].all() else np.flatnonzero(isu[a])
                    t = ub[a][isu[a]]
                    uniq, inv = np.unique(t, return_inverse=True)
                    gt.gterms.append(_GTerm(a, "U", sel, SegmentSum(inv, len(uniq)), uniq))
                if isv[a].any():
                    sel = None if isv[a].all() else np.flatnonzero(isv[a])
                    t = vb[a][isv[a]]
                    uniq, inv = np.unique(t, return_inverse=True)
                    gt.gterms.append(_GTerm(a, "V", sel, SegmentSum(inv, len(uniq)), uniq,
                                            cls=self.vclass_of_store[pos[a][0]]))
            self.terms.append(gt)

        # Unique W blocks per class, then map each W term's edges onto them.
        for k, wc in enumerate(self.wclasses):
            allp = np.concatenate(w_pairs[k])
            nvb = len(self.vclasses[wc.vclass].slots)
            # Order W blocks by V block so that a point's blocks are contiguous.
            keys = np.unique(allp[:, 1] * self.n_ublocks + allp[:, 0])
            wc.vblock, wc.ublock = keys // self.n_ublocks, keys % self.n_ublocks
            wc.to_v = SegmentSum(wc.vblock, nvb)
            wc.to_u = SegmentSum(wc.ublock, self.n_ublocks)
            wc.upos = (self.uoffset[wc.ublock][:, None] + np.arange(wc.du)).astype(np.int64)
            wc._keys = keys  # type: ignore[attr-defined]
        for gt, a, b, k, sel, tr, ubs, vbs in pending_w:
            keys = self.wclasses[k]._keys  # type: ignore[attr-defined]
            widx = np.searchsorted(keys, vbs * self.n_ublocks + ubs)
            uniq, inv = np.unique(widx, return_inverse=True)
            gt.hterms.append(_HTerm(a, b, "W", sel, tr, SegmentSum(inv, len(uniq)), uniq, cls=k))

        # Pairs of W blocks sharing a V block: the fill of the reduced system.
        self.pairs: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        for k1, c1 in enumerate(self.wclasses):
            for k2 in range(k1, len(self.wclasses)):
                c2 = self.wclasses[k2]
                if c1.vclass != c2.vclass:
                    continue
                w1, w2 = self._pairs_sharing_v(c1.vblock, c2.vblock)
                if k1 == k2:
                    keep = c1.ublock[w1] <= c2.ublock[w2]
                    w1, w2 = w1[keep], w2[keep]
                if len(w1):
                    self.pairs.append((k1, k2, w1, w2))
                    u1, u2 = c1.ublock[w1], c2.ublock[w2]
                    ublock_pairs.append(np.stack([u1, u2], 1))
                    ublock_pairs.append(np.stack([u2, u1], 1))
        diag = np.arange(self.n_ublocks)
        ublock_pairs.append(np.stack([diag, diag], 1))
        bp = np.concatenate(ublock_pairs) if ublock_pairs else np.zeros((0, 2), dtype=np.int64)
        self._block_pairs = np.unique(bp[:, 1] * max(self.n_ublocks, 1) + bp[:, 0])

    @staticmethod
    def _pairs_sharing_v(v1: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All index pairs (i, j) with ``v1[i] == v2[j]`` (both sorted by v), vectorised."""
        nv = int(max(v1.max(initial=-1), v2.max(initial=-1))) + 1
        c1 = np.bincount(v1, minlength=nv)
        c2 = np.bincount(v2, minlength=nv)
        s1 = np.concatenate([[0], np.cumsum(c1)[:-1]])
        s2 = np.concatenate([[0], np.cumsum(c2)[:-1]])
        per = c1 * c2
        total = int(per.sum())
        vv = np.repeat(np.arange(nv), per)
        k = np.arange(total) - np.repeat(np.cumsum(per) - per, per)
        i = k // np.maximum(c2[vv], 1)
        j = k % np.maximum(c2[vv], 1)
        return s1[vv] + i, s2[vv] + j

    def _block_entries(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scalar (row, col) of every entry of blocks (r, c), row-major within a block."""
        dr, dc = self.udims[r], self.udims[c]
        if len(r) == 0:
            return np.zeros((0, 0), np.int64), np.zeros((0, 0), np.int64)
        d1, d2 = int(dr[0]), int(dc[0])
        assert np.all(dr == d1) and np.all(dc == d2)
        rows = self.uoffset[r][:, None, None] + np.arange(d1)[None, :, None]
        cols = self.uoffset[c][:, None, None] + np.arange(d2)[None, None, :]
        rows, cols = np.broadcast_arrays(rows, cols)
        return rows.reshape(len(r), -1), cols.reshape(len(r), -1)

    def _build_pattern(self) -> None:
        n, nb = self.n, max(self.n_ublocks, 1)
        bc, br = self._block_pairs // nb, self._block_pairs % nb
        rows_l, cols_l = [], []
        # Blocks of different sizes are expanded per size class.
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
        indices = (keys % max(n, 1)).astype(np.int32)
        colidx = keys // max(n, 1)
        indptr = np.searchsorted(colidx, np.arange(n + 1)).astype(np.int32)
        self.pattern = sp.csc_matrix((np.zeros(len(keys)), indices, indptr), shape=(n, n))
        self.nnz = len(keys)
        diag = np.arange(n)
        self.diag_pos = _positions(keys, diag, diag, n)

        for gt in self.terms:
            for t in gt.hterms:
                if t.kind != "U":
                    continue
                pa, pb = t.dest[:, 0], t.dest[:, 1]
                r, c = self._block_entries(pa, pb)
                pos = _positions(keys, r, c, n)
                if t.a != t.b:
                    # Entry (i, j) of block (pa, pb) sits at (col pb+j, row pa+i) transposed.
                    d1, d2 = int(self.udims[pa[0]]), int(self.udims[pb[0]])
                    rt = c.reshape(-1, d1, d2)
                    ct = r.reshape(-1, d1, d2)
                    t.dest_t = _positions(keys, rt, ct, n).reshape(len(pa), -1)
                t.dest = pos
            for g in gt.gterms:
                if g.kind == "U":
                    d = int(self.udims[g.dest[0]])
                    g.dest = self.uoffset[g.dest][:, None] + np.arange(d)
        self.pair_terms: list[_PairTerm] = []
        for k1, k2, w1, w2 in self.pairs:
            c1, c2 = self.wclasses[k1], self.wclasses[k2]
            u1, u2 = c1.ublock[w1], c2.ublock[w2]
            key = u1 * self.n_ublocks + u2
            order = np.argsort(key, kind="stable")
            w1, w2, key = w1[order], w2[order], key[order]
            uniq, inv = np.unique(key, return_inverse=True)
            tu1, tu2 = uniq // self.n_ublocks, uniq % self.n_ublocks
            r, c = self._block_entries(tu1, tu2)
            dest = _positions(keys, r, c, n)
            off = tu1 != tu2
            dest_t = None
            if off.any():
                rt = c.reshape(-1, c1.du, c2.du)
                ct = r.reshape(-1, c1.du, c2.du)
                dest_t = _positions(keys, rt, ct, n).reshape(len(tu1), -1)[off]
            self.pair_terms.append(
                _PairTerm(k1, k2, w1, w2, SegmentSum(inv, len(uniq)), dest, dest_t,
                          off if off.any() else None)
            )
        # Diagonal blocks, for block-Jacobi preconditioning and the marginals.
        self.diag_blocks: list[tuple[int, np.ndarray, np.ndarray]] = []
        for d in np.unique(self.udims):
            blocks = np.flatnonzero(self.udims == d)
            r, c = self._block_entries(blocks, blocks)
            self.diag_blocks.append((int(d), blocks, _positions(keys, r, c, n)))

    # --- numbers -----------------------------------------------------------------------------

    def assemble(
        self,
        jacobians: list[tuple[np.ndarray, ...]],
        weighted: list[tuple[np.ndarray, ...]],
        weighted_errors: list[np.ndarray],
    ) -> Assembly:
        """Accumulate ``JᵀΩJ`` and ``−JᵀΩe`` of every edge group into the fixed structure.

        Args:
            jacobians: Per group, per position ``(m, e, d)``.
            weighted: Per group, per position ``ρ' Ω J`` ``(m, e, d)``.
            weighted_errors: Per group ``ρ' Ω e`` ``(m, e)``.
        """
        h = np.zeros(self.nnz)
        bu = np.zeros(self.n)
        v = [np.zeros((len(c.slots), c.dim, c.dim)) for c in self.vclasses]
        bv = [np.zeros((len(c.slots), c.dim)) for c in self.vclasses]
        w = [np.zeros((len(c.ublock), c.du, c.dv)) for c in self.wclasses]
        for gt, J, WJ, we in zip(self.terms, jacobians, weighted, weighted_errors, strict=True):
            for t in gt.hterms:
                ja, wjb = (J[t.b], WJ[t.a]) if t.transpose else (J[t.a], WJ[t.b])
                if t.sel is not None:
                    ja, wjb = ja[t.sel], wjb[t.sel]
                blk = t.reduce(np.matmul(np.swapaxes(ja, 1, 2), wjb))
                if t.kind == "U":
                    flat = blk.reshape(len(blk), -1)
                    h[t.dest] += flat
                    if t.dest_t is not None:
                        h[t.dest_t] += flat
                elif t.kind == "V":
                    v[t.cls][t.dest] += blk
                    if t.mirror:
                        v[t.cls][t.dest] += np.swapaxes(blk, 1, 2)
                else:
                    w[t.cls][t.dest] += blk
            for g in gt.gterms:
                ja = J[g.a] if g.sel is None else J[g.a][g.sel]
                e = we if g.sel is None else we[g.sel]
                gb = g.reduce(-np.einsum("mei,me->mi", ja, e))
                if g.kind == "U":
                    bu[g.dest] += gb
                else:
                    bv[g.cls][g.dest] += gb
        return Assembly(h, bu, v, bv, w)

    def reduce(
        self, asm: Assembly, lam: float
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
        """Damp by ``λ`` and eliminate the V blocks.

        Args:
            asm: The assembled system.
            lam: Levenberg damping added to every diagonal entry (0 for none).

        Returns:
            ``(s_data, rhs, vinv, y)``: the reduced matrix's data, its right-hand side, the
            inverted (damped) V blocks per class, and ``Y = W V⁻¹`` per W class.

        Raises:
            NotPositiveDefiniteError: if a V block is not positive definite.
        """
        s = asm.h_data.copy()
        if lam:
            s[self.diag_pos] += lam
        vinv = []
        for vb in asm.v:
            vd = vb + lam * np.eye(vb.shape[1]) if lam else vb
            vinv.append(batched_inverse_spd(vd))
        rhs = asm.bu.copy()
        y = []
        for k, wc in enumerate(self.wclasses):
            yk = np.matmul(asm.w[k], vinv[wc.vclass][wc.vblock])
            y.append(yk)
            assert wc.to_u is not None
            contrib = np.einsum("nij,nj->ni", yk, asm.bv[wc.vclass][wc.vblock])
            rhs -= self._scatter_u(wc, contrib)
        for pt in self.pair_terms:
            prod = np.matmul(y[pt.k1][pt.w1], np.swapaxes(asm.w[pt.k2][pt.w2], 1, 2))
            red = pt.reduce(prod).reshape(pt.reduce.n_targets, -1)
            s[pt.dest] -= red
            if pt.dest_t is not None:
                s[pt.dest_t] -= red[pt.offdiag]
        return s, rhs, vinv, y

    def _scatter_u(self, wc: WClass, contrib: np.ndarray) -> np.ndarray:
        """Sum per-W-block vectors ``(n, du)`` into a full U-sized vector."""
        assert wc.to_u is not None
        out = np.zeros(self.n)
        summed = wc.to_u(contrib)  # (n_ublocks, du); rows of other stores stay zero
        blocks = np.flatnonzero(self.ustore == wc.ustore)
        if len(blocks):
            out[(self.uoffset[blocks][:, None] + np.arange(wc.du)).ravel()] = summed[
                blocks
            ].ravel()
        return out

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
            assert wc.to_v is not None
            wt = np.einsum("nij,ni->nj", asm.w[k], du[wc.upos])
            r[wc.vclass] -= wc.to_v(wt)
        return [np.einsum("nij,nj->ni", vi, ri) for vi, ri in zip(vinv, r, strict=True)]

    def hessian_product(self, asm: Assembly, xu: np.ndarray, xv: list[np.ndarray]
                        ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The undamped full Hessian times a vector ``[xu, xv]``.

        Args:
            asm: The assembled system.
            xu: U part of the vector.
            xv: V parts per class.
        """
        hu = self.csc(asm.h_data) @ xu
        hv = [np.einsum("nij,nj->ni", vb, x) for vb, x in zip(asm.v, xv, strict=True)]
        for k, wc in enumerate(self.wclasses):
            assert wc.to_v is not None
            hu += self._scatter_u(wc, np.einsum("nij,nj->ni", asm.w[k], xv[wc.vclass][wc.vblock]))
            hv[wc.vclass] += wc.to_v(np.einsum("nij,ni->nj", asm.w[k], xu[wc.upos]))
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
