"""``EdgeSet``: a handle on some edges of one group, with batched per-edge queries and edits.

``SparseOptimizer.add_edges`` returns one for the edges it added; indexing it with a mask or
indices gives another (a view, for chained edits). A set holds the edges' *uids* (their serial
numbers in the group, see :class:`~graphopt.storage.EdgeGroup`), so it stays valid when other
edges of the group are removed; using a set some of whose own edges were removed raises a
:class:`~graphopt.errors.GraphError`.

Queries (``chi2``, ``errors``) evaluate the whole group once per state of the estimates (one
batched ``evaluate``) and slice; edits (levels, kernels) change numbers, not the structure.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from graphopt.edge import BaseEdge
from graphopt.errors import GraphError
from graphopt.numeric import frozen_copy
from graphopt.removal import remove_edges
from graphopt.robust_kernel import RobustKernel
from graphopt.row_weights import row_dots
from graphopt.storage import EdgeGroup

if TYPE_CHECKING:
    from graphopt.graph import Graph


def _per_group(graph: Graph, g: EdgeGroup, what: str,
               compute: Callable[[EdgeGroup, tuple[np.ndarray, ...]], Any]) -> Any:
    """``compute(g, x)`` at the current estimates ``x`` of every edge of a group, cached until
    an estimate or the group changes (one batched call however many edges ask)."""
    graph.flush()
    g.finalize()
    key = (id(g), what)
    hit = graph._evals.get(key)
    if hit is not None and hit[0] is g and hit[1] == (g.size, g.removals):
        # Slots move only when vertices of the group's stores are removed.
        stores = hit[2]
        if hit[3] != tuple(st.removals for st, _ in stores):
            hit = None
    else:
        hit = None
    if hit is None:
        stores = graph.group_slots(g)
        hit = (g, (g.size, g.removals), stores, tuple(st.removals for st, _ in stores), None,
               None)
    state = tuple(st.version for st, _ in stores)
    if hit[4] != state:
        raw = g.raw_eval  # the optimiser's last evaluation of every edge, if at this state
        if what == "errors" and raw is not None and raw[0] == (state, g.next_uid, g.removals):
            # The optimiser's arrays stay its own; its e'Ωe of every edge if it kept it.
            result: Any = (_chi2(g, raw[1].copy()) if raw[2] is None
                           else (frozen_copy(raw[1]), frozen_copy(raw[2])))
        else:
            result = compute(g, tuple(st.estimates[slots] for st, slots in stores))
        hit = (*hit[:4], state, result)
        graph._evals[key] = hit
    return hit[5]


def _errors(g: EdgeGroup, x: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    out = g.etype.evaluate(x, g.measurements, g.context())
    e = np.asarray(out.error, dtype=float)
    if e.shape != (g.size, g.dim):
        raise GraphError(f"{g.etype.__name__}.evaluate returned an error of shape {e.shape}, "
                         f"expected {(g.size, g.dim)}")
    return _chi2(g, e)


def _chi2(g: EdgeGroup, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e, e'Ωe)`` of a group's errors, both made read-only."""
    if g.info_is_identity:
        s = row_dots(e, e)
    else:
        assert g.information is not None
        if g.information.ndim == 2:
            oe = e @ g.information
        elif g.info_diagonal is not None:  # per-edge diagonal: the product's values, scaled
            oe = e * g.info_diagonal
        else:
            oe = np.einsum("mij,mj->mi", g.information, e)
        s = row_dots(e, oe)
    e.flags.writeable = False
    s.flags.writeable = False
    return e, s


def _depth(g: EdgeGroup, x: tuple[np.ndarray, ...]) -> np.ndarray:
    ok = np.asarray(g.etype.depth_positive(x, g.measurements, g.context()))
    if ok.shape != (g.size,):
        raise GraphError(f"{g.etype.__name__}.depth_positive returned shape {ok.shape}, "
                         f"expected ({g.size},)")
    ok = ok.astype(bool)
    ok.flags.writeable = False
    return ok


