"""The block index (U/V/W blocks, co-visibility order) and the reduced pattern, against
brute-force enumerations of the edges."""

from __future__ import annotations

import numpy as np
import pytest
from schur_toys import EdgeCamChain, EdgeObs, VertexCam, VertexLandmark, multi_toy

from graphopt import SparseOptimizer
from graphopt.linear import SchurConfig, SchurCostModel
from graphopt.linear.indexing import pairs_sharing_key, unique_ints
from graphopt.linear.ordering import co_visibility_order
from graphopt.linear.pattern import ReducedPattern, with_data


def built(opt: SparseOptimizer):
    opt.initialize_optimization()
    return opt.linear_system


def strip_toy() -> SparseOptimizer:
    """8 cameras (the first fixed) in a strip: landmark j is seen by cameras c and c + 1
    (c = 1 + j % 6), and a prior joins cameras 1 and 5: a sparse reduced pattern."""
    rng = np.random.default_rng(2)
    nc, npt = 8, 30
    obs = np.array([(c, j) for j in range(npt) for c in (1 + j % 6, 2 + j % 6)])
    opt = SparseOptimizer("lm", "dense")
    opt.add_vertices(VertexCam, np.arange(nc), rng.normal(size=(nc, 4)),
                     fixed=np.arange(nc) == 0)
    opt.add_vertices(VertexLandmark, 100 + np.arange(npt), rng.normal(size=(npt, 3)),
                     marginalized=True)
    opt.add_edges(EdgeObs, np.stack([obs[:, 0], 100 + obs[:, 1]], 1),
                  rng.normal(size=(len(obs), 2)))
    opt.add_edges(EdgeCamChain, np.array([[1, 5], [0, 1]]), np.zeros((2, 4)))
    return opt


