"""Building the direct-BA optimisation problem: poses, points (world or inverse depth) and one
photometric patch edge per (point, image) pair.

:func:`build_problem` returns a :class:`DirectBAProblem`: the optimizer and how to read the
estimates back. Conventions: poses are ``T_cw`` with the update ``T ← exp(δ)·T``; the first
pose is fixed (it fixes the gauge; monocular scale remains a free direction that LM's damping
holds); points are marginalised (Schur complement).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from graphopt import SparseOptimizer, make_kernel
from graphopt.edge import EdgeContext
from graphopt.io.directba import DirectBAData
from graphopt.lie import transform_inverse
from graphopt.types.photometric import PhotometricParams, numeric_variant, photometric_edge_types
from graphopt.types.vertices import VertexPointInverseDepth, VertexPointXYZ, VertexSE3Expmap

__all__ = [
    "PARAMETRIZATIONS",
    "DirectBAProblem",
    "build_problem",
    "choose_anchors",
    "inverse_depth_to_world",
]

#: Point parametrisations of :func:`build_problem`.
PARAMETRIZATIONS = ("xyz", "inverse-depth")


@dataclass
class DirectBAProblem:
    """A built optimisation problem and how to read the result back.

    Args:
        optimizer: The :class:`graphopt.SparseOptimizer` with vertices and edges.
        data: The input problem.
        parametrization: ``"xyz"`` or ``"inverse-depth"``.
        params: The shared :class:`PhotometricParams`.
        point_index: Index into ``data.points`` of every point vertex (in add order).
        anchors: Anchor image of every point vertex (inverse depth), else ``None``.
        n_edges: Number of edges.
        dropped_points: Points left out (inverse depth: behind every camera).
        extra: Free-form notes.
    """

    optimizer: Any
    data: DirectBAData
    parametrization: str
    params: PhotometricParams
    point_index: np.ndarray
    anchors: np.ndarray | None
    n_edges: int
    dropped_points: int = 0
    extra: dict = field(default_factory=dict)

    def poses(self) -> np.ndarray:
        """Current ``(n, 4, 4)`` poses ``T_cw``."""
        return self.optimizer.estimates_of(VertexSE3Expmap)

    def points(self) -> np.ndarray:
        """Current world points ``(N', 3)`` (in ``point_index`` order)."""
        if self.parametrization == "xyz":
            return self.optimizer.estimates_of(VertexPointXYZ)
        assert self.anchors is not None
        q = self.optimizer.estimates_of(VertexPointInverseDepth)
        return inverse_depth_to_world(q, self.poses()[self.anchors])


def inverse_depth_to_world(q: np.ndarray, T_anchor: np.ndarray) -> np.ndarray:
    """World points from ``[a, b, ρ]`` and their anchor poses.

    Args:
        q: ``(N, 3)`` inverse-depth points.
        T_anchor: ``(N, 4, 4)`` anchor ``T_cw``.
    """
    pa = np.c_[q[:, :2], np.ones(len(q))] / q[:, 2:3]
    Twc = transform_inverse(T_anchor)
    return np.einsum("nij,nj->ni", Twc[:, :3, :3], pa) + Twc[:, :3, 3]


def _initial_errors(data: DirectBAData, params: PhotometricParams) -> tuple[np.ndarray, np.ndarray]:
    """Per (image, point) squared patch error and activity at the initial estimates."""
    n, N = len(data.poses), len(data.points)
    img = np.repeat(np.arange(n), N)
    pid = np.tile(np.arange(N), n)
    etype = photometric_edge_types(params.patch)[0]
    ev = etype.evaluate((data.poses[img], data.points[pid]), data.patches[pid],
                        EdgeContext(params, {"image": img}))
    assert ev.active is not None
    return np.einsum("me,me->m", ev.error, ev.error).reshape(n, N), ev.active.reshape(n, N)


def choose_anchors(data: DirectBAData, params: PhotometricParams) -> np.ndarray:
    """Anchor image of every point: its known host, else the image where the patch fits best.

    The best fit is the smallest initial squared patch error among the images that see the point
    inside the margin and in front; points seen by none fall back to the image where they are
    deepest in front (they may still be dropped if behind every camera).

    Args:
        data: The problem.
        params: Photometric parameters (patch, margin).
    """
    if data.hosts is not None:
        return np.asarray(data.hosts, dtype=np.int64)
    s, active = _initial_errors(data, params)
    score = np.where(active, s, np.inf)
    best = np.argmin(score, axis=0)
    none = ~active.any(axis=0)
    if none.any():
        z = np.einsum("nij,pj->npi", data.poses[:, :3, :3], data.points[none])[..., 2]
        z += data.poses[:, None, 2, 3]
        best[none] = np.argmax(z, axis=0)
    return best


def build_problem(
    data: DirectBAData,
    parametrization: str = "xyz",
    robust: str | None = "huber",
    delta: float = 0.5,
    solver: str = "auto",
    algorithm: str = "lm",
    gradient: str = "central",
    numeric: bool = False,
    dtype: str = "float32",
    verbose: bool = False,
    stream: Any = None,
) -> DirectBAProblem:
    """Build the optimizer for a direct BA problem.

    Every (point, image) pair becomes an edge (the task's skeleton). Edges are ordered by image
    and by the initial projection's pixel row so that the image gathers walk memory roughly in
    order (cache locality of the per-edge pixel windows).

    Args:
        data: The problem (patch size is taken from ``data.patches``).
        parametrization: ``"xyz"`` (world points) or ``"inverse-depth"`` (``[a, b, ρ]`` in an
            anchor image, see :func:`choose_anchors`).
        robust: Robust kernel name (``None``/``"none"`` for plain least squares).
        delta: Kernel width (on ``sqrt(e'e)``; the task uses Huber with 0.5).
        solver: Linear solver for the reduced camera system.
        algorithm: ``"lm"``, ``"gn"`` or ``"dogleg"``.
        gradient: ``"central"`` or ``"interpolated"`` (see :class:`PhotometricParams`).
        numeric: Use numeric instead of analytic Jacobians (benchmark).
        dtype: Image dtype for the gathers (see :class:`PhotometricParams`).
        verbose: Print g2o's iteration lines.
        stream: Stream for the iteration lines (stdout by default).

    Raises:
        ValueError: Unknown parametrization, kernel, solver or algorithm.
    """
    if parametrization not in PARAMETRIZATIONS:
        raise ValueError(f"unknown parametrization {parametrization!r}; "
                         f"choose one of {', '.join(PARAMETRIZATIONS)}")
    patch = data.patch
    fx, fy, cx, cy = data.intrinsics
    params = PhotometricParams(data.images, fx, fy, cx, cy, patch=patch, gradient=gradient,
                               dtype=dtype)
    kernel = None if robust in (None, "none", "") else make_kernel(robust, delta)
    opt = SparseOptimizer(algorithm=algorithm, solver=solver, verbose=verbose,
                          stream=stream if stream is not None else sys.stdout)
    n, N = len(data.poses), len(data.points)
    pose_ids = np.arange(n)
    fixed = np.zeros(n, dtype=bool)
    fixed[0] = True  # gauge
    opt.add_vertices(VertexSE3Expmap, pose_ids, data.poses, fixed=fixed)
    edge_xyz, edge_inv, edge_host = photometric_edge_types(patch)
    if numeric:
        edge_xyz, edge_inv, edge_host = (
            numeric_variant(t) for t in (edge_xyz, edge_inv, edge_host)
        )

    # Edge order: image-major, then by the initial pixel row (memory order of the gathers).
    img = np.repeat(np.arange(n), N)
    pid = np.tile(np.arange(N), n)
    pc = np.einsum("mij,mj->mi", data.poses[img, :3, :3], data.points[pid]) + data.poses[img, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        row = np.nan_to_num(fy * pc[:, 1] / pc[:, 2] + cy, nan=0.0, posinf=1e9, neginf=-1e9)
    order = np.lexsort((row, img))
    img, pid = img[order], pid[order]

    anchors = None
    dropped = 0
    if parametrization == "xyz":
        point_index = np.arange(N)
        opt.add_vertices(VertexPointXYZ, n + point_index, data.points, marginalized=True)
        opt.add_edges(edge_xyz, np.c_[img, n + pid], data.patches[pid], robust_kernel=kernel,
                      params=params, data={"image": img})
        n_edges = len(img)
    else:
        anchor_all = choose_anchors(data, params)
        Ta = data.poses[anchor_all]
        pa = np.einsum("nij,nj->ni", Ta[:, :3, :3], data.points) + Ta[:, :3, 3]
        keep = pa[:, 2] > 1e-6
        dropped = int(N - keep.sum())
        point_index = np.flatnonzero(keep)
        anchors = anchor_all[keep]
        pa = pa[keep]
        q = np.c_[pa[:, :2] / pa[:, 2:3], 1.0 / pa[:, 2]]
        slot = np.full(N, -1)
        slot[point_index] = np.arange(len(point_index))
        opt.add_vertices(VertexPointInverseDepth, n + point_index, q, marginalized=True)
        sel = slot[pid] >= 0
        img, pid = img[sel], pid[sel]
        anc = anchor_all[pid]
        host = img == anc
        if host.any():
            opt.add_edges(edge_host, np.c_[anc[host], n + pid[host]], data.patches[pid[host]],
                          robust_kernel=kernel, params=params, data={"image": img[host]})
        other = ~host
        if other.any():
            opt.add_edges(edge_inv, np.c_[anc[other], img[other], n + pid[other]],
                          data.patches[pid[other]], robust_kernel=kernel, params=params,
                          data={"image": img[other]})
        n_edges = len(img)
    opt.initialize_optimization()
    return DirectBAProblem(opt, data, parametrization, params, point_index, anchors, n_edges,
                           dropped)
