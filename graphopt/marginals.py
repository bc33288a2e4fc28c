"""Marginal covariances: blocks of ``H⁻¹`` through the Schur complement.

For a non-marginalised vertex ``u`` the block is ``(S⁻¹)_uu``. For a marginalised vertex ``p``
with W blocks ``W_up`` it is ``V_p⁻¹ + Σ_{u,u'} Y_upᵀ (S⁻¹)_uu' Y_u'p`` with ``Y = W V⁻¹``
(the reduction hands over ``Yᵀ = V⁻¹Wᵀ``).
Only the columns of ``S⁻¹`` that these formulas touch are solved for.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graphopt.errors import GraphError

if TYPE_CHECKING:
    from graphopt.optimizer import SparseOptimizer


def marginal_covariances(opt: SparseOptimizer, ids: list[int]) -> dict[int, np.ndarray]:
    """Covariance blocks for the given vertex ids.

    Args:
        opt: An initialised optimizer.
        ids: Vertex ids (neither fixed nor unknown).

    Returns:
        ``{id: (d, d) covariance}``.
    """
    sysm, solver = opt._system, opt.solver
    assert sysm is not None and solver is not None
    asm, _ = opt.linearize()
    s, _, vinv = sysm.reduce(asm, 0.0)
    yt = sysm.y_transposed(asm, vinv)
    index = sysm.index
    store_index = {id(st): i for i, st in enumerate(opt._store_list)}
    wanted: list[tuple[int, str, int, int, np.ndarray]] = []
    cols: list[np.ndarray] = []
    for vid in ids:
        if vid not in opt._ids:
            raise GraphError(f"compute_marginals: vertex {vid} does not exist")
        st, slot = opt._ids[vid]
        si = store_index[id(st)]
        if index.ublock[si][slot] >= 0:
            ub = int(index.ublock[si][slot])
            idx = index.uoffset[ub] + np.arange(index.udims[ub])
            wanted.append((vid, "u", ub, -1, idx))
            cols.append(idx)
        elif index.vblock[si][slot] >= 0:
            vc = index.vclass_of_store[si]
            vb = int(index.vblock[si][slot])
            wanted.append((vid, "v", vc, vb, np.zeros(0, dtype=np.int64)))
            for wc in index.wclasses:
                if wc.vclass == vc:
                    for w in np.flatnonzero(wc.vblock == vb):
                        cols.append(wc.upos[w])
        else:
            raise GraphError(f"compute_marginals: vertex {vid} is fixed")
    need = np.unique(np.concatenate(cols)) if cols else np.zeros(0, dtype=np.int64)
    col_of = {int(c): i for i, c in enumerate(need)}
    X = np.zeros((sysm.n, 0))
    if len(need):
        E = np.zeros((sysm.n, len(need)))
        E[need, np.arange(len(need))] = 1.0
        X = solver.solve(s, E)
        X = X.reshape(sysm.n, len(need))
    out: dict[int, np.ndarray] = {}
    for vid, kind, a, b, idx in wanted:
        if kind == "u":
            out[vid] = X[np.ix_(idx, [col_of[int(c)] for c in idx])].copy()
            continue
        cov = vinv[a][b].copy()
        parts = []  # (Yᵀ block (dv, du), scalar rows of u)
        for k, wc in enumerate(index.wclasses):
            if wc.vclass == a:
                for w in np.flatnonzero(wc.vblock == b):
                    parts.append((yt[k][w], wc.upos[w]))
        for y1, r1 in parts:
            for y2, r2 in parts:
                block = X[np.ix_(r1, [col_of[int(c)] for c in r2])]
                cov += y1 @ block @ y2.T
        out[vid] = cov
    return out
