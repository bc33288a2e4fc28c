"""What ``graphopt-g2o`` shows of a SLAM graph: the poses and landmarks in id order
(:class:`GraphView`), a top-down before/after PNG (:func:`write_png`) and a rerun recording
(:class:`SlamRecording`).

Poses are drawn as one trajectory in id order (the order of odometry in every data set here);
pose-pose edges between poses that are not neighbours in that order are loop closures. 3D graphs
are projected onto the x–y plane in the PNG; 2D graphs lie in the plane ``z = 0`` of the
recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graphopt.apps._cli import RunRecording, write_png_image
from graphopt.optimizer import SparseOptimizer
from graphopt.recording_view import (
    BEFORE,
    OUTLIER,
    TRUTH,
    ErrorScale,
    outlier_mask,
    summary_markdown,
)
from graphopt.types.slam_graph import VERTEX_TYPES, SlamGraph

__all__ = ["GraphView", "SlamRecording", "graph_view", "recording_markdown", "write_png"]

_POSE_TAGS = ("VERTEX_SE2", "VERTEX_SE3:QUAT")
_POINT_TAGS = ("VERTEX_XY", "VERTEX_TRACKXYZ")
_POSE_EDGES = ("EDGE_SE2", "EDGE_SE3:QUAT")


def _xyz(tag: str, est: np.ndarray) -> np.ndarray:
    """``(n, 3)`` positions of a tag's estimates (``z = 0`` for 2D)."""
    if tag == "VERTEX_SE3:QUAT":
        return est[:, :, 3].copy()
    if tag == "VERTEX_TRACKXYZ":
        return np.array(est[:, :3], dtype=float)
    out = np.zeros((len(est), 3))
    out[:, :2] = est[:, :2]
    return out


@dataclass
class GraphView:
    """The positions of a built graph's poses and landmarks, in id order.

    Args:
        optimizer: The optimizer holding the graph.
        pose_ids: ``(n,)`` pose ids, sorted.
        closures: ``(c, 2)`` indices into the poses of the pose-pose edges that do not join
            neighbours in id order (loop closures).
        dimension: 2 or 3 (3 if any pose is 3D).
        parts: Per vertex tag present: ``(tag, order)``, the permutation that sorts the
            optimizer's estimates of that tag by id.
    """

    optimizer: SparseOptimizer
    pose_ids: np.ndarray
    closures: np.ndarray
    dimension: int
    parts: list[tuple[str, np.ndarray]]

    def _gather(self, tags: tuple[str, ...]) -> np.ndarray:
        blocks = [_xyz(tag, self.optimizer.estimates_of(VERTEX_TYPES[tag])[order])
                  for tag, order in self.parts if tag in tags]
        return np.concatenate(blocks) if blocks else np.zeros((0, 3))

    def poses(self) -> np.ndarray:
        """``(n, 3)`` pose positions in id order (``z = 0`` for 2D poses)."""
        return self._gather(_POSE_TAGS)

    def landmarks(self) -> np.ndarray:
        """``(k, 3)`` landmark positions in id order (``z = 0`` for 2D points)."""
        return self._gather(_POINT_TAGS)

    def headings(self) -> np.ndarray:
        """``(n,)`` headings of 2D poses in id order (empty for 3D graphs)."""
        blocks = [self.optimizer.estimates_of(VERTEX_TYPES[tag])[order][:, 2]
                  for tag, order in self.parts if tag == "VERTEX_SE2"]
        return np.concatenate(blocks) if blocks else np.zeros(0)


