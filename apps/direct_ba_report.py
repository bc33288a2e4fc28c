"""Reports of a direct-BA run: errors against the truth (synthetic scene), a top-down PNG of
cameras and points before/after, and the rerun recording.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from graphopt.apps._cli import RunRecording, write_png_image
from graphopt.apps.direct_ba_problem import DirectBAProblem
from graphopt.lie import so3_log, transform_inverse
from graphopt.recording_view import (
    BEFORE,
    MANY_OUTLIERS,
    OUTLIER,
    TRUTH,
    ErrorScale,
    outlier_mask,
    summary_markdown,
)

__all__ = ["DirectBARecording", "pose_errors", "recording_markdown", "truth_report", "write_png"]


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


#: Length in pixels of the largest (magnified) camera shift arrow; points use their 90th
#: percentile shift.
ARROW_PX = 60.0
#: About how many point shifts are drawn as arrows.
ARROW_POINTS = 300


def _magnification(shift_px: float) -> float:
    """Factor that stretches a ``shift_px``-pixel shift to :data:`ARROW_PX` (never below 1)."""
    return max(1.0, ARROW_PX / shift_px) if shift_px > 0 else 1.0


def _nice_length(x: float) -> float:
    """The largest of 1, 2, 5 × 10^k not above ``x``."""
    k = 10.0 ** np.floor(np.log10(x))
    return float(max(m * k for m in (1, 2, 5) if m * k <= x))


def _arrows(canvas: np.ndarray, start: np.ndarray, end: np.ndarray, mag: float,
            colour: tuple[int, int, int], width: int) -> None:
    """Arrows from ``start`` along ``(end − start) · mag`` (pixel coordinates)."""
    import cv2

    tips = start + (end - start) * mag
    for a, b in zip(start, tips, strict=True):
        if np.isfinite(a).all() and np.isfinite(b).all():
            cv2.arrowedLine(canvas, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), colour,
                            width, cv2.LINE_AA, tipLength=0.25)


def write_png(path: str | Path, problem: DirectBAProblem, before: tuple[np.ndarray, np.ndarray],
              after: tuple[np.ndarray, np.ndarray]) -> None:
    """Top-down (x–z) picture of cameras and points before (red/grey) and after (green/blue),
    with their shifts drawn as magnified arrows (factors in the legend) and a scale bar.

    Args:
        path: Destination ``.png`` (replaced atomically).
        problem: The problem (for the truth on the synthetic scene).
        before: ``(poses, points)`` before optimisation.
        after: ``(poses, points)`` after.
    """
    import cv2

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
    shift_c = float(np.linalg.norm(c_after - c_before, axis=1).max())
    ok = np.isfinite(before[1]).all(axis=1) & np.isfinite(after[1]).all(axis=1)
    moved = np.linalg.norm(after[1][ok] - before[1][ok], axis=1)
    shift_p = float(np.median(moved)) if ok.any() else float("nan")
    # The changes are far below a pixel at the scene's scale: draw them as arrows, magnified
    # so that the largest camera shift spans ARROW_PX pixels (points: their 90th percentile).
    mag_c = _magnification(shift_c * scale)
    _arrows(canvas, px(c_before), px(c_after), mag_c, (0, 120, 0), 2)
    idx = np.flatnonzero(ok)[:: max(1, int(ok.sum()) // ARROW_POINTS)]
    mag_p = _magnification(float(np.percentile(moved, 90)) * scale if len(moved) else 0.0)
    _arrows(canvas, px(before[1][idx]), px(after[1][idx]), mag_p, (200, 120, 40), 1)
    legend = [("cameras before", (0, 0, 220)), ("cameras after", (0, 160, 0)),
              ("points before", (170, 170, 170)), ("points after", (200, 120, 40)),
              (f"camera shifts (arrows) x{mag_c:.3g}", (0, 120, 0)),
              (f"point shifts (arrows, {len(idx)} points) x{mag_p:.3g}", (200, 120, 40))]
    if problem.data.true_poses is not None:
        legend.append(("true cameras", (0, 0, 0)))
    for i, (text, colour) in enumerate(legend):
        cv2.putText(canvas, text, (12, 22 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                    cv2.LINE_AA)
    bar = _nice_length(100.0 / scale)  # about 100 px of world units
    x1, y = size - pad, size - 40
    x0 = int(round(x1 - bar * scale))
    cv2.line(canvas, (x0, y), (x1, y), (0, 0, 0), 2)
    cv2.putText(canvas, f"{bar:g} world units", (x0, y - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, f"top view: x right, z up (world units); largest camera shift "
                f"{shift_c:.3g}, median point shift {shift_p:.3g}", (12, size - 12),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    write_png_image(path, canvas)


class DirectBARecording(RunRecording):
    """The run as a rerun recording.

    3-D (``world``, camera-like axes: x right, y down, z forward): ``world/before/points`` and
    ``world/before/cameras`` (centres) in grey, once; at every iteration ``world/after/points``
    coloured by each point's RMS photometric residual over its active patches and
    ``world/after/cameras/{k}`` (frusta); ``world/after/outliers`` (points with a patch the
    kernel down-weights at the end) at the last iteration. 2-D, one view per image:
    ``images/{k}/image`` once and ``images/{k}/patches`` (the patches' projections coloured by
    their RMS residual, on the same scale) at every iteration, ``images/{k}/outliers`` at the
    last. ``metrics/…`` and ``summary``.

    Args:
        path: Destination ``.rrd`` file.
        problem: The problem.
        prog: The app's name (rerun application id).
    """

    def __init__(self, path: str, problem: DirectBAProblem, prog: str) -> None:
        data = problem.data
        n, h, w = data.images.shape
        views = [(f"images/{k}", f"image {k}") for k in range(n)]
        # The data's world frame is camera-like (x right, y down, z forward).
        super().__init__(path, prog, camera_xyz="RDF", world_xyz="RDF",
                         blueprint={"world_name": "cameras and points", "images": views,
                                    "image_size": (w, h)})
        self.problem = problem
        fx, fy, cx, cy = data.intrinsics
        self.intrinsics = (fx, fy, cx, cy)
        # Per-camera (n, 2) arrays: Recorder reads a 1-D focal as one value per camera.
        self.cam = {"focal": np.tile([fx, fy], (n, 1)),
                    "principal_point": np.tile([cx, cy], (n, 1)),
                    "resolution": np.tile([w, h], (n, 1))}
        self.patch_pixels = data.patch * data.patch
        # Structure once: each photometric edge's image and point row (in point_index order).
        groups = [g for g in problem.optimizer.edge_groups() if "image" in g.data]
        self.groups = groups
        self.image = np.concatenate([g.data["image"] for g in groups]).astype(np.intp)
        vid = np.concatenate([g.vertex_ids[:, -1] for g in groups]) - n
        self.point = np.searchsorted(problem.point_index, vid).astype(np.intp)
        #: Per logged iteration, (per-edge RMS residual, per-point RMS residual).
        self.errors: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.scale: ErrorScale | None = None
        self.outliers = 0
        self.outliers_hidden = False

    def _residuals(self) -> tuple[np.ndarray, np.ndarray]:
        """RMS residual per pixel of each edge's patch, and of each point over its active
        patches (an inactive edge, projected off its image, has a zero error), at the optimizer's
        last evaluation."""
        chi2 = np.concatenate([g.last_chi2 for g in self.groups])
        edge = np.sqrt(np.maximum(chi2, 0.0) / self.patch_pixels)
        npts = len(self.problem.point_index)
        total = np.bincount(self.point, chi2, minlength=npts)
        count = np.bincount(self.point, chi2 > 0, minlength=npts)
        with np.errstate(all="ignore"):
            return edge, np.sqrt(total / (count * self.patch_pixels))

    def _pixels(self, poses: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``(m, 2)`` projection of each edge's point into its image."""
        fx, fy, cx, cy = self.intrinsics
        T = poses[self.image]
        pc = np.einsum("mij,mj->mi", T[:, :3, :3], points[self.point]) + T[:, :3, 3]
        with np.errstate(all="ignore"):
            uv = np.column_stack([fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy])
        return np.nan_to_num(uv, nan=-1e4, posinf=-1e4, neginf=-1e4)

    def log_state(self, iteration: int, chi2: float, first: bool = False,
                  seconds: float | None = None) -> None:
        """Log the current estimates and chi2.

        Args:
            iteration: Iteration number (0 = before optimisation).
            chi2: The robust chi2 at this iteration.
            first: Also log the images and the start (and true) trajectories, once.
            seconds: The iteration's wall time (None at iteration 0).
        """
        rec, p = self.rec, self.problem
        self.log_metrics(iteration, chi2, seconds)
        poses, points = p.poses(), np.nan_to_num(p.points())
        if first:
            for k, im in enumerate(p.data.images):
                rec.log_image(np.clip(im, 0, 255).astype(np.uint8), entity=f"images/{k}/image")
            rec.log_points(points, BEFORE, entity="world/before/points", radius=-1.0,
                           static=True)
            rec.log_points(transform_inverse(poses)[:, :3, 3], BEFORE,
                           entity="world/before/cameras", radius=-3.0, static=True)
            if p.data.true_poses is not None:
                rec.log_trajectory(transform_inverse(p.data.true_poses)[:, :3, 3],
                                   entity="world/truth/trajectory", color=TRUTH,
                                   radius=-0.75, static=True)
        rec.log_cameras(poses, entity="world/after/cameras", trajectory=False, **self.cam)
        rec.log_points(points, entity="world/after/points", radius=-1.5)
        uv = self._pixels(poses, points)
        for k in range(len(poses)):
            rec.log_points2d(uv[self.image == k], entity=f"images/{k}/patches", radius=-1.0)
        edge, point = self._residuals()
        self.errors.append((int(iteration), edge.astype(np.float32), point.astype(np.float32)))

    def finish(self) -> None:
        """Colour every logged iteration on the final residuals' scale and log the outliers
        (the optimizer's last evaluation must be at the final estimate)."""
        edge, _ = self._residuals()
        self.scale = ErrorScale.from_final(edge[edge > 0], "RMS photometric residual per "
                                           "pixel of a patch (points: over their patches)",
                                           "grey levels")
        n = len(self.problem.data.images)
        for iteration, e, pt in self.errors:
            self.rec.set_iteration(iteration)
            self.rec.log_colors(self.scale.colors(pt), entity="world/after/points")
            colors = self.scale.colors(e)
            for k in range(n):
                self.rec.log_colors(colors[self.image == k], entity=f"images/{k}/patches",
                                    kind="points2d")
        self.errors = []
        self.rec.set_iteration(self.iteration)
        out = np.concatenate([outlier_mask(g) for g in self.groups])
        self.outliers = int(out.sum())
        self.outliers_hidden = self.outliers > MANY_OUTLIERS * len(out)
        if self.outliers_hidden:
            self.hide(["world/after/outliers", *[f"images/{k}/outliers" for k in range(n)]])
        if out.any():
            p = self.problem
            points = np.nan_to_num(p.points())
            self.rec.log_points(points[np.unique(self.point[out])], OUTLIER,
                                entity="world/after/outliers", radius=-2.5)
            uv = self._pixels(p.poses(), points)
            for k in range(n):
                pick = out & (self.image == k)
                self.rec.log_points2d(uv[pick], OUTLIER, entity=f"images/{k}/outliers",
                                      radius=-0.75)


