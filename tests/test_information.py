"""Information matrices: per-edge matrices that are all the same are stored once, a diagonal
shared matrix weights the Jacobians by a row scaling, and every form assembles the same
``H = Σ JᵀΩJ`` and ``b = −Σ JᵀΩe`` as a dense sum computed here edge by edge."""

from __future__ import annotations

import numpy as np
import pytest

from graphopt import SparseOptimizer
from graphopt.edge import EdgeContext
from graphopt.linear.pattern import with_data
from graphopt.types import EdgeSE2, VertexSE2

N = 6  # poses on a loop, the first fixed
LOOP = np.array([[i, (i + 1) % N] for i in range(N)] + [[0, 3], [1, 4]])


def _poses(rng: np.random.Generator) -> np.ndarray:
    xy = rng.normal(scale=2.0, size=(N, 2))
    return np.column_stack([xy, rng.uniform(-np.pi, np.pi, N)])


def _build(info: np.ndarray | None) -> tuple[SparseOptimizer, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    x = _poses(rng)
    z = rng.normal(scale=0.5, size=(len(LOOP), 3))
    opt = SparseOptimizer(solver="dense")
    for i in range(N):
        opt.add_vertex(VertexSE2(i, x[i], fixed=i == 0))
    opt.add_edges(EdgeSE2, LOOP, z, information=info)
    opt.initialize_optimization()
    return opt, x, z


def _dense(x: np.ndarray, z: np.ndarray, infos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``H`` and ``b`` over the free poses 1..N-1, summed edge by edge."""
    lin = EdgeSE2.linearize((x[LOOP[:, 0]], x[LOOP[:, 1]]), z, EdgeContext({}, {}))
    H, b = np.zeros((3 * N, 3 * N)), np.zeros(3 * N)
    for k, (i, j) in enumerate(LOOP):
        J = np.zeros((3, 3 * N))
        J[:, 3 * i:3 * i + 3] = lin.jacobians[0][k]
        J[:, 3 * j:3 * j + 3] = lin.jacobians[1][k]
        H += J.T @ infos[k] @ J
        b -= J.T @ infos[k] @ lin.error[k]
    return H[3:, 3:], b[3:]


def _assembled(opt: SparseOptimizer) -> tuple[np.ndarray, np.ndarray]:
    assert opt.problem is not None and opt.linear_system is not None
    asm, _ = opt.problem.linearize()
    return with_data(opt.linear_system.pattern, asm.h_data).toarray(), asm.bu


DIAG = np.diag([100.0, 500.0, 500.0])
FULL = np.array([[40.0, 3.0, -2.0], [3.0, 25.0, 1.5], [-2.0, 1.5, 60.0]])


@pytest.mark.parametrize(("given", "stored_ndim", "diagonal"), [
    ("per-edge diagonal, all equal", 2, True),
    ("per-edge full, all equal", 2, False),
    ("per-edge, one differs", 3, False),
    ("shared full", 2, False),
])
def test_information_forms_assemble_the_dense_sum(given: str, stored_ndim: int,
                                                  diagonal: bool) -> None:
    m = len(LOOP)
    infos = np.broadcast_to(DIAG if "diagonal" in given else FULL, (m, 3, 3)).copy()
    if "differs" in given:
        infos[3] = 2.0 * FULL
    arg = infos[0] if given.startswith("shared") else infos
    opt, x, z = _build(arg)
    g = opt.edge_groups()[0]
    assert g.information is not None and g.information.ndim == stored_ndim
    assert (g.info_diagonal is not None) == diagonal
    if diagonal:
        np.testing.assert_array_equal(g.info_diagonal, np.diag(DIAG))
    H_ref, b_ref = _dense(x, z, infos)
    H, b = _assembled(opt)
    scale = np.abs(H_ref).max()
    np.testing.assert_allclose(H, H_ref, rtol=1e-12, atol=1e-13 * scale)
    np.testing.assert_allclose(b, b_ref, rtol=1e-12, atol=1e-13 * np.abs(b_ref).max())
    # chi2 = Σ e'Ωe with each edge's own matrix.
    e = EdgeSE2.error((x[LOOP[:, 0]], x[LOOP[:, 1]]), z, EdgeContext({}, {}))
    chi2 = float(np.einsum("mi,mij,mj->", e, infos, e))
    assert opt.chi2() == pytest.approx(chi2, rel=1e-13)


def test_edge_reads_back_its_information_after_the_collapse() -> None:
    infos = np.broadcast_to(DIAG, (len(LOOP), 3, 3)).copy()
    opt, _, _ = _build(infos)
    g = opt.edge_groups()[0]
    for i in (0, len(LOOP) - 1):
        got = g.information_of(i)
        np.testing.assert_array_equal(got, DIAG)
        got[0, 0] = -1.0  # a copy: the shared matrix is not changed through it
    np.testing.assert_array_equal(g.information, DIAG)


def test_diagonal_information_checks_as_the_eigenvalues_would() -> None:
    """Per-edge diagonal matrices (σ⁻²·I) skip the eigenvalue test: the same answers —
    accepted as given, collapsed when all equal, the first indefinite one named."""
    from graphopt.object_batch import BatchError, checked_information

    vids = np.stack([np.arange(5), np.arange(5) + 1], axis=1)
    info = np.array([1.0, 2.0, 3.0, 4.0, 5.0])[:, None, None] * np.eye(3)
    assert checked_information(EdgeSE2, vids, info) is info
    same = np.repeat(2.0 * np.eye(3)[None], 5, axis=0)
    np.testing.assert_array_equal(checked_information(EdgeSE2, vids, same), 2.0 * np.eye(3))
    bad = info.copy()
    bad[3, 2, 2] = -0.5
    with pytest.raises(BatchError, match=r"vertices \[3, 4\]: .*not positive semi-definite") as e:
        checked_information(EdgeSE2, vids, bad)
    assert e.value.culprit == 3
    bad[3, 2, 2] = -1e-12  # within the eigenvalue test's tolerance
    assert checked_information(EdgeSE2, vids, bad) is bad


@pytest.mark.parametrize("compiled_loop", [False, True])
def test_per_edge_diagonal_information_scales_rows_with_the_products_values(
        compiled_loop: bool) -> None:
    """Per-edge diagonal information (σ⁻²·I) weighs by a row scaling; the run is that of the
    general products to the bit (an off-diagonal 1e-300 forces those: it adds less than half
    an ulp to every product). The compiled loop (graphopt.compiled), which sums edge by edge,
    gives the same run to rounding."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import slam_backend_scenes as scenes

    from graphopt import RobustKernelHuber, compiled
    from graphopt.types import EdgeStereoSE3ProjectXYZOnlyPose, VertexSE3Expmap

    s = scenes.motion_only(60, True)
    runs = []
    for off in (0.0, 1e-300):
        info = s.inv_sigma2[:, None, None] * np.eye(3) + off * (1.0 - np.eye(3))
        opt = SparseOptimizer(algorithm="lm", solver="dense")
        opt.add_vertices(VertexSE3Expmap, [0], s.T_init[None])
        es = opt.add_edges(EdgeStereoSE3ProjectXYZOnlyPose, np.zeros((60, 1), dtype=int), s.z,
                           information=info, robust_kernel=RobustKernelHuber(2.8),
                           params=scenes.STEREO, data={"Xw": s.Xw})
        g = opt.edge_groups()[0]
        g.finalize()
        assert (g.info_diagonal is not None) == (off == 0.0)
        compiled.set_enabled(compiled_loop)
        try:
            res = opt.optimize(6)
        finally:
            compiled.set_enabled(True)
        # Only the diagonal information's run can take the loop.
        loop = opt.problem._compiled[0][2] is not None  # type: ignore[union-attr]
        assert loop == (compiled_loop and off == 0.0 and compiled.available())
        runs.append(([i.chi2 for i in res.info], es.chi2(), opt.vertex(0).estimate))
    assert len(runs[0][0]) >= 2
    if compiled_loop:
        np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=1e-12)
        np.testing.assert_allclose(runs[0][1], runs[1][1], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(runs[0][2], runs[1][2], rtol=0, atol=1e-12)
        return
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    np.testing.assert_array_equal(runs[0][2], runs[1][2])


def test_row_dots_are_einsums_bits() -> None:
    """The two-column fast form of ``e'Ωe`` gives einsum's bits (so chi2 and every iteration
    are unchanged); other widths are einsum itself."""
    from graphopt.row_weights import row_dots

    rng = np.random.default_rng(3)
    for r in (1, 2, 3, 6):
        a = rng.normal(size=(1000, r)) * rng.uniform(1e-3, 1e3, (1000, 1))
        b = a * rng.uniform(0.1, 10.0, (1000, r))
        np.testing.assert_array_equal(row_dots(a, b), np.einsum("me,me->m", a, b))
