"""Group-structured tangents of matrix-valued per-vertex jets, found and used by the tape.

A pose updated by ``exp(δ) · T`` has the derivative ``∂T/∂δ_k = G_k T`` at ``δ = 0`` for
fixed generators ``G_k`` (a rotation's: the cross-product matrices ``[e_k]×``); one updated
by ``T · exp(δ)`` has ``T G_k``. Matrices derived from such an estimate inherit it (a BAL
camera's rotation matrix, computed from its angle-axis after the left update). Nothing has
to be declared: :func:`detect` fits ``G`` to the per-vertex derivatives that ``oplus`` and
``derived`` produced on jets, and keeps it only if it reproduces every vertex's derivatives
to 1e-12 relative — a verified factorisation of the tangent, not an assumption.

The reverse pass then contracts an edge's adjoint ``g`` of entries ``(a, b)`` of such a
matrix ``V`` as ``Σ g_ab (G_k V)_ab = Σ_(a,j) G_k[a, j] Σ_b g_ab V_jb`` (left): a generator
is sparse (a ``[e_k]×`` has two entries), so this costs a few products per entry, read from
the edge's own values, where the general contraction gathers ``k`` derivatives per entry and
edge from the vertices and multiplies each.
"""

from __future__ import annotations

from math import isqrt
from typing import Any

import numpy as np

__all__ = ["Plan", "Structure", "clear", "contract", "contract_deferred", "contract_product",
           "defer", "detect", "piece"]

#: ``(adjoint entry, column of V, [(direction, coefficient)])`` per product.
Plan = list[tuple[int, int, list[tuple[int, float]]]]

#: Relative agreement required between ``G V`` (or ``V G``) and the derivatives.
TOLERANCE = 1e-12


class Structure:
    """``∂V/∂δ_(lo+k) = G_k V`` (``left``) or ``V G_k`` for ``(N, N)`` values ``V``.

    Args:
        G: ``(k, N, N)`` generators.
        lo: The first direction.
        left: Left (``G_k V``) or right (``V G_k``) structure.
        zero: ``(N·N,)`` entries of ``V`` that are 0 at every vertex (skipped).
        one: ``(N·N,)`` entries of ``V`` that are 1 at every vertex (no product).
    """

    def __init__(self, G: np.ndarray, lo: int, left: bool, zero: np.ndarray,
                 one: np.ndarray) -> None:
        self.G, self.lo, self.left, self.zero, self.one = G, lo, left, zero, one
        self.N = G.shape[1]
        self._plans: dict[tuple[bytes, int], Plan | None] = {}
        self._products: dict[tuple[bytes, tuple[int, ...]], Plan | None] = {}

    def product_plan(self, entries: np.ndarray) -> Plan | None:
        """For ``Y = A B`` with ``A`` the rectangular block ``entries`` ``(rows, cols)`` of a
        left-structured ``V``: ``(row a of A, row j of Y, [(k, c)])`` such that the product
        adds ``c Σ_l g[a, l] Y[j, l]`` into direction ``k`` — as ``(G_k V)[rows, cols] B =
        G_k[rows, :] V[:, cols] B`` and ``V[j, cols] B`` is ``Y[j]`` for ``j`` in the block.
        ``None`` for a right structure, a piece that is not a block, or a generator that
        reaches a row of ``V`` outside the block whose entries in its columns are not all 0.
        """
        key = (entries.tobytes(), entries.shape)
        if key in self._products:
            return self._products[key]
        plan = self._product_plan(entries) if self.left and entries.ndim == 2 else None
        self._products[key] = plan
        return plan

    def _product_plan(self, entries: np.ndarray) -> Plan | None:
        N = self.N
        r0, c0 = divmod(int(entries[0, 0]), N)
        nr, nc = entries.shape
        block = (r0 + np.arange(nr))[:, None] * N + (c0 + np.arange(nc))[None, :]
        if r0 + nr > N or c0 + nc > N or not np.array_equal(entries, block):
            return None
        zero = self.zero.reshape(N, N)
        out: Plan = []
        for i in range(nr):
            for j in range(N):
                coef = self.G[:, r0 + i, j]
                ks = np.flatnonzero(coef)
                if not len(ks):
                    continue
                if r0 <= j < r0 + nr:
                    out.append((i, j - r0, [(int(k), float(coef[k])) for k in ks]))
                elif not zero[j, c0:c0 + nc].all():
                    return None
        return out

    def plan(self, entries: np.ndarray, k: int) -> Plan | None:
        """How to contract the flat entries ``entries`` of ``V`` through the generators, or
        ``None`` when that costs more products than gathering ``k`` derivatives per entry
        (dense generators)."""
        key = (entries.tobytes(), k)
        if key in self._plans:
            return self._plans[key]
        terms = self.terms(entries)
        cost = sum(1 + len(c) for _, _, c in terms)
        plan = terms if cost <= 2 * k * entries.size else None
        self._plans[key] = plan
        return plan

    def terms(self, entries: np.ndarray) -> Plan:
        """For the flat entries ``p`` of a piece of ``V``: ``(i, column, [(k, coefficient)])``,
        the product of adjoint ``i`` with ``V``'s flat ``column`` adds into direction ``k``."""
        N, out = self.N, []
        for i, p in enumerate(entries.ravel().tolist()):
            a, b = divmod(int(p), N)
            for j in range(N):
                coef = self.G[:, a, j] if self.left else self.G[:, j, b]
                col = j * N + b if self.left else a * N + j
                ks = np.flatnonzero(coef)
                if len(ks) and not self.zero[col]:
                    out.append((i, col, [(int(k), float(coef[k])) for k in ks]))
        return out


