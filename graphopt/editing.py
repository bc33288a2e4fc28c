"""The editing half of :class:`~graphopt.optimizer.SparseOptimizer`'s g2o facade: removing
edges and vertices between runs, and the initialised level.

Levels and kernels are edited through :class:`~graphopt.edge_set.EdgeSet` (what ``add_edges``
returns) or the edge objects; estimates through ``set_estimates_of`` or the vertex objects.
Those edits change numbers only; a removal makes the next run build a new structure.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from graphopt.edge import BaseEdge
from graphopt.edge_set import EdgeSet
from graphopt.errors import GraphError
from graphopt.graph import Graph
from graphopt.removal import remove_edges, remove_vertices
from graphopt.vertex import BaseVertex


class GraphEditing:
    """Removal and level queries over ``self.graph`` (a mixin of the optimizer)."""

    graph: Graph

    @property
    def level(self) -> int:
        """The initialised level (the edges of this level are active)."""
        return self.graph.level

    def remove_edge(self, edge: BaseEdge) -> bool:
        """Remove one edge added with :meth:`add_edge` (g2o's ``removeEdge``); it can be added
        again. The structure is rebuilt at the next run.

        Args:
            edge: The edge.

        Raises:
            GraphError: the edge is not in this optimizer.
        """
        self.graph.flush()
        if edge._group is None or edge._graph is not self.graph:
            raise GraphError(f"remove_edge: {edge!r} is not in this optimizer")
        remove_edges(self.graph, edge._group, np.array([edge._index]))
        return True

    def remove_vertices(self, ids: Iterable[int] | np.ndarray) -> None:
        """Remove vertices no edge uses any more (their objects keep their last estimate).
        The structure is rebuilt at the next run.

        Args:
            ids: Vertex ids.

        Raises:
            GraphError: an unknown id, or edges still using some of them (naming them).
        """
        self.graph.flush()
        remove_vertices(self.graph, np.asarray(list(ids) if not isinstance(ids, np.ndarray)
                                              else ids))

    def remove_vertex(self, vertex: BaseVertex | int) -> bool:
        """Remove one vertex (g2o's ``removeVertex``), see :meth:`remove_vertices`.

        Args:
            vertex: The vertex or its id.
        """
        self.remove_vertices([vertex.id if isinstance(vertex, BaseVertex) else int(vertex)])
        return True

    def edge_sets(self) -> list[EdgeSet]:
        """One :class:`~graphopt.edge_set.EdgeSet` per edge group, over all its edges (for
        graphs built by others, such as a file reader)."""
        self.graph.flush()
        out = []
        for g in self.graph.groups.values():
            g.finalize()
            out.append(EdgeSet(self.graph, g, g.uids.copy(), ascending=True))
        return out
