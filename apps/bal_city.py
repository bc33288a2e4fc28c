"""``graphopt-bal-city``: a city-scale synthetic BAL problem with local co-visibility.

Cameras drive along a random walk through a grid of streets (about ``passes`` times along each
street, so that the walk comes back to places it has seen); points lie on the façades on both
sides of the street, on the ground and up to the roofs (geometry: :mod:`.bal_city_geometry`).
Every point is seen by a *track* of 2 to ``max_track``
consecutive cameras along the path — the cameras near it — and a fraction ``revisit`` of the
points also by a second run of cameras on a later (or earlier) pass through the same place,
which closes loops as in real large reconstructions. Each camera is thus co-visible with a few
dozen others (its neighbours along the path and on other passes): the reduced camera system is
sparse, like the large BAL problems' (Final-13682: 13,682 cameras, 4,456,117 points,
28,987,644 observations).

The counts are exact: cameras, points and observations are parameters (``CityConfig``), with
presets scaled from Final-13682's (``--preset 1M|3M|10M|29M``). Projections follow BAL's camera
(``P = R X + t``, ``p = −P_xy/P_z``, radial distortion, focal; the camera looks down −z), every
observation is in front of its camera and inside its image, observations get Gaussian pixel
noise, and the initial cameras and points are the ground truth perturbed. The scene is a
deterministic function of the configuration (seed included); points are generated in chunks of
:data:`CHUNK_POINTS` with one random stream each, so a file is streamed to disk without the
whole problem in memory (29M observations: about 1 GB of memory; see ``docs/scale.md``).

Usage::

    graphopt-bal-city OUTPUT [--preset 1M|3M|10M|29M] [--cameras C --points N
                      --observations M] [--seed S] [--truth FILE] [--max-track K]
                      [--revisit F] [--quiet]

OUTPUT ending in ``.gz`` or ``.bz2`` is compressed (bzip2 writes about 10 MB/s).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from graphopt.apps import _cli
from graphopt.apps.bal_city_geometry import (
    CHUNK_POINTS,
    CityConfig,
    camera_path,
    chunk,
    track_lengths,
    windows,
)
from graphopt.apps.bal_preprocess import perturb
from graphopt.io.bal import BALProblem, BALWriter, quantize
from graphopt.types.bal import bal_project

__all__ = ["CHUNK_POINTS", "FINAL_13682", "CityConfig", "CityScene", "city_scene",
           "co_visibility", "preset", "write_city"]

PROG = "graphopt-bal-city"
#: (cameras, points, observations) of BAL's largest problem, Final-13682.
FINAL_13682 = (13682, 4456117, 28987644)
#: Decimal places of observations and points in the file (and in memory: see ``quantize``).
DECIMALS = 6
#: Decimal places of the ground-truth file's observations and points.
TRUTH_DECIMALS = 9


def preset(name: str, seed: int = 0) -> CityConfig:
    """Final-13682's counts scaled to a number of observations (``"1M"``, ``"29M"``, …).

    Args:
        name: ``<number>M`` (millions of observations; ``29M`` is Final-13682's exact counts).
        seed: Random seed.
    """
    if name.upper() == "29M":
        c, n, m = FINAL_13682
    else:
        m = int(round(float(name.upper().rstrip("M")) * 1e6))
        f = m / FINAL_13682[2]
        c, n = max(3, round(FINAL_13682[0] * f)), max(1, round(FINAL_13682[1] * f))
    return CityConfig(cameras=c, points=n, observations=m, seed=seed)


# --- the scene ------------------------------------------------------------------------------


@dataclass
class CityScene:
    """A generated problem and its ground truth.

    Args:
        problem: Noisy observations and perturbed initial cameras and points (the values a
            reader gets back from the written file).
        truth: True cameras and points, and the noise-free projections as observations.
        config: What was generated.
    """

    problem: BALProblem
    truth: BALProblem
    config: CityConfig


def _generate(cfg: CityConfig) -> tuple[np.ndarray, np.ndarray, Iterator[tuple[np.ndarray, ...]]]:
    """True and initial cameras, and an iterator over chunks of ``(true points, initial
    points, point index, camera index, true projections, noisy observations)``."""
    cfg.check()
    path = camera_path(cfg, np.random.default_rng([cfg.seed, 0]))
    rng = np.random.default_rng([cfg.seed, 2])
    k = track_lengths(cfg, rng)
    tracks = (k, *windows(cfg, path, k, rng))
    init = perturb(BALProblem(path.cameras, np.zeros((0, 3)), np.zeros(0, np.int64),
                              np.zeros(0, np.int64), np.zeros((0, 2))),
                   cfg.rotation_sigma, cfg.translation_sigma, 0.0, seed=cfg.seed + 3).cameras

    def chunks() -> Iterator[tuple[np.ndarray, ...]]:
        for lo in range(0, cfg.points, CHUNK_POINTS):
            hi = min(lo + CHUNK_POINTS, cfg.points)
            X, pt, cam = chunk(cfg, path, tracks, lo, hi)
            uv, _ = bal_project(path.cameras[cam], X[pt - lo])
            noise = np.random.default_rng([cfg.seed, 3, lo // CHUNK_POINTS])
            obs = quantize(uv + noise.normal(0.0, cfg.pixel_sigma, uv.shape), DECIMALS)
            X0 = quantize(X + noise.normal(0.0, cfg.point_sigma, X.shape), DECIMALS)
            yield X, X0, pt, cam, uv, obs

    return path.cameras, init, chunks()


def city_scene(config: CityConfig) -> CityScene:
    """Generate a city scene in memory (for tests and small problems; files: :func:`write_city`).

    Args:
        config: What to generate.

    Returns:
        The scene; observations are sorted by point, then camera.
    """
    true_cams, init_cams, chunks = _generate(config)
    parts = list(zip(*chunks, strict=True))
    X, X0, pt, cam, uv, obs = (np.concatenate(p) for p in parts)
    problem = BALProblem(init_cams, X0, cam, pt, obs)
    truth = BALProblem(true_cams.copy(), X, cam, pt, uv)
    return CityScene(problem, truth, config)


def co_visibility(num_cameras: int, camera_index: np.ndarray, point_index: np.ndarray,
                  chunk: int = 4_000_000) -> np.ndarray:
    """Number of other cameras each camera shares a point with (the off-diagonal blocks of its
    column of the reduced camera system).

    Args:
        num_cameras: Cameras.
        camera_index: ``(m,)`` camera of every observation.
        point_index: ``(m,)`` point of every observation, sorted.
        chunk: Observations per pass (a chunk ends at a point's last observation).
    """
    acc = sp.csr_matrix((num_cameras, num_cameras), dtype=np.int32)
    m, lo = len(point_index), 0
    while lo < m:
        hi = min(m, lo + chunk)
        if hi < m:
            hi = int(np.searchsorted(point_index, point_index[hi - 1], side="left")) or hi
        p = point_index[lo:hi] - point_index[lo]
        inc = sp.csr_matrix((np.ones(hi - lo, np.int32), (p, camera_index[lo:hi])),
                            shape=(int(p[-1]) + 1, num_cameras))
        acc = acc + (inc.T @ inc).astype(bool).astype(np.int32)
        lo = hi
    return np.diff(acc.indptr) - (acc.diagonal() > 0)


@dataclass(frozen=True)
class CityStats:
    """What :func:`write_city` wrote.

    Args:
        per_camera: ``(min, median, max)`` observations per camera.
        co_visible: ``(min, median, max)`` cameras co-visible with a camera.
        seconds: Wall-clock seconds.
    """

    per_camera: tuple[int, int, int]
    co_visible: tuple[int, int, int]
    seconds: float


def write_city(path: str, config: CityConfig, truth: str | None = None,
               progress: Callable[[int], None] | None = None) -> CityStats:
    """Generate a city scene chunk by chunk and stream it to a BAL file (atomically).

    Args:
        path: Destination (``.gz``/``.bz2``: compressed).
        config: What to generate.
        truth: Optional second file: true cameras (exact) and points and noise-free
            observations (to :data:`TRUTH_DECIMALS` decimal places).
        progress: Called with the number of observations written after every chunk.

    Returns:
        Statistics of the scene.
    """
    t0 = time.perf_counter()
    true_cams, init_cams, chunks = _generate(config)
    c, n, m = config.cameras, config.points, config.observations
    out = BALWriter(path, c, n, m, DECIMALS)
    gt = BALWriter(truth, c, n, m, TRUTH_DECIMALS) if truth else None
    points, true_points, cams, pts = [], [], [], []
    try:
        done = 0
        for X, X0, pt, cam, uv, obs in chunks:
            out.observations(cam, pt, obs)
            if gt is not None:
                gt.observations(cam, pt, uv)
                true_points.append(X)
            points.append(X0)
            cams.append(cam.astype(np.int32))
            pts.append(pt.astype(np.int32))
            done += len(pt)
            if progress is not None:
                progress(done)
        for w, cm, ps in ((out, init_cams, points), (gt, true_cams, true_points)):
            if w is not None:
                w.cameras(cm)
                for p in ps:
                    w.points(p)
                w.close()
    except BaseException:
        out.discard()
        if gt is not None:
            gt.discard()
        raise
    cam_all, pt_all = np.concatenate(cams), np.concatenate(pts)
    per = np.bincount(cam_all, minlength=c)
    cov = co_visibility(c, cam_all, pt_all)
    stat = lambda a: (int(a.min()), int(np.median(a)), int(a.max()))  # noqa: E731
    return CityStats(stat(per), stat(cov), time.perf_counter() - t0)


# --- command line ---------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser.

    Returns:
        The parser.
    """
    p = _cli.OneLineParser(prog=PROG, description="Write a city-scale synthetic BAL problem "
                           "(cameras along streets, local co-visibility).")
    p.add_argument("output", metavar="OUTPUT", help="BAL file to write (.txt, .txt.gz, .txt.bz2)")
    p.add_argument("--preset", default=None, metavar="SIZE",
                   help="Final-13682's counts scaled to SIZE observations: 1M, 3M, 10M, 29M "
                        "(Final-13682 itself); default 1M")
    p.add_argument("--cameras", type=int, default=None)
    p.add_argument("--points", type=int, default=None)
    p.add_argument("--observations", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-track", type=int, default=None, metavar="K",
                   help="longest track (default 12)")
    p.add_argument("--revisit", type=float, default=None, metavar="F",
                   help="fraction of points also seen from another pass (default 0.1)")
    p.add_argument("--truth", metavar="FILE", help="also write the ground truth as a BAL file")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def _config(args: argparse.Namespace) -> CityConfig:
    counts = (args.cameras, args.points, args.observations)
    if args.preset is not None and any(x is not None for x in counts):
        raise _cli.AppError("give --preset or the three counts, not both")
    if args.preset is None and any(x is not None for x in counts):
        if any(x is None for x in counts):
            raise _cli.AppError("give all three of --cameras, --points and --observations")
        cfg = CityConfig(cameras=args.cameras, points=args.points,
                         observations=args.observations, seed=args.seed)
    else:
        try:
            cfg = preset(args.preset or "1M", args.seed)
        except ValueError:
            raise _cli.AppError(f"--preset must look like 1M, 3M or 29M, got {args.preset!r}"
                                ) from None
    if args.max_track is not None:
        cfg = replace(cfg, max_track=args.max_track)
    if args.revisit is not None:
        cfg = replace(cfg, revisit=args.revisit)
    try:
        cfg.check()
    except ValueError as exc:
        raise _cli.AppError(str(exc)) from None
    return cfg


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Generate and write the scene as configured by parsed options.

    Args:
        args: Options from :func:`build_parser`.

    Returns:
        A summary.
    """
    cfg = _config(args)
    _cli.check_outputs({"OUTPUT": args.output, "--truth": args.truth})
    last = [time.perf_counter()]

    def progress(done: int) -> None:
        if not args.quiet and time.perf_counter() - last[0] > 5.0:
            last[0] = time.perf_counter()
            print(f"{PROG}: {done:,} of {cfg.observations:,} observations", file=sys.stderr)

    stats = write_city(args.output, cfg, args.truth, progress)
    summary = {"output": args.output, "cameras": cfg.cameras, "points": cfg.points,
               "observations": cfg.observations, "seed": cfg.seed,
               "observations_per_camera": stats.per_camera,
               "co_visible_cameras": stats.co_visible, "seconds": stats.seconds}
    if not args.quiet:
        print(f"{PROG}: wrote {args.output}: {cfg.cameras:,} cameras, {cfg.points:,} points, "
              f"{cfg.observations:,} observations in {stats.seconds:.1f} s\n"
              f"  observations per camera min/median/max {stats.per_camera}, co-visible "
              f"cameras per camera {stats.co_visible}")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``graphopt-bal-city``.

    Args:
        argv: Arguments (``sys.argv[1:]`` if None).

    Returns:
        Exit status: 0 on success, 1 on an error, 2 on bad options.
    """
    return _cli.run_main(PROG, build_parser(), run, argv, user_errors=(ValueError,))


if __name__ == "__main__":
    sys.exit(main())
