"""The three Schur strategies, each forced by ``SchurConfig``, against the dense Schur
complement of the full system and against each other; the automatic choice; the config."""

from __future__ import annotations

import numpy as np
import pytest
from schur_toys import ba_toy, full_in_schur_order, multi_toy, scalar_index

from graphopt.linear import SchurConfig, SchurCostModel
from graphopt.linear.pattern import with_data
from graphopt.linear.schur_dense import DensePlan
from graphopt.linear.schur_gram import GramPlan
from graphopt.linear.schur_sparse import SparsePlan
from graphopt.linear.schur_strategy import VFactors

STRATEGIES = ["sparse", "dense", "gram"]


def dense_schur(H: np.ndarray, b: np.ndarray, n: int, lam: float, diagonal: bool
                ) -> tuple[np.ndarray, np.ndarray]:
    """``S = U + λD − W (V + λD)⁻¹ Wᵀ`` and ``b_u − W (V + λD)⁻¹ b_v``, densely."""
    d = np.clip(np.diag(H), 1e-6, 1e32) if diagonal else np.ones(len(H))
    Hd = H + lam * np.diag(d)
    W = Hd[:n, n:]
    X = np.linalg.solve(Hd[n:, n:], np.column_stack([W.T, b[n:]]))
    return Hd[:n, :n] - W @ X[:, :-1], b[:n] - W @ X[:, -1]


@pytest.mark.parametrize("lam, diagonal", [(0.0, False), (1e-2, False), (1e-3, True)])
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_forced_strategy_gives_the_dense_schur_complement(strategy: str, lam: float,
                                                          diagonal: bool) -> None:
    full, schur = multi_toy(False), multi_toy(True, SchurConfig(strategy))
    for o in (full, schur):
        o.initialize_optimization()
    system = schur.linear_system
    # Cameras (U) see landmarks and lines (two V classes); intrinsics (U) see landmarks.
    assert [(w.ustore, w.vclass) for w in system.index.wclasses] == [(0, 0), (1, 0), (0, 1)]
    assert [t.name for t in system.reduction.strategies] == [strategy] * 3
    # Cameras and intrinsics meet through the landmarks: always by sparse pairs.
    assert [(c.k, c.k2) for c in system.reduction.couplings] == [(0, 1)]
    H, b = full_in_schur_order(full, schur)
    s_ref, rhs_ref = dense_schur(H, b, system.n, lam, diagonal)
    asm, _ = schur.problem.linearize()
    s, rhs, vinv = system.reduce(asm, lam, system.damping(asm, diagonal))
    S = with_data(system.pattern, s).toarray()
    scale = np.abs(s_ref).max()
    np.testing.assert_allclose(S, s_ref, rtol=1e-10, atol=1e-11 * scale)
    np.testing.assert_allclose(rhs, rhs_ref, rtol=1e-10, atol=1e-11 * np.abs(rhs_ref).max())
    # V⁻¹ of the damped landmark blocks, against the dense inverse of the first one.
    n_v = system.index.vclasses[0].dim
    v0 = H[system.n:system.n + n_v, system.n:system.n + n_v]
    d0 = np.clip(np.diag(v0), 1e-6, 1e32) if diagonal else np.ones(n_v)
    np.testing.assert_allclose(vinv[0][0], np.linalg.inv(v0 + lam * np.diag(d0)), rtol=1e-10)


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_forced_strategy_steps_equal_the_full_step(strategy: str) -> None:
    full, schur = multi_toy(False), multi_toy(True, SchurConfig(strategy))
    for o in (full, schur):
        o.initialize_optimization()
    asm_f, _ = full.problem.linearize()
    ref = full.problem.solve(asm_f, 1e-3, full.problem.damping(asm_f, True))[0]
    asm, _ = schur.problem.linearize()
    du, dv = schur.problem.solve(asm, 1e-3, schur.problem.damping(asm, True))
    got = np.empty_like(ref)
    step = np.concatenate([du, *(x.ravel() for x in dv)])
    for fi, si in zip(scalar_index(full.linear_system), scalar_index(schur.linear_system),
                      strict=True):
        got[fi[fi >= 0]] = step[si[si >= 0]]
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-12 * np.abs(ref).max())