def detect(j: Any) -> Structure | None:
    """The structure of a per-vertex jet ``(vertices, N, N)`` or ``(vertices, N·N)``, or
    ``None`` (not square, ``N`` outside 2…4, or no generators fit every vertex)."""
    v, t = j.value, j.tangent
    nv = len(v)
    if v.dtype.kind != "f" or nv == 0 or v.ndim not in (2, 3) or t.shape[1:] != v.shape:
        return None
    S = v[0].size
    N = isqrt(S)
    if N * N != S or not 2 <= N <= 4 or (v.ndim == 3 and v.shape[1] != N):
        return None
    V = v.reshape(nv, N, N)
    T = t.reshape(len(t), nv, N, N)
    scale = float(np.max(np.abs(T), initial=0.0))
    if scale == 0.0 or not np.all(np.isfinite(T)):
        return None
    for left in (True, False):
        if left:  # G (Σ V Vᵀ) = Σ T Vᵀ
            A = np.einsum("vij,vlj->il", V, V)
            B = np.einsum("kvij,vlj->kil", T, V)
        else:  # (Σ Vᵀ V) G = Σ Vᵀ T
            A = np.einsum("vji,vjl->il", V, V)
            B = np.einsum("vji,kvjl->kil", V, T)
        try:  # (a singular A: the fit below fails, or solve raises)
            Ainv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            return None
        G = B @ Ainv if left else Ainv @ B
        # Entries within rounding of an integer are that integer (a rotation's generators are
        # 0 and ±1; the fit's last bits vary with the estimates): the same generators at every
        # linearisation, a coefficient 1 costs no product, and a replayed block program
        # (graphopt.autodiff.programs) keyed by them applies again. The check below decides.
        near = np.round(G)
        snap = np.abs(G - near) < TOLERANCE * max(1.0, float(np.max(np.abs(G))))
        G[snap] = near[snap]
        G += 0.0  # (−0 is 0)
        fit = np.matmul(G[:, None], V[None]) if left else np.matmul(V[None], G[:, None])
        if float(np.max(np.abs(fit - T))) <= TOLERANCE * scale:
            flat = v.reshape(nv, S)
            return Structure(G, j.lo, left, np.all(flat == 0.0, axis=0),
                             np.all(flat == 1.0, axis=0))
    return None


def contract_product(J: Any, lo: int, plan: Plan, g: np.ndarray, Y: np.ndarray,
                     a: int, b: int) -> None:
    """``J[:, lo+k, a:b] += c Σ_l g[:, :, i, l] Y[:, j, l]`` for a :meth:`product_plan`.

    Args:
        J: The block's Jacobian rows (:class:`graphopt.autodiff.reverse.Rows`).
        lo: The structure's first direction.
        plan: The product's plan.
        g: ``(r, m, rows, q)`` the adjoint of ``Y``.
        Y: ``(m, rows, q)`` the product.
        a: First edge of the block the rows are.
        b: One past the last.
    """
    for i, j, ks in plan:
        for col in range(Y.shape[2]):
            prod = (g[:, :, i, col] * Y[:, j, col])[:, None, :]
            for k, c in ks:
                J.add(lo + k, lo + k + 1, a, b, prod, c)


