"""The implicit Schur complement: products with ``S = U_λ − W V_λ⁻¹ Wᵀ`` without forming ``S``.

For an iterative solver (``ITERATIVE_SCHUR`` in Ceres, the "Bundle Adjustment in the Large"
paper) only products ``S x`` are needed. The W blocks are not formed either: the assembly of a
matrix-free system keeps, per W term of an edge group, the edges' ``J_v`` and ``ρ'ΩJ_u``
(:mod:`graphopt.linear.jacobian_w`), and a product is

1. ``y = Wᵀ x`` per V block: ``t_e = ρ'ΩJ_u,e x_u(e)`` (a BSR product over the Jacobian array
   as it is), then ``Σ_e J_v,eᵀ t_e`` per V block (the V term's contraction);
2. ``z = V_λ⁻¹ y``: batched ``(d_v, d_v)`` products;
3. ``W z`` per U block: ``s_e = J_v,e z_v(e)`` (BSR), then ``Σ_e (ρ'ΩJ_u,e)ᵀ s_e`` per U
   block (the gradient's sums).

The same multiply-adds as with the W blocks (``r·(d_u + d_v)`` = 24 per BAL observation each
way, against 27 per W block), but the W blocks (216 bytes per BAL observation) are never
assembled next to the Jacobians (192): the Jacobians are what the system keeps. Measured at 1M
BAL observations (city-1M, one thread, with the chunked linearisation and ``int32`` indices):
the linearisation's peak 683 → 434 MiB of numpy arrays, ``bal_memory.py``'s peak RSS 952 → 637
B/obs; a product with ``S`` 33 → 39 ms (``Wᵀx`` takes two passes), the linearisation and the
damped reduction faster (no W assembly), 5 LM iterations 15.4 → 16.6 s at 1M and 41.6 →
40.6 s at 3M (``docs/scale.md``, section 4). The V blocks are numbered in the order the
edges first reach them (``BlockIndex``), so that the per-edge products read and write them
about in memory order.

Nothing of ``S``'s structure is built: the block index leaves out the fill
(``BlockIndex(matrix_free=True)``), so the U part lives in ``H_uu``'s pattern, and no Schur
strategy or symbolic factorisation exists. The preconditioners are block-Jacobi on the damped
U blocks, or Schur-Jacobi: the diagonal blocks of ``S``, ``U_λ,uu − Σ_w W_w V_λ⁻¹ W_wᵀ``,
summed from the edges' own ``Wᵀ_e = J_v,eᵀ ρ'ΩJ_u,e`` in chunks (bounded memory), the
repeated pairs' edges summed per pair first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.block_ops import batched_cholesky_inverses

try:  # SciPy's C kernel; it accumulates into a given output array.
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:  # pragma: no cover - private module: the public product below
    _csr_matvec = None

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.structure import BlockIndex

#: Preconditioner names: block-Jacobi on the damped U blocks, or on the diagonal blocks of S.
PRECONDITIONERS = ("jacobi", "schur-jacobi")


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
class _StoreRows:
    """Where the U blocks of one W class's store are among the U groups.

    Args:
        group: The U group of the store's blocks (one dimension per store).
        rows: ``(n_u,)`` the blocks' rows in that group.
    """

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
        self.maps: list[_StoreRows] = []
        for wc in index.wclasses:
            ub = np.flatnonzero(index.ustore == wc.ustore)
            self.maps.append(_StoreRows(int(group_of[ub[0]]), row_of[ub]))

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
        self.rhs = asm.bu.copy()
        if ix.wclasses:
            assert asm.wjac is not None, "a matrix-free assembly keeps the W terms' Jacobians"
            asm.wjac.w_product([np.einsum("nij,nj->ni", vi, b)
                                for vi, b in zip(self.vinv, asm.bv, strict=True)],
                               self.rhs, -1.0)

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
        assert self.asm.wjac is not None
        y = self.asm.wjac.wt_product(x)
        z = [np.einsum("nij,nj->ni", vi, yc) for vi, yc in zip(self.vinv, y, strict=True)]
        self.asm.wjac.w_product(z, out, -1.0)
        return out

    # --- preconditioners ---------------------------------------------------------------------

    def diagonal_blocks(self, schur: bool) -> list[np.ndarray]:
        """The diagonal blocks of ``U_λ`` or of ``S``, per U group ``(n_g, d, d)``.

        Args:
            schur: Subtract ``Σ_w W_w V_λ⁻¹ W_wᵀ`` (the diagonal blocks of ``S``).
        """
        st = self.structure
        blocks = [self.u_data[g.pos] for g in st.groups]
        if schur and st.index.wclasses:
            assert self.asm.wjac is not None
            for m, wvw in zip(st.maps, self.asm.wjac.schur_diagonal(self.vinv), strict=True):
                blocks[m.group][m.rows] -= wvw
        return blocks

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
