"""The order of a V class's blocks, chosen once.

For an explicit Schur complement, the co-visibility order: vertices seen by the same U blocks
become neighbours, which keeps the dense Schur panels narrow and lets vertices with identical U
sets share a panel (``schur_dense.py``). For products from the edges' Jacobians (matrix-free),
the order in which the edges first reach them: the products then read and write the V blocks
about in memory order (at 1M BAL observations, ``J_v z`` per edge 14.5 → 6 ms).
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp

#: Most multiply-adds of a dense co-visibility product ``incᵀ inc`` (V blocks x U blocks²):
#: below, it costs less than SciPy's sparse set-up (ba_demo's 500 x 13: 0.6 → 0.05 ms).
_DENSE_PRODUCT = 1 << 21


def dense_co_visibility(n_v: int, n_u: int) -> bool:
    """Whether the co-visibility product ``incᵀ inc`` of ``n_v`` V blocks and ``n_u`` U blocks
    is cheaper dense (a NumPy product) than sparse (SciPy's set-up dominates small ones).

    Args:
        n_v: V blocks (rows of ``inc``).
        n_u: U blocks (its columns).
    """
    return n_v * n_u * n_u <= _DENSE_PRODUCT


@functools.lru_cache(maxsize=4)
def _tags(n: int) -> np.ndarray:
    """``(n,)`` fixed random 62-bit tags of U blocks (read-only; cached: the generator's
    set-up is most of the cost on small problems)."""
    tag = np.random.default_rng(0x5EED).integers(0, 2**62, size=n, dtype=np.int64)
    tag.flags.writeable = False
    return tag


def co_visibility_order(v: np.ndarray, u: np.ndarray, n_v: int, n_u: int,
                        spectral_max: int) -> np.ndarray:
    """The new order of a V class's blocks: new block ``b`` is old block ``order[b]``.

    U blocks are first put in a 1-D order that follows their co-visibility (the Fiedler vector
    of the co-visibility graph for up to ``spectral_max`` U blocks). V blocks are then sorted by
    the last and first U block they meet in that order, and by a hash of their whole U set
    (identical sets become runs).

    Args:
        v: V block of every (V block, U block) pair linked by an edge, unique pairs sorted by
            V, then U block.
        u: U block of every pair.
        n_v: Blocks in the V class.
        n_u: U blocks of the whole system.
        spectral_max: Most U blocks ordered by the Fiedler vector (else their own order).
    """
    tag = _tags(max(n_u, 1))  # per U block: set hashes
    lo = np.full(n_v, n_u, dtype=np.int64)
    hi = np.full(n_v, -1, dtype=np.int64)
    h = np.zeros(n_v, dtype=np.int64)
    if len(v):
        ru = _u_rank(v, u, n_v, n_u, spectral_max)[u]
        first = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
        lo[v[first]] = np.minimum.reduceat(ru, first)
        hi[v[first]] = np.maximum.reduceat(ru, first)
        with np.errstate(over="ignore"):
            h[v[first]] = np.add.reduceat(tag[u], first)  # wraps: a set hash
    return np.lexsort((h, lo, hi))


def _u_rank(v: np.ndarray, u: np.ndarray, n_v: int, n_u: int, spectral_max: int
            ) -> np.ndarray:
    """Position of every U block in a 1-D order that keeps co-visible U blocks close."""
    if n_u < 3 or n_u > spectral_max:
        return np.arange(n_u)
    if dense_co_visibility(n_v, n_u):  # small: a dense product (exact counts all the same)
        inc = np.zeros((n_v, n_u))
        inc[v, u] = 1.0  # pairs are unique
        c = inc.T @ inc
    else:
        sinc = sp.csr_matrix((np.ones(len(v)), (v, u)), shape=(n_v, n_u))
        c = (sinc.T @ sinc).toarray()
    np.fill_diagonal(c, 0.0)
    lap = np.diag(c.sum(axis=1)) - c
    _, vec = np.linalg.eigh(lap)
    order = np.argsort(vec[:, 1], kind="stable")
    rank = np.empty(n_u, dtype=np.int64)
    rank[order] = np.arange(n_u)
    return rank


def first_seen_order(stream: np.ndarray, n_v: int) -> np.ndarray:
    """V blocks in the order a stream of edges first reaches them (unreached ones last, in
    their own order): new block ``b`` is old block ``order[b]``.

    Args:
        stream: V block of every edge, in the edges' order.
        n_v: Blocks in the V class.
    """
    first = np.full(n_v, len(stream), dtype=np.int64)
    np.minimum.at(first, stream, np.arange(len(stream), dtype=np.int64))
    return np.argsort(first, kind="stable")
