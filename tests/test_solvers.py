"""The linear solvers against each other (graphopt.solvers)."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import SOLVERS, build_pose_graph, step_in_graph_order

from graphopt.solvers import CHOLMOD_AVAILABLE


@pytest.mark.parametrize("solver", SOLVERS)
def test_solvers_give_the_same_step(solver: str) -> None:
    steps = {}
    for name in ("dense", solver):
        opt, _, _ = build_pose_graph("lm", name)
        opt.initialize_optimization()
        asm, _ = opt.problem.linearize()
        steps[name] = step_in_graph_order(opt.problem, opt.problem.solve(asm, 1e-2)[0])
    np.testing.assert_allclose(steps[solver], steps["dense"], rtol=1e-7, atol=1e-9)
    assert np.abs(steps["dense"]).max() > 1e-3  # a real step, not zeros


def test_cholmod_fallback_warns_once(monkeypatch) -> None:
    import graphopt.solvers as solvers

    monkeypatch.setattr(solvers, "CHOLMOD_AVAILABLE", False)
    monkeypatch.setattr(solvers, "_warned", False)
    with pytest.warns(RuntimeWarning, match="CHOLMOD .* not available.*'scipy'"):
        first = solvers.make_solver("cholmod")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = solvers.make_solver("cholmod")  # no second warning
    assert first.name == second.name == "scipy"
    opt, _, _ = build_pose_graph("lm", "cholmod")
    assert opt.optimize(10).final_chi2 < 120


def test_pcg_tolerance_and_iteration_cap() -> None:
    from graphopt import LinearSolverPCG, PCGConfig

    opt, _, _ = build_pose_graph("lm", "dense")
    opt.initialize_optimization()
    asm, _ = opt.problem.linearize()
    ref = opt.problem.solve(asm, 1e-2)[0]
    system = opt.linear_system
    s, rhs, _ = system.reduce(asm, 1e-2)
    for cfg, close in ((PCGConfig(tolerance=1e-12), True), (PCGConfig(max_iterations=2), False)):
        pcg = LinearSolverPCG(cfg)
        pcg.analyze(system.pattern, system.udims)
        x = pcg.solve(s, rhs)
        assert np.allclose(x, ref, rtol=1e-7, atol=1e-9) == close
        if not close:
            assert pcg.last_iterations == 2


def test_auto_solver_chooses_by_size_and_fill() -> None:
    from graphopt.solvers import LinearSolverAuto

    opt, _, _ = build_pose_graph("lm", LinearSolverAuto())
    opt.initialize_optimization()
    assert opt.solver.chosen.name == "dense"  # 117 unknowns
    opt2, _, _ = build_pose_graph("lm", LinearSolverAuto(dense_max_size=50))
    opt2.initialize_optimization()
    assert opt2.solver.chosen.name in ("cholmod", "scipy")
    # The choice is made before the pattern (block_order): only CHOLMOD renumbers the blocks.
    for o, renumbered in ((opt, False), (opt2, opt2.solver.chosen.name == "cholmod")):
        ub = o.problem.system.index.ublock[0]
        assert (not np.array_equal(ub[ub >= 0], np.arange(int((ub >= 0).sum())))) == renumbered
    assert opt.optimize(20).final_chi2 == pytest.approx(opt2.optimize(20).final_chi2, rel=1e-9)


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_names_the_blas_it_runs_on() -> None:
    from graphopt.solvers import cholmod_blas

    path = cholmod_blas()  # e.g. /usr/lib/x86_64-linux-gnu/openblas-pthread/libblas.so.3
    assert "blas" in path.lower() and ".so" in path, path


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_modes_and_orderings_give_the_same_step() -> None:
    from graphopt.solvers import LinearSolverCholmod

    steps = []
    for mode, ordering in (("auto", "auto"), ("auto", "default"), ("simplicial", "amd"),
                           ("supernodal", "nesdis")):
        opt, _, _ = build_pose_graph("lm", LinearSolverCholmod(mode, ordering))
        opt.initialize_optimization()
        asm, _ = opt.problem.linearize()
        steps.append(step_in_graph_order(opt.problem, opt.problem.solve(asm, 1e-2)[0]))
    for s in steps[1:]:
        np.testing.assert_allclose(s, steps[0], rtol=1e-9, atol=1e-12)
    assert np.abs(steps[0]).max() > 1e-3
    with pytest.raises(ValueError, match="unknown CHOLMOD mode"):
        LinearSolverCholmod("fast")


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_refuses_values_that_do_not_fit_the_pattern() -> None:
    import scipy.sparse as sp

    from graphopt.solvers import LinearSolverCholmod

    a = sp.csc_matrix(np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]]))
    solver = LinearSolverCholmod()
    solver.analyze(a, np.array([1, 1, 1]))
    rhs = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(solver.solve(a.data, rhs), np.linalg.solve(a.toarray(), rhs),
                               rtol=1e-12)
    with pytest.raises(ValueError, match="6 values for a pattern of 7"):
        solver.solve(a.data[:-1], rhs)


def _block_spd(sizes: list[int], density: float, seed: int):
    """A random SPD matrix made of dense blocks of ``sizes`` (symmetric block pattern)."""
    import scipy.sparse as sp

    rng = np.random.default_rng(seed)
    nb, off = len(sizes), np.concatenate([[0], np.cumsum(sizes)])
    mask = np.triu(rng.random((nb, nb)) < density, 1)
    mask = mask | mask.T | np.eye(nb, dtype=bool)
    j = rng.standard_normal((int(off[-1]) * 2, int(off[-1])))
    a = j.T @ j  # dense SPD; keep the chosen blocks, then make it diagonally dominant
    keep = np.repeat(np.repeat(mask, sizes, axis=0), sizes, axis=1)
    a = np.where(keep, a, 0.0)
    a += np.diag(np.abs(a).sum(axis=1))
    return sp.csc_matrix(a), np.array(sizes)


def _analyze_in_block_order(solver, a, sizes: np.ndarray):
    """Ask ``solver`` for its block order of ``a``, build the permuted matrix as the optimizer
    would and analyse it; return ``(keys, perm, permuted matrix)``."""
    import scipy.sparse as sp

    nb, off = len(sizes), np.concatenate([[0], np.cumsum(sizes)])
    coo = sp.coo_matrix(a)
    blk = np.repeat(np.arange(nb), sizes)
    keys = np.unique(blk[coo.col] * nb + blk[coo.row])
    order = solver.block_order(keys, sizes)
    assert order is not None and sorted(order) == list(range(nb))
    perm = np.concatenate([np.arange(off[b], off[b + 1]) for b in order])
    pa = sp.csc_matrix(a[perm][:, perm])
    pa.sort_indices()
    solver.analyze(pa, sizes[order])
    np.testing.assert_array_equal(solver._order, np.arange(a.shape[0]))  # natural: as given
    return keys, perm, pa


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_cholmod_block_order_solves_like_dense() -> None:
    """Small blocks (2-D poses and points): CHOLMOD orders the blocks, the pattern is built in
    that order and factorised as it comes; solutions (one and two columns) match LAPACK's."""
    from graphopt.solvers import LinearSolverCholmod

    a, sizes = _block_spd([3, 2, 3, 3, 2, 3, 1, 3] * 5, 0.15, 4)
    solver = LinearSolverCholmod()
    keys, perm, pa = _analyze_in_block_order(solver, a, sizes)
    rng = np.random.default_rng(5)
    for rhs in (rng.standard_normal(a.shape[0]), rng.standard_normal((a.shape[0], 2))):
        np.testing.assert_allclose(solver.solve(pa.data, rhs[perm]),
                                   np.linalg.solve(a.toarray(), rhs)[perm], rtol=1e-10,
                                   atol=1e-12)
    # Without the question, or with an ordering named, CHOLMOD orders the scalar unknowns.
    scalar = LinearSolverCholmod()
    scalar.analyze(a, sizes)
    assert not np.array_equal(scalar._order, np.arange(a.shape[0]))
    assert LinearSolverCholmod(ordering="amd").block_order(keys, sizes) is None


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
@pytest.mark.parametrize("mode", ["auto", "supernodal", "simplicial"])
def test_cholmod_block_order_of_large_blocks(mode: str) -> None:
    """6x6 blocks (3-D poses): NESDIS on the block graph, then the pattern as given."""
    from graphopt.solvers import LinearSolverCholmod

    a, sizes = _block_spd([6] * 30, 0.2, 8)
    solver = LinearSolverCholmod(mode)
    _, perm, pa = _analyze_in_block_order(solver, a, sizes)
    rhs = np.random.default_rng(9).standard_normal(a.shape[0])
    np.testing.assert_allclose(solver.solve(pa.data, rhs[perm]),
                               np.linalg.solve(a.toarray(), rhs)[perm], rtol=1e-10, atol=1e-12)


