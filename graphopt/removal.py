"""Removing edges and vertices from a :class:`~graphopt.graph.Graph` (g2o's ``removeEdge`` and
``removeVertex``).

The arrays close their gaps: edges keep their uids (so :class:`~graphopt.edge_set.EdgeSet`\\ s
stay valid), vertices get new slots (the bound vertex objects follow). Objects removed become
free objects again, keeping their values, and can be added again. The structure built on the
old graph is stale: the next run builds a new one.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from graphopt.errors import GraphError

if TYPE_CHECKING:
    from graphopt.graph import Graph
    from graphopt.storage import EdgeGroup, VertexStore


def remove_edges(graph: Graph, group: EdgeGroup, index: np.ndarray) -> None:
    """Remove edges of a group (an emptied group leaves the graph).

    Args:
        graph: The graph.
        group: The group.
        index: ``(r,)`` distinct edge indices in the group.
    """
    graph.flush()
    if not len(index):
        return
    gone = group.uids[index]
    objs = [e for e in graph._edge_objects if e._group is group]
    if objs:  # edge objects among them become free objects again (re-addable)
        hit = np.isin(np.array([e._uid for e in objs]), gone)
        for e, h in zip(objs, hit.tolist(), strict=True):
            if h:
                e._detach()
        graph._edge_objects = [e for e in graph._edge_objects if e._group is not None]
    group.remove(index)
    graph.removals += 1
    if group.size == 0:
        graph.groups.pop((group.etype, id(group.params)), None)


def remove_vertices(graph: Graph, ids: Any) -> None:
    """Remove vertices that no edge uses any more.

    Args:
        graph: The graph.
        ids: Vertex ids.

    Raises:
        GraphError: an unknown id, or edges still using some of them (naming them).
    """
    arr = np.atleast_1d(np.asarray(ids))
    if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
        raise GraphError(f"remove_vertices: ids must be integers, got {ids!r}")
    wanted = np.unique(arr.astype(np.int64))
    known = graph.ids
    unknown = [v for v in wanted.tolist() if v not in known]
    if unknown:
        raise GraphError(f"remove_vertices: no vertex with id {unknown[:10]}")
    for g in graph.groups.values():
        g.finalize()
        used = np.isin(g.vertex_ids, wanted).any(axis=1)
        if used.any():
            busy = np.intersect1d(g.vertex_ids[used], wanted)
            raise GraphError(
                f"remove_vertices: vertices {busy[:10].tolist()} are still used by "
                f"{int(used.sum())} {g.etype.__name__} edges (first on vertices "
                f"{g.vertex_ids[int(np.flatnonzero(used)[0])].tolist()}); remove those first")
    by_store: dict[int, tuple[VertexStore, list[int]]] = {}
    for vid in wanted.tolist():
        st, slot = known.pop(vid)
        by_store.setdefault(id(st), (st, []))[1].append(slot)
        v = graph._objects.pop(vid, None)
        if v is not None:
            v._detach()
    graph.removals += bool(by_store)
    for st, slots in by_store.values():
        st.remove(np.array(slots))
        if len(st) == 0:
            del graph.stores[st.vtype]
        for slot, vid in enumerate(st.ids.tolist()):
            known[vid] = (st, slot)
            v = graph._objects.get(vid)
            if v is not None:
                v._slot = slot
