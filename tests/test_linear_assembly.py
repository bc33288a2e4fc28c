"""Assembly and the λ-free products of one linearisation, against the dense Hessian of the
same problem with nothing marginalised."""

from __future__ import annotations

import numpy as np
import pytest
from schur_toys import full_in_schur_order, multi_toy

from graphopt.linear import Assembly, SchurConfig, SchurCostModel
from graphopt.linear.pattern import with_data


@pytest.fixture(scope="module")
def toy():
    """The multi-class toy linearised, with the dense full Hessian in its ``[U; V]`` order."""
    full, schur = multi_toy(False), multi_toy(True)
    for o in (full, schur):
        o.initialize_optimization()
    H, b = full_in_schur_order(full, schur)
    asm, _ = schur.problem.linearize()
    return schur.linear_system, asm, H, b


def v_offsets(ix) -> np.ndarray:
    return np.cumsum([ix.n] + [len(c.slots) * c.dim for c in ix.vclasses])


def test_assembly_holds_the_blocks_of_the_full_hessian(toy) -> None:
    system, asm, H, b = toy
    ix = system.index
    n = ix.n
    scale = np.abs(H).max()
    np.testing.assert_allclose(with_data(system.pattern, asm.h_data).toarray(), H[:n, :n],
                               rtol=1e-12, atol=1e-14 * scale)
    np.testing.assert_allclose(asm.bu, b[:n], rtol=1e-12, atol=1e-14 * np.abs(b).max())
    voff = v_offsets(ix)
    for c, (cls, v, bv) in enumerate(zip(ix.vclasses, asm.v, asm.bv, strict=True)):
        d = cls.dim
        assert v.shape == (len(cls.slots), d, d) and bv.shape == (len(cls.slots), d)
        for blk in range(len(cls.slots)):
            r = slice(voff[c] + blk * d, voff[c] + (blk + 1) * d)
            np.testing.assert_allclose(v[blk], H[r, r], rtol=1e-12, atol=1e-14 * scale)
            np.testing.assert_allclose(bv[blk], b[r], rtol=1e-12, atol=1e-14 * scale)
    for k, w in enumerate(ix.wclasses):
        assert asm.wt[k].shape == (len(w.ublock), w.dv, w.du)
        for i in range(len(w.ublock)):
            rv = voff[w.vclass] + w.vblock[i] * w.dv + np.arange(w.dv)
            np.testing.assert_allclose(asm.wt[k][i], H[np.ix_(rv, w.upos[i])], rtol=1e-12,
                                       atol=1e-14 * scale)
    # Nothing is left out: every V-U entry of H lies in some W block.
    covered = np.zeros_like(H, dtype=bool)
    for w in ix.wclasses:
        for i in range(len(w.ublock)):
            rv = voff[w.vclass] + w.vblock[i] * w.dv + np.arange(w.dv)
            covered[np.ix_(rv, w.upos[i])] = True
    assert not H[n:, :n][~covered[n:, :n]].any()


def test_gram_summed_u_blocks_equal_the_contractions() -> None:
    def assembled(cost: SchurCostModel) -> tuple[int, Assembly]:
        opt = multi_toy(True, SchurConfig("sparse", cost))
        opt.initialize_optimization()
        return opt.linear_system.assembler.u_gram_terms, opt.problem.linearize()[0]

    n_ref, ref = assembled(SchurCostModel(gram_enabled=False))
    n_got, got = assembled(SchurCostModel(sparse_mac=1e9))
    # Camera and intrinsics diagonal blocks of the landmark edges, camera blocks of the lines
    # and of the chain's two positions.
    assert (n_ref, n_got) == (0, 5)
    np.testing.assert_allclose(got.h_data, ref.h_data, rtol=1e-12,
                               atol=1e-13 * np.abs(ref.h_data).max())
    np.testing.assert_array_equal(got.bu, ref.bu)


def test_is_finite_sees_every_part(toy) -> None:
    system, asm, _, _ = toy
    assert system.is_finite(asm)
    for part in ("h_data", "bu", "v", "bv"):
        bad = Assembly(asm.h_data.copy(), asm.bu.copy(), [x.copy() for x in asm.v],
                       [x.copy() for x in asm.bv], asm.wt)
        target = getattr(bad, part)
        (target if isinstance(target, np.ndarray) else target[-1]).reshape(-1)[3] = np.inf
        assert not system.is_finite(bad), part


