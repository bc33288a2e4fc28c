"""An initial estimate for a SLAM graph from its edges, as g2o's ``computeInitialGuess`` makes
one: poses by composing the pose-pose measurements along a breadth-first spanning tree from the
fixed poses, then every landmark from its first observation by a placed pose.

The search runs one BFS *level* at a time: each level gathers the neighbours of the whole
frontier, keeps each newly reached pose once (through its first edge in file order) and composes
all their estimates in one batched call. There is no Python loop per vertex or per edge; the
number of iterations is the depth of the tree.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graphopt.types import isometry3 as iso
from graphopt.types.slam2d import normalize_theta

__all__ = ["PoseGroup", "SE2_GROUP", "SE3_GROUP", "bfs_levels", "place_landmarks",
           "propagate_poses"]


@dataclass(frozen=True)
class PoseGroup:
    """How poses of one kind compose (for the propagation).

    Args:
        compose: ``(A, B) -> A·B`` on stacks of poses.
        inverse: ``A -> A⁻¹``.
        identity: One identity pose (the estimate of a root with no vertex line).
    """

    compose: Callable[[np.ndarray, np.ndarray], np.ndarray]
    inverse: Callable[[np.ndarray], np.ndarray]
    identity: np.ndarray


def _se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """g2o's ``SE2`` product on ``(n, 3)`` poses."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.stack([a[:, 0] + c * b[:, 0] - s * b[:, 1], a[:, 1] + s * b[:, 0] + c * b[:, 1],
                     normalize_theta(a[:, 2] + b[:, 2])], axis=1)


def _se2_inverse(a: np.ndarray) -> np.ndarray:
    """g2o's ``SE2::inverse`` on ``(n, 3)`` poses."""
    th = normalize_theta(-a[:, 2])
    c, s = np.cos(th), np.sin(th)
    return np.stack([-(c * a[:, 0] - s * a[:, 1]), -(s * a[:, 0] + c * a[:, 1]), th], axis=1)


SE2_GROUP = PoseGroup(_se2_compose, _se2_inverse, np.zeros(3))
SE3_GROUP = PoseGroup(iso.compose, iso.inverse, np.eye(3, 4))


def _gather_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenate ``arange(s, s + c)`` for all pairs, without a loop."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    ends = np.cumsum(counts)
    return np.arange(total) - np.repeat(ends - counts, counts) + np.repeat(starts, counts)


def bfs_levels(
    n: int, src: np.ndarray, dst: np.ndarray, roots: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Breadth-first spanning forest of an undirected graph, level by level.

    Args:
        n: Number of nodes (``0 … n−1``).
        src: ``(m,)`` first node of each edge.
        dst: ``(m,)`` second node of each edge.
        roots: ``(r,)`` start nodes (level 0).

    Returns:
        Per level after the roots: ``(nodes, edges, forward)``: the newly reached nodes, the
        edge that reaches each (the lowest-numbered such edge from the previous level) and
        whether it is traversed from ``src`` to ``dst``.
    """
    m = len(src)
    ends = np.concatenate([src, dst])
    other = np.concatenate([dst, src])
    edge = np.concatenate([np.arange(m), np.arange(m)])
    order = np.lexsort((edge, ends))
    other, edge = other[order], edge[order]
    indptr = np.searchsorted(ends[order], np.arange(n + 1))
    visited = np.zeros(n, dtype=bool)
    visited[roots] = True
    frontier = np.unique(roots)
    levels = []
    while len(frontier):
        k = _gather_ranges(indptr[frontier], indptr[frontier + 1] - indptr[frontier])
        nb, ne = other[k], edge[k]
        keep = ~visited[nb]
        nb, ne = nb[keep], ne[keep]
        by_edge = np.lexsort((ne, nb))  # per node, its lowest-numbered edge first
        nb, ne = nb[by_edge], ne[by_edge]
        nodes, first = np.unique(nb, return_index=True)
        if not len(nodes):
            break
        edges = ne[first]
        visited[nodes] = True
        levels.append((nodes, edges, dst[edges] == nodes))
        frontier = nodes
    return levels


def propagate_poses(
    group: PoseGroup,
    estimates: np.ndarray,
    roots: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    measurements: np.ndarray,
) -> np.ndarray:
    """Set every pose reachable from the roots by composing measurements along the BFS tree.

    ``to = from · Z`` along an edge, ``from = to · Z⁻¹`` against it (g2o's
    ``EdgeSE2``/``EdgeSE3::initialEstimate``).

    Args:
        group: :data:`SE2_GROUP` or :data:`SE3_GROUP`.
        estimates: ``(n, *pose_shape)`` poses; the roots' rows are used, the others are
            overwritten where reached (updated in place).
        roots: ``(r,)`` indices of the poses to start from.
        src: ``(m,)`` ``from`` index of each pose-pose edge.
        dst: ``(m,)`` ``to`` index of each edge.
        measurements: ``(m, *pose_shape)`` relative poses ``Z``.

    Returns:
        ``(n,)`` boolean mask of the poses reached (roots included).
    """
    reached = np.zeros(len(estimates), dtype=bool)
    reached[roots] = True
    for nodes, edges, forward in bfs_levels(len(estimates), src, dst, roots):
        z = measurements[edges]
        parent = np.where(forward, src[edges], dst[edges])
        back = ~forward
        if back.any():
            z = z.copy()
            z[back] = group.inverse(z[back])
        estimates[nodes] = group.compose(estimates[parent], z)
        reached[nodes] = True
    return reached


def place_landmarks(
    observe: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    poses: np.ndarray,
    reached: np.ndarray,
    pose_idx: np.ndarray,
    landmark_idx: np.ndarray,
    measurements: np.ndarray,
    n_landmarks: int,
    landmarks: np.ndarray,
) -> np.ndarray:
    """Set each landmark from its first observation (file order) by a reached pose.

    Args:
        observe: ``(poses (k, …), measurements (k, …), edge indices (k,)) -> (k, d)``
            landmark positions in the world.
        poses: Pose estimates, indexed by ``pose_idx``.
        reached: Mask over ``poses`` of the placed ones.
        pose_idx: ``(m,)`` observing pose of each observation edge.
        landmark_idx: ``(m,)`` landmark of each edge (``0 … n_landmarks−1``).
        measurements: ``(m, d)`` observations.
        n_landmarks: Number of landmarks.
        landmarks: ``(n_landmarks, d)`` estimates, overwritten where placed (in place).

    Returns:
        ``(n_landmarks,)`` boolean mask of the landmarks placed.
    """
    usable = np.flatnonzero(reached[pose_idx])
    lm, first = np.unique(landmark_idx[usable], return_index=True)
    e = usable[first]
    if len(e):
        landmarks[lm] = observe(poses[pose_idx[e]], measurements[e], e)
    placed = np.zeros(n_landmarks, dtype=bool)
    placed[lm] = True
    return placed
