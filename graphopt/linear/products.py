"""Products of one assembled linearisation that do not depend on the damping λ.

The W blocks enter as a SciPy BSR matrix whose data *is* the ``Wᵀ`` array (``wt_product``) or
as each W class's constant contraction (``WClass.rhs``): no gather, no segment sum. A
matrix-free assembly has no W blocks: its products come from the W terms' Jacobians
(:class:`~graphopt.linear.jacobian_w.JacobianProducts`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

try:  # SciPy's BSR kernel, called on the arrays directly (see wt_product)
    from scipy.sparse._sparsetools import bsr_matvec as _bsr_matvec
except ImportError:  # pragma: no cover - a SciPy without it: the public product
    _bsr_matvec = None

from graphopt.linear.block_ops import block_products
from graphopt.linear.pattern import with_data

if TYPE_CHECKING:
    from graphopt.linear.assembly import Assembly
    from graphopt.linear.jacobian_w import JacobianProducts
    from graphopt.linear.structure import BlockIndex


def _wjac(asm: Assembly) -> JacobianProducts:
    """The W products of a matrix-free assembly (which has no W blocks)."""
    assert asm.wjac is not None, "an assembly has W blocks or the W terms' Jacobians"
    return asm.wjac


def is_finite(asm: Assembly) -> bool:
    """Whether the U part, the V blocks and both right-hand sides are finite.

    Args:
        asm: The assembled system.
    """
    total = float(asm.h_data.sum() + asm.bu.sum())
    if asm.v:
        total += sum(float(v.sum()) for v in asm.v) + sum(float(b.sum()) for b in asm.bv)
    return math.isfinite(total)


def damping(index: BlockIndex, asm: Assembly, diagonal: bool
            ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The damping matrix ``D`` (a diagonal) as ``(u part, [v parts])``.

    Args:
        index: The block index.
        asm: The assembled system.
        diagonal: ``False``: the identity (g2o's LM). ``True``: ``diag(H)`` clipped to
            ``[1e-6, 1e32]`` (Marquardt's scaling, as Ceres does).
    """
    if not diagonal:
        return np.ones(index.n), [np.ones(b.shape) for b in asm.bv]
    du = np.clip(asm.h_data[index.pattern.diag_pos], 1e-6, 1e32)
    return du, [np.clip(np.einsum("nii->ni", v), 1e-6, 1e32) for v in asm.v]


def max_diagonal(index: BlockIndex, asm: Assembly) -> float:
    """Largest diagonal entry of the full (undamped) Hessian (for LM's initial λ).

    Args:
        index: The block index.
        asm: The assembled system.
    """
    vals = [asm.h_data[index.pattern.diag_pos]]
    vals += [np.einsum("nii->ni", vb).ravel() for vb in asm.v]
    vals = [x for x in vals if x.size]
    return float(max(x.max() for x in vals)) if vals else 0.0


def class_y_transposed(index: BlockIndex, asm: Assembly, vinv: list[np.ndarray], k: int
                       ) -> np.ndarray:
    """``Yᵀ = V⁻¹ Wᵀ`` of every W block of class ``k``, ``(n, dv, du)``.

    Args:
        index: The block index.
        asm: The assembled system.
        vinv: Inverted (damped) V blocks per class.
        k: The W class.
    """
    wc = index.wclasses[k]
    wt = asm.wt[k] if asm.wt is not None else _wjac(asm).class_wt(k)
    return block_products(vinv[wc.vclass][wc.vblock], wt)


def wt_product(index: BlockIndex, asm: Assembly, k: int, xu: np.ndarray) -> np.ndarray:
    """``Σ_w Wᵀ_w x_u[u_w]`` per V block of W class ``k``, as ``(n_v, dv)``.

    Args:
        index: The block index.
        asm: The assembled system.
        k: The W class.
        xu: A vector over the U part.
    """
    wc = index.wclasses[k]
    if asm.wt is None:
        return _wjac(asm).wt_product(xu, k)[wc.vclass]
    n_v = len(wc.bsr_indptr) - 1
    n_u = (wc.ucols.stop - wc.ucols.start) // wc.du
    x = np.ascontiguousarray(xu[wc.ucols], dtype=float)
    if _bsr_matvec is not None and wc.bsr_cols.dtype == wc.bsr_indptr.dtype:
        # SciPy's kernel on the W array as it is: no bsr_matrix object (its checks cost tens
        # of µs a call, most of a small problem's back-substitution).
        out = np.zeros(n_v * wc.dv)
        _bsr_matvec(n_v, n_u, wc.dv, wc.du, wc.bsr_indptr, wc.bsr_cols,
                    np.ascontiguousarray(asm.wt[k]).reshape(-1), x, out)
        return out.reshape(n_v, wc.dv)
    m = sp.bsr_matrix((asm.wt[k], wc.bsr_cols, wc.bsr_indptr),  # pragma: no cover
                      shape=(n_v * wc.dv, n_u * wc.du))
    return (m @ x).reshape(n_v, wc.dv)


def w_product(index: BlockIndex, asm: Assembly, k: int, xv: np.ndarray) -> np.ndarray:
    """``Σ_w W_w xv[w]`` per U block of W class ``k``, as ``(n_u, du)`` (rows
    ``WClass.rhs_dest``; an assembly with W blocks).

    Args:
        index: The block index.
        asm: The assembled system.
        k: The W class.
        xv: ``(n_w, dv)``: a V-side vector taken per W block.
    """
    return index.wclasses[k].rhs(asm.wt[k], xv[:, :, None])[:, :, 0]


def back_substitute(index: BlockIndex, asm: Assembly, du: np.ndarray, vinv: list[np.ndarray]
                    ) -> list[np.ndarray]:
    """``Δv = V⁻¹ (b_v − Wᵀ Δu)`` per V class.

    Args:
        index: The block index.
        asm: The assembled system.
        du: Solution of the reduced system.
        vinv: Inverted damped V blocks per class.
    """
    r = [b.copy() for b in asm.bv]
    if asm.wt is None and index.wclasses:  # one pass over the W terms' Jacobians
        for rc, y in zip(r, _wjac(asm).wt_product(du), strict=True):
            rc -= y
    for k, wc in enumerate(index.wclasses if asm.wt is not None else []):
        r[wc.vclass] -= wt_product(index, asm, k, du)
    return [block_products(vi, ri[:, :, None])[:, :, 0] for vi, ri in zip(vinv, r, strict=True)]


def hessian_product(index: BlockIndex, asm: Assembly, xu: np.ndarray, xv: list[np.ndarray]
                    ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The undamped full Hessian times a vector ``[xu, xv]``.

    Args:
        index: The block index.
        asm: The assembled system.
        xu: U part of the vector.
        xv: V parts per class.
    """
    hu = with_data(index.pattern.csc, asm.h_data) @ xu
    hv = [block_products(vb, x[:, :, None])[:, :, 0] for vb, x in zip(asm.v, xv, strict=True)]
    if asm.wt is None:
        if index.wclasses:
            wj = _wjac(asm)
            wj.w_product(xv, hu)
            for h, y in zip(hv, wj.wt_product(xu), strict=True):
                h += y
        return hu, hv
    for k, wc in enumerate(index.wclasses):
        hu[wc.rhs_dest] += w_product(index, asm, k, xv[wc.vclass][wc.vblock])
        hv[wc.vclass] += wt_product(index, asm, k, xu)
    return hu, hv