def edge_blocks(system, gi: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """U and V blocks of group ``gi``'s edges, per position, from the per-store maps."""
    ix = system.index
    pos = ix.positions[gi]
    return ([ix.ublock[s][slots] for s, slots in pos], [ix.vblock[s][slots] for s, slots in pos])


def test_blocks_are_numbered_per_store() -> None:
    system = built(multi_toy(True))
    ix = system.index
    # Stores: cameras (7, the first fixed), intrinsics (3), landmarks (60), lines (25).
    np.testing.assert_array_equal(ix.ublock[0], [-1, 0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(ix.ublock[1], [6, 7, 8])
    assert (ix.ublock[2] == -1).all() and (ix.ublock[3] == -1).all()
    assert (ix.vblock[0] == -1).all() and (ix.vblock[1] == -1).all()
    np.testing.assert_array_equal(ix.udims, [4] * 6 + [2] * 3)
    np.testing.assert_array_equal(ix.uoffset, [0, 4, 8, 12, 16, 20, 24, 26, 28, 30])
    assert ix.n == system.n == 30 and ix.n_ublocks == 9
    assert ix.vclass_of_store == [-1, -1, 0, 1]
    assert [(c.store, c.dim, len(c.slots)) for c in ix.vclasses] == [(2, 3, 60), (3, 2, 25)]
    for c in ix.vclasses:  # V block b is the vertex in slot slots[b], and back
        vb = ix.vblock[c.store]
        np.testing.assert_array_equal(np.sort(vb), np.arange(len(c.slots)))
        np.testing.assert_array_equal(vb[c.slots], np.arange(len(c.slots)))
    assert system.schur and not built(multi_toy(False)).schur


def test_w_classes_hold_every_coupled_pair_once() -> None:
    system = built(multi_toy(True))
    ix = system.index
    found: dict[tuple[int, int], set[tuple[int, int]]] = {}
    for gi, pos in enumerate(ix.positions):
        ub, vb = edge_blocks(system, gi)
        for x in range(len(pos)):
            for y in range(len(pos)):
                ok = (ub[x] >= 0) & (vb[y] >= 0)
                key = (pos[x][0], ix.vclass_of_store[pos[y][0]])
                found.setdefault(key, set()).update(zip(ub[x][ok].tolist(), vb[y][ok].tolist(),
                                                        strict=True))
    found = {k: v for k, v in found.items() if v}
    assert len(found) == len(ix.wclasses) == 3
    for w in ix.wclasses:
        pairs = list(zip(w.ublock.tolist(), w.vblock.tolist(), strict=True))
        assert set(pairs) == found[(w.ustore, w.vclass)] and len(set(pairs)) == len(pairs)
        assert pairs == sorted(pairs, key=lambda p: (p[1], p[0]))  # by V, then U block
        assert (w.du, w.dv) == (ix.stores[w.ustore].vtype.dimension, ix.vclasses[w.vclass].dim)
        np.testing.assert_array_equal(w.upos, ix.uoffset[w.ublock][:, None] + np.arange(w.du))
    assert ix.wclass_of == {(w.ustore, w.vclass): k for k, w in enumerate(ix.wclasses)}


@pytest.mark.parametrize("k1, k2", [(0, 0), (1, 1), (2, 2), (0, 1)])
def test_w_pairs_share_a_v_block(k1: int, k2: int) -> None:
    ix = built(multi_toy(True)).index
    c1, c2 = ix.wclasses[k1], ix.wclasses[k2]
    w1, w2 = ix.w_pairs(k1, k2)
    ref = {(a, b) for a in range(len(c1.ublock)) for b in range(len(c2.ublock))
           if c1.vblock[a] == c2.vblock[b] and (k1 != k2 or c1.ublock[a] < c2.ublock[b])}
    assert set(zip(w1.tolist(), w2.tolist(), strict=True)) == ref and len(w1) == len(ref) > 0


# Strip: 7 diagonal blocks, 6 camera pairs through landmarks and the prior, both triangles.
# Multi: every camera and intrinsics block meets every other through some landmark.
@pytest.mark.parametrize("toy, n_blocks", [(strip_toy, 7 + 2 * 6 + 2),
                                           (lambda: multi_toy(True), 81)])
def test_pattern_holds_the_u_blocks_edges_and_fill(toy, n_blocks: int) -> None:
    system = built(toy())
    ix = system.index
    blocks = {(u, u) for u in range(ix.n_ublocks)}
    for gi in range(len(ix.positions)):  # U-U blocks of the edges (the camera chain)
        ub, _ = edge_blocks(system, gi)
        for a in range(len(ub)):
            for b in range(len(ub)):
                ok = (ub[a] >= 0) & (ub[b] >= 0)
                blocks |= set(zip(ub[a][ok].tolist(), ub[b][ok].tolist(), strict=True))
    for c in range(len(ix.vclasses)):  # fill: U blocks that share a V block
        us: dict[int, set[int]] = {}
        for w in ix.wclasses:
            if w.vclass == c:
                for u, v in zip(w.ublock.tolist(), w.vblock.tolist(), strict=True):
                    us.setdefault(v, set()).add(u)
        blocks |= {(a, b) for s in us.values() for a in s for b in s}
    dense = np.zeros((ix.n, ix.n), dtype=bool)
    for a, b in blocks:
        dense[ix.uoffset[a]:ix.uoffset[a + 1], ix.uoffset[b]:ix.uoffset[b + 1]] = True
    got = with_data(system.pattern, np.ones(ix.pattern.nnz)).toarray() != 0
    np.testing.assert_array_equal(got, dense)
    assert ix.pattern.nnz == dense.sum() and len(blocks) == n_blocks
    nb = ix.n_ublocks
    a, b = np.divmod(np.arange(nb * nb), nb)
    np.testing.assert_array_equal(ix.pattern.has_blocks(a, b),
                                  [p in blocks for p in zip(a.tolist(), b.tolist(), strict=True)])
    assert system.pattern.indices.dtype == np.int32
    # Positions: entry (r, c) holds data[positions(r, c)].
    rng = np.random.default_rng(0)
    r, c = np.nonzero(dense)
    pick = rng.choice(len(r), 50, replace=False)
    data = rng.normal(size=ix.pattern.nnz)
    m = with_data(system.pattern, data).toarray()
    np.testing.assert_array_equal(data[ix.pattern.positions(r[pick], c[pick])],
                                  m[r[pick], c[pick]])
    np.testing.assert_array_equal(data[ix.pattern.diag_pos], np.diag(m))


def test_to_s_sums_blocks_into_both_triangles() -> None:
    ix = built(strip_toy()).index
    tu1, tu2 = np.array([1, 2, 0]), np.array([1, 3, 4])  # a diagonal, fill and the prior
    blocks = np.random.default_rng(1).normal(size=(3, 4, 4))
    s = ix.pattern.to_s(tu1, tu2) @ blocks.reshape(-1)
    ref = np.zeros((ix.n, ix.n))
    for a, b, blk in zip(tu1, tu2, blocks, strict=True):
        ra, rb = slice(ix.uoffset[a], ix.uoffset[a + 1]), slice(ix.uoffset[b], ix.uoffset[b + 1])
        ref[ra, rb] += blk
        if a != b:
            ref[rb, ra] += blk.T
    np.testing.assert_array_equal(with_data(ix.pattern.csc, s).toarray(), ref)


@pytest.mark.parametrize("spectral_max", [0, 600])
def test_v_blocks_with_the_same_cameras_become_runs(spectral_max: int) -> None:
    """Points seen by the same camera set get consecutive V blocks (whatever their ids)."""
    rng = np.random.default_rng(5)
    nc, npt = 9, 120
    sets = [rng.choice(nc, 3, replace=False) for _ in range(8)]
    which = rng.integers(0, len(sets), npt)
    obs = np.array([(i, j) for j in range(npt) for i in sets[which[j]]])
    opt = SparseOptimizer("lm", "dense", schur=SchurConfig(
        cost=SchurCostModel(spectral_max=spectral_max)))
    opt.add_vertices(VertexCam, np.arange(nc), rng.normal(size=(nc, 4)))
    opt.add_vertices(VertexLandmark, 100 + np.arange(npt), rng.normal(size=(npt, 3)),
                     marginalized=True)
    opt.add_edges(EdgeObs, np.stack([obs[:, 0], 100 + obs[:, 1]], 1),
                  rng.normal(size=(len(obs), 2)))
    ix = built(opt).index
    distinct = {frozenset(x.tolist()) for x in sets}
    set_id = {s: i for i, s in enumerate(sorted(distinct, key=sorted))}
    which = np.array([set_id[frozenset(sets[w].tolist())] for w in which])
    set_of_block = which[ix.vclasses[0].slots]  # the camera set of every V block, in order
    changes = np.count_nonzero(np.diff(set_of_block))
    assert changes == len(np.unique(which)) - 1 >= 5  # one run per set


def test_co_visibility_order_follows_a_chain() -> None:
    """U blocks seen together in a chain 0-5-1-4-2-3 (each V block sees two neighbours):
    the V blocks come out in chain order."""
    chain = [0, 5, 1, 4, 2, 3]
    v = np.repeat(np.arange(5), 2)
    u = np.array([[chain[i], chain[i + 1]] for i in range(5)]).ravel()
    perm = np.array([3, 0, 4, 1, 2])  # V blocks given in a shuffled order
    inv = np.argsort(perm)
    v2, u2 = inv[v], u
    order = np.lexsort((u2, v2))
    new = co_visibility_order(v2[order], u2[order], 5, 6, spectral_max=600)
    seq = perm[new]  # the chain position of every V block in the new order
    assert seq.tolist() in ([0, 1, 2, 3, 4], [4, 3, 2, 1, 0])
    # Without the spectral order, U blocks keep their numbering: the order is another one.
    assert perm[co_visibility_order(v2[order], u2[order], 5, 6, spectral_max=0)].tolist() != \
        seq.tolist()


def test_index_helpers() -> None:
    x = np.array([5, 1, 5, 3, 1, 9])
    for size in (10, 10**9):  # bitmap and sort paths
        uniq, inv = unique_ints(x, size, True)
        np.testing.assert_array_equal(uniq, [1, 3, 5, 9])
        np.testing.assert_array_equal(uniq[inv], x)
    i, j = pairs_sharing_key(np.array([0, 0, 2]), np.array([0, 1, 2, 2]))
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 0), (1, 0), (2, 2), (2, 3)]
    from graphopt.linear.indexing import concat_ranges

    assert concat_ranges(np.array([7, 0, 3]), np.array([2, 0, 3])).tolist() == [7, 8, 3, 4, 5]
    assert concat_ranges(np.zeros(0, np.int64), np.zeros(0, np.int64)).tolist() == []


@pytest.mark.parametrize("size", [0, 1, 7, 5000])
def test_sorted_unique_equals_numpy(size: int) -> None:
    from graphopt.linear.indexing import sorted_unique, unique_ints

    x = np.random.default_rng(size).integers(-3, 2 * size + 5, size=size) * 1_000_003
    u, inv = sorted_unique(x, return_inverse=True)
    ref, ref_inv = np.unique(x, return_inverse=True)
    np.testing.assert_array_equal(u, ref)
    np.testing.assert_array_equal(inv, ref_inv)
    np.testing.assert_array_equal(sorted_unique(x), ref)
    y = np.abs(x) // 1_000_003
    big = 10**9  # the sort path of unique_ints
    for got, want in ((unique_ints(y, big, True), np.unique(y, return_inverse=True)),
                      (unique_ints(y, int(y.max(initial=0)) + 1, True),
                       np.unique(y, return_inverse=True))):
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("two", [False, True])
def test_reduced_pattern_of_one_block_is_dense_column_major(two: bool) -> None:
    """One U block (a motion-only BA's pose) takes a shortcut; its pattern, positions and
    destinations are those of the general construction (the first block of two)."""
    d = 6
    if two:  # the general construction: blocks 0 and 1, block 0's entries
        p = ReducedPattern(np.array([0, d, 2 * d]), np.array([d, d]), np.array([0, 3]))
    else:
        p = ReducedPattern(np.array([0, d]), np.array([d]), np.array([0]))
    first = p.csc.indptr[: d + 1]
    assert first.dtype == np.int32 and p.csc.indices.dtype == np.int32
    np.testing.assert_array_equal(first, np.arange(d + 1) * d)
    np.testing.assert_array_equal(p.csc.indices[: d * d], np.tile(np.arange(d), d))
    np.testing.assert_array_equal(p.diag_pos[:d], np.arange(d) * (d + 1))
    rows, cols = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
    np.testing.assert_array_equal(p.positions(rows.ravel(), cols.ravel()),
                                  cols.ravel() * d + rows.ravel())
    zero = np.zeros(1, dtype=np.int64)
    pos, post = p.dest(zero, zero, transposes=False)
    np.testing.assert_array_equal(np.ravel(pos), (cols * d + rows).ravel())
    assert post is None