def group_errors(graph: Graph, g: EdgeGroup) -> tuple[np.ndarray, np.ndarray]:
    """Errors and ``eᵀΩe`` (no kernel, every level) of every edge of a group at the current
    estimates, cached until an estimate or the group changes.

    Args:
        graph: The graph holding the group.
        g: The group.

    Returns:
        ``(errors (m, dimension), chi2 (m,))`` (read-only: do not modify).

    Raises:
        GraphError: the type's ``evaluate`` returned an error of the wrong shape.
    """
    graph.flush()
    g.finalize()
    if g.size == 0:
        return np.zeros((0, g.dim)), np.zeros(0)
    return _per_group(graph, g, "errors", _errors)


def group_depth_positive(graph: Graph, g: EdgeGroup) -> np.ndarray:
    """``(m,)`` the type's ``depth_positive`` of every edge of a group at the current
    estimates (read-only), cached like :func:`group_errors`.

    Args:
        graph: The graph holding the group.
        g: The group.

    Raises:
        GraphError: the type has no ``depth_positive``, or it returned the wrong shape.
    """
    graph.flush()
    g.finalize()
    if g.size == 0:
        return np.zeros(0, dtype=bool)
    return _per_group(graph, g, "depth", _depth)


def _check_levels(levels: Any, m: int, who: str) -> int | np.ndarray:
    """A level for all or ``(m,)`` levels, each a non-negative integer, else a GraphError."""
    arr = np.asarray(levels)
    if arr.dtype.kind not in "iu" or (arr.ndim == 1 and len(arr) != m) or arr.ndim > 1:
        raise GraphError(f"{who}.set_level: levels must be one non-negative integer or {m} of "
                         f"them, got {levels!r:.80}")
    if arr.size and int(arr.min()) < 0:
        raise GraphError(f"{who}.set_level: levels must be non-negative, got {int(arr.min())}")
    return int(arr) if arr.ndim == 0 else arr.astype(np.int64)


