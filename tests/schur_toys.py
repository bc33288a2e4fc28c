"""Small bundle-adjustment-like problems for the linear-system tests, and dense references.

``ba_toy``: cameras and landmarks, one W class. ``multi_toy``: cameras and intrinsics (U)
seeing landmarks, cameras seeing lines (two V classes), and a chain prior between cameras;
three W classes, two of which share the landmarks (coupled) and two the cameras' rows of S.
"""

from __future__ import annotations

import numpy as np

from graphopt import BaseEdge, RobustKernelHuber, SparseOptimizer, VertexVector
from graphopt.linear import LinearSystem, SchurConfig
from graphopt.linear.pattern import with_data


class VertexCam(VertexVector):
    dimension = 4


class VertexLandmark(VertexVector):
    dimension = 3


class VertexIntrinsics(VertexVector):
    dimension = 2


class VertexLine(VertexVector):
    dimension = 2


def observe(c: np.ndarray, p: np.ndarray, gain: np.ndarray | float = 1.0) -> np.ndarray:
    """A smooth nonlinear 'projection' of landmarks ``p`` by cameras ``c``."""
    return p[:, :2] * c[:, :2] * gain + np.sin(p[:, 2:3] * c[:, 2:4]) + c[:, :2] * c[:, 2:4]


class EdgeObs(BaseEdge):
    """A camera observing a landmark (numeric Jacobians)."""

    dimension = 2
    vertex_types = (VertexCam, VertexLandmark)

    @classmethod
    def error(cls, x, z, ctx):
        return observe(*x) - z


class EdgeObsIntrinsics(EdgeObs):
    """A camera with its intrinsics (a gain) observing a landmark."""

    vertex_types = (VertexCam, VertexIntrinsics, VertexLandmark)

    @classmethod
    def error(cls, x, z, ctx):
        c, k, p = x
        return observe(c, p, 1 + k) - z


class EdgeLine(BaseEdge):
    """A line (marginalised position first) seen by a camera."""

    dimension = 2
    vertex_types = (VertexLine, VertexCam)

    @classmethod
    def error(cls, x, z, ctx):
        line, c = x
        return np.cos(line * c[:, :2]) + line * c[:, 2:4] - z


class EdgeDifference(BaseEdge):
    """``x₁ − x₀ − z`` between two vertices of one vector type (subclasses name the type)."""

    @classmethod
    def error(cls, x, z, ctx):
        return x[1] - x[0] - z


class EdgeCamChain(EdgeDifference):
    """A prior between consecutive cameras (U-U blocks off the diagonal)."""

    dimension = 4
    vertex_types = (VertexCam, VertexCam)


def ba_toy(marginalize: bool, solver: str = "dense", seed: int = 1, per_point: int = 3,
           schur: SchurConfig | None = None) -> SparseOptimizer:
    """6 cameras (the first fixed) and 40 landmarks, each seen by ``per_point`` cameras."""
    rng = np.random.default_rng(seed)
    nc, npt = 6, 40
    obs = np.array([(i, j) for j in range(npt)
                    for i in rng.choice(nc, per_point, replace=False)])
    C = rng.normal(size=(nc, 4))
    P = rng.normal(size=(npt, 3))
    Z = observe(C[obs[:, 0]], P[obs[:, 1]])
    Z += rng.normal(0, 0.01, Z.shape)
    info = np.array([[2.0, 0.3], [0.3, 1.0]])
    opt = SparseOptimizer("lm", solver, schur=schur)
    opt.add_vertices(VertexCam, np.arange(nc), C + 0.05, fixed=np.arange(nc) == 0)
    opt.add_vertices(VertexLandmark, 100 + np.arange(npt), P + 0.05, marginalized=marginalize)
    opt.add_edges(EdgeObs, np.stack([obs[:, 0], 100 + obs[:, 1]], 1), Z, information=info)
    return opt


def multi_toy(marginalize: bool, schur: SchurConfig | None = None, seed: int = 3,
              kernel: bool = True) -> SparseOptimizer:
    """7 cameras (the first fixed), 3 intrinsics, 60 landmarks, 25 lines; Huber on the
    landmark observations (``kernel``), so that ρ'ΩJ is not J."""
    rng = np.random.default_rng(seed)
    nc, nk, npt, nl = 7, 3, 60, 25
    opt = SparseOptimizer("lm", "dense", schur=schur)
    opt.add_vertices(VertexCam, np.arange(nc), rng.normal(size=(nc, 4)),
                     fixed=np.arange(nc) == 0)
    opt.add_vertices(VertexIntrinsics, 100 + np.arange(nk), 0.1 * rng.normal(size=(nk, 2)))
    opt.add_vertices(VertexLandmark, 1000 + np.arange(npt), rng.normal(size=(npt, 3)),
                     marginalized=marginalize)
    opt.add_vertices(VertexLine, 5000 + np.arange(nl), rng.normal(size=(nl, 2)),
                     marginalized=marginalize)
    obs = np.array([(i, i % nk, j) for j in range(npt) for i in rng.choice(nc, 3, replace=False)])
    opt.add_edges(EdgeObsIntrinsics, np.stack([obs[:, 0], 100 + obs[:, 1], 1000 + obs[:, 2]], 1),
                  rng.normal(size=(len(obs), 2)), information=np.array([[2.0, 0.3], [0.3, 1.0]]),
                  robust_kernel=RobustKernelHuber(0.5) if kernel else None)
    lines = np.array([(j, i) for j in range(nl) for i in rng.choice(nc, 4, replace=False)])
    opt.add_edges(EdgeLine, np.stack([5000 + lines[:, 0], lines[:, 1]], 1),
                  rng.normal(size=(len(lines), 2)))
    opt.add_edges(EdgeCamChain, np.stack([np.arange(nc - 1), np.arange(1, nc)], 1),
                  0.1 * rng.normal(size=(nc - 1, 4)))
    return opt


def scalar_index(system: LinearSystem) -> list[np.ndarray]:
    """Per store, ``(n_store, d)`` scalar index of every slot's entries in the order
    ``[U part; V classes one after the other]`` (−1 for fixed vertices)."""
    ix = system.index
    voff = np.cumsum([ix.n] + [len(c.slots) * c.dim for c in ix.vclasses])
    out = []
    for si, st in enumerate(ix.stores):
        d = st.vtype.dimension
        idx = np.full((len(st), d), -1, dtype=np.int64)
        ub, vb = ix.ublock[si], ix.vblock[si]
        idx[ub >= 0] = ix.uoffset[ub[ub >= 0]][:, None] + np.arange(d)
        vc = ix.vclass_of_store[si]
        if vc >= 0:
            idx[vb >= 0] = voff[vc] + vb[vb >= 0][:, None] * d + np.arange(d)
        out.append(idx)
    return out


def full_in_schur_order(full: SparseOptimizer, schur: SparseOptimizer
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The full system's dense Hessian and gradient, both linearised now, permuted into the
    Schur system's ``[U; V]`` order."""
    fs, ss = full.linear_system, schur.linear_system
    assert fs is not None and ss is not None and not fs.schur
    asm, _ = full.problem.linearize()
    H = with_data(fs.pattern, asm.h_data)
    perm = np.empty(fs.n, dtype=np.int64)
    for fi, si in zip(scalar_index(fs), scalar_index(ss), strict=True):
        perm[si[si >= 0]] = fi[fi >= 0]
    return H.toarray()[np.ix_(perm, perm)], asm.bu[perm]
