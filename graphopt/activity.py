"""Edge activity without a new structure: the edges of other levels weigh nothing.

g2o optimises the edges whose level is the initialised one (``setLevel``; ORB-SLAM moves
outliers to level 1) and leaves out the vertices none of them reaches. graphopt keeps the
structure built for all edges — the block pattern, the Schur plan, the solver's symbolic
analysis — and changes numbers only:

* an inactive edge's error and Jacobian rows are zero (:func:`only_active`), so it adds
  nothing to ``H``, the gradient or the chi2;
* a free vertex whose edges are all inactive (*idle*) would then have a zero block — a
  singular system under Gauss–Newton, a step of λ alone under LM — so its diagonal gets the
  identity with a zero right-hand side (:class:`IdleAnchors`): its step is exactly zero and the
  other vertices' steps are those of the graph without it (its rows and columns are decoupled).

A change of levels costs a comparison per edge and, for the idle vertices, a count per edge
and position; nothing is rebuilt.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graphopt.edge import Linearization

if TYPE_CHECKING:
    from graphopt.linear import Assembly
    from graphopt.linear.structure import BlockIndex


def only_active(out: Linearization, active: np.ndarray) -> Linearization:
    """``out`` with the rows of inactive edges zeroed (also where they were not finite: an
    outlier behind the camera must not poison the system) and the activity masks combined.

    Args:
        out: A group's evaluation or linearisation.
        active: ``(m,)`` the edges at the initialised level.
    """
    a2 = active[:, None]
    a3 = active[:, None, None]
    jac = tuple(np.where(a3, j, 0.0) for j in out.jacobians)
    red = None if out.reduced_error is None else np.where(a2, out.reduced_error, 0.0)
    act = active if out.active is None else active & np.asarray(out.active, dtype=bool)
    return Linearization(np.where(a2, out.error, 0.0), jac, red, act)


class IdleAnchors:
    """The identity on the diagonal blocks of idle vertices (free, with edges, none active).

    Recomputed only when some group's activity changed (``activity_version``); a graph whose
    edges are all active costs one comparison per group and linearisation.

    Args:
        index: The block index of the linear system.
    """

    def __init__(self, index: BlockIndex) -> None:
        self.index = index
        self._key: tuple[int, ...] | None = None
        self._upos: np.ndarray | None = None  # data positions in h_data (U diagonals)
        self._v: list[tuple[int, np.ndarray]] = []  # (V class, V blocks)

    def _update(self) -> None:
        ix = self.index
        # Levels and kernel assignments (a kernel's width does not make a vertex idle).
        key = tuple([g.activity_count for g in ix.groups])
        if key == self._key:
            return
        self._key = key
        self._upos, self._v = None, []
        if all(g.active_edges is None for g in ix.groups):
            return
        # Active edges per vertex, counted over every group and position.
        counts = [np.zeros(len(st.estimates), dtype=np.int64) for st in ix.stores]
        for g, pos in zip(ix.groups, ix.positions, strict=True):
            act = g.active_edges
            for si, slots in pos:
                counts[si] += np.bincount(slots if act is None else slots[act],
                                          minlength=len(counts[si]))
        upos, v = [], []
        for si, st in enumerate(ix.stores):
            idle = counts[si] == 0
            ub = ix.ublock[si]
            u = ub[idle & (ub >= 0)]
            if len(u):
                cols = (ix.uoffset[u][:, None] + np.arange(st.vtype.dimension)).ravel()
                upos.append(ix.pattern.diag_pos[cols])
            vc = ix.vclass_of_store[si]
            if vc >= 0:
                vb = ix.vblock[si][idle]
                vb = vb[vb >= 0]
                if len(vb):
                    v.append((int(vc), vb))
        self._upos = np.concatenate(upos) if upos else None
        self._v = v

    def apply(self, asm: Assembly) -> None:
        """Add the identity to the idle vertices' blocks of a fresh assembly (in place; their
        right-hand sides are already zero).

        Args:
            asm: The assembled system.
        """
        self._update()
        if self._upos is not None:
            asm.h_data[self._upos] += 1.0
        for vc, blocks in self._v:
            d = asm.v[vc].shape[1]
            asm.v[vc][blocks[:, None], np.arange(d), np.arange(d)] += 1.0
