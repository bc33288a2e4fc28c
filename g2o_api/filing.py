"""Filing: the records of a g2o optimizer become arrays at ``initialize_optimization`` — one
:class:`~graphopt.g2o.vertices.Bank` per graphopt vertex type, one
:class:`~graphopt.g2o.batch.Batch` per g2o edge class and parameters.

Every step is a pass over the records: a list comprehension reading one slot (Python 3.11
specialises the read: about 9 ns a record, half the cost of ``map`` with an ``attrgetter``) or
a C pass (``set``, ``count``, ``bytes.join``); a Python loop per record only where a graph
needs one (vertices an edge type reads as another graphopt type, vertices of two classes
sharing a graphopt type, records filed before, whose estimates come from their store).
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import compress, repeat
from operator import attrgetter, is_, itemgetter
from typing import Any

import numpy as np

from graphopt.errors import GraphError

from .batch import Batch, stack_information, stack_measurements
from .edges import BaseEdge
from .vertices import Bank, BaseVertex, core_type

__all__ = ["bucket_edges", "by_class", "file_edges", "file_vertices"]

_ID = attrgetter("_id")
#: Up to this many vertex ids (edges x positions), the check that every one was added is a set
#: of Python ints; above, ``np.isin``.
_SET_CHECK = 1024


def by_class(records: list[Any]) -> dict[type, list[Any]]:
    """The records by class, each list in the order given."""
    types = list(map(type, records))
    classes = dict.fromkeys(types)  # in order of first appearance
    if len(classes) == 1:
        return {types[0]: records}
    # One C pass per class (programs have a few classes; a Python loop costs 4x a pass).
    return {c: list(compress(records, map(is_, types, repeat(c)))) for c in classes}


def bucket_edges(edges: Any) -> dict[tuple[Any, ...], list[Any]]:
    """The edges by class and parameter key, in the order added (one batch each).

    Args:
        edges: The edge records (an iterable, in the order added).
    """
    buckets: dict[tuple[Any, ...], list[Any]] = {}
    for cls, recs in by_class(list(edges)).items():
        key = cls._shared_key(recs)
        if key is not None:  # the usual case: one key for the class
            buckets[(cls, key)] = recs
            continue
        keys = cls._keys_of(recs)
        for e, key in zip(recs, keys, strict=True):
            b = buckets.get((cls, key))
            if b is None:
                buckets[(cls, key)] = b = []
            b.append(e)
    return buckets


def _read_as(edge_buckets: dict[tuple[Any, ...], list[BaseEdge]]) -> dict[int, str]:
    """``{id(vertex): graphopt type name}`` of the vertices an edge type reads as another
    graphopt type than their class's (``EdgeProjectPSI2UV``'s inverse-depth point)."""
    names: dict[int, str] = {}
    for (cls, _), recs in edge_buckets.items():
        for pos, name in cls._vertex_as.items():
            for e in recs:
                v = e.vertex(pos)
                if v is not None:
                    names[id(v)] = name
    return names


def file_vertices(vertices: list[BaseVertex],
                  edge_buckets: dict[tuple[Any, ...], list[BaseEdge]]) -> dict[type, Bank]:
    """One bank per graphopt vertex type, its records in the order added.

    Args:
        vertices: The optimizer's vertex records, in the order added.
        edge_buckets: Its edges by class and parameter key (:func:`bucket_edges`).
    """
    names = _read_as(edge_buckets)
    classes = by_class(vertices)
    buckets: dict[str, list[BaseVertex]] = {}
    if names or len({c._gname for c in classes}) < len(classes):
        for v in vertices:  # a record at a time: the order added within each type
            buckets.setdefault(names.get(id(v)) or v._gname, []).append(v)
    else:
        buckets = {c._gname: recs for c, recs in classes.items()}
    banks = {}
    for name, recs in buckets.items():
        gtype = core_type(name)
        cls, n = type(recs[0]), len(recs)
        est = np.empty((n, *gtype.estimate_shape))
        todo, where = recs, slice(None)  # the records to convert: all, unless
        if [v._bank for v in recs].count(None) != n:  # some were filed before (their store's)
            where = []
            for i, v in enumerate(recs):
                if v._bank is None:
                    where.append(i)
                else:
                    est[i] = v._bank.estimates()[v._slot]
            todo = [recs[i] for i in where]
        if todo:  # one conversion
            raws = [v._est for v in todo]
            if any(map(is_, raws, repeat(None))):
                raws = [r if r is not None else v._default() for r, v in zip(raws, todo,
                                                                              strict=True)]
            conv = cls._to_array(raws, [v._id for v in todo])
            cls._finish(conv, todo)
            est[where] = conv
        banks[gtype] = Bank(gtype, recs, est)
    return banks


def _check_known(cls: type, vids: np.ndarray, perm: tuple[int, ...],
                 vertices: dict[int, BaseVertex]) -> None:
    """Raise a GraphError naming the first edge one of whose vertices was not added.

    Args:
        cls: The g2o edge class.
        vids: ``(m, k)`` vertex ids in graphopt's position order (``perm``: position ``p``
            holds g2o vertex ``perm[p]``).
        perm: The class's permutation.
        vertices: ``{id: vertex}`` of the optimizer.
    """
    if vids.size <= _SET_CHECK:  # a few edges: a set of ints (isin: 10 µs at any size)
        if vertices.keys() >= set(vids.ravel().tolist()):
            return
        missing = np.array([[v not in vertices for v in row] for row in vids.tolist()])
    else:
        missing = ~np.isin(vids, np.fromiter(vertices, dtype=np.int64, count=len(vertices)))
        if not missing.any():
            return
    i, p = (int(a[0]) for a in np.nonzero(missing))
    g2o_order = [int(vids[i, perm.index(g)]) for g in range(len(perm))]
    raise GraphError(f"{cls.__name__} on vertices {g2o_order}: vertex {int(vids[i, p])} "
                     f"(position {perm[p]}) was not added to the optimizer")


def file_edges(owner: Any, edge_buckets: dict[tuple[Any, ...], list[BaseEdge]],
               vertices: dict[int, BaseVertex], core_param: Callable[[type, Any], Any]
               ) -> dict[Batch, list[BaseEdge]]:
    """One batch per g2o edge class and parameter key, with the edge records of each.

    Args:
        owner: The g2o optimizer (the batches' owner).
        edge_buckets: The edges by class and parameter key (:func:`bucket_edges`).
        vertices: ``{id: vertex}``, filed (each has its bank).
        core_param: graphopt's parameter object of a class and key.
    """
    batches: dict[Batch, list[BaseEdge]] = {}
    for (cls, pkey), recs in edge_buckets.items():
        gtype = cls._core_type(pkey)
        m, k = len(recs), len(recs[0]._v)  # the class's count, or the edges' own (LotsOf)
        perm = cls._perm if len(cls._perm) == k else tuple(range(k))
        more = [e._vn for e in recs] if k > 2 else []
        vids = np.empty((m, k), dtype=np.int64)  # in graphopt's position order (perm)
        for p, g in enumerate(perm):  # vertex ids column by column
            ids = ([e._v0._id for e in recs] if g == 0 else [e._v1._id for e in recs] if g == 1
                   else list(map(_ID, map(itemgetter(g - 2), more))))
            vids[:, p] = ids
        _check_known(cls, vids, perm, vertices)
        banks = [vertices[int(vids[0, p])]._bank for p in range(k)]
        meas = stack_measurements(cls, recs)
        info = stack_information(cls, recs, gtype.dimension)
        batch = Batch(owner, cls, gtype, core_param(cls, pkey), recs, vids, banks, meas, info,
                      cls._data(recs))
        batches[batch] = recs
    return batches