def test_pose_graph_is_numbered_in_the_solvers_block_order() -> None:
    """The optimizer builds the pattern in the order CHOLMOD asks for, and the run is the same
    as with the graph's order (dense solver)."""
    if not CHOLMOD_AVAILABLE:
        pytest.skip("CHOLMOD (scikit-sparse) is not installed")
    histories = []
    for solver in ("cholmod", "dense"):
        opt, _, _ = build_pose_graph("lm", solver, n=60)
        opt.initialize_optimization()
        ub = opt.problem.system.index.ublock[0]
        renumbered = not np.array_equal(ub[ub >= 0], np.arange(len(ub[ub >= 0])))
        assert renumbered == (solver == "cholmod")
        histories.append(opt.optimize(8).chi2_history)
    np.testing.assert_allclose(histories[0], histories[1], rtol=1e-9)


def _reversed_dense(broken: bool = False):
    """A dense solver that asks for the U blocks in reverse order (or for a broken order)."""
    from graphopt.solvers import LinearSolverDense

    class Reversed(LinearSolverDense):
        def block_order(self, keys: np.ndarray, block_sizes: np.ndarray) -> np.ndarray:
            order = np.arange(len(block_sizes))[::-1].copy()
            if broken:
                order[0] = order[1]
            return order

    return Reversed()


