"""The small batched kernels against NumPy/SciPy references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import graphopt.linear.block_ops as bo
from graphopt.errors import NotPositiveDefiniteError
from graphopt.linear.block_ops import batched_cholesky_inverses, block_products
from graphopt.linear.gathered_gram import GatheredGram


@pytest.mark.parametrize("d", [1, 2, 3, 4, 6])
def test_cholesky_inverses_match_lapack(d: int) -> None:
    rng = np.random.default_rng(d)
    B = rng.normal(size=(50, d, d + 2))
    A = B @ np.swapaxes(B, 1, 2)
    diag = rng.uniform(0.1, 1.0, size=(50, d))
    A_before = A.copy()
    linv, inv = batched_cholesky_inverses(A, diag)
    Ad = A + diag[:, :, None] * np.eye(d)
    L = np.linalg.cholesky(Ad)
    np.testing.assert_allclose(linv, np.linalg.inv(L), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(inv @ Ad, np.broadcast_to(np.eye(d), Ad.shape), atol=1e-9)
    assert np.all(np.triu(linv, 1) == 0.0)
    np.testing.assert_array_equal(A, A_before)  # the damping is not written into A
    np.testing.assert_allclose(batched_cholesky_inverses(Ad)[1], inv, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("d", [1, 3, 5])
def test_cholesky_inverses_reject_indefinite_blocks(d: int) -> None:
    A = np.broadcast_to(np.eye(d), (4, d, d)).copy()
    A[2, d - 1, d - 1] = -1.0  # the last pivot is negative
    with pytest.raises(NotPositiveDefiniteError):
        batched_cholesky_inverses(A)
    A[2, d - 1, d - 1] = 0.0  # a zero pivot
    with pytest.raises(NotPositiveDefiniteError):
        batched_cholesky_inverses(A)
    A[2, d - 1, d - 1] = 0.5
    with pytest.raises(NotPositiveDefiniteError):  # damped into indefiniteness
        batched_cholesky_inverses(A, np.full((4, d), -1.0))


@pytest.mark.parametrize("fmt", ["csr", "csc"])
@pytest.mark.parametrize("kernel", ["scipy", "fallback"])
def test_csr_product_into_overwrites_the_output(fmt: str, kernel: str, monkeypatch) -> None:
    if kernel == "fallback":
        monkeypatch.setattr(bo, "_csr_matvecs", None)
        monkeypatch.setattr(bo, "_csc_matvecs", None)
    rng = np.random.default_rng(3)
    A = sp.random(30, 20, density=0.2, format=fmt, random_state=4)
    A.indices, A.indptr = A.indices.astype(np.int32), A.indptr.astype(np.int32)
    B = rng.normal(size=(21, 7))  # one row more than A has columns: only the first are read
    out = np.full(30 * 7, 5.0)  # stale values must not survive
    bo.csr_product_into(30, 20, 7, A.indptr, A.indices, A.data, B.reshape(-1), out,
                        csc=fmt == "csc")
    np.testing.assert_allclose(out.reshape(30, 7), A @ B[:20], rtol=1e-12)


def test_gathered_gram_sums_block_products_per_target() -> None:
    rng = np.random.default_rng(7)
    r, d, nz, n_targets = 3, 4, 60, 9
    Z = rng.normal(size=(nz, r, d))
    # Targets with 0, 1, a few and many terms (more than max_blocks: split into pieces);
    # target 3 only pairs blocks with themselves (one gather serves both sides).
    counts = [0, 1, 2, 5, 7, 40, 3, 11, 90]
    target = np.repeat(np.arange(n_targets), counts)
    a = rng.integers(0, nz, len(target))
    b = rng.integers(0, nz, len(target))
    b[target == 3] = a[target == 3]
    perm = rng.permutation(len(target))  # terms need not come sorted
    target, a, b = target[perm], a[perm], b[perm]
    gram = GatheredGram(target, a, b, n_targets, r, d, max_blocks=16, ratio=1.25)
    Y = rng.normal(size=(nz, r, d))
    for B in (None, Y):  # Σ Zᵀ Z and Σ Zᵀ Y
        ref = np.zeros((n_targets, d, d))
        for t, i, j in zip(target, a, b, strict=True):
            ref[t] += Z[i].T @ (Z if B is None else B)[j]
        out = np.full((gram.n_out, d, d), np.nan)
        gram(Z.reshape(nz, r * d), out, None if B is None else B.reshape(nz, r * d))
        got = np.zeros((n_targets, d, d))
        np.add.at(got, gram.targets, out)  # pieces of a target add up
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    assert gram.padded > len(target)  # padded blocks were zeroed, or the sums would differ
    assert np.bincount(gram.targets, minlength=n_targets)[8] == 6  # 90 terms, 16 per piece
    assert 0 not in gram.targets  # no terms, no output
    assert any(c[4] for c in gram.chunks)  # target 3's chunk gathers once
    assert all(m <= 16 for _, _, m, *_ in gram.chunks)


@pytest.mark.parametrize("same", [True, False])
def test_gathered_gram_of_one_output_plans_as_the_general_case(same: bool) -> None:
    """One target (a motion-only BA's pose block) takes a shortcut: the same plan and sums as
    the general plan of that target beside an empty one."""
    rng = np.random.default_rng(11)
    r, d, nz, q = 2, 6, 40, 25
    Z = rng.normal(size=(nz, r * d))
    a = rng.integers(0, nz, q)
    b = a if same else rng.integers(0, nz, q)
    one = GatheredGram(np.zeros(q, dtype=int), a, b, 1, r, d)
    two = GatheredGram(np.zeros(q, dtype=int), a, b, 2, r, d)  # target 1: no terms
    assert (one.chunks, one.padded, one.gathered, one.n_out) == (
        two.chunks, two.padded, two.gathered, two.n_out)
    for name in ("ia", "ib", "pads", "targets"):
        x, y = getattr(one, name), getattr(two, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    B = None if same else Z[::-1].copy()
    got, ref = np.full((1, d, d), np.nan), np.full((1, d, d), np.nan)
    one(Z, got, B)
    two(Z, ref, B)
    assert np.array_equal(got, ref)
    want = sum(Z[i].reshape(r, d).T @ (Z if B is None else B)[j].reshape(r, d)
               for i, j in zip(a, b, strict=True))
    np.testing.assert_allclose(got[0], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("p", "q", "k"), [(3, 3, 6), (3, 3, 1), (2, 4, 9), (1, 1, 1)])
def test_block_products_match_matmul(p: int, q: int, k: int) -> None:
    rng = np.random.default_rng(p * 100 + q * 10 + k)
    A, B = rng.normal(size=(37, p, q)), rng.normal(size=(37, q, k))
    np.testing.assert_allclose(block_products(A, B), np.matmul(A, B), rtol=1e-14, atol=1e-14)
    # Non-contiguous inputs (a transposed view) and an empty batch.
    At = np.swapaxes(rng.normal(size=(37, q, p)), 1, 2)
    np.testing.assert_allclose(block_products(At, B), np.matmul(At, B), rtol=1e-14, atol=1e-14)
    assert block_products(A[:0], B[:0]).shape == (0, p, k)