class EdgeSet:
    """Some edges of one group (one edge type and parameter object).

    Args:
        graph: The graph.
        group: The edges' group.
        uids: ``(m,)`` their uids.
    """

    def __init__(self, graph: Graph, group: EdgeGroup, uids: np.ndarray,
                 ascending: bool = False) -> None:
        self._graph = graph
        self._group = group
        self._uids = uids
        # The uids are distinct and ascending (a set of add_edges or of a whole group): as
        # many rows as the group has edges are then all of them, in order (see _whole).
        self._ascending = ascending

    def _whole(self, rows: np.ndarray) -> bool:
        """Whether ``rows`` (:meth:`_rows`) are every edge of the group, in order: its arrays
        are then copied or set whole, not through an index."""
        return self._ascending and len(rows) == self._group.size

    # --- what the set is -----------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._uids)

    def __repr__(self) -> str:
        return f"EdgeSet({self.edge_type.__name__}, {len(self)} edges)"

    @property
    def edge_type(self) -> type[BaseEdge]:
        """The edges' type."""
        return self._group.etype

    @property
    def group(self) -> EdgeGroup:
        """The group the edges live in."""
        return self._group

    def _rows(self) -> np.ndarray:
        """The edges' current indices in the group.

        Raises:
            GraphError: some of the set's edges were removed.
        """
        self._graph.flush()
        g = self._group
        try:
            return g.index_of(self._uids)
        except GraphError as exc:
            raise GraphError(f"EdgeSet of {g.etype.__name__}: {exc}".replace(
                f": {g.etype.__name__}:", ":")) from None

    @property
    def ids(self) -> np.ndarray:
        """``(m, k)`` the vertex ids of every edge (a copy)."""
        rows = self._rows()  # first: it finalises the group
        return self._group.vertex_ids[rows].copy()

    @property
    def measurements(self) -> np.ndarray:
        """``(m, *measurement_shape)`` the measurements (a copy)."""
        rows = self._rows()
        return self._group.measurements[rows].copy()

    def __getitem__(self, key: Any) -> EdgeSet:
        """The edges selected by a ``(m,)`` boolean mask, integer indices or a slice.

        Args:
            key: The selection.
        """
        return EdgeSet(self._graph, self._group, self._uids[self._select(key, "indexing")])

    def _select(self, key: Any, what: str) -> np.ndarray | slice:
        m = len(self)
        if isinstance(key, slice):
            return key
        arr = np.asarray(key)
        if arr.dtype == bool:
            if arr.shape != (m,):
                raise GraphError(f"EdgeSet of {self.edge_type.__name__} ({what}): a mask must "
                                 f"have shape ({m},), got {arr.shape}")
            return np.flatnonzero(arr)
        if arr.dtype.kind in "iu" and arr.ndim <= 1:
            arr = np.atleast_1d(arr).astype(np.int64)
            if arr.size and (int(arr.min()) < -m or int(arr.max()) >= m):
                raise GraphError(f"EdgeSet of {self.edge_type.__name__} ({what}): index out "
                                 f"of range for {m} edges")
            return arr
        raise GraphError(f"EdgeSet of {self.edge_type.__name__} ({what}): select with a ({m},) "
                         f"boolean mask, integer indices or a slice, got {key!r:.80}")

    # --- queries -------------------------------------------------------------------------------

    def chi2(self) -> np.ndarray:
        """``(m,)`` ``eᵀΩe`` of every edge at the current estimates, without the kernel and
        whatever its level (g2o's per-edge ``chi2()`` after ``computeError()``)."""
        rows = self._rows()
        out = group_errors(self._graph, self._group)[1]
        return out.copy() if self._whole(rows) else out[rows]

    def errors(self) -> np.ndarray:
        """``(m, dimension)`` errors at the current estimates."""
        rows = self._rows()
        out = group_errors(self._graph, self._group)[0]
        return out.copy() if self._whole(rows) else out[rows]

    def is_depth_positive(self) -> np.ndarray:
        """``(m,)`` whether each edge's point lies in front of its camera(s) (the type's
        ``depth_positive``, projection types only; evaluated for the whole group once per
        state of the estimates).

        Raises:
            GraphError: the type has no ``depth_positive``.
        """
        rows = self._rows()
        ok = group_depth_positive(self._graph, self._group)
        return ok.copy() if self._whole(rows) else ok[rows]

    def levels(self) -> np.ndarray:
        """``(m,)`` every edge's level."""
        rows = self._rows()
        levels = self._group.levels
        return np.array(levels) if self._whole(rows) else levels[rows]

    # --- edits ---------------------------------------------------------------------------------

    def set_level(self, levels: Any) -> None:
        """Set the edges' levels (g2o's ``setLevel``): the edges whose level is the one
        initialised are active. No new structure.

        Args:
            levels: One non-negative integer for all, or ``(m,)`` of them.

        Raises:
            GraphError: levels that are not non-negative integers, or of the wrong shape.
        """
        value = _check_levels(levels, len(self), f"EdgeSet of {self.edge_type.__name__}")
        rows = self._rows()
        self._group.set_levels(slice(None) if self._whole(rows) else rows, value)

    def set_robust_kernel(self, kernel: RobustKernel | None) -> None:
        """Give every edge of the set this robust kernel (``None``: none). No new structure.

        Args:
            kernel: The kernel.
        """
        if kernel is not None and not isinstance(kernel, RobustKernel):
            raise GraphError(f"EdgeSet of {self.edge_type.__name__}: robust_kernel must be a "
                             f"RobustKernel or None, got {kernel!r}")
        rows = self._rows()
        self._group.set_kernel(slice(None) if self._whole(rows) else rows, kernel)

    def remove(self, mask: Any = None) -> None:
        """Remove edges from the optimizer (the structure is rebuilt at the next run); the set
        keeps the others.

        Args:
            mask: ``(m,)`` booleans (or indices) of the edges to remove; ``None``: all.
        """
        rows = self._rows()
        sel = np.arange(len(self)) if mask is None else self._select(mask, "remove")
        remove_edges(self._graph, self._group, np.unique(np.atleast_1d(rows[sel])))
        keep = np.ones(len(self), dtype=bool)
        keep[sel] = False
        self._uids = self._uids[keep]
