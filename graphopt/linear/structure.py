"""The block index of the normal equations, built once per graph structure.

Vertices that are neither fixed nor marginalised are *U* blocks (numbered across the stores);
marginalised ones are *V* blocks (numbered within their store's *V class*, in co-visibility
order); *W* blocks couple a U and a V block that share an edge, grouped into *W classes* by (U
store, V class). The reduced matrix ``S = U − W V⁻¹ Wᵀ`` has the U blocks, the U-U blocks of
the edges and the *fill* (pairs of U blocks that share a V block); its scalar pattern is
:class:`~graphopt.linear.pattern.ReducedPattern`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.errors import GraphError
from graphopt.linear.block_ops import csr_product_into
from graphopt.linear.indexing import pairs_sharing_key, pairs_within_key, unique_ints
from graphopt.linear.ordering import co_visibility_order, dense_co_visibility, first_seen_order
from graphopt.linear.pattern import ReducedPattern

if TYPE_CHECKING:
    from graphopt.storage import EdgeGroup, VertexStore

#: Per edge group, per vertex position: ``(store index, slots (m,))``.
Positions = list[list[tuple[int, np.ndarray]]]


@dataclass
class VClass:
    """All marginalised vertices of one store.

    Args:
        store: The store.
        dim: Their tangent dimension.
        slots: ``(n,)`` store slot of every V block, by V block index.
    """

    store: int
    dim: int
    slots: np.ndarray


class EdgeSums:
    """``out[t] = Σ_{e ∈ sel, target(e) = t} A_eᵀ B_e`` for blocks ``A`` ``(m, r, d)`` and
    ``B`` ``(m, r, d2)`` with few columns ``d2`` (a gradient ``Jᵀe``, ``Σ_w W_w x_w``).

    One product per column ``k`` of ``B`` with a constant CSC matrix: a column per row
    ``(e, i)`` of the blocks, holding ``B[e, i, k]`` in row ``target(e)``. SciPy's loop reads
    ``A`` once, in memory order, and sums its rows into the output, so nothing is gathered;
    the index is 4 bytes per row ``(e, i)`` (:class:`~graphopt.linear.block_ops.
    EdgeContraction` keeps ``4·d``), plus the column pointers, shared by sums over the same
    rows. Against the contraction: as fast for ``d2 = 1``, twice as slow for ``d2 = 3`` (so the
    V blocks keep the contraction).

    Args:
        target: Target of every block in ``sel``.
        n_targets: Number of targets.
        r: Rows of a block.
        sel: Sorted blocks that take part (``None``: all, ``target`` per block).
        m: Number of blocks (with ``sel``).
        indptr: ``arange(m·r + 1)`` to share (all blocks only), or ``None``.
    """

    def __init__(self, target: np.ndarray, n_targets: int, r: int,
                 sel: np.ndarray | None = None, m: int | None = None,
                 indptr: np.ndarray | None = None) -> None:
        m = len(target) if sel is None else int(m if m is not None else len(target))
        idx_t = np.int32 if max(n_targets, m * r) < 2**31 else np.int64
        self.indices = np.repeat(np.asarray(target).astype(idx_t), r)
        if sel is None or len(sel) == m:
            self.indptr = indptr if indptr is not None else np.arange(m * r + 1, dtype=idx_t)
            self._rows = None
        else:
            has = np.zeros(m * r, dtype=idx_t)
            self._rows = (np.asarray(sel)[:, None] * r + np.arange(r)).ravel()
            has[self._rows] = 1
            self.indptr = np.concatenate([np.zeros(1, idx_t), np.cumsum(has, dtype=idx_t)])
        self.n_targets, self.m, self.r = n_targets, m, r

    @property
    def all(self) -> bool:
        """Whether every block takes part."""
        return self._rows is None

    @staticmethod
    def pointers(m: int, r: int) -> np.ndarray:
        """``arange(m·r + 1)``: column pointers to share between sums over all of ``m``
        blocks of ``r`` rows.

        Args:
            m: Blocks.
            r: Rows of a block.
        """
        return np.arange(m * r + 1, dtype=np.int32 if m * r < 2**31 else np.int64)

    def __call__(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """``out`` as ``(n_targets, d, d2)``.

        Args:
            A: ``(m, r, d)`` blocks.
            B: ``(m, r, d2)`` blocks.
        """
        m, r, d = A.shape
        d2 = B.shape[2]
        a = np.ascontiguousarray(A).reshape(-1)
        out = np.empty((d2, self.n_targets * d))
        for k in range(d2):
            data = B[:, :, k].reshape(-1)  # a copy unless d2 == 1
            if self._rows is not None:
                data = data[self._rows]
            csr_product_into(self.n_targets, m * r, d, self.indptr, self.indices, data, a,
                             out[k], csc=True)
        if d2 == 1:
            return out.reshape(self.n_targets, d, 1)
        return np.ascontiguousarray(out.reshape(d2, self.n_targets, d).transpose(1, 2, 0))


class BlockRows:
    """``(n, du)`` scalar rows of the U block of every W block, computed when indexed (an
    ``(n, du)`` array would cost ``8·du`` bytes per W block).

    Args:
        ublock: ``(n,)`` U block of every W block.
        uoffset: Scalar offset of every U block.
        du: U block dimension.
    """

    def __init__(self, ublock: np.ndarray, uoffset: np.ndarray, du: int) -> None:
        self._ublock, self._uoffset, self._du = ublock, uoffset, du
        self.shape = (len(ublock), du)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, w: object) -> np.ndarray:
        return self._uoffset[self._ublock[w]][..., None] + np.arange(self._du)

    def __array__(self, dtype: object = None, copy: object = None) -> np.ndarray:
        out = self[slice(None)]
        return out if dtype is None else out.astype(dtype)


@dataclass
class WClass:
    """The W blocks between the U vertices of one store and one V class.

    Blocks are stored transposed (``Wᵀ``, ``(dv, du)``, the layout every product wants) and
    sorted by V block, then U block.

    Args:
        ustore: The U vertices' store.
        vclass: The V class.
        du: U block dimension.
        dv: V block dimension.
        ublock: ``(n,)`` global U block of every W block (``int32`` where ``u · (n_ublocks
            + 1)`` and ``v · dv²`` fit in it, else ``int64``).
        vblock: ``(n,)`` block within the V class of every W block (same type).
        upos: ``(n, du)`` scalar rows of every W block's U block (computed when indexed).
        bsr_indptr: ``(n_v + 1,)`` W blocks of every V block.
        ucols: The store's scalar U entries.
        n_ublocks: U blocks of the graph (the base of :attr:`keys`).
        ub0: The store's first U block (its U blocks are contiguous).
        uoffset: Scalar offset of every U block (the block index's).

    :attr:`rhs`, :attr:`rhs_dest` and :attr:`bsr_cols`, which only products with assembled W
    blocks use, are computed on first use (a matrix-free system never builds them).
    """

    ustore: int
    vclass: int
    du: int
    dv: int
    ublock: np.ndarray
    vblock: np.ndarray
    upos: BlockRows
    bsr_indptr: np.ndarray
    ucols: slice
    n_ublocks: int
    ub0: int
    uoffset: np.ndarray

    @cached_property
    def _targets(self) -> tuple[np.ndarray, np.ndarray]:
        return unique_ints(self.ublock, max(self.n_ublocks, 1), True)

    @cached_property
    def rhs(self) -> EdgeSums:
        """``Σ_w W_w x[w]`` into the U blocks of the class (``Wᵀ`` used in place: it is
        ``Σ_w (Wᵀ_w)ᵀ x[w]``)."""
        uu, inv = self._targets
        return EdgeSums(inv, len(uu), self.dv)

    @cached_property
    def rhs_dest(self) -> np.ndarray:
        """``(n_u, du)`` scalar rows of the U blocks :attr:`rhs` sums into."""
        return self.uoffset[self._targets[0]][:, None] + np.arange(self.du)

    @cached_property
    def bsr_cols(self) -> np.ndarray:
        """``(n,)`` column block of every W block among the store's U blocks: ``Wᵀ`` of the
        class is a BSR matrix whose data is the W array as it is (the type of
        :attr:`bsr_indptr`: SciPy would convert mixed indices at every product)."""
        return (self.ublock - self.ub0).astype(self.bsr_indptr.dtype)

    @property
    def keys(self) -> np.ndarray:
        """``(n,)`` sorted ``vblock · n_ublocks + ublock`` (computed on use, at set-up)."""
        return self.vblock.astype(np.int64) * max(self.n_ublocks, 1) + self.ublock


class BlockIndex:
    """U, V and W blocks of a graph, their numbering, and the reduced pattern.

    Args:
        stores: The vertex stores.
        groups: The finalised edge groups.
        positions: Per group, per vertex position: ``(store index, slots (m,))``.
        spectral_max: Most U blocks ordered by co-visibility (see
            :func:`~graphopt.linear.ordering.co_visibility_order`).
        matrix_free: Whether the reduced system is only ever used through products (an
            implicit Schur solver): then ``S``'s fill is left out of the pattern, which holds
            only the U blocks and the U-U blocks of edges (``H_uu``). A callable decides, given
            this index once its U, V and W blocks are numbered (before the pattern is built).
        u_order: Given the U-U block keys (sorted unique ``col · n_ublocks + row``, both
            triangles) and the U blocks' sizes, an order of the U blocks to number them in,
            or ``None`` for the graph's order (a linear solver's
            :meth:`~graphopt.solvers.base.LinearSolver.block_order`); asked only when no
            vertex is marginalised.

    Attributes:
        stores: The vertex stores (as given).
        groups: The edge groups (as given).
        positions: The groups' positions (as given).
        ublock: Per store, ``(n_store,)`` global U block of every slot (−1: not a U block).
        vblock: Per store, ``(n_store,)`` V block of every slot within its V class (−1: none).
        vclass_of_store: Per store, its V class (−1: none).
        vclasses: The V classes.
        wclasses: The W classes, in the order edges first reveal them.
        wclass_of: The W class of every ``(U store, V class)``.
        n_ublocks: Number of U blocks.
        udims: ``(n_ublocks,)`` dimension of every U block.
        ustore: ``(n_ublocks,)`` store of every U block.
        uoffset: ``(n_ublocks + 1,)`` scalar offset of every U block, then ``n``.
        n: Size of the reduced system.
        matrix_free: Whether the pattern leaves out the fill (see the argument).
        pattern: The scalar pattern of ``S`` (of ``H_uu`` when ``matrix_free``).

    Raises:
        GraphError: if an edge joins two different marginalised vertices.
    """

    def __init__(self, stores: list[VertexStore], groups: list[EdgeGroup], positions: Positions,
                 spectral_max: int = 600,
                 matrix_free: bool | Callable[[BlockIndex], bool] = False,
                 u_order: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None
                 ) -> None:
        self.stores, self.groups, self.positions = stores, groups, positions
        self._number_blocks()
        nb = max(self.n_ublocks, 1)
        u_keys, w_found = self._scan_edges()
        self._fill: dict[int, np.ndarray] = {}
        self._inc: list[tuple[np.ndarray, np.ndarray]] = []
        # A V class with one W class: that class's blocks are the incidence, renumbered.
        only: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for vc in range(len(self.vclasses)):
            v, u = self._incidence(vc, w_found)
            self._inc.append((v, u))  # the U pairs of the fill do not depend on V's numbering
            single = sum(c == vc for _, c in w_found) == 1
            order = self._order_v_blocks(vc, v, u, w_found, spectral_max, renumber=not single,
                                         stream=matrix_free is True)
            if single:
                only[vc] = (v, u, order)
        self.wclass_of: dict[tuple[int, int], int] = {}
        self.wclasses: list[WClass] = []
        for key, found in w_found.items():
            self.wclass_of[key] = len(self.wclasses)
            self.wclasses.append(self._wclass(*key, found, only.pop(key[1], None)))
        del w_found
        self.matrix_free = bool(matrix_free(self) if callable(matrix_free) else matrix_free)
        keys = [u_keys]
        if not self.matrix_free:
            keys += [self.fill_keys(vc) for vc in range(len(self.vclasses))]
        self._inc, self._fill = [], {}  # only needed while the pattern is built
        block_keys = unique_ints(np.concatenate(keys), nb * nb)
        if u_order is not None and not self.vclasses and self.n_ublocks:
            order = u_order(block_keys, self.udims)
            if order is not None:
                block_keys = self._renumber_u(np.asarray(order, dtype=np.int64), block_keys)
        self.pattern = ReducedPattern(self.uoffset, self.udims, block_keys)

    def _renumber_u(self, order: np.ndarray, keys: np.ndarray) -> np.ndarray:
        """Number the U blocks in ``order`` (new block ``b`` is old block ``order[b]``; no V
        classes, so nothing else holds U numbers yet); return ``keys`` renumbered."""
        nb = self.n_ublocks
        if len(order) != nb or not np.array_equal(np.sort(order), np.arange(nb)):
            raise ValueError(f"a U block order must be a permutation of {nb} blocks")
        new_id = np.empty(nb, dtype=np.int64)
        new_id[order] = np.arange(nb)
        self.ublock = [np.where(ub >= 0, new_id[np.maximum(ub, 0)], -1) for ub in self.ublock]
        self.udims, self.ustore = self.udims[order], self.ustore[order]
        self.uoffset = np.concatenate([[0], np.cumsum(self.udims)]).astype(np.int64)
        return unique_ints(new_id[keys // nb] * nb + new_id[keys % nb], nb * nb)

    def fill_keys(self, vc: int) -> np.ndarray:
        """The fill of V class ``vc`` (pairs of U blocks that share one of its V blocks, the
        structure of ``IncᵀInc``) as keys ``col · n_ublocks + row``, both triangles with the
        diagonal; computed once, and only while the index is built.

        Args:
            vc: The V class.
        """
        if vc not in self._fill:
            nb = max(self.n_ublocks, 1)
            v, u = self._inc[vc]
            n_v = len(self.vclasses[vc].slots)
            if dense_co_visibility(n_v, nb):  # small: no SciPy set-up (the same pairs)
                dense = np.zeros((n_v, nb))
                dense[v, u] = 1.0
                row, col = np.nonzero(dense.T @ dense)
                self._fill[vc] = col.astype(np.int64) * nb + row
            else:
                inc = sp.csr_matrix((np.ones(len(v)), (v, u)), shape=(n_v, nb))
                fill = (inc.T @ inc).tocoo()
                del inc
                self._fill[vc] = fill.col.astype(np.int64) * nb + fill.row
        return self._fill[vc]

    def blocks_of(self, gi: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """U and V blocks of every edge of group ``gi``, per position (−1: none).

        Args:
            gi: The group.
        """
        pos = self.positions[gi]
        return ([self.ublock[s][slots] for s, slots in pos],
                [self.vblock[s][slots] for s, slots in pos])

    def w_pairs(self, k1: int, k2: int) -> tuple[np.ndarray, np.ndarray]:
        """Pairs of W blocks ``(w1, w2)`` of classes ``k1`` and ``k2`` that share a V block.

        For a class with itself only the pairs with ``u(w1) < u(w2)`` (``S`` is symmetric;
        the diagonal pairs ``(w, w)`` are summed apart).

        Args:
            k1: A W class.
            k2: A W class of the same V class.
        """
        c1, c2 = self.wclasses[k1], self.wclasses[k2]
        if k1 == k2:  # a V block's W blocks are sorted by U block: u(w1) < u(w2) is w1 < w2
            return pairs_within_key(c1.vblock)
        return pairs_sharing_key(c1.vblock, c2.vblock)

    # --- construction ------------------------------------------------------------------------

    def _number_blocks(self) -> None:
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

    def _scan_edges(self) -> tuple[np.ndarray, dict[tuple[int, int], list[np.ndarray]]]:
        """U-U block keys (``col · n_ublocks + row``, with the diagonal) and, per W class key
        ``(U store, V class)`` in the order edges reveal them, the ``(U block, V block)`` pairs
        of its edges."""
        nb = max(self.n_ublocks, 1)
        u_keys = [np.arange(self.n_ublocks) * (nb + 1)]
        w_found: dict[tuple[int, int], list[np.ndarray]] = {}
        for gi, pos in enumerate(self.positions):
            ub, vb = self.blocks_of(gi)
            for a, b in combinations(range(len(pos)), 2):
                both_v = (vb[a] >= 0) & (vb[b] >= 0)
                if both_v.any() and (pos[a][0] != pos[b][0]
                                     or np.any(vb[a][both_v] != vb[b][both_v])):
                    raise GraphError(
                        f"{self.groups[gi].etype.__name__}: an edge connects two different "
                        "marginalised vertices; the Schur complement needs marginalised "
                        "vertices that are independent given the others"
                    )
                for x, y in ((a, b), (b, a)):
                    ok = (ub[x] >= 0) & (ub[y] >= 0)
                    u_keys.append(ub[y][ok] * nb + ub[x][ok])
                    ok = (ub[x] >= 0) & (vb[y] >= 0)
                    if ok.any():
                        key = (pos[x][0], self.vclass_of_store[pos[y][0]])
                        w_found.setdefault(key, []).append(np.stack([ub[x][ok], vb[y][ok]], 1))
        return np.concatenate(u_keys), w_found

    def _incidence(self, vc: int, w_found: dict[tuple[int, int], list[np.ndarray]]
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Unique ``(V block, U block)`` pairs of V class ``vc`` linked by an edge, sorted by V,
        then U block."""
        nb = max(self.n_ublocks, 1)
        keys = [p[:, 1] * nb + p[:, 0]
                for (_, c), found in w_found.items() if c == vc for p in found]
        if not keys:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        k = unique_ints(np.concatenate(keys), len(self.vclasses[vc].slots) * nb)
        return k // nb, k % nb

    def _order_v_blocks(self, vc: int, v: np.ndarray, u: np.ndarray,
                        w_found: dict[tuple[int, int], list[np.ndarray]],
                        spectral_max: int, renumber: bool = True, stream: bool = False
                        ) -> np.ndarray:
        """Renumber V class ``vc``'s blocks in co-visibility order (in ``vblock``, the class's
        slots and, if ``renumber``, the scanned pairs), given its incidence ``(v, u)``; return
        the order (new block ``b`` is old block ``order[b]``). With ``stream`` (a system known
        to be matrix-free), in the order the edges first reach them instead."""
        c = self.vclasses[vc]
        nv = len(c.slots)
        if stream:
            seen = [p[:, 1] for (_, cls), found in w_found.items() if cls == vc for p in found]
            order = first_seen_order(np.concatenate(seen) if seen else np.zeros(0, np.int64),
                                     nv)
        else:
            order = co_visibility_order(v, u, nv, self.n_ublocks, spectral_max)
        new_id = np.empty(nv, dtype=np.int64)
        new_id[order] = np.arange(nv)
        vb = self.vblock[c.store]
        vb[vb >= 0] = new_id[vb[vb >= 0]]
        c.slots = c.slots[order]
        for (_, cls), found in w_found.items():
            if cls == vc and renumber:
                for p in found:
                    p[:, 1] = new_id[p[:, 1]]
        return order

    def _wclass(self, ustore: int, vclass: int, found: list[np.ndarray],
                incidence: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> WClass:
        """The W class of ``(ustore, vclass)`` from its edges' ``(U block, V block)`` pairs,
        or from the V class's incidence ``(v, u, order)`` when the class is its only one."""
        nb = max(self.n_ublocks, 1)
        du = self.stores[ustore].vtype.dimension
        dv = self.vclasses[vclass].dim
        n_v = len(self.vclasses[vclass].slots)
        # int32 where every product the strategies form of them (u·n_ublocks + u,
        # v·dv²) fits: 8 bytes less per W block.
        small = nb * (nb + 1) < 2**31 and n_v * dv * dv < 2**31
        blk_t = np.int32 if small else np.int64
        if incidence is not None:  # the rows of the incidence in the new V order: no sort
            found.clear()
            v, u, order = incidence
            start = np.searchsorted(v, np.arange(n_v + 1))
            cnt = np.diff(start)[order]
            first = np.cumsum(cnt) - cnt
            rows = np.arange(int(cnt.sum()), dtype=np.int64)
            rows += np.repeat(start[:-1][order] - first, cnt)
            ublock = u[rows].astype(blk_t)
            del rows
            vblock = np.repeat(np.arange(n_v, dtype=blk_t), cnt)
        else:
            allp = found[0] if len(found) == 1 else np.concatenate(found)
            found.clear()  # the pairs are in the keys now
            keys = unique_ints(allp[:, 1] * nb + allp[:, 0], n_v * nb)
            del allp
            vblock, ublock = (keys // nb).astype(blk_t), (keys % nb).astype(blk_t)
            del keys
        ub_store = np.flatnonzero(self.ustore == ustore)  # a store's U blocks are contiguous
        ucols = slice(int(self.uoffset[ub_store[0]]), int(self.uoffset[ub_store[-1] + 1]))
        # BSR indices in int32 where they fit (SciPy would convert them at every product).
        bsr_t = np.int32 if max(len(ublock), len(ub_store)) < 2**31 else np.int64
        return WClass(ustore, vclass, du, dv, ublock, vblock,
                      BlockRows(ublock, self.uoffset, du),
                      np.searchsorted(vblock, np.arange(n_v + 1)).astype(bsr_t), ucols, nb,
                      int(ub_store[0]), self.uoffset)
