"""``W V⁻¹ Wᵀ`` of a W class by dense BLAS ``syrk`` products over panels of V blocks.

With ``V = LLᵀ``, ``M = L⁻¹Wᵀ`` of a panel's W blocks, laid out densely as
``(rows·dv, cols·du)`` (zeros where a V block does not meet a U block), is one product of a
constant-structure CSR matrix holding the entries of ``L⁻¹`` with the W array as it is: the
small products and their placement happen in one C loop. ``MᵀM`` is the panel's share of
``W V⁻¹ Wᵀ`` and ``Mᵀ L⁻¹b_v`` its share of ``W V⁻¹ b_v``. V blocks come numbered in
co-visibility order (``ordering.py``), which keeps every panel's ``M`` narrow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import scipy.linalg.blas as blas
import scipy.sparse as sp

from graphopt.linear.block_ops import csr_product_into
from graphopt.linear.indexing import unique_ints
from graphopt.linear.schur_config import SchurCostModel
from graphopt.linear.schur_strategy import SchurPlan, SchurStrategy, VFactors

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex


@dataclass
class Panel:
    """A run of consecutive V blocks and the U blocks they meet: one dense ``syrk``.

    Args:
        v0: First V block.
        w0: First W block ...
        w1: ... and the end of the panel's W block range.
        rows: V blocks in the panel.
        cols: U blocks it meets.
        indptr: CSR rows: (V block, row of L⁻¹, U block) → entries of L⁻¹ ...
        indices: ... times rows (W block, i) of the panel's W array.
        d0: Start ...
        d1: ... and end of the panel's range in the class's gathered L⁻¹ entries.
        r0: Offset of the panel's ``MᵀM`` (column-major) in the result buffer.
        rhs_pos: Positions in the reduced right-hand side of the panel's U columns.
    """

    v0: int
    w0: int
    w1: int
    rows: int
    cols: int
    indptr: np.ndarray
    indices: np.ndarray
    d0: int
    d1: int
    r0: int
    rhs_pos: np.ndarray


#: Most entries of the map into ``S`` built without SciPy's conversion from (row, column)
#: pairs: its linear-time sort wins on larger maps (BAL-16's 800k: 4.8 against 9.8 ms).
_DIRECT_CSR = 50_000


class DensePanels(SchurStrategy):
    """The panels of one W class: their CSR structures, buffers and map into ``S``.

    Args:
        index: The block index.
        plan: The planned panels.

    Attributes:
        panels: The panels, in V block order.
    """

    name = "dense"

    def __init__(self, index: BlockIndex, plan: DensePlan) -> None:
        super().__init__(index, plan)
        c = index.wclasses[self.k]
        nb = max(index.n_ublocks, 1)
        dv, du = c.dv, c.du
        uu = unique_ints(c.ublock, nb)
        lu = np.searchsorted(uu, c.ublock)
        di, dj = np.arange(du)[:, None], np.arange(du)[None, :]
        # L⁻¹ is lower triangular: row i of a V block's Z = L⁻¹Wᵀ takes entries j ≤ i.
        ti, tj = np.tril_indices(dv)
        self.panels: list[Panel] = []
        lidx, d0, largest, r0 = [], 0, 0, 0
        to_rows, to_cols = [], []
        for v0, v1, w0, w1, cams in plan.spans:  # panels, not vertices
            nc = len(cams)
            n = nc * du  # columns of M
            la, lb = np.divmod(np.arange(nc * nc), nc)
            ga, gb = uu[cams[la]], uu[cams[lb]]
            # Keep the block pairs present in S (others have no common V block at all).
            present = index.pattern.has_blocks(ga, gb)
            la, lb, ga, gb = la[present], lb[present], ga[present], gb[present]
            dest, _ = index.pattern.dest(ga, gb, transposes=False)
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
            indptr = np.zeros(n_out + 1, dtype=np.int64)  # rows' starts: counts, summed
            np.cumsum(np.bincount(out_row, minlength=n_out), out=indptr[1:])
            indices = ((w - w0)[:, None] * dv + tj).ravel()[order]
            lidx.append((c.vblock[w][:, None] * dv * dv + ti * dv + tj).ravel()[order])
            idx_t = np.int32 if max(n_out, (w1 - w0) * dv) < 2**31 else np.int64
            rhs_pos = (index.uoffset[uu[cams]][:, None] + np.arange(du)).reshape(-1)
            self.panels.append(Panel(v0, w0, w1, v1 - v0, nc, indptr.astype(idx_t),
                                     indices.astype(idx_t), d0, d0 + len(indices), r0, rhs_pos))
            to_rows.append(dest.reshape(-1))
            to_cols.append(r0 + src.reshape(-1))
            d0 += len(indices)
            r0 += n * n
            largest = max(largest, n_out * du)
        self._scratch = np.zeros(largest)  # room for the largest panel's M
        self._scratch.fill(0.0)  # touch the pages here, not in the first iteration
        self._lidx = np.concatenate(lidx) if lidx else np.zeros(0, np.int64)
        self._results = np.zeros(r0)  # every panel's MᵀM, one after the other
        rows = np.concatenate(to_rows) if to_rows else np.zeros(0, np.int64)
        cols = np.concatenate(to_cols) if to_cols else np.zeros(0, np.int64)
        # Sums the upper-triangle entries of the results into S's pattern: one sparse product
        # instead of a fancy-indexed subtraction per panel.
        nnz = index.pattern.nnz
        if len(rows) > _DIRECT_CSR:
            self._to_s = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(nnz, r0))
        else:  # small: CSR directly, what SciPy's conversion gives at half its set-up cost
            idx_t = np.int32 if max(len(rows), nnz, r0) < 2**31 else np.int64
            order = np.argsort(rows * max(r0, 1) + cols)  # (row, column): unique keys
            indptr = np.zeros(nnz + 1, dtype=idx_t)
            np.cumsum(np.bincount(rows, minlength=nnz), out=indptr[1:])
            self._to_s = sp.csr_matrix((np.ones(len(rows)), cols[order].astype(idx_t), indptr),
                                       shape=(nnz, r0))

    def reduce_into(self, s: np.ndarray, rhs: np.ndarray, asm: Assembly,
                    factors: VFactors) -> None:
        """Per panel ``Z = L⁻¹Wᵀ``, ``ZᵀZ`` by ``syrk`` and ``Zᵀ L⁻¹b_v``; the results into S.

        Arguments as in :meth:`SchurStrategy.reduce_into`.
        """
        wc = self.index.wclasses[self.k]
        dv, du = wc.dv, wc.du
        x = factors.l_inv_b(wc.vclass)
        lvals = np.take(factors.linv[wc.vclass].reshape(-1), self._lidx)
        wflat = np.ascontiguousarray(asm.wt[self.k]).reshape(-1)
        for p in self.panels:  # cache-sized tiles of V blocks with similar U sets
            n_out, n = p.rows * dv * p.cols, p.cols * du
            m = self._scratch[:n_out * du]
            csr_product_into(n_out, (p.w1 - p.w0) * dv, du, p.indptr, p.indices,
                             lvals[p.d0:p.d1], wflat[p.w0 * dv * du:p.w1 * dv * du], m)
            m2 = m.reshape(p.rows * dv, n)  # Z = L⁻¹Wᵀ, dense over the panel
            c = self._results[p.r0:p.r0 + n * n].reshape(n, n, order="F")
            blas.dsyrk(1.0, m2.T, trans=0, c=c, overwrite_c=1)  # m2ᵀ m2, upper triangle
            rhs[p.rhs_pos] -= m2.T @ x[p.v0:p.v0 + p.rows].reshape(-1)
        s -= self._to_s @ self._results


@dataclass(frozen=True)
class DensePlan(SchurPlan):
    """Dense panels for W class ``k``.

    Args:
        k: The W class.
        spans: Per panel ``(v0, v1, w0, w1, local U blocks)``.
        seconds: Modelled seconds per reduction.
        elements: Elements of all panels' matrices together.
    """

    strategy: ClassVar[type[SchurStrategy]] = DensePanels
    k: int
    spans: tuple[tuple[int, int, int, int, np.ndarray], ...]
    seconds: float
    elements: int

    @classmethod
    def plan(cls, index: BlockIndex, k: int, cost: SchurCostModel) -> DensePlan | None:
        """Panels of W class ``k`` and their modelled cost (``None`` without W blocks).

        V blocks come in runs with identical U sets. A greedy scan merges the next run into
        the current panel while that is cheaper than starting a new one (fewer, larger BLAS
        calls against wider panels, but more zeros in them).

        Args:
            index: The block index.
            k: The W class.
            cost: The cost model.
        """
        c = index.wclasses[k]
        n_v = len(index.vclasses[c.vclass].slots)
        nw = len(c.ublock)
        if nw == 0:
            return None
        uu = unique_ints(c.ublock, max(index.n_ublocks, 1))
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
        max_rows = max(1, cost.panel_rows // dv)
        lul = lu.tolist()
        ws = wstart.tolist()
        closed: list[tuple[int, int, int, float]] = []  # panels: v0, v1, U mask, cost
        cur: tuple[int, int, int, float] | None = None  # the open panel
        for r0, r1 in zip(run_start.tolist(), run_end.tolist(), strict=True):  # runs
            mask = 0
            for x in lul[ws[r0]:ws[r0 + 1]]:
                mask |= 1 << x
            nset = mask.bit_count()
            if nset == 0:
                continue  # V blocks that meet no U block of this class
            for a in range(r0, r1, max_rows):  # split runs longer than a panel
                b = min(r1, a + max_rows)
                alone = _panel_seconds(cost, (b - a) * dv, nset * du, (ws[b] - ws[a]) * dv * du)
                if cur is not None:
                    v0, _, cmask, ccost = cur
                    um = cmask | mask
                    merged = _panel_seconds(cost, (b - v0) * dv, um.bit_count() * du,
                                                (ws[b] - ws[v0]) * dv * du)
                    if b - v0 <= max_rows and merged < ccost + alone:
                        cur = (v0, b, um, merged)
                        continue
                    closed.append(cur)
                cur = (a, b, mask, alone)
        if cur is not None:
            closed.append(cur)
        seconds = sum(p[3] for p in closed)
        elements = sum((v1 - v0) * dv * m.bit_count() * du for v0, v1, m, _ in closed)
        spans = []
        for v0, v1, m, _ in closed:
            local = np.array([i for i in range(m.bit_length()) if m >> i & 1], dtype=np.int64)
            spans.append((v0, v1, ws[v0], ws[v1], local))
        return cls(k, tuple(spans), seconds, elements)


def _panel_seconds(cost: SchurCostModel, rows: int, n: int, placed: int) -> float:
    """Modelled seconds of one panel: a ``rows × n`` matrix of which ``placed`` values are
    formed (per-panel overhead, ``syrk`` at a column-dependent BLAS rate, the values formed,
    the panel's elements, the ``n × n`` result)."""
    syrk = cost.blas_mac * rows * n * (n + cost.blas_half) / 2
    return (cost.panel + syrk + cost.place * placed + cost.area * rows * n
            + cost.dense_element * n * n)