def recording_markdown(prog: str, s: dict[str, Any], rec: DirectBARecording,
                       solver_text: str) -> str:
    """The recording's summary document.

    Args:
        prog: The app's name.
        s: The app's summary dictionary.
        rec: The recording (its colour scale and outliers).
        solver_text: How to name the linear solver.
    """
    rows = [
        ("input", f"`{s['input']}`"),
        ("size", f"{s['poses']} images, {s['points']} points ({s['parametrization']})"),
        ("edges", f"{s['edges']} patches {s['patch']}x{s['patch']}; active "
                  f"{s['active_edges']} → {s['active_edges_final']}"),
        ("algorithm", s["algorithm"]),
        ("linear solver", solver_text),
        ("robust kernel", s["robust_kernel"] or "none"),
        ("stop", f"{s['stop_reason']} after {s['iterations']} iterations"),
        ("chi2", f"{s['initial_chi2']:.6g} → {s['final_chi2']:.6g} (robust, Σ ρ(e'e))"),
        ("seconds", f"{s['seconds']:.3f} ({s['seconds_per_iteration']:.4f} per iteration, "
                    "without the recording)"),
    ]
    if "final_rotation_error_deg_mean" in s:
        rows.append(("vs truth", f"rotation {s['initial_rotation_error_deg_mean']:.3g} → "
                                 f"{s['final_rotation_error_deg_mean']:.3g} deg (mean), points "
                                 f"{s['initial_point_error_m_median']:.3g} → "
                                 f"{s['final_point_error_m_median']:.3g} (median)"))
    notes = [] if rec.scale is None else [rec.scale.legend()]
    share = rec.outliers / max(s["edges"], 1)
    notes.append(
        "**Entities**: `world/before` the start (grey; toggle it with its eye in the blueprint "
        "panel), `world/after` the estimate at the selected iteration, `images/{k}` each image "
        "with its patches' projections"
        + (f"; `outliers` ({rec.outliers} patches, {100 * share:.0f} % of the edges, that the "
           "kernel down-weights at the end: ρ' < 1 beyond its width) in magenta"
           + (", hidden at first: the kernel is narrower than most residuals (show them with "
              "their eye)" if rec.outliers_hidden else "") if rec.outliers else "")
        + ". Scrub the `iteration` timeline to replay the run.")
    return summary_markdown(prog, rows, notes)