def class_rows(ix, voff: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Scalar rows of W class ``k``'s U store and V class in the ``[U; V]`` order."""
    w = ix.wclasses[k]
    return (np.arange(w.ucols.start, w.ucols.stop),
            np.arange(voff[w.vclass], voff[w.vclass + 1]))


def test_each_strategy_subtracts_its_own_share() -> None:
    """``reduce_into`` of one W class subtracts ``W_k V⁻¹ W_kᵀ`` and ``W_k V⁻¹ b_v`` of that
    class only; the coupling of two classes subtracts their cross terms (no rhs)."""
    full = multi_toy(False)
    full.initialize_optimization()
    for strategy in STRATEGIES:
        schur = multi_toy(True, SchurConfig(strategy))
        schur.initialize_optimization()
        H, b = full_in_schur_order(full, schur)
        ix, red = schur.linear_system.index, schur.linear_system.reduction
        n = ix.n
        voff = np.cumsum([n] + [len(c.slots) * c.dim for c in ix.vclasses])
        asm, _ = schur.problem.linearize()
        factors = VFactors(ix, asm, [None] * len(ix.vclasses))

        for k, t in enumerate(red.strategies):
            assert t.name == strategy and t.k == k
            s, rhs = np.zeros(ix.pattern.nnz), np.zeros(n)
            t.reduce_into(s, rhs, asm, factors)
            u, v = class_rows(ix, voff, k)
            y = H[np.ix_(u, v)] @ np.linalg.inv(H[np.ix_(v, v)])
            share = np.zeros((n, n))
            share[np.ix_(u, u)] = y @ H[np.ix_(v, u)]
            share_b = np.zeros(n)
            share_b[u] = y @ b[v]
            np.testing.assert_allclose(-with_data(ix.pattern.csc, s).toarray(), share,
                                       rtol=1e-10, atol=1e-12 * np.abs(share).max())
            np.testing.assert_allclose(-rhs, share_b, rtol=1e-10,
                                       atol=1e-12 * np.abs(share_b).max())
        (c,) = red.couplings
        s, rhs = np.zeros(ix.pattern.nnz), np.zeros(n)
        c.reduce_into(s, rhs, asm, factors)
        (u1, v), (u2, _) = class_rows(ix, voff, c.k), class_rows(ix, voff, c.k2)
        cross = H[np.ix_(u1, v)] @ np.linalg.inv(H[np.ix_(v, v)]) @ H[np.ix_(v, u2)]
        ref = np.zeros((n, n))
        ref[np.ix_(u1, u2)], ref[np.ix_(u2, u1)] = cross, cross.T
        np.testing.assert_allclose(-with_data(ix.pattern.csc, s).toarray(), ref, rtol=1e-10,
                                   atol=1e-12 * np.abs(ref).max())
        assert not rhs.any() and np.abs(cross).max() > 1e-3


def test_strategies_agree_with_each_other_on_the_ba_toy() -> None:
    out = {}
    for strategy in STRATEGIES:
        opt = ba_toy(True, per_point=4, schur=SchurConfig(strategy))
        opt.initialize_optimization()
        asm, _ = opt.problem.linearize()
        out[strategy] = opt.linear_system.reduce(asm, 1e-2)[:2]
    for strategy in ("dense", "gram"):
        for got, ref in zip(out[strategy], out["sparse"], strict=True):
            np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-11 * np.abs(ref).max())


@pytest.mark.parametrize("cost, expected", [
    (SchurCostModel(dense_limit=0, gram_enabled=False), "sparse"),
    (SchurCostModel(sparse_mac=1e-3, gram_enabled=False), "dense"),
    (SchurCostModel(sparse_mac=1e-3, dense_limit=0), "gram"),
    (SchurCostModel(sparse_mac=0.0), "sparse"),  # nothing beats a free sparse product
])
def test_auto_follows_the_cost_model(cost: SchurCostModel, expected: str) -> None:
    opt = multi_toy(True, SchurConfig("auto", cost))
    opt.initialize_optimization()
    assert [t.name for t in opt.linear_system.reduction.strategies] == [expected] * 3