_COLUMNS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


def clear() -> None:
    """Forget the columns of :func:`contract` and the deferred products of :func:`defer` (at
    the start of a reverse pass)."""
    _COLUMNS.clear()
    _DEFERRED.clear()


def _column(full: np.ndarray, col: int) -> np.ndarray:
    """Flat entry ``col`` of every edge's ``V``, contiguous (gathered once per block)."""
    hit = _COLUMNS.get((id(full), col))  # (full itself is kept: its id stays its own)
    if hit is None:
        c = full.reshape(len(full), -1)[:, col]
        # (np.copy, not np.ascontiguousarray: it keeps a traced array traced, replay.py)
        hit = _COLUMNS[id(full), col] = (full, c if c.flags.c_contiguous else np.copy(c))
    return hit[1]


def contract(J: Any, lo: int, plan: Plan, full: np.ndarray, g: np.ndarray, a: int,
             b: int, one: np.ndarray) -> None:
    """``J[:, lo+k, a:b] += Σ_p g[:, :, p] (G_k V)_p`` for a piece of ``V``.

    Args:
        J: The block's Jacobian rows (:class:`graphopt.autodiff.reverse.Rows`).
        lo: The structure's first direction.
        plan: :meth:`Structure.plan` of the piece's entries.
        full: ``(m, N, N)`` or ``(m, N·N)``: each edge's whole ``V``.
        g: ``(r, m, *piece)`` the piece's adjoint.
        a: First edge of the block the piece's rows are.
        b: One past the last.
        one: ``(N·N,)`` entries of ``V`` that are 1 at every vertex (no product).
    """
    r, m = g.shape[:2]
    gf = g.reshape(r, m, -1)
    for i, col, ks in plan:
        prod = (gf[:, :, i] if one[col] else gf[:, :, i] * _column(full, col))[:, None, :]
        for k, c in ks:
            J.add(lo + k, lo + k + 1, a, b, prod, c)


#: Recorded sums of products of structured entries and arrays, by their terms (see
#: ``_Node.terms`` in :mod:`graphopt.autodiff.tape`): ``Σ_b V_jb x_b`` of an error written
#: entry by entry is such a sum, which :func:`contract_deferred` reuses.
SUMS: dict[frozenset[tuple[int, int, int]], np.ndarray] = {}

#: ``(leaf node, plan, g, x, rows, v ⊙ x)`` per deferred product (see :func:`defer`).
_DEFERRED: list[tuple[Any, Plan, np.ndarray, np.ndarray, tuple[int, int], Any]] = []


def defer(v: Any, leaf: Any, g: np.ndarray, x: np.ndarray, y: Any = None) -> bool:
    """Keep the adjoint ``g ⊙ x`` of one entry ``v`` of a structured matrix (the factor of a
    recorded ``v * x``) as the pair, for :func:`contract_deferred`; ``False`` if ``v`` is no
    longer that leaf or its generators are dense (the caller forms ``g ⊙ x``).

    An error written entry by entry (``P_a = Σ_b V_ab x_b``) hands the same adjoint ``g`` of
    ``P_a`` to every ``V_ab``; kept as pairs, their contraction ``Σ_b g x_b (G_k V)_ab =
    Σ_j G_k[a, j] g (Σ_b V_jb x_b)`` forms each ``Σ_b V_jb x_b`` once, per edge, and
    multiplies it by ``g`` once per generator entry: the cross-product rule of ``R X`` that a
    hand-written Jacobian uses, found from the entries.

    Args:
        v: The entry (gathered rows of a structured per-vertex jet, ``(m,)``).
        leaf: Its recorded node when the product was recorded.
        g: ``(r, m)`` the adjoint of the product.
        x: ``(m,)`` the other factor's value.
        y: ``(m,)`` the product ``v ⊙ x`` (its value, computed already), if known.
    """
    if v._tape is not leaf or v.rows is None:
        return False
    entries = leaf.entries if leaf.entries is not None else np.arange(1)
    plan = leaf.struct.plan(entries, len(leaf.source))
    if plan is None:
        return False
    _DEFERRED.append((leaf, plan, g, x, v.rows, y))
    return True


