"""How the apps' recordings look: the viewer layout (blueprint), error colours with their legend,
the robust-kernel outliers and the Markdown summary.

Every app's recording has the same shape, so that a reviewer who has seen one can read the others:

* a large 3-D (or 2-D) view of ``world``: ``world/before/...`` the start in a muted grey (logged
  once; toggle it with its eye in the blueprint panel), ``world/after/...`` the estimate at the
  selected ``iteration`` coloured by its error (the colours of every iteration use the final
  run's scale, :class:`ErrorScale`), ``world/after/outliers`` what the robust kernel
  down-weights at the end (:func:`outlier_mask`);
* beside it ``metrics/log10_chi2`` (the cost on a log scale), ``metrics/iteration_seconds`` and
  the ``summary`` document (input, sizes, algorithm, solver, stop reason, chi2, seconds, and the
  legend of the colours);
* for direct BA, below them, one 2-D view per image (``images/{k}``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "AFTER",
    "MANY_OUTLIERS",
    "BEFORE",
    "OUTLIER",
    "TRUTH",
    "ErrorScale",
    "error_colors",
    "outlier_mask",
    "run_blueprint",
    "summary_markdown",
]

#: Muted grey of the start (``world/before``).
BEFORE = (120, 120, 120)
#: Colour of an estimate drawn without error colours (e.g. a trajectory line).
AFTER = (20, 100, 190)
#: Colour of the ground truth (``world/truth``, generated scenes): a muted green, apart from the
#: start's grey.
TRUTH = (110, 175, 110)
#: Colour of the robust-kernel outliers (``world/after/outliers``).
OUTLIER = (230, 0, 230)
#: When more than this share of the edges are outliers (a kernel narrower than the noise), the
#: outlier entities start hidden: they would cover the error colours.
MANY_OUTLIERS = 0.25
#: The error colour map's stops, from no error to the scale's top: blue, teal, yellow, red.
_STOPS = np.array([[40, 90, 220], [30, 185, 160], [240, 200, 40], [215, 35, 35]], float)
_STOP_NAMES = ("blue", "teal", "yellow", "red")


def error_colors(values: Any, top: float) -> np.ndarray:
    """Colours of errors on a linear scale from 0 (blue) to ``top`` and above (red).

    Args:
        values: ``(n,)`` non-negative errors; non-finite ones are drawn as the top.
        top: The error drawn red (and everything above it).

    Returns:
        ``(n, 3)`` uint8 colours.
    """
    v = np.asarray(values, dtype=float)
    t = np.where(np.isfinite(v), v, np.inf) / max(float(top), 1e-300)
    x = np.clip(t, 0.0, 1.0) * (len(_STOPS) - 1)
    i = np.minimum(x.astype(np.intp), len(_STOPS) - 2)
    f = (x - i)[:, None]
    return np.round(_STOPS[i] * (1 - f) + _STOPS[i + 1] * f).astype(np.uint8)


@dataclass(frozen=True)
class ErrorScale:
    """The colour scale of a run's errors: 0 blue … ``top`` and above red.

    ``top`` is three times the median final error: a point drawn red ends the run with at least
    three times the typical error, wherever it started.

    Args:
        top: The error drawn red.
        quantity: What the errors are, e.g. ``"per-point RMS reprojection error"``.
        unit: Their unit, e.g. ``"px"`` (empty for chi2).
    """

    top: float
    quantity: str
    unit: str = ""

    @classmethod
    def from_final(cls, final: Any, quantity: str, unit: str = "") -> ErrorScale:
        """The scale of the final errors (3 × their median; 1 if none is finite and positive).

        Args:
            final: ``(n,)`` errors at the end of the run.
            quantity: What they are.
            unit: Their unit.
        """
        v = np.asarray(final, dtype=float)
        v = v[np.isfinite(v) & (v > 0)]
        top = 3.0 * float(np.median(v)) if len(v) else 1.0
        return cls(top if top > 0 else 1.0, quantity, unit)

    def colors(self, values: Any) -> np.ndarray:
        """``(n, 3)`` uint8 colours of ``values`` on this scale."""
        return error_colors(values, self.top)

    def legend(self) -> str:
        """One Markdown line naming the colours' values."""
        unit = f" {self.unit}" if self.unit else ""
        steps = [f"{name} {self.top * k / 3:.3g}{unit}" for k, name in enumerate(_STOP_NAMES)]
        return (f"**Colours**: {self.quantity}, linear: " + " → ".join(steps)
                + " and above (3 × the final median; the same scale at every iteration)")


