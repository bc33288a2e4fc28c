"""What ``graphopt-bal`` records: the reconstruction at every iteration, coloured by each point's
RMS reprojection error, with the start, the robust-kernel outliers, the cost and a summary.

Entities (layout of :mod:`graphopt.recording_view`): ``world/before/points`` and
``world/before/cameras`` (camera centres), the start in grey, logged once;
``world/after/points`` (coloured by the error at that iteration, on the final run's scale) and
``world/after/cameras/{k}`` (frusta; BAL cameras look down −z) at every iteration;
``world/after/outliers`` (points with an observation the kernel down-weights at the end) at the
last iteration; ``metrics/…`` and ``summary``. Frames that differ by less than a person can see
are not drawn again (:data:`STILL`), which bounds the file of a long run.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.apps._cli import RunRecording
from graphopt.io.bal import BALProblem
from graphopt.lie import make_transform, so3_exp, transform_inverse
from graphopt.recording_view import BEFORE, OUTLIER, ErrorScale, outlier_mask, summary_markdown
from graphopt.types.bal import EdgeBALProjection, reprojection_errors

__all__ = ["MAX_POINTS", "STILL", "BALRecording", "cameras_to_poses", "point_rms",
           "recording_markdown"]

#: At most this many points are recorded (an evenly spaced subset beyond): the viewer cannot show
#: more as separate dots, and the file grows with every iteration.
MAX_POINTS = 100_000
#: An iteration whose points all moved less than this fraction of the scene's scale (and whose
#: errors changed by less than 1 %) is not drawn again: the viewer shows the last frame drawn
#: (its cost and time are still logged). The last iteration is always drawn.
STILL = 1e-4
#: Observations projected per pass (bounds the temporary arrays).
CHUNK = 1 << 20


def cameras_to_poses(cams: np.ndarray) -> np.ndarray:
    """``(c, 4, 4)`` world-to-camera transforms of BAL cameras ``(c, 9)``."""
    return make_transform(so3_exp(cams[:, :3]), cams[:, 3:6])


def point_rms(problem: BALProblem, cams: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Per-point RMS reprojection error (pixels) over the point's observations.

    Args:
        problem: The problem (observations and their indices).
        cams: ``(c, 9)`` cameras.
        pts: ``(n, 3)`` points.

    Returns:
        ``(n,)`` errors; NaN for a point without observations.
    """
    n = len(pts)
    total = np.zeros(n)
    for lo in range(0, problem.num_observations, CHUNK):
        part = BALProblem(cams, pts, problem.camera_index[lo:lo + CHUNK],
                          problem.point_index[lo:lo + CHUNK], problem.observations[lo:lo + CHUNK])
        with np.errstate(all="ignore"):
            r, _ = reprojection_errors(part)
        total += np.bincount(part.point_index, np.einsum("ij,ij->i", r, r), minlength=n)
    count = np.bincount(problem.point_index, minlength=n)
    with np.errstate(all="ignore"):
        return np.sqrt(total / count)


