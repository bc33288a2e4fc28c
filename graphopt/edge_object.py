"""The per-object front of an edge type: g2o's edge objects as thin records.

:class:`EdgeObject` is the object half of :class:`~graphopt.edge.BaseEdge`: an edge made with
``EdgeType(...)`` and ``set_*`` holds its values until the optimizer takes it into its group's
arrays (in bulk, see :mod:`graphopt.object_batch`); after that its getters and setters address
its row by uid. ``_uid``: −1 not added, −2 added and waiting in the optimizer's buffer, else the
edge's uid in ``_group``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from graphopt.errors import GraphError
from graphopt.robust_kernel import RobustKernel, kernel_key
from graphopt.vertex import BaseVertex, _own  # one copy rule for both kinds of object

if TYPE_CHECKING:
    from graphopt.edge_group import EdgeGroup


def check_level(level: Any) -> int:
    """``level`` as an int, or a :class:`GraphError` if it is not a non-negative integer.

    Args:
        level: An edge level (g2o's ``setLevel``) or the level to initialise.
    """
    if isinstance(level, bool | np.bool_) or not isinstance(level, int | np.integer) or level < 0:
        raise GraphError(f"a level must be a non-negative integer, got {level!r}")
    return int(level)


class EdgeObject:
    """The per-object API of :class:`~graphopt.edge.BaseEdge` (see there for the arguments)."""

    dimension: ClassVar[int]
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]]
    _group: EdgeGroup | Any

    def __init__(
        self,
        vertices: Sequence[BaseVertex | int] | None = None,
        measurement: Any = None,
        information: Any = None,
        robust_kernel: RobustKernel | None = None,
        params: Any = None,
        data: dict[str, Any] | None = None,
    ) -> None:
        k = len(self.vertex_types)
        if vertices is None:
            self._vertices: list[BaseVertex | int | None] = [None] * k
        else:
            if len(vertices) != k:
                raise ValueError(f"{type(self).__name__} takes {k} vertices, got {len(vertices)}")
            self._vertices = list(vertices)
        self._measurement = _own(measurement)
        self._information = _own(information)
        self._robust_kernel = robust_kernel
        self.params = params
        self.data = dict(data) if data else {}
        self._level = 0
        self._group: Any = None
        self._uid = -1
        self._graph: Any = None

    @property
    def _index(self) -> int:
        """The edge's current index in its group (edges removed before it move it)."""
        g = self._group
        if not g.removals:
            return self._uid
        return int(g.index_of(np.array([self._uid]))[0])

    def _fixed_once_added(self, what: str) -> None:
        """Raise if the edge is in the arrays (``_uid >= 0``), where ``what`` is structure."""
        if self._uid >= 0:
            raise GraphError(f"{self!r}: the {what} of an added edge cannot change; remove it "
                             "(remove_edge), change it and add it again")

    def _detach(self) -> None:
        """Keep the edge's values on the object and leave the group (removed or rejected)."""
        if self._uid >= 0:
            i = self._index
            self._measurement = self._group.measurements[i].copy()
            self._information = self._group.information_of(i)
            self._robust_kernel = self._given(self._group.kernel_of(i))
            self._level = int(self._group.levels[i])
        self._group, self._uid, self._graph = None, -1, None

    def set_vertex(self, i: int, vertex: BaseVertex | int) -> None:
        """Attach the vertex at position ``i``.

        Args:
            i: Position, ``0 <= i < len(vertex_types)``.
            vertex: A vertex object or its id.

        Raises:
            GraphError: the edge is in the optimizer's arrays (added and flushed).
        """
        if not 0 <= i < len(self._vertices):
            raise IndexError(f"{type(self).__name__} has no vertex position {i}")
        self._fixed_once_added("vertices")
        self._vertices[i] = vertex

    def vertex(self, i: int) -> BaseVertex | int | None:
        """The vertex (or id) at position ``i``.

        Args:
            i: Position.
        """
        return self._vertices[i]

    @property
    def vertices(self) -> list[BaseVertex | int | None]:
        """The vertices (or ids) by position."""
        return list(self._vertices)

    @property
    def measurement(self) -> np.ndarray | None:
        """The measurement."""
        if self._uid >= 0:
            return self._group.measurements[self._index].copy()
        return None if self._measurement is None else np.asarray(self._measurement, float)

    def set_measurement(self, z: Any) -> None:
        """Set the measurement (before the edge is added, or while it waits in the buffer).

        Args:
            z: Array of shape ``measurement_shape``.

        Raises:
            GraphError: the edge is in the optimizer's arrays (added and flushed).
        """
        self._fixed_once_added("measurement")
        self._measurement = _own(z)

    @property
    def information(self) -> np.ndarray:
        """The information matrix."""
        if self._uid >= 0:
            return self._group.information_of(self._index)
        if self._information is None:
            return np.eye(self.dimension)
        return np.asarray(self._information, dtype=float)

    def set_information(self, info: Any) -> None:
        """Set the information matrix (before the edge is added, or while it waits in the
        buffer).

        Args:
            info: ``(dimension, dimension)`` symmetric positive semi-definite matrix.

        Raises:
            GraphError: the edge is in the optimizer's arrays (added and flushed).
        """
        self._fixed_once_added("information")
        self._information = _own(info)

    @property
    def robust_kernel(self) -> RobustKernel | None:
        """The robust kernel or ``None``: the object given to this edge while its group uses it
        (kernels equal by value share one slot, whose object may be another edge's)."""
        if self._uid >= 0:
            return self._given(self._group.kernel_of(self._index))
        return self._robust_kernel

    def _given(self, slot: RobustKernel | None) -> RobustKernel | None:
        """The kernel given to this edge if the group's ``slot`` for it is equal to it by value,
        else ``slot`` (a kernel set on the edge's group since, e.g. through an ``EdgeSet``)."""
        mine = self._robust_kernel
        if slot is None or mine is None or mine is slot:
            return slot
        return mine if kernel_key(mine) == kernel_key(slot) else slot

    def set_robust_kernel(self, kernel: RobustKernel | None) -> None:
        """Set the robust kernel (also after the edge was added: no new structure).

        Args:
            kernel: A kernel, or ``None`` for plain least squares.
        """
        self._robust_kernel = kernel
        if self._uid >= 0:
            self._group.set_kernel(self._index, kernel)

    def level(self) -> int:
        """The edge's level (g2o's ``level()``): it is active when the optimizer is initialised
        with this level."""
        if self._uid >= 0:
            self._group.finalize()
            return int(self._group.levels[self._index])
        return self._level

    def set_level(self, level: int) -> None:
        """Set the edge's level (g2o's ``setLevel``; no new structure).

        Args:
            level: A non-negative integer.
        """
        level = check_level(level)
        if self._uid >= 0:
            self._group.set_levels(self._index, level)
        else:
            self._level = level

    def chi2(self) -> float:
        """``e' Ω e`` of this edge at the current estimates, without the kernel (g2o's
        ``chi2()``; evaluated with all edges of its group, once per state)."""
        if self._group is None:
            raise ValueError("the edge is not in an optimizer")
        chi = self._graph.edge_chi2(self._group)  # takes buffered edges into the arrays first
        return float(chi[self._index])

    def is_depth_positive(self) -> bool:
        """Whether the edge's point is in front of its camera(s) at the current estimates
        (g2o's ``isDepthPositive``; projection types; evaluated with all edges of its group,
        once per state)."""
        if self._group is None:
            raise ValueError("the edge is not in an optimizer")
        ok = self._graph.edge_depth_positive(self._group)  # takes buffered edges in first
        return bool(ok[self._index])

    def __repr__(self) -> str:
        ids = [v._id if isinstance(v, BaseVertex) else v for v in self._vertices]
        return f"{type(self).__name__}(vertices={ids})"