def graph_view(slam: SlamGraph) -> GraphView:
    """The view of a graph built by :func:`graphopt.types.slam_graph.build_graph`.

    Args:
        slam: The built graph.

    Returns:
        The :class:`GraphView`.
    """
    opt = slam.optimizer
    parts = []
    for tag in (*_POSE_TAGS, *_POINT_TAGS):
        if tag in slam.vertex_ids:
            parts.append((tag, np.argsort(opt.ids_of(VERTEX_TYPES[tag]), kind="stable")))
    pose_ids = np.concatenate([np.sort(opt.ids_of(VERTEX_TYPES[t])) for t, _ in parts
                               if t in _POSE_TAGS] or [np.zeros(0, np.int64)])
    pairs = [slam.edges[t].ids for t in _POSE_EDGES if t in slam.edges]
    ids = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
    order = np.argsort(pose_ids)
    index = order[np.searchsorted(pose_ids, ids, sorter=order)] if len(ids) else ids
    closures = index[np.abs(index[:, 0] - index[:, 1]) != 1]
    return GraphView(opt, pose_ids, closures.reshape(-1, 2),
                     3 if "VERTEX_SE3:QUAT" in slam.vertex_ids else 2, parts)


# --------------------------------------------------------------------------------------------
# PNG
# --------------------------------------------------------------------------------------------

_PANEL, _PAD, _HEAD = 720, 64, 36
_BEFORE, _AFTER, _TRUTH = (40, 40, 215), (190, 100, 20), (150, 150, 150)  # BGR
_BLACK = (0, 0, 0)
#: The after panel also shows the start (faint) when its extent is at most this times the result's.
_OVERLAY_SPAN = 1.5


def _faint(colour: tuple[int, int, int], alpha: float = 0.2) -> tuple[int, int, int]:
    """``colour`` blended with white."""
    return tuple(int(round(255 - alpha * (255 - c))) for c in colour)  # type: ignore[return-value]


def _nice_step(span: float) -> float:
    """A 1-2-5 tick step giving about 5 ticks over ``span``."""
    raw = span / 5.0
    base = 10.0 ** math.floor(math.log10(raw))
    return next(m * base for m in (1.0, 2.0, 5.0, 10.0) if m * base >= raw)