class BALRecording(RunRecording):
    """The run as a rerun recording (see the module's docstring for the entities).

    Args:
        path: Destination ``.rrd`` file.
        prog: The app's name (rerun application id).
        problem: The problem (observations give each camera's image extent).
        scene_scale: Typical camera-to-scene distance (frustum depth is 5 % of it).
    """

    def __init__(self, path: str, prog: str, problem: BALProblem, scene_scale: float) -> None:
        super().__init__(path, prog, camera_xyz="RUB",
                         blueprint={"world_name": "cameras and points"})
        self.problem = problem
        # Image size is not in BAL files: use the extent of each camera's observations.
        ext = np.zeros((problem.num_cameras, 2))
        np.maximum.at(ext, problem.camera_index, np.abs(problem.observations))
        self.resolution = np.maximum(2.0 * ext, 2.0)
        self.plane = 0.05 * scene_scale
        self.scene_scale = scene_scale
        n = problem.num_points
        self.shown = (np.arange(n) if n <= MAX_POINTS
                      else np.unique(np.linspace(0, n - 1, MAX_POINTS).astype(np.intp)))
        #: Per logged iteration, the shown points' errors (coloured at the end, on one scale).
        self.errors: list[tuple[int, np.ndarray]] = []
        self.scale: ErrorScale | None = None
        self.outliers = 0
        #: The last frame logged (shown points, errors) and a skipped one not yet logged.
        self.last: tuple[np.ndarray, np.ndarray] = (np.zeros((0, 3)), np.zeros(0))
        self.pending: tuple[int, np.ndarray, np.ndarray] | None = None

    def log_start(self, cams: np.ndarray, pts: np.ndarray, cost: float) -> None:
        """Log the start: once in grey (``world/before``), and as iteration 0.

        Args:
            cams: ``(c, 9)`` cameras.
            pts: ``(n, 3)`` points.
            cost: ``½Σ‖r‖²``.
        """
        self.rec.log_points(pts[self.shown], BEFORE, entity="world/before/points", radius=-1.0,
                            static=True)
        centers = transform_inverse(cameras_to_poses(cams))[:, :3, 3]
        self.rec.log_points(centers, BEFORE, entity="world/before/cameras", radius=-3.0,
                            static=True)
        self.log_state(0, cams, pts, cost)

    def log_state(self, iteration: int, cams: np.ndarray, pts: np.ndarray, cost: float,
                  seconds: float | None = None) -> None:
        """Log the estimates, the cost and the iteration's seconds.

        Args:
            iteration: Iteration number (0 = before optimisation).
            cams: ``(c, 9)`` cameras.
            pts: ``(n, 3)`` points.
            cost: ``½Σ‖r‖²``.
            seconds: The iteration's wall time (None at iteration 0).
        """
        self.log_metrics(iteration, cost, seconds)
        # Non-finite points would be dropped and misalign the colours logged at the end.
        shown = np.nan_to_num(pts[self.shown], nan=0.0, posinf=0.0, neginf=0.0)
        self.rec.log_cameras(
            cameras_to_poses(cams), focal=np.abs(cams[:, 6]), resolution=self.resolution,
            principal_point=self.resolution / 2.0, image_plane_distance=self.plane,
            entity="world/after/cameras", trajectory=False)
        err = point_rms(self.problem, cams, pts)[self.shown].astype(np.float32)
        if iteration and self._invisible(shown, err):
            self.pending = (int(iteration), shown, err)  # logged by finish() if it is the last
            return
        self._log_frame(int(iteration), shown, err)

    def _invisible(self, shown: np.ndarray, err: np.ndarray) -> bool:
        """Whether a frame differs from the last one logged by less than a person can see:
        every point moved less than :data:`STILL` of the scene's scale and no error changed
        by 1 %."""
        moved = float(np.abs(shown - self.last[0]).max(initial=0.0))
        with np.errstate(all="ignore"):
            change = np.abs(err - self.last[1]) / np.maximum(self.last[1], 1e-6)
        return moved < STILL * self.scene_scale and float(np.nanmax(change, initial=0.0)) < 0.01

    def _log_frame(self, iteration: int, shown: np.ndarray, err: np.ndarray) -> None:
        """Log a frame's points and keep its errors for the colours."""
        self.rec.set_iteration(iteration)
        self.rec.log_points(shown, None, entity="world/after/points", radius=-1.5)
        self.errors.append((iteration, err))
        self.last = (shown, err)
        self.pending = None

    def finish(self, opt: Any, pts: np.ndarray) -> None:
        """Colour every logged iteration on the final errors' scale and log the outliers.

        Args:
            opt: The optimizer after the run (its edges' robust kernels and errors).
            pts: ``(n, 3)`` final points.
        """
        if self.pending is not None:  # the end is always shown exactly
            self._log_frame(*self.pending)
        self.scale = ErrorScale.from_final(self.errors[-1][1], "per-point RMS reprojection "
                                           "error", "px")
        for iteration, err in self.errors:
            self.rec.set_iteration(iteration)
            self.rec.log_colors(self.scale.colors(err), entity="world/after/points")
        self.errors = []
        opt.compute_active_errors()
        groups = [g for g in opt.edge_groups() if g.etype is EdgeBALProjection]
        mask = np.concatenate([outlier_mask(g) for g in groups]) if groups else np.zeros(0, bool)
        self.rec.set_iteration(self.iteration)
        if mask.any():
            points = np.unique(self.problem.point_index[mask])
            self.outliers = int(mask.sum())
            self.rec.log_points(pts[points], OUTLIER, entity="world/after/outliers",
                                radius=-3.0)


def recording_markdown(prog: str, s: dict[str, Any], rec: BALRecording) -> str:
    """The recording's summary document.

    Args:
        prog: The app's name.
        s: The app's summary dictionary.
        rec: The recording (its colour scale, shown points and outliers).
    """
    lm = f" ({s['lm_schedule']} schedule, {s['lm_damping']} damping)" if s.get("lm_damping") \
        else ""
    shown = len(rec.shown)
    rows = [
        ("input", f"`{s['input']}`"),
        ("size", f"{s['cameras']} cameras, {s['points']} points, {s['observations']} "
                 "observations"),
        ("algorithm", f"{s['algorithm']}{lm}"),
        ("linear solver", s["solver_text"]),
        ("robust kernel", s["robust_kernel"] or "none"),
        ("stop", f"{s['stop_reason']} after {s['iterations']} iterations"),
        ("chi2", f"{s['initial_chi2']:.6g} → {s['final_chi2']:.6g}"),
        ("RMS reprojection error", f"{s['initial_rms_px']:.4g} px → {s['rms_px']:.4g} px"),
        ("seconds", f"{s['seconds']:.3f} ({s['seconds_per_iteration']:.4f} per iteration, "
                    "without the recording)"),
    ]
    notes = []
    if rec.scale is not None:
        notes.append(rec.scale.legend())
    notes.append(
        "**Entities**: `world/before` the start (grey; toggle it with its eye in the blueprint "
        "panel), `world/after` the estimate at the selected iteration"
        + (f" ({shown} of {s['points']} points, evenly spaced)" if shown < s["points"] else "")
        + (f", `world/after/outliers` ({rec.outliers} observations the kernel down-weights "
           "at the end: ρ' < 1 beyond its width) in magenta" if rec.outliers else "")
        + ". Scrub the `iteration` timeline to replay the run.")
    return summary_markdown(f"{prog}", rows, notes)
