"""A generated Manhattan-world 2D pose graph with known ground truth, and trajectory errors.

``graphopt-g2o`` without an input file optimises :func:`manhattan_world`'s graph and reports
:func:`trajectory_error` of the result against the truth. The graph imitates Olson's Manhattan
world (``w10000``): a robot walks a square grid in unit steps, turning by ±90° at random; every
step gives an odometry edge and every earlier pose within ``closure_radius`` of the current one a
candidate loop closure (up to ``max_closures`` per pose, about 6 edges per pose in total). The
initial estimate composes the noisy odometry, so it drifts.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock

__all__ = ["manhattan_world", "trajectory_error"]

_STEPS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # heading index h → unit step (θ = hπ/2)


def _wrap(theta: np.ndarray) -> np.ndarray:
    """Angles wrapped to ``[-π, π)``."""
    return (theta + np.pi) % (2 * np.pi) - np.pi


def _rotate(theta: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(θ_i) v_i`` for ``(n,)`` angles and ``(n, 2)`` vectors."""
    c, s = np.cos(theta), np.sin(theta)
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE2 products ``a_i · b_i`` of ``(n, 3)`` poses ``x y θ``."""
    return np.column_stack([a[:, :2] + _rotate(a[:, 2], b[:, :2]), _wrap(a[:, 2] + b[:, 2])])


def _between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE2 relative poses ``a_i⁻¹ · b_i``: ``b`` seen from ``a`` (g2o's ``EDGE_SE2``)."""
    return np.column_stack([_rotate(-a[:, 2], b[:, :2] - a[:, :2]), _wrap(b[:, 2] - a[:, 2])])


def _walk(poses: int, side: int, turn_probability: float, rng: np.random.Generator
          ) -> tuple[np.ndarray, np.ndarray]:
    """Grid positions ``(n, 2)`` and heading indices ``(n,)`` of a walk inside ``[0, side]²``.

    Pose ``k`` has already turned: it moves one step along its heading to pose ``k + 1``, which
    turns left or right with ``turn_probability`` (else goes straight), or, where that would
    leave the square, takes one of the moves that stay inside at random.
    """
    u = rng.random((poses, 3)).tolist()
    dx, dy = _STEPS[:, 0].tolist(), _STEPS[:, 1].tolist()
    xs, ys, hs = [], [], []
    x = y = side // 2
    h = 0
    for u_turn, u_side, u_pick in u:
        xs.append(x)
        ys.append(y)
        hs.append(h)
        x, y = x + dx[h], y + dy[h]
        want = (h + (1 if u_side < 0.5 else 3)) % 4 if u_turn < turn_probability else h
        stay = [o for o in (want, h, (h + 1) % 4, (h + 3) % 4)
                if 0 <= x + dx[o] <= side and 0 <= y + dy[o] <= side]
        h = want if stay[0] == want else stay[int(u_pick * len(stay))]
    pos = np.column_stack([xs, ys]).astype(np.int64)
    heading = np.array(hs, dtype=np.int64)
    return pos, heading


