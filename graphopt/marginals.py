"""Marginal covariances: blocks of ``H⁻¹`` through the Schur complement.

For a non-marginalised vertex ``u`` the block is ``(S⁻¹)_uu``. For a marginalised vertex ``p``
with W blocks ``W_up`` it is ``V_p⁻¹ + Σ_{u,u'} Y_upᵀ (S⁻¹)_uu' Y_u'p`` with ``Y = W V⁻¹``
(the reduction hands over ``Yᵀ = V⁻¹Wᵀ``).
Only the columns of ``S⁻¹`` that these formulas touch are solved for.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from graphopt.errors import GraphError
from graphopt.problem import Problem
from graphopt.vertex import BaseVertex

if TYPE_CHECKING:
    from graphopt.graph import Graph


def marginals_of(graph: Graph, problem: Problem, vertices: Iterable[BaseVertex | int]
                 ) -> dict[int, np.ndarray]:
    """:func:`marginal_covariances` of vertices given as objects or ids of ``graph``.

    Args:
        graph: The graph.
        problem: Its initialised numeric problem.
        vertices: Vertices or ids (not fixed).

    Raises:
        GraphError: an unknown vertex (or, from :func:`marginal_covariances`, a fixed one).
    """
    wanted = []
    for v in vertices:
        vid = v.id if isinstance(v, BaseVertex) else int(v)
        if vid not in graph.ids:
            raise GraphError(f"compute_marginals: vertex {vid} does not exist")
        st, slot = graph.ids[vid]
        wanted.append((vid, problem.stores.index(st), slot))
    return marginal_covariances(problem, wanted)


def marginal_covariances(problem: Problem, vertices: list[tuple[int, int, int]]
                         ) -> dict[int, np.ndarray]:
    """Covariance blocks of the given vertices at the current estimates.

    Args:
        problem: The initialised numeric problem.
        vertices: ``(id, store index, slot)`` of each vertex (not fixed).

    Returns:
        ``{id: (d, d) covariance}``.

    Raises:
        GraphError: a fixed vertex.
        NotPositiveDefiniteError: if ``H`` is singular (e.g. no gauge fixed).
    """
    system, solver = problem.system, problem.solver
    index = system.index
    asm, _ = problem.linearize()
    s, _, vinv = system.reduce(asm, 0.0)
    yt = system.y_transposed(asm, vinv)
    wanted: list[tuple[int, str, int, int, np.ndarray]] = []
    cols: list[np.ndarray] = []
    for vid, si, slot in vertices:
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
    X = np.zeros((index.n, 0))
    if len(need):
        E = np.zeros((index.n, len(need)))
        E[need, np.arange(len(need))] = 1.0
        X = solver.solve(s, E)
        X = X.reshape(index.n, len(need))
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
