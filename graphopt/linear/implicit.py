"""The implicit Schur complement: products with ``S = U_λ − W V_λ⁻¹ Wᵀ`` without forming ``S``.

For an iterative solver (``ITERATIVE_SCHUR`` in Ceres, the "Bundle Adjustment in the Large"
paper) only products ``S x`` are needed. They are computed from the assembled W blocks
(``Wᵀ``, ``(n_w, d_v, d_u)``, one per linked pair of a U and a V block), in three steps that
are each one C loop over the W blocks:

1. ``y = Wᵀ x`` per V block: a block-sparse (BSR) product whose data is the ``Wᵀ`` array as it
   is (rows: V blocks, columns: U blocks; the W blocks are sorted by V block);
2. ``z = V_λ⁻¹ y``: batched ``(d_v, d_v)`` products;
3. ``W z`` per U block: the W class's sums (``WClass.rhs``, an ``EdgeSums``), whose data is
   again the ``Wᵀ`` array as it is, applied to ``z`` gathered per W block.

The W blocks rather than the per-observation Jacobians: they are already assembled (one per
camera–point pair, fewer than the observations when a pair is observed twice), take 27 values
per BAL observation against 48 for ``J`` and ``ρ'ΩJ`` of both vertices, and cost the same
multiply-adds per product (27 each way); the Jacobians are then not kept after the assembly.
Measured at 1M BAL-like W blocks on this machine (one thread): step 1 11 ms, step 3 28 ms (a
BSR product of a transposed copy of ``Wᵀ`` takes 12 ms, but the copy costs 150 ms and 216 bytes
per W block every linearisation), step 2 3 ms.

Nothing of ``S``'s structure is built: the block index leaves out the fill
(``BlockIndex(matrix_free=True)``), so the U part lives in ``H_uu``'s pattern, and no Schur
strategy or symbolic factorisation exists. The preconditioners are block-Jacobi on the damped
U blocks, or Schur-Jacobi: the diagonal blocks of ``S``,
``U_λ,uu − Σ_w Wᵀ_wᵀ V_λ⁻¹ Wᵀ_w``, summed in chunks of W blocks (bounded memory).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.block_ops import batched_cholesky_inverses

try:  # SciPy's C kernels; they accumulate into a given output array.
    from scipy.sparse._sparsetools import bsr_matvec as _bsr_matvec
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:  # pragma: no cover - private module: the public products below
    _bsr_matvec = _csr_matvec = None

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex

#: Preconditioner names: block-Jacobi on the damped U blocks, or on the diagonal blocks of S.
PRECONDITIONERS = ("jacobi", "schur-jacobi")

#: W blocks per chunk of the Schur-Jacobi sums (about 6 MB of ``(c, 9, 9)`` products for BAL).
CHUNK = 8192


@dataclass
class _UGroup:
    """The U blocks of one dimension: scalar indices and their diagonal blocks' data positions.

    Args:
        dim: Block dimension ``d``.
        blocks: ``(n_g,)`` U block numbers.
        idx: ``(n_g, d)`` scalar indices.
        pos: ``(n_g, d, d)`` data positions of the diagonal blocks in the U pattern.
    """

    dim: int
    blocks: np.ndarray
    idx: np.ndarray
    pos: np.ndarray


@dataclass
class _WMaps:
    """The index arrays one W class's products need (int32 where SciPy's kernels take them).

    Args:
        k: The W class.
        n_v: V blocks of its V class.
        n_u: U blocks of its U store.
        indptr: ``(n_v + 1,)`` BSR row pointer (W blocks of every V block).
        cols: ``(n_w,)`` BSR column (U block within the store) of every W block.
        out_rows: ``(n_t · d_u,)`` scalar rows of the U blocks the class reaches (the targets of
            ``WClass.rhs``), or ``None`` when those are the store's U blocks in order.
        target: ``(n_w,)`` target (index into those U blocks) of every W block.
        n_t: Targets.
        group: The U group of the store's blocks.
        rows: ``(n_t,)`` the targets' rows in that group.
    """

    k: int
    n_v: int
    n_u: int
    indptr: np.ndarray
    cols: np.ndarray
    out_rows: np.ndarray | None
    target: np.ndarray
    n_t: int
    group: int
    rows: np.ndarray


class ImplicitSchur:
    """The structure of the implicit products, built once from a matrix-free block index.

    Args:
        index: The block index (``matrix_free``: its pattern is ``H_uu``'s).

    Attributes:
        index: The block index.
        groups: The U blocks grouped by dimension.
    """

    def __init__(self, index: BlockIndex) -> None:
        self.index = index
        pattern = index.pattern
        self._indptr = pattern.csc.indptr
        self._indices = pattern.csc.indices
        self.groups: list[_UGroup] = []
        for d in np.unique(index.udims):
            blocks = np.flatnonzero(index.udims == d)
            idx = index.uoffset[blocks][:, None] + np.arange(d)
            rows = np.broadcast_to(idx[:, :, None], (len(blocks), d, d))
            cols = np.broadcast_to(idx[:, None, :], (len(blocks), d, d))
            pos = pattern.positions(rows.reshape(-1), cols.reshape(-1)).reshape(len(blocks), d, d)
            self.groups.append(_UGroup(int(d), blocks, idx, pos))
        group_of = np.empty(index.n_ublocks, dtype=np.int64)
        row_of = np.empty(index.n_ublocks, dtype=np.int64)
        for gi, g in enumerate(self.groups):
            group_of[g.blocks] = gi
            row_of[g.blocks] = np.arange(len(g.blocks))
        self.maps: list[_WMaps] = []
        for k, wc in enumerate(index.wclasses):
            n_u = (wc.ucols.stop - wc.ucols.start) // wc.du
            uu = np.searchsorted(index.uoffset, wc.rhs_dest[:, 0])  # targets of WClass.rhs
            rows = wc.rhs_dest.reshape(-1)
            whole = len(uu) == n_u and bool(np.all(np.diff(uu) == 1))
            self.maps.append(_WMaps(
                k, len(wc.bsr_indptr) - 1, n_u, wc.bsr_indptr.astype(np.int32),
                wc.bsr_cols.astype(np.int32), None if whole else rows,
                np.searchsorted(uu, wc.ublock).astype(np.int32), len(uu),
                int(group_of[uu[0]]), row_of[uu]))

    def operator(self, asm: Assembly, lam: float,
                 damp: tuple[np.ndarray, list[np.ndarray]] | None = None) -> SchurOperator:
        """``S`` of one assembly and damping, as products.

        Args:
            asm: The assembled system (``h_data`` in ``H_uu``'s pattern).
            lam: Levenberg damping (0 for none).
            damp: The diagonal ``D`` as ``(u part, [v parts])``; ``None`` for the identity.

        Raises:
            NotPositiveDefiniteError: if a damped V block is not positive definite.
        """
        return SchurOperator(self, asm, lam, damp)


class SchurOperator:
    """``S = U_λ − W V_λ⁻¹ Wᵀ`` of one assembly and λ: its products, right-hand side and
    preconditioners.

    Args:
        structure: The implicit structure.
        asm: The assembled system.
        lam: Levenberg damping.
        damp: The diagonal ``D``; ``None`` for the identity.

    Attributes:
        n: Size of ``S``.
        u_data: Data of ``U_λ`` in ``H_uu``'s pattern.
        vinv: Per V class ``(n, d, d)`` inverted damped V blocks.
        rhs: ``(n,)`` the reduced right-hand side ``b_u − W V_λ⁻¹ b_v``.
        products: Products with ``S`` computed so far.

    Raises:
        NotPositiveDefiniteError: if a damped V block is not positive definite.
    """

    def __init__(self, structure: ImplicitSchur, asm: Assembly, lam: float,
                 damp: tuple[np.ndarray, list[np.ndarray]] | None) -> None:
        ix = structure.index
        self.structure, self.asm, self.n = structure, asm, ix.n
        self.u_data = asm.h_data.copy()
        vdamp: list[np.ndarray | None] = [None] * len(asm.v)
        if lam:
            du, dv = damp if damp is not None else (np.ones(ix.n), [np.ones(b.shape)
                                                                  for b in asm.bv])
            self.u_data[ix.pattern.diag_pos] += lam * du
            vdamp = [lam * d for d in dv]
        # Only V⁻¹ is kept (not L⁻¹ as the explicit strategies need): 72 bytes a point fewer.
        self.vinv = [batched_cholesky_inverses(vb, d)[1] for vb, d in
                     zip(asm.v, vdamp, strict=True)]
        self.products = 0
        self._wt = [np.ascontiguousarray(w).reshape(-1) for w in asm.wt]
        self.rhs = asm.bu.copy()
        self._sub_w(self.rhs, [np.einsum("nij,nj->ni", vi, b)
                               for vi, b in zip(self.vinv, asm.bv, strict=True)])

    # --- products ----------------------------------------------------------------------------

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """``S x``.

        Args:
            x: ``(n,)`` vector.
        """
        self.products += 1
        ix = self.structure.index
        out = np.zeros(self.n)
        if _csr_matvec is not None:  # symmetric: the CSC pattern read as CSR is the same matrix
            _csr_matvec(self.n, self.n, self.structure._indptr, self.structure._indices,
                        self.u_data, x, out)
        else:  # pragma: no cover
            out += sp.csr_matrix((self.u_data, self.structure._indices, self.structure._indptr),
                                 shape=(self.n, self.n)) @ x
        if not ix.wclasses:
            return out
        y = [np.zeros((len(c.slots), c.dim)) for c in ix.vclasses]
        for m, wc in zip(self.structure.maps, ix.wclasses, strict=True):
            xu = x[wc.ucols]
            if _bsr_matvec is not None:
                _bsr_matvec(m.n_v, m.n_u, wc.dv, wc.du, m.indptr, m.cols, self._wt[m.k], xu,
                            y[wc.vclass].reshape(-1))
            else:  # pragma: no cover
                w = sp.bsr_matrix((self.asm.wt[m.k], m.cols, m.indptr),
                                  shape=(m.n_v * wc.dv, m.n_u * wc.du))
                y[wc.vclass] += (w @ xu).reshape(m.n_v, wc.dv)
        z = [np.einsum("nij,nj->ni", vi, yc) for vi, yc in zip(self.vinv, y, strict=True)]
        self._sub_w(out, z)
        return out

    def _sub_w(self, out: np.ndarray, z: list[np.ndarray]) -> None:
        """``out −= W z`` (``z`` per V class, ``(n_v, d_v)``)."""
        ix = self.structure.index
        for m, wc in zip(self.structure.maps, ix.wclasses, strict=True):
            zw = np.take(z[wc.vclass], wc.vblock, axis=0)  # per W block
            # The class's sums Σ_w (Wᵀ_w)ᵀ z_w per U block, over the W array as it is.
            buf = wc.rhs(self.asm.wt[m.k], zw[:, :, None]).reshape(-1)
            if m.out_rows is None:
                out[wc.ucols] -= buf
            else:
                out[m.out_rows] -= buf

    # --- preconditioners ---------------------------------------------------------------------

    def diagonal_blocks(self, schur: bool) -> list[np.ndarray]:
        """The diagonal blocks of ``U_λ`` or of ``S``, per U group ``(n_g, d, d)``.

        Args:
            schur: Subtract ``Σ_w Wᵀ_wᵀ V_λ⁻¹ Wᵀ_w`` (the diagonal blocks of ``S``).
        """
        st = self.structure
        blocks = [self.u_data[g.pos] for g in st.groups]
        if schur:
            for m, wc in zip(st.maps, st.index.wclasses, strict=True):
                blocks[m.group][m.rows] -= self._wvw_diagonal(m, wc.vclass)
        return blocks

    def _wvw_diagonal(self, m: _WMaps, vclass: int) -> np.ndarray:
        """``Σ_w Wᵀ_wᵀ V_λ⁻¹ Wᵀ_w`` per target U block of W class ``m.k``, ``(n_t, d_u, d_u)``.

        Per chunk of W blocks, ``Yᵀ = V⁻¹Wᵀ`` and ``Wᵀ_wᵀ Yᵀ_w`` (batched products), summed
        into the targets by a 0/1 sparse product over the chunk (once per solve).
        """
        wc = self.structure.index.wclasses[m.k]
        du = wc.du
        wt = self.asm.wt[m.k]
        vinv = self.vinv[vclass]
        acc = np.zeros((m.n_t, du * du))
        for c0 in range(0, len(wt), CHUNK):
            c1 = min(c0 + CHUNK, len(wt))
            yt = np.matmul(np.take(vinv, wc.vblock[c0:c1], axis=0), wt[c0:c1])
            blocks = np.matmul(np.swapaxes(wt[c0:c1], 1, 2), yt).reshape(c1 - c0, -1)
            scatter = sp.csr_matrix((np.ones(c1 - c0), (m.target[c0:c1], np.arange(c1 - c0))),
                                    shape=(m.n_t, c1 - c0))
            acc += scatter @ blocks
        return acc.reshape(m.n_t, du, du)

    def preconditioner(self, kind: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """The inverted diagonal blocks of the preconditioner, per U group ``(idx, inv)``.

        Args:
            kind: ``"jacobi"`` (blocks of ``U_λ``) or ``"schur-jacobi"`` (blocks of ``S``).

        Raises:
            NotPositiveDefiniteError: if a block is not positive definite.
        """
        if kind not in PRECONDITIONERS:
            raise ValueError(f"unknown preconditioner {kind!r}; choose one of "
                             f"{', '.join(PRECONDITIONERS)}")
        blocks = self.diagonal_blocks(kind == "schur-jacobi")
        out = []
        for g, b in zip(self.structure.groups, blocks, strict=True):
            if not np.all(np.isfinite(b)):
                raise NotPositiveDefiniteError("a preconditioner block is not finite")
            out.append((g.idx, batched_cholesky_inverses(b)[1]))
        return out
