"""The geometry of ``graphopt-bal-city``'s scenes (see :mod:`graphopt.apps.bal_city`): the
configuration, the cameras' path through a street grid, the tracks (which cameras see a point)
and the placement of points on façades, ground and roofs so that every camera of a track sees
its point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from graphopt.lie import so3_exp, so3_log
from graphopt.types.bal import bal_project

__all__ = ["CHUNK_POINTS", "CameraPath", "CityConfig", "camera_path", "chunk", "track_lengths",
           "windows"]

#: Points per generated chunk; every chunk has its own random stream (so the scene does not
#: depend on how it is consumed).
CHUNK_POINTS = 65536


@dataclass(frozen=True)
class CityConfig:
    """What to generate.

    Args:
        cameras: Number of cameras.
        points: Number of points.
        observations: Number of observations (between ``2·points`` and ``max_track·points``).
        seed: Random seed.
        max_track: Longest track (cameras seeing one point).
        revisit: Fraction of points (with tracks of 4 or more) also seen from another pass.
        spacing: Distance between consecutive cameras along the path (m).
        block: Length of a street between two crossings (m).
        passes: About how often the walk drives along each street.
        street_half_width: Distance from the street's centre line to the façades (m).
        focal: Nominal focal length (px); cameras vary by ±10 %.
        half_image: Half the image size (px); projections outside are not observations.
        pixel_sigma: Observation noise (px).
        rotation_sigma: Initial rotation noise (rad).
        translation_sigma: Initial translation noise (m).
        point_sigma: Initial point noise (m).
    """

    cameras: int = 472
    points: int = 153726
    observations: int = 1000000
    seed: int = 0
    max_track: int = 12
    revisit: float = 0.1
    spacing: float = 1.5
    block: float = 80.0
    passes: float = 2.0
    street_half_width: float = 8.0
    focal: float = 500.0
    half_image: float = 500.0
    pixel_sigma: float = 0.5
    rotation_sigma: float = 1e-3
    translation_sigma: float = 0.02
    point_sigma: float = 0.05

    def check(self) -> None:
        """Raise ``ValueError`` for counts no scene can have."""
        c, n, m, k = self.cameras, self.points, self.observations, self.max_track
        if c < 3 or n < 1 or not 2 <= k <= c:
            raise ValueError(f"need at least 3 cameras, 1 point and 2 <= max_track <= cameras "
                             f"(got {c} cameras, {n} points, max_track {k})")
        if not 2 * n <= m <= k * n:
            raise ValueError(f"{m} observations of {n} points: every point needs 2 to "
                             f"max_track={k} observations, so between {2 * n} and {k * n}")
        if not 0.0 <= self.revisit <= 1.0:
            raise ValueError(f"revisit must be in [0, 1], got {self.revisit}")



# --- the path -------------------------------------------------------------------------------


@dataclass
class CameraPath:
    """Cameras along the path: ground truth, centres, headings, their place keys."""

    cameras: np.ndarray  # (c, 9) true BAL cameras
    centers: np.ndarray  # (c, 3)
    right: np.ndarray  # (c, 3) unit vector to the right of the street direction
    lateral: np.ndarray  # (c,) offset from the street's centre line, along ``right``
    place: np.ndarray  # (c,) key of the cell and heading (cameras at one place, one direction)


def _street_walk(rng: np.random.Generator, segments: int, grid: int) -> np.ndarray:
    """Crossings ``(segments + 1, 2)`` of a non-backtracking random walk on a ``grid²`` grid
    (``grid = 2``: round and round one block)."""
    dirs = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    pos = rng.integers(0, grid, 2)
    d = int(rng.integers(4))
    out = [pos.copy()]
    for _ in range(segments):
        options = [(o, w) for o, w in ((d, 2.0), ((d + 1) % 4, 1.0), ((d + 3) % 4, 1.0))
                   if ((pos + dirs[o] >= 0) & (pos + dirs[o] < grid)).all()]  # ahead, turns
        w = np.array([w for _, w in options])
        d = options[int(rng.choice(len(options), p=w / w.sum()))][0]
        pos = pos + dirs[d]
        out.append(pos.copy())
    return np.array(out, dtype=float)


def camera_path(cfg: CityConfig, rng: np.random.Generator) -> CameraPath:
    """Cameras every ``spacing`` metres along a walk through the street grid, looking ahead
    (with a few degrees of yaw, pitch and roll), in the right lane, corners rounded.

    Args:
        cfg: The configuration.
        rng: The path's random stream.
    """
    c = cfg.cameras
    length = cfg.spacing * (c + 2)
    # g crossings a side have 2·g·(g − 1) streets: about ``passes`` times the path's length.
    grid = max(2, round(0.5 + math.sqrt(0.25 + length / (2.0 * cfg.block * cfg.passes))))
    segments = math.ceil(length / cfg.block) + 2
    poly = _street_walk(rng, segments, grid) * cfg.block
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])

    def at(s: np.ndarray) -> np.ndarray:
        s = np.clip(s, 0.0, cum[-1])
        k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(poly) - 2)
        f = ((s - cum[k]) / (cum[k + 1] - cum[k]))[:, None]
        return poly[k] * (1 - f) + poly[k + 1] * f

    def smooth(s: np.ndarray) -> np.ndarray:  # corners rounded over ±6 m
        return np.mean([at(s + o) for o in np.linspace(-6.0, 6.0, 9)], axis=0)

    s = 6.0 + cfg.spacing * (np.arange(c) + rng.uniform(-0.2, 0.2, c))
    xy = smooth(s)
    head = smooth(s + 1.0) - smooth(s - 1.0)
    head /= np.linalg.norm(head, axis=1, keepdims=True)
    right = np.column_stack([head[:, 1], -head[:, 0], np.zeros(c)])
    lateral = 2.0 + rng.normal(0.0, 0.3, c)  # the right lane
    centers = np.column_stack([xy, np.zeros(c)]) + lateral[:, None] * right
    centers[:, 2] = 1.6 + rng.normal(0.0, 0.05, c)
    yaw, pitch = np.radians(rng.normal(0.0, 5.0, c)), np.radians(rng.normal(0.0, 2.0, c))
    look = np.column_stack([np.cos(yaw) * head[:, 0] - np.sin(yaw) * head[:, 1],
                            np.sin(yaw) * head[:, 0] + np.cos(yaw) * head[:, 1], np.zeros(c)])
    look = np.cos(pitch)[:, None] * look + np.sin(pitch)[:, None] * [0.0, 0.0, 1.0]
    r = np.cross(look, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    R = np.stack([r, np.cross(r, look), -look], axis=1)  # rows: right, up, back (BAL: −z ahead)
    R = so3_exp(rng.normal(0.0, np.radians(1.0), (c, 3))) @ R
    cams = np.zeros((c, 9))
    cams[:, :3] = so3_log(R)
    cams[:, 3:6] = -np.einsum("nij,nj->ni", so3_exp(cams[:, :3]), centers)
    cams[:, 6] = cfg.focal * rng.uniform(0.9, 1.1, c)
    cams[:, 7] = rng.normal(0.0, 0.02, c)
    cams[:, 8] = rng.normal(0.0, 0.002, c)
    cell = np.floor(xy / 6.0).astype(np.int64) + 1
    quadrant = np.round(np.arctan2(head[:, 1], head[:, 0]) / (np.pi / 2)).astype(np.int64) % 4
    span = int(cell.max()) + 2
    place = (cell[:, 0] * span + cell[:, 1]) * 4 + quadrant
    return CameraPath(cams, centers, right, lateral, place)


# --- tracks ---------------------------------------------------------------------------------


def track_lengths(cfg: CityConfig, rng: np.random.Generator) -> np.ndarray:
    """``(n,)`` track lengths in ``[2, max_track]`` summing to exactly ``observations``:
    2 plus a Poisson number (clipped), then ±1 on random tracks until the sum is right.

    Args:
        cfg: The configuration.
        rng: The tracks' random stream.
    """
    n, m, kmax = cfg.points, cfg.observations, cfg.max_track
    k = 2 + np.minimum(rng.poisson(m / n - 2.0, n), kmax - 2)
    while (diff := m - int(k.sum())) != 0:
        room = np.flatnonzero(k < kmax) if diff > 0 else np.flatnonzero(k > 2)
        pick = rng.choice(room, size=min(abs(diff), len(room)), replace=False)
        k[pick] += 1 if diff > 0 else -1
    return k


def windows(cfg: CityConfig, path: CameraPath, k: np.ndarray, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: first window's start and length, second window's last camera (−1: none).

    The second window ends at a camera of the same place and heading as the first window's
    last camera, at least ``2·max_track`` cameras away along the path (another pass).

    Args:
        cfg: The configuration.
        path: The cameras.
        k: ``(n,)`` track lengths.
        rng: The tracks' random stream.
    """
    c, kmax = cfg.cameras, cfg.max_track
    split = (k >= 4) & (rng.random(len(k)) < cfg.revisit)
    k1 = np.where(split, k // 2, k)
    start = (rng.random(len(k)) * (c - k1 + 1)).astype(np.int64)
    last = start + k1 - 1
    order = np.argsort(path.place, kind="stable")
    keys = path.place[order]
    lo = np.searchsorted(keys, path.place[last])
    size = np.searchsorted(keys, path.place[last], side="right") - lo
    k2 = k - k1
    other = np.full(len(k), -1, dtype=np.int64)
    for _ in range(4):  # a few draws among the cameras of the place: one of another pass
        cand = order[lo + (rng.random(len(k)) * size).astype(np.int64)]
        good = (other < 0) & (np.abs(cand - last) >= 2 * kmax) & (cand - k2 + 1 >= 0)
        other[good] = cand[good]
    ok = split & (other >= 0)
    k1 = np.where(ok, k1, k)
    start = np.minimum(start, c - k1)
    return start, k1, np.where(ok, other, -1)


def _track_cameras(start: np.ndarray, k1: np.ndarray, end2: np.ndarray, k: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Observations of the tracks ``(point (sum k,), camera (sum k,))``, by point and camera."""
    pt = np.repeat(np.arange(len(k)), k)
    first = np.cumsum(k) - k
    j = np.arange(len(pt)) - first[pt]
    cam = np.where(j < k1[pt], start[pt] + j, end2[pt] - (k[pt] - 1 - j))
    order = np.lexsort((cam, pt))
    return pt[order], cam[order]


def _visible(cfg: CityConfig, cams: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projections ``(k, 2)`` of points by cameras, and whether each is an observation: in
    front (1 m at least) and inside the image."""
    uv, pz = bal_project(cams, X)
    ok = (pz < -1.0) & (np.abs(uv) < cfg.half_image).all(axis=1)
    return uv, ok


def _place_points(cfg: CityConfig, path: CameraPath, ref: np.ndarray, rng: np.random.Generator
                  ) -> np.ndarray:
    """A point per reference camera: a ray through the central part of its image, to the
    façade it meets, the ground, a building at the end of the street (40–80 m) or a roof's
    edge (8–30 m high)."""
    n = len(ref)
    hw = 0.8 * cfg.half_image / cfg.focal
    d_cam = np.column_stack([rng.uniform(-hw, hw, n), rng.uniform(-hw, hw, n), -np.ones(n)])
    R = so3_exp(path.cameras[ref, :3])
    d = np.einsum("nji,nj->ni", R, d_cam)  # Rᵀ d: the ray in the world
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    C = path.centers[ref]
    across = np.einsum("ni,ni->n", d, path.right[ref])
    wall = cfg.street_half_width + rng.normal(0.0, 0.3, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = (np.sign(across) * wall - path.lateral[ref]) / across
        t_ground = np.where(d[:, 2] < 0, -C[:, 2] / d[:, 2], np.inf)
    t_wall = np.where(np.isfinite(t_wall) & (t_wall > 0), t_wall, np.inf)
    t = np.minimum(np.minimum(t_wall, t_ground), rng.uniform(40.0, 80.0, n))
    roof = rng.uniform(8.0, 30.0, n)  # nothing above the roofs: the ray stops at the edge
    with np.errstate(divide="ignore"):
        t = np.where(d[:, 2] > 0, np.minimum(t, (roof - C[:, 2]) / d[:, 2]), t)
    t[t < 3.0] = np.nan  # too close (looking down at the road): placed again
    return C + t[:, None] * d


def chunk(cfg: CityConfig, path: CameraPath, tracks: tuple[np.ndarray, ...], lo: int, hi: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True points ``lo:hi``, and their observations ``(point, camera)`` (global indices).

    A point is placed from the last camera of its first window; if some camera of its track
    does not see it, it is placed again (a new ray), and after four tries its first window
    moves along the path (and loses its second one). The chunk has its own random stream.

    Args:
        cfg: The configuration.
        path: The cameras.
        tracks: Per point: length, first window's start and length, second window's end.
        lo: First point.
        hi: End of the points.
    """
    rng = np.random.default_rng([cfg.seed, 1, lo // CHUNK_POINTS])
    k, start, k1, end2 = (a[lo:hi].copy() for a in tracks)
    c = cfg.cameras
    X = np.zeros((hi - lo, 3))
    todo = np.arange(hi - lo)
    for attempt in range(200):
        pt, cam = _track_cameras(start[todo], k1[todo], end2[todo], k[todo])
        X[todo] = _place_points(cfg, path, start[todo] + k1[todo] - 1, rng)
        _, ok = _visible(cfg, path.cameras[cam], X[todo][pt])
        bad = np.unique(pt[~ok])
        if not len(bad):
            break
        todo = todo[bad]
        if attempt % 4 == 3:
            k1[todo], end2[todo] = k[todo], -1
            start[todo] = (rng.random(len(todo)) * (c - k[todo] + 1)).astype(np.int64)
    else:  # pragma: no cover - geometry guarantees a visible placement long before
        raise RuntimeError(f"{len(todo)} points of chunk {lo}:{hi} found no visible placement")
    pt, cam = _track_cameras(start, k1, end2, k)
    return X, pt + lo, cam
