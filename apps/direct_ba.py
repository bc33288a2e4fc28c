"""graphopt-direct-ba: direct (photometric) bundle adjustment, real data or a synthetic scene.

Usage::

    graphopt-direct-ba [DATA_DIR] [--iterations N] [--robust KERNEL --robust-delta D]
                       [--parametrization xyz|inverse-depth] [--patch 4] [--solver ...]
                       [--rrd FILE] [--png FILE] [--json FILE] [--quiet]

With ``DATA_DIR`` (poses.txt, points.txt, 0.png…) every (point, image) pair is a photometric
patch edge, as in the task's skeleton; without it a synthetic textured room is rendered from known
poses, perturbed and recovered, and the errors against the truth are reported.

Conventions: poses are ``T_cw`` with the update ``T ← exp(δ)·T``; the first pose is fixed (it
fixes the gauge; monocular scale remains a free direction that LM's damping holds); points are
marginalised (Schur complement). ``chi2`` is g2o's robust chi2 ``Σ ρ(e'e)`` over active edges.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from graphopt.apps.direct_ba_scene import synthetic_scene
from graphopt.io.directba import DirectBAData, DirectBAFormatError, load_directba
from graphopt.lie import so3_log, transform_inverse
from graphopt.types.photometric import PhotometricParams, numeric_variant, photometric_edge_types
from graphopt.types.vertices import VertexPointInverseDepth, VertexPointXYZ, VertexSE3Expmap

PROG = "graphopt-direct-ba"
PARAMETRIZATIONS = ("xyz", "inverse-depth")
SOLVERS = ("auto", "cholmod", "dense", "pcg", "scipy")
PATCHES = (2, 4, 6, 8)

#: Synthetic scene used without DATA_DIR (7 frames like the task's data).
SYNTHETIC = {"n_frames": 7, "n_points": 2000, "seed": 0}


class AppError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


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
    from graphopt.edge import EdgeContext

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
    from graphopt import SparseOptimizer, make_kernel

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


# --------------------------------------------------------------------------------------------
# errors against the truth


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (degrees) and camera-centre (metres) errors of every pose.

    Args:
        T_est: ``(n, 4, 4)`` estimated ``T_cw``.
        T_true: ``(n, 4, 4)`` true ``T_cw``.
    """
    dR = T_est[:, :3, :3] @ np.swapaxes(T_true[:, :3, :3], 1, 2)
    rot = np.degrees(np.linalg.norm(so3_log(dR), axis=1))
    c_est = transform_inverse(T_est)[:, :3, 3]
    c_true = transform_inverse(T_true)[:, :3, 3]
    return rot, np.linalg.norm(c_est - c_true, axis=1)


def truth_report(problem: DirectBAProblem) -> dict[str, float]:
    """Errors against the truth (synthetic scene): mean/max over the free poses, median points.

    Args:
        problem: The problem (its data must carry ``true_poses``/``true_points``).
    """
    data = problem.data
    assert data.true_poses is not None and data.true_points is not None
    out: dict[str, float] = {}
    truth = data.true_points[problem.point_index]
    c_true = transform_inverse(data.true_poses)[:, :3, 3]
    for when, T, X in (("initial", data.poses, data.points[problem.point_index]),
                       ("final", problem.poses(), problem.points())):
        rot, trans = pose_errors(T[1:], data.true_poses[1:])
        out[f"{when}_rotation_error_deg_mean"] = float(rot.mean())
        out[f"{when}_rotation_error_deg_max"] = float(rot.max())
        out[f"{when}_translation_error_m_mean"] = float(trans.mean())
        out[f"{when}_translation_error_m_max"] = float(trans.max())
        # Monocular scale is a gauge freedom (only the first pose is fixed): also report the
        # centre errors after the best scale about the fixed first camera.
        a = transform_inverse(T)[:, :3, 3] - c_true[0]
        b = c_true - c_true[0]
        scale = float((a * b).sum() / max(float((a * a).sum()), 1e-300))
        out[f"{when}_scale"] = scale
        out[f"{when}_translation_error_scale_aligned_m_mean"] = float(
            np.linalg.norm(scale * a - b, axis=1)[1:].mean())
        out[f"{when}_point_error_m_median"] = float(np.median(np.linalg.norm(X - truth, axis=1)))
    return out