def _closures(pos: np.ndarray, radius: float, max_closures: int, rng: np.random.Generator
              ) -> np.ndarray:
    """``(m, 2)`` pairs ``(j, k)`` with ``j < k - 1`` and ``|p_j - p_k| <= radius``, at most
    ``max_closures`` per ``k``, drawn uniformly among the candidates.

    Positions are grid points, so the candidates of ``k`` are the earlier poses in the cells
    ``p_k + o`` for the integer offsets ``|o| <= radius``: a sorted (cell, pose) key gives each
    cell's range, and Floyd's algorithm draws distinct ranks within the ranges' union.
    """
    n, reach = len(pos), int(np.floor(radius))
    grid = np.arange(-reach, reach + 1)
    offsets = np.array([(a, b) for a in grid for b in grid if a * a + b * b <= radius**2 + 1e-9])
    low = pos.min(0) - reach
    height = int(pos[:, 1].max() - low[1]) + reach + 1

    def cell(p: np.ndarray) -> np.ndarray:
        return ((p[:, 0] - low[0]) * height + p[:, 1] - low[1]) * n

    keys = np.sort(cell(pos) + np.arange(n))  # by cell, then pose index
    before = np.arange(n) - 1  # candidates j < k - 1
    first = np.stack([np.searchsorted(keys, cell(pos + o)) for o in offsets], 1)
    count = np.stack([np.searchsorted(keys, cell(pos + o) + before) for o in offsets], 1) - first
    count = np.maximum(count, 0)
    total = count.sum(1)
    m = max_closures
    rank = np.tile(np.arange(m), (n, 1))  # everything when there are at most m candidates
    draw = np.full((n, m), -1)
    u = rng.random((n, m))
    for i in range(m):  # Floyd: for j = T-m … T-1 take t ∈ [0, j], or j if t was taken
        j = total - m + i
        t = np.floor(u[:, i] * (j + 1)).astype(np.int64)
        draw[:, i] = np.where((draw[:, :i] == t[:, None]).any(1), j, t)
    rank = np.where((total > m)[:, None], draw, rank)
    valid = rank < total[:, None]
    end = np.cumsum(count, 1)
    bucket = (rank[:, :, None] >= end[:, None, :]).sum(-1).clip(max=len(offsets) - 1)
    rows = np.arange(n)[:, None]
    where = first[rows, bucket] + rank - (end - count)[rows, bucket]
    j = keys[np.where(valid, where, 0)] % n
    k = np.broadcast_to(rows, rank.shape)
    pairs = np.column_stack([j[valid], k[valid]])
    return pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]


def manhattan_world(
    poses: int = 1000,
    seed: int = 0,
    *,
    sigma_xy: float = 0.05,
    sigma_theta: float = 0.01,
    turn_probability: float = 0.3,
    side: int | None = None,
    closure_radius: float = 1.0,
    max_closures: int = 6,
) -> tuple[GraphFile, np.ndarray]:
    """Generate a Manhattan-world 2D pose graph (``VERTEX_SE2``/``EDGE_SE2``, ``FIX 0``).

    Edge measurements are the true relative poses composed with ``N(0, Σ)`` noise,
    ``z = z_true · (δx, δy, δθ)``, ``Σ = diag(σ_xy², σ_xy², σ_θ²)``; the information is ``Σ⁻¹``.
    Odometry edges join ``k, k+1``; loop closures join an earlier pose ``j < k - 1`` to ``k``.
    The vertices' estimates compose the noisy odometry from the true first pose.

    Args:
        poses: Number of poses (>= 2).
        seed: Random seed (the graph is a deterministic function of the arguments).
        sigma_xy: Measurement noise of x and y (grid units).
        sigma_theta: Measurement noise of the heading (radians).
        turn_probability: Chance of a ±90° turn at each pose.
        side: Grid size (positions in ``[0, side]²``); default ``max(4, round(√(poses/10)))``,
            about 10 visits per grid point.
        closure_radius: Earlier poses at most this far from a pose are loop-closure candidates.
        max_closures: At most this many loop closures per pose (chosen at random).

    Returns:
        The graph (path ``"<generated>"``, line numbers 0) and the true poses ``(poses, 3)``
        ``x y θ`` with ``θ`` in ``[-π, π)``.
    """
    if poses < 2:
        raise ValueError(f"manhattan_world: need at least 2 poses, got {poses}")
    rng = np.random.default_rng(seed)
    side = max(4, round(np.sqrt(poses / 10))) if side is None else int(side)
    pos, heading = _walk(poses, side, turn_probability, rng)
    truth = np.column_stack([pos.astype(float), _wrap(heading * (np.pi / 2))])
    loops = _closures(pos, closure_radius, max_closures, rng)
    ids = np.concatenate([np.column_stack([np.arange(poses - 1), np.arange(1, poses)]), loops])
    sigma = np.array([sigma_xy, sigma_xy, sigma_theta])
    noise = rng.standard_normal((len(ids), 3)) * sigma
    meas = _compose(_between(truth[ids[:, 0]], truth[ids[:, 1]]), noise)
    # Initial estimate: chain the noisy odometry (the first poses - 1 edges) from the truth.
    odo = meas[: poses - 1]
    theta = truth[0, 2] + np.concatenate([[0.0], np.cumsum(odo[:, 2])])
    steps = _rotate(theta[:-1], odo[:, :2])
    estimate = np.column_stack([truth[0, :2] + np.vstack([[0.0, 0.0], np.cumsum(steps, 0)]),
                                _wrap(theta)])
    information = np.broadcast_to(np.diag(1.0 / sigma**2), (len(ids), 3, 3)).copy()
    graph = GraphFile(
        path="<generated>",
        vertices={"VERTEX_SE2": VertexBlock(np.arange(poses), estimate,
                                            np.zeros(poses, dtype=np.int64))},
        edges={"EDGE_SE2": EdgeBlock(ids, meas, information, np.zeros(len(ids), dtype=np.int64))},
        fixed=np.array([0], dtype=np.int64),
        notes=[f"Manhattan world: {poses} poses on a {side}x{side} grid, {poses - 1} odometry and "
               f"{len(loops)} loop-closure edges, sigma_xy {sigma_xy:g}, sigma_theta "
               f"{sigma_theta:g}, seed {seed}"],
    )
    return graph, truth