def test_auto_picks_the_cheapest_plan() -> None:
    """Every class gets the strategy of least modelled cost: with the default model (sparse on
    toys this small) and with dearer sparse products (dense panels, and Gram products once
    every point is in every camera)."""
    chosen = []
    for cost in (SchurCostModel(), SchurCostModel(sparse_mac=2e-8)):
        for per_point in (2, 4, 6):
            opt = ba_toy(True, per_point=per_point, schur=SchurConfig(cost=cost))
            opt.initialize_optimization()
            ix = opt.linear_system.index
            pairs = ix.w_pairs(0, 0)
            plans = {"sparse": SparsePlan.plan(ix, 0, pairs, cost),
                     "dense": DensePlan.plan(ix, 0, cost),
                     "gram": GramPlan.plan(ix, 0, pairs, cost)}
            seconds = {name: p.seconds for name, p in plans.items() if p is not None}
            assert len(seconds) == 3 and len(set(seconds.values())) == 3
            chosen.append(opt.linear_system.reduction.strategies[0].name)
            assert chosen[-1] == min(seconds, key=seconds.get)
    assert chosen == ["sparse"] * 3 + ["dense", "dense", "gram"]


def test_gram_is_not_considered_when_disabled() -> None:
    cost = SchurCostModel(sparse_mac=1e-3, blas_mac=1.0, gram_enabled=False)
    opt = ba_toy(True, schur=SchurConfig(cost=cost))
    opt.initialize_optimization()
    assert opt.linear_system.reduction.strategies[0].name == "sparse"
    assert opt.linear_system.assembler.u_gram_terms == 0
    opt = ba_toy(True, schur=SchurConfig(cost=SchurCostModel(sparse_mac=1e-3, blas_mac=1.0)))
    opt.initialize_optimization()
    assert opt.linear_system.reduction.strategies[0].name == "gram"
    assert opt.linear_system.assembler.u_gram_terms == 1


def test_forced_dense_over_its_limit_is_an_error() -> None:
    opt = ba_toy(True, schur=SchurConfig("dense", SchurCostModel(dense_limit=10)))
    with pytest.raises(ValueError, match="over SchurCostModel.dense_limit"):
        opt.initialize_optimization()
    # Auto falls back to another strategy instead.
    opt = ba_toy(True, schur=SchurConfig("auto", SchurCostModel(dense_limit=10)))
    opt.initialize_optimization()
    assert opt.linear_system.reduction.strategies[0].name != "dense"


def test_optimizer_hands_its_config_to_the_linear_system() -> None:
    cfg = SchurConfig("gram")
    opt = ba_toy(True, schur=cfg)
    assert opt.linear_system is None
    opt.initialize_optimization()
    assert opt.linear_system.config is cfg
    assert ba_toy(True).optimize(3).final_chi2 == pytest.approx(opt.optimize(3).final_chi2,
                                                                rel=1e-9)


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="unknown Schur strategy 'fast'; choose one of auto, "
                                         "sparse, dense, gram"):
        SchurConfig("fast")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="must be a SchurCostModel"):
        SchurConfig(cost={"sparse_mac": 1.0})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="gather must be a finite number >= 0"):
        SchurCostModel(gather=-1e-9)
    with pytest.raises(ValueError, match="blas_mac must be a finite number"):
        SchurCostModel(blas_mac=float("nan"))
    with pytest.raises(ValueError, match="panel_rows must be >= 1"):
        SchurCostModel(panel_rows=0)
    with pytest.raises(TypeError, match="gram_enabled must be a bool"):
        SchurCostModel(gram_enabled=1)  # type: ignore[arg-type]
    assert SchurConfig().strategy == "auto" and SchurConfig().cost == SchurCostModel()
    assert SchurCostModel().dense_limit == 64_000_000  # the fitted defaults