# --------------------------------------------------------------------------------------------
# outputs


def _intensity_colors(patches: np.ndarray) -> np.ndarray:
    g = np.clip(patches.mean(axis=1), 0, 255).astype(np.uint8)
    return np.stack([g, g, g], axis=1)


def write_png(path: str | Path, problem: DirectBAProblem, before: tuple[np.ndarray, np.ndarray],
              after: tuple[np.ndarray, np.ndarray]) -> None:
    """Top-down (x–z) picture of cameras and points before (red/grey) and after (green/blue).

    Args:
        path: Destination ``.png`` (replaced atomically).
        problem: The problem (for the truth on the synthetic scene).
        before: ``(poses, points)`` before optimisation.
        after: ``(poses, points)`` after.
    """
    import cv2

    from graphopt.io.atomic import atomic_path

    size, pad = 900, 50
    c_before = transform_inverse(before[0])[:, :3, 3]
    c_after = transform_inverse(after[0])[:, :3, 3]
    allp = np.vstack([before[1], after[1]])
    finite = np.isfinite(allp).all(axis=1)
    lo = np.minimum(np.percentile(allp[finite], 2, axis=0), np.minimum(c_before, c_after).min(0))
    hi = np.maximum(np.percentile(allp[finite], 98, axis=0), np.maximum(c_before, c_after).max(0))
    span = max(hi[0] - lo[0], hi[2] - lo[2], 1e-9)
    scale = (size - 2 * pad) / span

    def px(p: np.ndarray) -> np.ndarray:
        # x to the right, z (viewing direction) up the picture.
        u = pad + (p[:, 0] - lo[0]) * scale
        v = size - pad - (p[:, 2] - lo[2]) * scale
        return np.stack([u, v], axis=1)

    canvas = np.full((size, size, 3), 255, np.uint8)
    for pts, colour in ((before[1], (170, 170, 170)), (after[1], (200, 120, 40))):
        q = px(pts[np.isfinite(pts).all(axis=1)])
        inside = (q >= 0).all(axis=1) & (q < size).all(axis=1)
        q = q[inside].astype(int)
        canvas[q[:, 1], q[:, 0]] = colour
    if problem.data.true_poses is not None:
        ct = transform_inverse(problem.data.true_poses)[:, :3, 3]
        for p in px(ct).astype(int):
            cv2.drawMarker(canvas, tuple(int(x) for x in p), (0, 0, 0), cv2.MARKER_CROSS, 14, 1)
    for cams, colour in ((c_before, (0, 0, 220)), (c_after, (0, 160, 0))):
        q = px(cams).astype(int)
        cv2.polylines(canvas, [q.reshape(-1, 1, 2)], False, colour, 1, cv2.LINE_AA)
        for p in q:
            cv2.circle(canvas, tuple(int(x) for x in p), 4, colour, -1, cv2.LINE_AA)
    legend = [("cameras before", (0, 0, 220)), ("cameras after", (0, 160, 0)),
              ("points before", (170, 170, 170)), ("points after", (200, 120, 40))]
    if problem.data.true_poses is not None:
        legend.append(("true cameras", (0, 0, 0)))
    for i, (text, colour) in enumerate(legend):
        cv2.putText(canvas, text, (12, 22 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                    cv2.LINE_AA)
    shift_c = float(np.linalg.norm(c_after - c_before, axis=1).max())
    ok = np.isfinite(before[1]).all(axis=1) & np.isfinite(after[1]).all(axis=1)
    shift_p = float(np.median(np.linalg.norm(after[1][ok] - before[1][ok], axis=1))) if ok.any() \
        else float("nan")
    cv2.putText(canvas, f"top view: x right, z up; largest camera shift {shift_c:.4g}, median "
                f"point shift {shift_p:.4g}", (12, size - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", canvas)
        if not ok:
            raise OSError(f"{path}: PNG encoding failed")
        tmp.write_bytes(buf.tobytes())


class _RerunLog:
    """Log the run to a rerun recording: frusta with images, points, chi2 per iteration."""

    def __init__(self, path: str, problem: DirectBAProblem) -> None:

        from graphopt.recording import Recorder

        # The data's world frame is camera-like (x right, y down, z forward).
        self.rec = Recorder(path, application_id=PROG, camera_xyz="RDF", world_xyz="RDF")
        self.problem = problem
        data = problem.data
        fx, fy, cx, cy = data.intrinsics
        n = len(data.poses)
        # Per-camera (n, 2) arrays: Recorder reads a 1-D focal as one value per camera.
        self.cam = {"focal": np.tile([fx, fy], (n, 1)),
                    "principal_point": np.tile([cx, cy], (n, 1)),
                    "resolution": np.tile([data.images.shape[2], data.images.shape[1]], (n, 1))}
        self.colors = _intensity_colors(data.patches[problem.point_index])

    def log_state(self, iteration: int, chi2: float, first: bool = False) -> None:
        rec, p = self.rec, self.problem
        rec.set_iteration(iteration)
        poses, points = p.poses(), p.points()
        images = None
        if first:
            images = [np.clip(im, 0, 255).astype(np.uint8) for im in p.data.images]
            # The start stays visible at every later iteration, for comparison.
            rec.log_points(points, [150, 150, 150], entity="world/initial/points")
            rec.log_trajectory(transform_inverse(poses)[:, :3, 3],
                               entity="world/initial/trajectory")
            if p.data.true_poses is not None:
                rec.log_trajectory(transform_inverse(p.data.true_poses)[:, :3, 3],
                                   entity="world/truth/trajectory")
        rec.log_cameras(poses, images=images, **self.cam)
        rec.log_points(points, self.colors)
        rec.log_scalar("chi2", chi2)

    def close(self) -> None:
        self.rec.close()

    def abort(self) -> None:
        self.rec.abort()


# --------------------------------------------------------------------------------------------
# command line


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Direct (photometric) bundle adjustment of the task's data (DATA_DIR with "
        "poses.txt, points.txt, 0.png...) or, without DATA_DIR, of a synthetic textured scene.",
    )
    ap.add_argument("data_dir", nargs="?", metavar="DATA_DIR", help="data folder")
    ap.add_argument("--iterations", type=int, default=40, metavar="N",
                    help="LM iterations (default 40)")
    ap.add_argument("--robust", default="huber", metavar="KERNEL",
                    help="robust kernel: huber (default), cauchy, tukey, ... or none")
    ap.add_argument("--robust-delta", type=float, default=0.5, metavar="D",
                    help="kernel width on sqrt(e'e) (default 0.5, the task's)")
    ap.add_argument("--parametrization", choices=PARAMETRIZATIONS, default="xyz",
                    help="point parametrisation (default xyz)")
    ap.add_argument("--patch", type=int, choices=PATCHES, default=4,
                    help="patch side (default 4; other sizes need the synthetic scene)")
    ap.add_argument("--solver", choices=SOLVERS, default="auto",
                    help="linear solver of the reduced camera system (default auto: dense "
                         "Cholesky for a small dense system, else CHOLMOD)")
    ap.add_argument("--rrd", metavar="FILE", help="write a rerun recording")
    ap.add_argument("--png", metavar="FILE", help="write a top-down before/after picture")
    ap.add_argument("--json", metavar="FILE", help="write a JSON summary")
    ap.add_argument("--quiet", action="store_true", help="no iteration lines or summary")
    return ap


def _check_output(path: str | None, option: str) -> None:
    if path is None:
        return
    folder = Path(path).resolve().parent
    if not folder.is_dir():
        raise AppError(f"{option} {path}: folder {folder} does not exist")
    if Path(path).is_dir():
        raise AppError(f"{option} {path}: is a directory")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the app with parsed arguments; returns the JSON summary.

    Args:
        args: Parsed command line (see :func:`main`).

    Raises:
        AppError: Bad input or output location (one-line message).
    """
    from graphopt import GraphError, NotPositiveDefiniteError

    if args.iterations < 0:
        raise AppError("--iterations must be >= 0")
    if not (math.isfinite(args.robust_delta) and args.robust_delta > 0):
        raise AppError("--robust-delta must be a positive number")
    for path, opt in ((args.rrd, "--rrd"), (args.png, "--png"), (args.json, "--json")):
        _check_output(path, opt)
    out = sys.stdout
    say = (lambda *a: print(*a, file=out)) if not args.quiet else (lambda *a: None)

    t0 = time.perf_counter()
    try:
        if args.data_dir is not None:
            if args.patch != 4:
                raise AppError(f"--patch {args.patch}: the data's points.txt holds 4x4 patches; "
                               "other sizes work with the synthetic scene (no DATA_DIR)")
            data = load_directba(args.data_dir)
        else:
            data = synthetic_scene(patch=args.patch, **SYNTHETIC)
    except DirectBAFormatError as exc:
        raise AppError(str(exc)) from None
    load_s = time.perf_counter() - t0
    try:
        problem = build_problem(data, args.parametrization, args.robust, args.robust_delta,
                                args.solver, verbose=not args.quiet, stream=out)
    except (ValueError, GraphError) as exc:
        raise AppError(str(exc)) from None
    opt = problem.optimizer
    before = (problem.poses(), problem.points())
    opt.compute_active_errors()
    active0 = opt.active_edge_count()
    say(f"# {PROG}: {data.source}: {len(data.poses)} poses, {len(problem.point_index)} points "
        f"({problem.parametrization}), {problem.n_edges} edges, {active0} active, patch "
        f"{data.patch}x{data.patch}, robust {args.robust} {args.robust_delta:g}, "
        f"solver {args.solver}; load {load_s:.2f} s")
    if problem.dropped_points:
        say(f"# {problem.dropped_points} points behind every camera were left out")

    rr_log = None
    if args.rrd:
        rr_log = _RerunLog(args.rrd, problem)
        rr_log.log_state(0, opt.active_robust_chi2(), first=True)
        opt.add_callback("post_iteration",
                         lambda o, info: rr_log.log_state(info.iteration + 1, info.chi2))
    try:
        res = opt.optimize(args.iterations)
    except (NotPositiveDefiniteError, FloatingPointError) as exc:
        if rr_log:
            rr_log.abort()
        raise AppError(f"optimisation failed: {exc}") from None
    except BaseException:
        if rr_log:
            rr_log.abort()
        raise
    opt.compute_active_errors()
    summary: dict[str, Any] = {
        "source": data.source,
        "parametrization": problem.parametrization,
        "patch": data.patch,
        "robust": args.robust,
        "robust_delta": args.robust_delta,
        "solver": args.solver,
        "poses": len(data.poses),
        "points": len(problem.point_index),
        "edges": problem.n_edges,
        "active_edges": active0,
        "active_edges_final": opt.active_edge_count(),
        "initial_chi2": res.initial_chi2,
        "final_chi2": res.final_chi2,
        "iterations": res.iterations,
        "stop_reason": res.stop_reason,
        "seconds": res.seconds,
        "seconds_per_iteration": res.seconds_per_iteration,
        "chi2_history": res.chi2_history,
    }
    if data.true_poses is not None:
        summary.update(truth_report(problem))
    if rr_log:
        rr_log.rec.log_text(f"chi2 {res.initial_chi2:.6g} -> {res.final_chi2:.6g}")
        rr_log.close()
    if args.png:
        write_png(args.png, problem, before, (problem.poses(), problem.points()))
    if args.json:
        from graphopt.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump(summary, f, indent=2)
            f.write("\n")
    say(f"# chi2 {res.initial_chi2:.6g} -> {res.final_chi2:.6g} in {res.iterations} iterations "
        f"({res.stop_reason}), {res.seconds:.3f} s, {res.seconds_per_iteration:.4f} s/iteration; "
        f"active edges {active0} -> {summary['active_edges_final']} of {problem.n_edges}")
    if data.true_poses is not None:
        s = summary
        say(f"# vs truth: rotation {s['initial_rotation_error_deg_mean']:.3f} -> "
            f"{s['final_rotation_error_deg_mean']:.4f} deg (mean), translation "
            f"{s['initial_translation_error_m_mean'] * 100:.2f} -> "
            f"{s['final_translation_error_m_mean'] * 100:.3f} cm (mean; "
            f"{s['final_translation_error_scale_aligned_m_mean'] * 100:.3f} cm after scale "
            f"{s['final_scale']:.4f}), points "
            f"{s['initial_point_error_m_median'] * 100:.2f} -> "
            f"{s['final_point_error_m_median'] * 100:.3f} cm (median)")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point.

    Args:
        argv: Arguments (``sys.argv[1:]`` by default).

    Returns:
        Exit status: 0 on success, 1 on a runtime error, 2 on a usage error.
    """
    args = _parser().parse_args(argv)
    try:
        run(args)
    except AppError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