def trajectory_error(estimate: np.ndarray, truth: np.ndarray, align: str = "first"
                     ) -> dict[str, Any]:
    """RMS position and heading error of 2D poses against the truth, after an alignment.

    Args:
        estimate: ``(n, 3)`` poses ``x y θ``.
        truth: ``(n, 3)`` true poses, in the same order.
        align: ``"first"``: move the estimate rigidly so that its first pose is the truth's (the
            gauge a ``FIX``-ed first pose sets); ``"se2"``: the rotation and translation that
            minimise the squared position error (2D Kabsch), for graphs fixed elsewhere.

    Returns:
        ``rms_position``, ``max_position`` (grid units), ``rms_heading``, ``max_heading``
        (radians, wrapped), ``poses`` and ``alignment`` (the ``align`` used).
    """
    est, tru = np.asarray(estimate, dtype=float), np.asarray(truth, dtype=float)
    if est.shape != tru.shape or est.ndim != 2 or est.shape[1] != 3 or len(est) == 0:
        raise ValueError(f"trajectory_error: need two (n, 3) arrays, got {est.shape} and "
                         f"{tru.shape}")
    if align == "first":
        delta = _compose(tru[:1], _between(est[:1], np.zeros((1, 3))))  # T = truth_0 · est_0⁻¹
        moved = _compose(np.repeat(delta, len(est), 0), est)
    elif align == "se2":
        mu_e, mu_t = est[:, :2].mean(0), tru[:, :2].mean(0)
        cov = (tru[:, :2] - mu_t).T @ (est[:, :2] - mu_e)
        angle = np.arctan2(cov[1, 0] - cov[0, 1], cov[0, 0] + cov[1, 1])
        shift = mu_t - _rotate(np.array([angle]), mu_e[None])[0]
        moved = _compose(np.repeat([[shift[0], shift[1], angle]], len(est), 0), est)
    else:
        raise ValueError(f"trajectory_error: align must be 'first' or 'se2', got {align!r}")
    dp = np.linalg.norm(moved[:, :2] - tru[:, :2], axis=1)
    dh = np.abs(_wrap(moved[:, 2] - tru[:, 2]))
    return {
        "rms_position": float(np.sqrt(np.mean(dp**2))),
        "max_position": float(dp.max()),
        "rms_heading": float(np.sqrt(np.mean(dh**2))),
        "max_heading": float(dh.max()),
        "poses": len(est),
        "alignment": align,
    }