def contract_deferred(J: Any) -> None:
    """Contract the products kept by :func:`defer`: grouped by their adjoint ``g`` and
    generator coefficients, each group's ``Σ x V_col`` is formed once (per edge) and
    multiplied by ``g`` once.

    Args:
        J: The block's Jacobian rows (:class:`graphopt.autodiff.reverse.Rows`).
    """
    groups: dict[tuple[Any, ...], list[Any]] = {}
    # The recorded products v ⊙ x by entry (flat column of V) and factor: where the
    # contraction needs the same product (V_jb x_b of another row's entry) it is reused.
    known: dict[tuple[int, int, int], np.ndarray] = {}
    rank: dict[tuple[int, int, int], int] = {}
    for leaf, plan, g, x, (a, b), y in _DEFERRED:
        lo, one = leaf.struct.lo, leaf.struct.one
        if y is not None and leaf.entries is not None and leaf.entries.size == 1:
            known[id(x), id(leaf.full), int(leaf.entries.flat[0])] = y
        for _, col, ks in plan:
            key = (id(g), lo, a, b, tuple(ks))
            grp = groups.get(key)
            if grp is None:
                grp = groups[key] = [g, lo, a, b, ks, {}]
            # (the same product twice — `v * x + v * x` — counts twice)
            name = (id(x), id(leaf.full), col)
            hit = grp[5].get(name)
            if hit is None:
                grp[5][name] = [x, leaf.full, col, bool(one[col]), 1]
                rank.setdefault(name, len(rank))
            else:
                hit[4] += 1
    products: dict[tuple[int, int, int], np.ndarray] = {}
    sums: dict[tuple[Any, ...], np.ndarray] = {}
    for g, lo, a, b, ks, members in groups.values():
        # (in the order first met, not by the ids in the names: the same sum in the same
        # order in every block, as a replayed block program has it, graphopt.autodiff.replay)
        names = tuple(sorted(members, key=rank.__getitem__))
        counts = tuple(members[n][4] for n in names)
        once = max(counts) == 1
        skey = names if once else (names, counts)
        s = sums.get(skey)
        if s is None and once:  # (a recorded sum adds each product once)
            s = sums[skey] = SUMS.get(frozenset(names))
        if s is None:
            for name in names:
                if name not in products:
                    x, full, col, is_one, _ = members[name]
                    y = known.get(name)
                    products[name] = (x if is_one else y if y is not None
                                      else x * _column(full, col))
            terms = [products[n] if c == 1 else c * products[n]
                     for n, c in zip(names, counts, strict=True)]
            s = terms[0]
            for t in terms[1:]:
                s = s + t
            sums[skey] = s
        if len(ks) == 1:  # (a rotation's generators: one direction each)
            J.add_product(lo + ks[0][0], a, b, g, s, ks[0][1])
            continue
        prod = (g * s)[:, None, :]
        for k, c in ks:
            J.add(lo + k, lo + k + 1, a, b, prod, c)
    _DEFERRED.clear()
    SUMS.clear()

_PIECES: dict[tuple[Any, ...], np.ndarray] = {}


def piece(entries: np.ndarray | None, shape: tuple[int, ...], key: tuple[Any, ...],
          ck: Any = None) -> np.ndarray:
    """The flat entries of a structured matrix that ``rows[(:,) + key]`` of gathered rows
    with trailing ``shape`` are (``entries``: the rows' own entries of the whole matrix, or
    ``None`` for all of it; ``ck``: a hashable name of ``key``, if it has a cheap one)."""
    if entries is None:  # the whole matrix: the same few pieces in every block
        ck = (shape, repr(key) if ck is None else ck)
        hit = _PIECES.get(ck)
        if hit is None:
            if len(_PIECES) > 256:
                _PIECES.clear()
            hit = _PIECES[ck] = np.arange(int(np.prod(shape))).reshape(shape)[key]
        return hit
    return np.asarray(entries[key])