def _poses_and_points(solver) -> object:
    """12 SE2 poses on a chain and 4 XY points each seen from 3 poses (two U stores)."""
    from graphopt import SparseOptimizer
    from graphopt.types import EdgeSE2, EdgeSE2PointXY, VertexPointXY, VertexSE2

    rng = np.random.default_rng(3)
    opt = SparseOptimizer("lm", solver)
    poses = np.column_stack([np.arange(12.0), rng.normal(0, 0.1, 12), rng.normal(0, 0.1, 12)])
    opt.add_vertices(VertexSE2, np.arange(12), poses, fixed=np.arange(12) == 0)
    opt.add_vertices(VertexPointXY, 100 + np.arange(4), rng.normal(0, 2, (4, 2)) + [5, 3])
    z = np.tile([1.0, 0.0, 0.0], (11, 1)) + rng.normal(0, 0.05, (11, 3))
    opt.add_edges(EdgeSE2, np.column_stack([np.arange(11), np.arange(1, 12)]), z,
                  np.diag([100.0, 100.0, 400.0]))
    pairs = np.array([[p, 100 + k] for k in range(4) for p in (k, k + 4, k + 8)])
    opt.add_edges(EdgeSE2PointXY, pairs, rng.normal(0, 2, (len(pairs), 2)), np.eye(2) * 25.0)
    return opt


def test_u_blocks_renumbered_in_a_solvers_order_give_the_same_run() -> None:
    """Two stores (poses and points) numbered in reverse by the solver's wish: same chi2 at
    every iteration as in the graph's order; an order that is not a permutation is refused."""
    from graphopt.solvers import LinearSolverDense

    plain = _poses_and_points(LinearSolverDense())
    rev = _poses_and_points(_reversed_dense())
    rev.initialize_optimization()
    index = rev.problem.system.index
    assert index.ublock[1][-1] == 0 and index.ustore[0] == 1  # the last point is block 0
    np.testing.assert_allclose(rev.optimize(6).chi2_history, plain.optimize(6).chi2_history,
                               rtol=1e-10)
    from graphopt.types import VertexPointXY, VertexSE2

    for vtype in (VertexSE2, VertexPointXY):
        np.testing.assert_allclose(rev.estimates_of(vtype), plain.estimates_of(vtype),
                                   rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="permutation of 15 blocks"):
        _poses_and_points(_reversed_dense(broken=True)).initialize_optimization()


@pytest.mark.skipif(not CHOLMOD_AVAILABLE, reason="CHOLMOD (scikit-sparse) is not installed")
def test_a_wrong_diagonal_hint_is_not_trusted() -> None:
    """``pattern.diag_pos`` (set by graphopt's patterns) is checked before it is used."""
    from graphopt.solvers import LinearSolverCholmod, LinearSolverDense

    a, sizes = _block_spd([3, 2, 3] * 4, 0.3, 11)
    a.sort_indices()
    cols = np.repeat(np.arange(a.shape[0]), np.diff(a.indptr))
    true_diag = np.flatnonzero(a.indices == cols)
    rhs = np.arange(1.0, a.shape[0] + 1)
    want = np.linalg.solve(a.toarray(), rhs)
    for hint in (true_diag, true_diag + 1, np.zeros(3, dtype=np.int64)):
        a.diag_pos = hint
        for solver in (LinearSolverCholmod(ordering="default"), LinearSolverDense()):
            solver.analyze(a, sizes)
            np.testing.assert_array_equal(solver.diag_pos, true_diag)
            np.testing.assert_allclose(solver.solve(a.data, rhs), want, rtol=1e-10)