def _span(points: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper x–y corner of the finite ``points``."""
    xy = np.concatenate([p[:, :2] for p in points])
    xy = xy[np.isfinite(xy).all(axis=1)]
    return (xy.min(0), xy.max(0)) if len(xy) else (np.zeros(2), np.ones(2))


@dataclass
class _Frame:
    """Maps x–y world coordinates into a square panel, equal scales, 3 % margins."""

    lo: np.ndarray
    scale: float

    @classmethod
    def around(cls, points: list[np.ndarray]) -> _Frame:
        lo, hi = _span(points)
        span = 1.06 * max(float((hi - lo).max()), 1e-9)
        return cls((lo + hi) / 2 - span / 2, (_PANEL - 2 * _PAD) / span)

    def px(self, xy: np.ndarray) -> np.ndarray:
        u = _PAD + (xy[:, 0] - self.lo[0]) * self.scale
        v = _PANEL - _PAD - (xy[:, 1] - self.lo[1]) * self.scale
        return np.round(np.column_stack([u, v]).clip(-1e5, 1e5)).astype(np.int32)


def _axes(panel: np.ndarray, f: _Frame, units: str) -> None:
    """Frame, ticks with values and axis labels of one panel."""
    import cv2

    x0, y0, x1, y1 = _PAD, _PAD, _PANEL - _PAD, _PANEL - _PAD
    panel[:y0 - 1] = panel[y1 + 1:] = 255  # clip what was drawn outside the frame
    panel[:, :x0 - 1] = panel[:, x1 + 1:] = 255
    cv2.rectangle(panel, (x0, y0), (x1, y1), _BLACK, 1)
    span = (_PANEL - 2 * _PAD) / f.scale
    step = _nice_step(span)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for axis in (0, 1):
        first = math.ceil(f.lo[axis] / step) * step
        for value in np.arange(first, f.lo[axis] + span + 1e-9 * step, step):
            label = f"{value:g}"
            width = cv2.getTextSize(label, font, 0.4, 1)[0][0]
            if axis == 0:
                u = int(round(x0 + (value - f.lo[0]) * f.scale))
                cv2.line(panel, (u, y1), (u, y1 + 5), _BLACK, 1)
                cv2.putText(panel, label, (u - width // 2, y1 + 20), font, 0.4, _BLACK, 1,
                            cv2.LINE_AA)
            else:
                v = int(round(y1 - (value - f.lo[1]) * f.scale))
                cv2.line(panel, (x0 - 5, v), (x0, v), _BLACK, 1)
                cv2.putText(panel, label, (x0 - 9 - width, v + 4), font, 0.4, _BLACK, 1,
                            cv2.LINE_AA)
    cv2.putText(panel, f"x [{units}]", ((x0 + x1) // 2 - 30, y1 + 42), font, 0.5, _BLACK, 1,
                cv2.LINE_AA)
    cv2.putText(panel, f"y [{units}]", (4, y0 - 10), font, 0.5, _BLACK, 1, cv2.LINE_AA)


def _draw_graph(panel: np.ndarray, f: _Frame, poses: np.ndarray, landmarks: np.ndarray,
                closures: np.ndarray, colour: tuple[int, int, int], faint: bool = False) -> None:
    """Loop closures (faint), the trajectory and the landmarks (crosses) in ``colour``; all
    faint if ``faint``."""
    import cv2

    q = f.px(poses[:, :2])
    if len(closures) and not faint:
        segs = q[closures].reshape(-1, 2, 1, 2)
        cv2.polylines(panel, list(segs), False, _faint(colour), 1, cv2.LINE_AA)
    line = _faint(colour, 0.45) if faint else colour
    if len(q) > 1:
        cv2.polylines(panel, [q.reshape(-1, 1, 2)], False, line, 1, cv2.LINE_AA)
    for p in f.px(landmarks[:, :2])[:5000]:
        cv2.drawMarker(panel, (int(p[0]), int(p[1])), line, cv2.MARKER_CROSS, 7, 1)


def write_png(
    path: str | Path,
    view: GraphView,
    before: tuple[np.ndarray, np.ndarray],
    after: tuple[np.ndarray, np.ndarray],
    *,
    titles: tuple[str, str],
    truth: np.ndarray | None = None,
    units: str = "file units",
) -> None:
    """Two top-down (x–y) panels: the graph before (red) and after (blue) optimisation.

    Each panel has its own scale (a drifting start can span far more than the result), equal
    for x and y, with ticks in the graph's units; loop closures are drawn faint, landmarks as
    crosses and the true trajectory (generated graphs) in grey beneath both. Where the start
    spans at most 1.5 times the result, the after panel shows it faint too, on one scale.

    Args:
        path: Destination ``.png`` (replaced atomically).
        view: The graph's view (loop closures, dimension).
        before: ``(poses (n, 3), landmarks (k, 3))`` positions before optimisation.
        after: The same after optimisation.
        titles: One line above each panel.
        truth: ``(n, 3)`` true pose positions, if known.
        units: Name of the length unit on the axes.
    """
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    extra = [truth] if truth is not None else []
    sizes = [float((hi - lo).max()) for lo, hi in (_span([*before, *extra]),
                                                    _span([*after, *extra]))]
    overlay = sizes[0] <= _OVERLAY_SPAN * max(sizes[1], 1e-12)
    panels = []
    for k, ((poses, marks), colour, title) in enumerate(
            ((before, _BEFORE, titles[0]), (after, _AFTER, titles[1]))):
        panel = np.full((_PANEL, _PANEL, 3), 255, np.uint8)
        shown = [poses, marks, *extra] + ([*before] if k == 1 and overlay else [])
        f = _Frame.around(shown)
        if truth is not None and len(truth) > 1:
            cv2.polylines(panel, [f.px(truth[:, :2]).reshape(-1, 1, 2)], False, _TRUTH, 3,
                          cv2.LINE_AA)
        if k == 1 and overlay:
            _draw_graph(panel, f, *before, view.closures, _BEFORE, faint=True)
        _draw_graph(panel, f, poses, marks, view.closures, colour)
        _axes(panel, f, units)
        cv2.putText(panel, title, (_PAD, _PAD - 28), font, 0.5, colour, 1, cv2.LINE_AA)
        panels.append(panel)
    head = np.full((_HEAD, 2 * _PANEL, 3), 255, np.uint8)
    legend = [("before", _BEFORE), ("after", _AFTER)]
    if overlay:
        legend[0] = ("before (faint in the after panel)", _BEFORE)
    if len(view.closures):
        legend.append(("loop closures (faint)", _faint(_AFTER, 0.5)))
    if len(before[1]):
        legend.append(("landmarks (+)", _BLACK))
    if truth is not None:
        legend.append(("ground truth", _TRUTH))
    view_name = "3D graph projected onto x-y:" if view.dimension == 3 else "top view:"
    cv2.putText(head, view_name, (12, 24), font, 0.55, _BLACK, 1, cv2.LINE_AA)
    x = 12 + cv2.getTextSize(view_name, font, 0.55, 1)[0][0] + 24
    for text, colour in legend:
        cv2.line(head, (x, 19), (x + 24, 19), colour, 3)
        cv2.putText(head, text, (x + 30, 24), font, 0.55, _BLACK, 1, cv2.LINE_AA)
        x += 30 + cv2.getTextSize(text, font, 0.55, 1)[0][0] + 24
    canvas = np.vstack([head, np.hstack(panels)])
    write_png_image(path, canvas)


# --------------------------------------------------------------------------------------------
# rerun
# --------------------------------------------------------------------------------------------


class SlamRecording(RunRecording):
    """The optimisation as a rerun recording on the ``iteration`` timeline.

    ``world/before/trajectory`` and ``world/before/landmarks``: the start in grey, logged once;
    at every iteration ``world/after/trajectory`` (the odometry edges, consecutive poses, as
    segments), ``world/after/loop_closures`` (the other pose-pose edges) and
    ``world/after/landmarks``, coloured by each edge's chi2 ``e'Ωe`` (landmarks: the mean over
    their edges) on the final run's scale; ``world/after/outliers`` (edges the robust kernel
    down-weights at the end) at the last iteration; ``world/truth/trajectory`` (generated
    graphs) once; ``metrics/…`` and ``summary``.

    Args:
        path: Destination ``.rrd`` file.
        prog: The app's name (rerun application id).
        view: The graph's view.
        timeline: The time panel's timeline: ``"step"`` for an online run (pass ``step`` to
            :meth:`log_state`; each step's iterations may restart at 0).
    """

    def __init__(self, path: str, prog: str, view: GraphView, timeline: str = "iteration"
                 ) -> None:
        poses = view.poses()
        eye = None
        if view.dimension == 2 and len(poses):  # a planar graph: look straight down on it
            lo, hi = poses.min(0), poses.max(0)
            c = (lo + hi) / 2.0
            span = float(max((hi - lo)[:2].max(), 1e-9))
            eye = ((c[0], c[1], 1.1 * span), (c[0], c[1], 0.0), (0.0, 1.0, 0.0))
        super().__init__(path, prog, camera_xyz="RDF",
                         blueprint={"world_name": "poses and edges", "eye": eye,
                                    "timeline": timeline})
        #: Per logged iteration, (step, iteration, pose-pose chi2, landmark mean chi2, the
        #: odometry mask of the pose-pose edges), coloured at the end.
        self.errors: list[tuple[int | None, int, np.ndarray, np.ndarray, np.ndarray]] = []
        self.scale: ErrorScale | None = None
        self.outliers = 0
        self.relayout(view)

    def relayout(self, view: GraphView) -> None:
        """Lay out the graph's edges again (an online run's graph grew since the last step).

        Args:
            view: The view of the graph as it is now (:func:`graph_view`).
        """
        self.view = view
        opt = view.optimizer
        marks = [np.sort(opt.ids_of(VERTEX_TYPES[t])) for t, _ in view.parts
                 if t in _POINT_TAGS]
        self.landmark_ids = np.concatenate(marks) if marks else np.zeros(0, np.int64)
        # Structure once per layout: per group of pose-pose or pose-landmark edges, the rows it
        # joins.
        self.groups: list[tuple[Any, np.ndarray, np.ndarray, bool]] = []
        for g in opt.edge_groups():
            name = g.etype.__name__
            if name in ("EdgeSE2", "EdgeSE3") and len(view.pose_ids):
                a, b = _rows(view.pose_ids, g.vertex_ids[:, 0]), _rows(view.pose_ids,
                                                                      g.vertex_ids[:, 1])
                self.groups.append((g, a, b, False))
            elif name in ("EdgeSE2PointXY", "EdgeSE3PointXYZ") and len(self.landmark_ids):
                self.groups.append((g, _rows(view.pose_ids, g.vertex_ids[:, 0]),
                                    _rows(self.landmark_ids, g.vertex_ids[:, 1]), True))
        pp = [(a, b) for _, a, b, mark in self.groups if not mark]
        a = np.concatenate([x for x, _ in pp]) if pp else np.zeros(0, np.intp)
        b = np.concatenate([y for _, y in pp]) if pp else np.zeros(0, np.intp)
        self.odometry = np.abs(a - b) == 1
        self.pairs = np.column_stack([a, b])

    def _chi2(self) -> tuple[np.ndarray, np.ndarray]:
        """Per pose-pose edge chi2 and per landmark mean chi2 at the last evaluation."""
        pp = [g.last_chi2 for g, _, _, mark in self.groups if not mark]
        edges = np.concatenate(pp) if pp else np.zeros(0)
        total = np.zeros(len(self.landmark_ids))
        count = np.zeros(len(self.landmark_ids))
        for g, _, b, mark in self.groups:
            if mark:
                total += np.bincount(b, g.last_chi2, minlength=len(total))
                count += np.bincount(b, minlength=len(total))
        with np.errstate(all="ignore"):
            return edges, total / count

    def log_state(self, iteration: int, chi2: float, *, seconds: float | None = None,
                  truth: np.ndarray | None = None, step: int | None = None) -> None:
        """Log the current estimates (at the optimizer's last evaluation) and chi2.

        Online runs call it with ``step`` (the ``step`` timeline) for every iteration of every
        step, and :meth:`relayout` first when the graph grew.

        Args:
            iteration: Iteration number (0 = before optimisation).
            chi2: chi2 at this iteration.
            seconds: The iteration's wall time (None at iteration 0).
            truth: True pose positions to log (once, at the start).
            step: The step (online runs), or None.
        """
        rec, view = self.rec, self.view
        self.log_metrics(iteration, chi2, seconds, step)
        poses, marks = view.poses(), view.landmarks()
        if not self.errors:  # the first state: the start
            rec.log_trajectory(poses, entity="world/before/trajectory", color=BEFORE,
                               radius=-0.75, static=True)
            if len(marks):
                rec.log_points(marks, BEFORE, entity="world/before/landmarks", radius=-1.5,
                               static=True)
            if truth is not None:
                rec.log_trajectory(truth, entity="world/truth/trajectory", color=TRUTH,
                                   radius=-0.75, static=True)
        poses = np.nan_to_num(poses)  # segments must stay aligned with their colours
        odo, closing = self.pairs[self.odometry], self.pairs[~self.odometry]
        rec.log_segments(poses[odo[:, 0]], poses[odo[:, 1]], entity="world/after/trajectory",
                         radius=-1.25)
        if len(closing):
            rec.log_segments(poses[closing[:, 0]], poses[closing[:, 1]],
                             entity="world/after/loop_closures", radius=-0.75)
        if len(marks):
            rec.log_points(np.nan_to_num(marks), entity="world/after/landmarks", radius=-2.0)
        edges, landmarks = self._chi2()
        self.errors.append((step, int(iteration), edges.astype(np.float32),
                            landmarks.astype(np.float32), self.odometry))

    def finish(self) -> None:
        """Colour every logged iteration on the final chi2's scale and log the outliers
        (the optimizer's last evaluation must be at the final estimate)."""
        final_edges, _ = self._chi2()
        every = [final_edges] + [g.last_chi2 for g, _, _, mark in self.groups if mark]
        self.scale = ErrorScale.from_final(
            np.concatenate(every), "chi2 e'Ωe of each edge"
            + (" (landmarks: the mean of their edges)" if len(self.landmark_ids) else ""))
        for step, iteration, edges, landmarks, odometry in self.errors:
            if step is not None:
                self.rec.set_step(step)
            self.rec.set_iteration(iteration)
            colors = self.scale.colors(edges)
            self.rec.log_colors(colors[odometry], entity="world/after/trajectory",
                                kind="lines")
            if (~odometry).any():
                self.rec.log_colors(colors[~odometry], entity="world/after/loop_closures",
                                    kind="lines")
            if len(landmarks):
                self.rec.log_colors(self.scale.colors(landmarks), entity="world/after/landmarks")
        self.errors = []
        if self.step is not None:
            self.rec.set_step(self.step)
        self.rec.set_iteration(self.iteration)
        poses, marks = self.view.poses(), self.view.landmarks()
        starts, ends = [], []
        for g, a, b, mark in self.groups:
            out = outlier_mask(g)
            starts.append(poses[a[out]])
            ends.append((marks if mark else poses)[b[out]])
            self.outliers += int(out.sum())
        if self.outliers:
            self.rec.log_segments(np.concatenate(starts), np.concatenate(ends),
                                  entity="world/after/outliers", color=OUTLIER, radius=-2.5)


def _rows(sorted_ids: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Rows of ``ids`` in ``sorted_ids`` (every id must be there)."""
    return np.searchsorted(sorted_ids, ids).astype(np.intp)


def recording_markdown(prog: str, s: dict[str, Any], rec: SlamRecording,
                       solver_text: str) -> str:
    """The recording's summary document.

    Args:
        prog: The app's name.
        s: The app's summary dictionary.
        rec: The recording (its colour scale and outliers).
        solver_text: How to name the linear solver.
    """
    counts = ", ".join(f"{t} {n}" for t, n in s["edge_types"].items())
    robust = (f"; with the kernel {s['initial_robust_chi2']:.6g} → "
              f"{s['final_robust_chi2']:.6g}" if s["robust_kernel"] else "")
    rows = [
        ("input", f"`{s['input']}`"),
        ("size", f"{s['vertices']} vertices, {s['edges']} edges ({counts}), "
                 f"{s['loop_closures']} loop closures"),
        ("algorithm", s["algorithm"] + (f" ({s['lm_schedule']} schedule)"
                                        if s.get("lm_schedule") else "")),
        ("linear solver", solver_text),
        ("robust kernel", s["robust_kernel"] or "none"),
        ("stop", f"{s['stop_reason']} after {s['iterations']} iterations"),
        ("chi2", f"{s['initial_chi2']:.6g} → {s['final_chi2']:.6g} (g2o's Σ e'Ωe{robust})"),
        ("seconds", f"{s['seconds']:.3f} ({s['seconds_per_iteration']:.4f} per iteration, "
                    "without the recording)"),
    ]
    g = s.get("ground_truth")
    if g is not None:
        rows.append(("vs ground truth", f"position RMS {g['initial']['rms_position']:.4g} → "
                                        f"{g['final']['rms_position']:.4g}"))
    notes = [] if rec.scale is None else [rec.scale.legend()]
    notes.append(
        "**Entities**: `world/before` the start (grey; toggle it with its eye in the blueprint "
        "panel), `world/after` the estimate at the selected iteration: `trajectory` (odometry "
        "edges), `loop_closures`"
        + (", `landmarks`" if len(rec.landmark_ids) else "")
        + (f", `outliers` ({rec.outliers} edges the kernel down-weights at the end: ρ' < 1 "
           "beyond its width) in magenta" if rec.outliers else "")
        + ("; `world/truth` the true trajectory (green)" if g is not None else "")
        + ". Scrub the `iteration` timeline to replay the run.")
    return summary_markdown(prog, rows, notes)

