"""Rerun recordings of an optimisation: point cloud, camera frusta, trajectory, cost.

Everything is logged on a sequence timeline ``iteration`` so that the viewer's time slider
replays the optimisation; online runs (one optimisation per new measurement) also set the
``step`` timeline (:meth:`Recorder.set_step`), so that a reviewer can scrub the steps, and the
iterations within the selected step. The ``.rrd`` file is written to a temporary file beside the
destination and renamed over it in :meth:`Recorder.close` (an existing file is only replaced by
a complete one).

Example::

    rec = Recorder("run.rrd")
    rec.set_iteration(0)
    rec.log_points(X)
    rec.log_cameras(T_cw, focal=f, resolution=(w, h))
    rec.log_scalar("cost", cost)
    ...
    rec.close()

Or as a context manager (``with Recorder(path) as rec: ...``), which closes on success and
discards the temporary file on error.

Entity layout (defaults): ``world/points``, ``world/cameras/{k}`` (Transform3D camera→world +
Pinhole, optional ``.../image``), ``world/trajectory``, ``metrics/{name}`` (scalar series; the
cost also as ``metrics/log10_{name}``, :meth:`Recorder.log_cost`), ``summary`` (a Markdown
:meth:`~Recorder.log_document`). The apps' layout (``world/before``, ``world/after``, the outliers)
and the blueprint that arranges the views are in :mod:`graphopt.recording_view`.

An online run, for example::

    rec = Recorder("online.rrd")
    rec.send_blueprint(run_blueprint(timeline="step"))   # graphopt.recording_view
    for step, batch in enumerate(batches):
        rec.set_step(step)                   # the step timeline stays set ...
        for it in iterations_of(batch):
            rec.set_iteration(it)            # ... while the iterations restart at 0
            rec.log_trajectory(poses)
            rec.log_cost(chi2)
    rec.log_document(summary_markdown)
    rec.close()
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from graphopt.io.atomic import PendingFile

__all__ = ["STEP_TIMELINE", "TIMELINE", "Recorder"]

#: Name of the sequence timeline everything is logged on.
TIMELINE = "iteration"
#: Name of the sequence timeline of online runs (one step per batch of new measurements).
STEP_TIMELINE = "step"


def _view_coordinates(rr: Any, name: str) -> Any:
    """``rr.ViewCoordinates.<NAME>``, with a clear error for an unknown name."""
    value = getattr(rr.ViewCoordinates, name.upper(), None)
    if value is None or not name.replace("_", "").isalpha():
        raise ValueError(f"unknown rerun view coordinates {name!r} (e.g. 'RDF', 'RUB', "
                         "'RIGHT_HAND_Z_UP')")
    return value


class Recorder:
    """Write a rerun ``.rrd`` recording of an optimisation run.

    Args:
        path: Destination ``.rrd`` file (replaced atomically on :meth:`close`).
        application_id: Rerun application id shown in the viewer.
        camera_xyz: Camera axis convention for the frusta: ``"RDF"`` (OpenCV: x right, y down,
            z forward, the default) or ``"RUB"`` (BAL/OpenGL: y up, looking down −z).
        world_xyz: Axis convention of the world frame for the viewer: ``"RIGHT_HAND_Z_UP"``
            (default) or any ``rerun.ViewCoordinates`` name, e.g. ``"RDF"`` when the world is a
            camera-like frame (x right, y down, z forward).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        application_id: str = "graphopt",
        *,
        camera_xyz: str = "RDF",
        world_xyz: str = "RIGHT_HAND_Z_UP",
    ) -> None:
        import rerun as rr  # imported lazily: rerun is heavy and only needed for recordings

        self._rr = rr
        self.path = Path(path)
        self._camera_xyz = _view_coordinates(rr, camera_xyz)
        world = _view_coordinates(rr, world_xyz)
        self._closed = False
        self._pending = PendingFile(self.path)
        try:
            self._rec = rr.RecordingStream(application_id, make_default=False)
            self._rec.save(str(self._pending.tmp))
            self._rec.log("world", world, static=True)
        except BaseException:
            self._pending.discard()
            raise

    # --- timeline ---------------------------------------------------------------------------

    def set_iteration(self, iteration: int) -> None:
        """Set the ``iteration`` timeline for everything logged next.

        Args:
            iteration: Iteration number (0 = before optimisation).
        """
        self._rec.set_time(TIMELINE, sequence=int(iteration))

    def set_step(self, step: int) -> None:
        """Set the ``step`` timeline (online runs) for everything logged next.

        The ``iteration`` timeline is independent: set both, the step first; each step's
        iterations may restart at 0.

        Args:
            step: Step number (0 = the first batch of measurements).
        """
        self._rec.set_time(STEP_TIMELINE, sequence=int(step))

    def send_blueprint(self, blueprint: Any) -> None:
        """Store the viewer layout in the recording (the viewer opens with it).

        Args:
            blueprint: A ``rerun.blueprint.Blueprint`` (see
                :func:`graphopt.recording_view.run_blueprint`).
        """
        self._rec.send_blueprint(blueprint)

    # --- logging ----------------------------------------------------------------------------

    def log_points(
        self,
        points: Any,
        colors: Any = None,
        *,
        entity: str = "world/points",
        radius: float | None = None,
        static: bool = False,
    ) -> None:
        """Log a point cloud.

        Args:
            points: ``(n, 3)`` points in the world frame; non-finite rows are dropped (so
                colours logged later for the same entity must skip them too: keep points
                finite when :meth:`log_colors` follows).
            colors: ``(3,)`` or ``(n, 3)`` uint8 colours (the viewer's default if None).
            entity: Entity path.
            radius: Point radius in scene units, or negative for screen pixels (viewer
                default if None).
            static: Log once for every time (e.g. the start, shown beside each iteration).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        ok = np.isfinite(pts).all(axis=1)
        col = None if colors is None else np.asarray(colors)
        if col is not None and col.ndim == 2:
            col = col[ok]
        self._rec.log(
            entity,
            self._rr.Points3D(pts[ok].astype(np.float32), colors=col,
                              radii=None if radius is None else [radius]),
            static=static,
        )

    def log_colors(self, colors: Any, *, entity: str, kind: str = "points") -> None:
        """Log only the colours of points or line strips (the positions stay as last logged).

        Used to colour every iteration once the colour scale is known (at the end of a run):
        set the iteration, then log its colours.

        Args:
            colors: ``(n, 3)`` uint8 colours, one per point (or strip) of the entity.
            entity: Entity path.
            kind: ``"points"`` (Points3D), ``"points2d"`` (Points2D) or ``"lines"``
                (LineStrips3D, e.g. segments).
        """
        archetype = {"points": self._rr.Points3D, "points2d": self._rr.Points2D,
                     "lines": self._rr.LineStrips3D}[kind]
        self._rec.log(entity, archetype.from_fields(colors=np.asarray(colors)))

    def log_cameras(
        self,
        T_cw: Any,
        *,
        focal: Any,
        resolution: Any,
        principal_point: Any = None,
        images: Any = None,
        entity: str = "world/cameras",
        image_plane_distance: float | None = None,
        trajectory: bool | str = True,
    ) -> None:
        """Log cameras as frusta (and optionally their images on the image plane).

        Args:
            T_cw: ``(c, 4, 4)`` world-to-camera transforms (or ``(c, 3, 4)``).
            focal: Focal length in pixels: scalar, ``(fx, fy)``, ``(c,)`` or ``(c, 2)``.
            resolution: ``(width, height)`` in pixels, or ``(c, 2)``.
            principal_point: ``(cx, cy)`` or ``(c, 2)``; the image centre if None.
            images: Optional sequence of ``c`` images (``(h, w)`` grey or ``(h, w, 3)`` RGB,
                uint8 or float) shown inside the frusta; ``None`` entries are skipped. Images are
                logged once per call; log them only at the first iteration if they never change.
            entity: Parent entity; camera ``k`` is ``{entity}/{k}``.
            image_plane_distance: Frustum depth in scene units (viewer default if None).
            trajectory: Also log the camera centres as a line strip: ``world/trajectory`` if
                True, the entity named if a string.
        """
        rr = self._rr
        T = np.asarray(T_cw, dtype=float)
        c = len(T)
        R_cw, t_cw = T[:, :3, :3], T[:, :3, 3]
        R_wc = np.swapaxes(R_cw, 1, 2)
        centers = -np.einsum("nij,nj->ni", R_wc, t_cw)
        fa = np.asarray(focal, dtype=float)
        if fa.ndim == 1 and len(fa) == 2 and c != 2:
            fa = fa[None, :]  # one (fx, fy) for every camera
        elif fa.ndim <= 1:
            fa = fa.reshape(-1, 1)  # a scalar, or one focal per camera
        try:
            f = np.broadcast_to(fa, (c, 2))
        except ValueError:
            raise ValueError(f"focal must be a scalar, (fx, fy), ({c},) or ({c}, 2); "
                             f"got shape {np.shape(focal)}") from None
        res = np.broadcast_to(np.asarray(resolution, dtype=float), (c, 2))
        pp = (res / 2.0 if principal_point is None
              else np.broadcast_to(np.asarray(principal_point, dtype=float), (c, 2)))
        for k in range(c):  # one entity per camera: rerun's Pinhole is per entity
            path = f"{entity}/{k}"
            self._rec.log(path, rr.Transform3D(translation=centers[k], mat3x3=R_wc[k]))
            self._rec.log(
                path,
                rr.Pinhole(
                    focal_length=[float(f[k, 0]), float(f[k, 1])],
                    principal_point=[float(pp[k, 0]), float(pp[k, 1])],
                    resolution=[float(res[k, 0]), float(res[k, 1])],
                    camera_xyz=self._camera_xyz,
                    image_plane_distance=image_plane_distance,
                ),
            )
            if images is not None and images[k] is not None:
                self._rec.log(f"{path}/image", rr.Image(np.asarray(images[k])))
        if trajectory and c > 1:
            where = trajectory if isinstance(trajectory, str) else "world/trajectory"
            self._rec.log(where, rr.LineStrips3D([centers]))

    def log_trajectory(
        self, centers: Any, *, entity: str = "world/trajectory", color: Any = None,
        radius: float | None = None, static: bool = False,
    ) -> None:
        """Log a trajectory (e.g. camera centres in order) as one line strip.

        Args:
            centers: ``(c, 3)`` positions.
            entity: Entity path.
            color: ``(3,)`` uint8 colour (the viewer's default if None).
            radius: Line radius in scene units, or negative for screen pixels (viewer default
                if None).
            static: Log once for every time.
        """
        self._rec.log(entity, self._rr.LineStrips3D(
            [np.asarray(centers, dtype=np.float32)], colors=None if color is None else [color],
            radii=None if radius is None else [radius]), static=static)

    def log_segments(
        self, starts: Any, ends: Any, *, entity: str, color: Any = None,
        radius: float | None = None, static: bool = False,
    ) -> None:
        """Log line segments (e.g. the loop closures of a pose graph) as one entity.

        Args:
            starts: ``(m, 3)`` first end of each segment.
            ends: ``(m, 3)`` second end.
            entity: Entity path.
            color: ``(3,)`` uint8 colour for all segments, or ``(m, 3)`` one per segment (the
                viewer's default if None).
            radius: Line radius in scene units, or negative for screen pixels (viewer default
                if None).
            static: Log once for every time.
        """
        strips = np.stack([np.asarray(starts, dtype=float), np.asarray(ends, dtype=float)], 1)
        col = None if color is None else np.asarray(color, dtype=np.uint8).reshape(-1, 3)
        self._rec.log(entity, self._rr.LineStrips3D(
            strips.astype(np.float32), colors=col, radii=None if radius is None else [radius]),
            static=static)

    def log_scalar(self, name: str, value: float) -> None:
        """Log one value of a scalar time series (e.g. the cost) at the current iteration.

        Args:
            name: Series name; logged at ``metrics/{name}``.
            value: The value (non-finite values are skipped).
        """
        if np.isfinite(value):
            self._rec.log(f"metrics/{name}", self._rr.Scalars([float(value)]))

    def name_series(self, name: str, label: str, color: Any = None) -> None:
        """Give a scalar series its legend label (and colour), once for the whole recording.

        Args:
            name: Series name (``metrics/{name}``).
            label: The legend's text, e.g. ``"log10 chi2"``.
            color: ``(3,)`` uint8 colour (the viewer's choice if None).
        """
        self._rec.log(f"metrics/{name}", self._rr.SeriesLines(
            names=[label], colors=None if color is None else [color]), static=True)

    def log_cost(self, value: float, name: str = "chi2") -> None:
        """Log a cost at the current iteration, as ``metrics/{name}`` and, for a plot on a
        logarithmic scale (rerun's plots have none), ``metrics/log10_{name}``.

        Args:
            value: The cost (non-finite values are skipped; ``0`` has no logarithm, so the
                log series skips it).
            name: Series name.
        """
        self.log_scalar(name, value)
        if np.isfinite(value) and value > 0:
            self.log_scalar(f"log10_{name}", float(np.log10(value)))

    def log_document(self, markdown: str, *, entity: str = "summary") -> None:
        """Log a Markdown document (e.g. the run's summary), static: shown at every time.

        Args:
            markdown: The text (Markdown).
            entity: Entity path.
        """
        self._rec.log(entity, self._rr.TextDocument(markdown, media_type="text/markdown"),
                      static=True)

    def log_image(self, image: Any, *, entity: str, static: bool = True) -> None:
        """Log an image (e.g. an input image under a 2-D view's residuals).

        Args:
            image: ``(h, w)`` grey or ``(h, w, 3)`` RGB ``uint8`` image.
            entity: Entity path.
            static: Log once for every time (the default: input images do not change).
        """
        self._rec.log(entity, self._rr.Image(np.asarray(image)), static=static)

    def log_points2d(self, points: Any, colors: Any = None, *, entity: str,
                     radius: float | None = None) -> None:
        """Log 2-D points (pixel coordinates), e.g. patch positions in an image.

        Args:
            points: ``(n, 2)`` points; non-finite rows are dropped.
            colors: ``(3,)`` or ``(n, 3)`` uint8 colours (the viewer's default if None).
            entity: Entity path.
            radius: Radius in pixels of the image (the viewer's default if None).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        ok = np.isfinite(pts).all(axis=1)
        col = None if colors is None else np.asarray(colors)
        if col is not None and col.ndim == 2:
            col = col[ok]
        self._rec.log(entity, self._rr.Points2D(pts[ok].astype(np.float32), colors=col,
                                                radii=None if radius is None else [radius]))

    def log_text(self, text: str, *, entity: str = "log") -> None:
        """Log a text line (e.g. a summary).

        Args:
            text: The text.
            entity: Entity path.
        """
        self._rec.log(entity, self._rr.TextLog(text))

    # --- lifetime ---------------------------------------------------------------------------

    def close(self) -> None:
        """Flush the recording and move it to :attr:`path`."""
        if self._closed:
            return
        self._closed = True
        self._rec.flush()
        self._rec.disconnect()  # closes the file sink and writes the footer
        self._pending.commit()

    def abort(self) -> None:
        """Discard the recording; the destination file is left untouched."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._rec.disconnect()
        self._pending.discard()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