def outlier_mask(group: Any) -> np.ndarray:
    """The edges of a group that its robust kernels down-weight beyond their width at the last
    evaluation: ``ρ'(s) < 1`` and ``s = e'Ωe > δ²``.

    For Huber these are exactly the edges with ``ρ' < 1``; kernels whose ``ρ'`` is below 1
    everywhere (Cauchy, Tukey, ...) count only the edges beyond their width ``δ``.

    Args:
        group: An :class:`~graphopt.storage.EdgeGroup` after an evaluation (e.g.
            ``optimizer.compute_active_errors()``).

    Returns:
        ``(m,)`` boolean mask; all False for edges without a kernel.
    """
    s = np.asarray(group.last_chi2, dtype=float)
    out = np.zeros(len(s), dtype=bool)
    index = np.asarray(group.kernel_index)
    for k, kernel in enumerate(group.kernels):
        pick = np.flatnonzero(index == k)
        if not len(pick):
            continue
        with np.errstate(all="ignore"):
            weight = kernel.robustify(s[pick])[1]
        out[pick] = (weight < 1.0) & (s[pick] > kernel.delta ** 2)
    return out


def summary_markdown(title: str, rows: Sequence[tuple[str, str]],
                     notes: Sequence[str] = ()) -> str:
    """The summary document: a title, a two-column table and notes (legend, entities).

    Args:
        title: First line (the app and its input).
        rows: ``(what, value)`` pairs.
        notes: Markdown paragraphs after the table.

    Returns:
        The Markdown text.
    """
    # The first row is the table's header (Markdown tables need one; an empty one shows as a
    # blank row).
    lines = [f"### {title}", ""]
    for i, (k, v) in enumerate(rows):
        lines.append(f"| {k} | {v} |")
        if i == 0:
            lines.append("|---|---|")
    for note in notes:
        lines += ["", note]
    return "\n".join(lines) + "\n"


def run_blueprint(
    *,
    spatial: str = "3d",
    world_name: str = "estimate",
    images: Sequence[tuple[str, str]] = (),
    image_size: tuple[float, float] | None = None,
    timeline: str = "iteration",
    eye: tuple[Any, Any, Any] | None = None,
    hidden: Sequence[str] = (),
) -> Any:
    """The layout of an app's recording: the world large on the left; the log10 cost, the
    seconds per iteration and the summary on the right; optionally a row of 2-D image views.

    Args:
        spatial: ``"3d"`` or ``"2d"`` (the world view's kind).
        world_name: Title of the world view.
        images: ``(origin, title)`` of 2-D views shown in a row below (direct BA's images).
        image_size: ``(width, height)``: the image views show exactly this (what lies outside,
            e.g. patches projected off the image, does not zoom them out).
        timeline: The time panel's timeline (``"step"`` for online runs).
        eye: ``(position, look_target, eye_up)`` of the 3-D view's camera (e.g. top-down for
            a planar graph); the viewer's choice if None.
        hidden: Entity paths (with their children) hidden at first in every view; the blueprint
            panel's eye shows them.

    Returns:
        A ``rerun.blueprint.Blueprint``.
    """
    import rerun.blueprint as rrb  # rerun is heavy: only imported when recording

    overrides = {path: rrb.EntityBehavior(visible=False) for path in hidden}

    if spatial == "3d":
        controls = None if eye is None else rrb.EyeControls3D(
            position=eye[0], look_target=eye[1], eye_up=eye[2])
        world = rrb.Spatial3DView(origin="world", name=world_name, eye_controls=controls,
                                  overrides=overrides)
    else:
        world = rrb.Spatial2DView(origin="world", name=world_name, overrides=overrides)
    side = rrb.Vertical(
        rrb.TimeSeriesView(origin="metrics/log10_chi2", name="log10 chi2",
                           plot_legend=rrb.PlotLegend(visible=False)),
        rrb.TimeSeriesView(origin="metrics/iteration_seconds", name="seconds per iteration",
                           plot_legend=rrb.PlotLegend(visible=False)),
        rrb.TextDocumentView(origin="summary", name="summary"),
        row_shares=[1.0, 0.7, 2.3],
    )
    root: Any = rrb.Horizontal(world, side, column_shares=[3.0, 2.0])
    if images:
        bounds = None if image_size is None else rrb.VisualBounds2D(
            x_range=[0.0, float(image_size[0])], y_range=[0.0, float(image_size[1])])
        row = rrb.Horizontal(*[rrb.Spatial2DView(origin=o, name=n, visual_bounds=bounds,
                                                 overrides=overrides) for o, n in images])
        root = rrb.Vertical(root, row, row_shares=[3.0, 1.0])
    return rrb.Blueprint(
        root,
        rrb.BlueprintPanel(state="expanded"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=timeline),
        auto_views=False,
    )