def test_damping_and_max_diagonal(toy) -> None:
    system, asm, H, _ = toy
    n = system.n
    du, dv = system.damping(asm, diagonal=False)
    assert (du == 1).all() and du.shape == (n,) and [d.shape for d in dv] == [
        b.shape for b in asm.bv] and all((d == 1).all() for d in dv)
    du, dv = system.damping(asm, diagonal=True)
    ref = np.clip(np.diag(H), 1e-6, 1e32)
    np.testing.assert_allclose(du, ref[:n], rtol=1e-12)
    np.testing.assert_allclose(np.concatenate([d.ravel() for d in dv]), ref[n:], rtol=1e-12)
    assert system.max_diagonal(asm) == pytest.approx(np.diag(H).max(), rel=1e-12)


def test_products_against_the_dense_hessian(toy) -> None:
    system, asm, H, b = toy
    ix = system.index
    n = ix.n
    voff = v_offsets(ix)
    rng = np.random.default_rng(4)
    x = rng.normal(size=len(H))
    xv = [x[voff[c]:voff[c + 1]].reshape(len(cls.slots), cls.dim)
          for c, cls in enumerate(ix.vclasses)]
    hu, hv = system.hessian_product(asm, x[:n], xv)
    ref = H @ x
    got = np.concatenate([hu, *(h.ravel() for h in hv)])
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    for k, w in enumerate(ix.wclasses):  # Wᵀ x_u per V block of the class
        rv = slice(voff[w.vclass], voff[w.vclass + 1])
        ref = H[rv, w.ucols] @ x[w.ucols]
        np.testing.assert_allclose(system.wt_product(asm, k, x[:n]).ravel(), ref, rtol=1e-10,
                                   atol=1e-12 * np.abs(ref).max())
    # Back-substitution: Δv = V⁻¹(b_v − Wᵀ Δu) solves the V rows of H Δ = b for any Δu.
    _, _, vinv = system.reduce(asm, 0.0)
    dv = system.back_substitute(asm, x[:n], vinv)
    step = np.concatenate([x[:n], *(d.ravel() for d in dv)])
    np.testing.assert_allclose((H @ step)[n:], b[n:], rtol=1e-9, atol=1e-10 * np.abs(b).max())
    # Yᵀ = V⁻¹Wᵀ per W block.
    for k, (w, yt) in enumerate(zip(ix.wclasses, system.y_transposed(asm, vinv), strict=True)):
        i = len(w.ublock) // 2
        rv = voff[w.vclass] + w.vblock[i] * w.dv + np.arange(w.dv)
        ref = np.linalg.solve(H[np.ix_(rv, rv)], H[np.ix_(rv, w.upos[i])])
        np.testing.assert_allclose(yt[i], ref, rtol=1e-9, atol=1e-12, err_msg=str(k))


@pytest.mark.parametrize("left_out", [0, 3, 40])  # all edges, a few (scratch), many (gather)
def test_edge_contraction_sums_the_selected_edges(left_out: int) -> None:
    from graphopt.linear.block_ops import EdgeContraction

    rng = np.random.default_rng(7)
    m, r, d1, d2, n_t = 60, 3, 3, 2, 9
    sel = np.sort(rng.choice(m, m - left_out, replace=False))
    target = rng.integers(0, n_t, len(sel))
    A, B = rng.standard_normal((m, r, d1)), rng.standard_normal((m, r, d2))
    con = EdgeContraction(sel, target, n_t, m, r, d1)
    assert con.scratch == (left_out == 3)
    want = np.zeros((n_t, d1, d2))
    for e, t in zip(sel, target, strict=True):
        want[t] += A[e].T @ B[e]
    np.testing.assert_allclose(con(A, B), want, rtol=1e-13, atol=1e-13)
    out = np.full(con.out_size(d2), np.nan)  # the scratch block is part of the buffer
    np.testing.assert_allclose(con(A, B, out), want, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("seed", range(4))
def test_u_gram_bound_never_exceeds_the_gram_estimate(seed: int) -> None:
    """``Assembler._u_gram`` skips planning a Gram when a lower bound of its modelled cost does
    not beat the sparse contraction: the bound (no padding, one output per target, one chunk)
    is at most the planned Gram's estimate, so the choice is the one the plan would make."""
    from graphopt.linear.gathered_gram import GatheredGram

    rng = np.random.default_rng(seed)
    cost = SchurCostModel()
    n_t, r, d = int(rng.integers(1, 40)), 2, 6
    counts = rng.integers(1, 3000 if seed % 2 else 30, n_t)  # every target has a term
    target = rng.permutation(np.repeat(np.arange(n_t), counts))
    sel = np.arange(len(target))
    gram = GatheredGram(target, sel, sel, n_t, r, d)
    bound = ((2 * cost.gram_gather * r * d + cost.gemm_mac * r * d * d) * len(sel)
             + cost.gemm_output * n_t + cost.gemm_chunk)
    assert bound <= cost.gram_seconds(gram, 2 * gram.padded) * (1 + 1e-12)
