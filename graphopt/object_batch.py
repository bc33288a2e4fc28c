"""Objects added one at a time, turned into arrays in bulk.

``add_vertex``/``add_edge`` only record the object (a few checks of attributes that are
``None``); when the optimizer next needs its arrays (initialisation, a query, a bulk call), the
buffered objects of one type become one batch: the functions here gather their fields into
arrays and name the first object whose field has the wrong shape or kind. The batch then goes
through the same checks as ``add_vertices``/``add_edges`` (the information matrices' are here,
:func:`checked_information`, shared by both paths). A :class:`BatchError` carries the object (or
row) to blame, which the graph drops from its buffer (it can be fixed and added again).
"""

from __future__ import annotations

from functools import partial
from operator import attrgetter, is_
from typing import Any

import numpy as np

from graphopt.edge import BaseEdge
from graphopt.edge_group import EdgeGroup
from graphopt.errors import GraphError
from graphopt.robust_kernel import RobustKernel, kernel_key
from graphopt.vertex import BaseVertex

_is_none = partial(is_, None)


class BatchError(GraphError):
    """A :class:`GraphError` caused by one object of a batch.

    Args:
        message: The message (naming the object).
        culprit: The object.
    """

    def __init__(self, message: str, culprit: Any) -> None:
        super().__init__(message)
        self.culprit = culprit


def _shape_of(value: Any) -> tuple[int, ...] | None:
    """The shape of ``value`` as a float array, or ``None`` if it is not numeric."""
    try:
        return np.asarray(value, dtype=float).shape
    except (TypeError, ValueError):
        return None


def _stack(values: list[Any], shape: tuple[int, ...]) -> np.ndarray | None:
    """``(n, *shape)`` floats, or ``None`` if some value is not numeric of that shape."""
    try:
        arr = np.array(values, dtype=float)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (len(values), *shape) else None


def _kernel_slot(group: EdgeGroup, kernel: Any, blame: Any, i: int) -> int:
    """The group's slot of a kernel (a :class:`BatchError` for edge ``i`` if it is none)."""
    try:
        return group.kernel_slot(kernel)
    except GraphError as exc:
        raise blame(i, str(exc)) from None


def vertex_batch(vtype: type[BaseVertex], objs: list[BaseVertex]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ids, estimates and flags of buffered vertices of one type.

    Args:
        vtype: Their type.
        objs: The vertices.

    Returns:
        ``(ids (n,), estimates (n, *estimate_shape), fixed (n,), marginalized (n,))``.

    Raises:
        BatchError: naming the first vertex whose estimate is not numeric, of the wrong shape,
            or invalid (non-finite or off the manifold).
    """
    n = len(objs)
    shape = tuple(vtype.estimate_shape)
    ids = np.fromiter((v._id for v in objs), np.int64, n)  # type: ignore[misc]
    est = _stack([v._estimate for v in objs], shape)
    if est is None:
        for v in objs:
            got = _shape_of(v._estimate)
            if got != shape:
                what = "is not numeric" if got is None else f"has shape {got}, expected {shape}"
                raise BatchError(f"vertex {v._id} ({vtype.__name__}): estimate {what}", v)
    assert est is not None
    ok = vtype.validate(est)
    if not np.all(ok):
        i = int(np.flatnonzero(~ok)[0])
        raise BatchError(f"vertex {int(ids[i])} ({vtype.__name__}): invalid estimate "
                         f"(non-finite or off the manifold): "
                         f"{np.array2string(est[i], threshold=20)}", objs[i])
    fixed = np.fromiter((v._fixed for v in objs), bool, n)
    marg = np.fromiter((v._marginalized for v in objs), bool, n)
    return ids, est, fixed, marg


def edge_batch(group: EdgeGroup, objs: list[BaseEdge]) -> dict[str, Any]:
    """The arrays of buffered edges of one group, as ``add_edges`` takes them.

    Args:
        group: Their group.
        objs: The edges.

    Returns:
        ``vids (m, k)``, ``meas``, ``info`` (``(e, e)`` when no edge has its own, else
        ``(m, e, e)``), ``kernel`` (one slot or ``(m,)``), ``levels`` (one or ``(m,)``),
        ``data``.

    Raises:
        BatchError: naming the first edge with a vertex that is not a vertex or an id, a
            measurement or information matrix of the wrong shape, or other data keys.
    """
    et = group.etype
    m, e = len(objs), et.dimension
    try:  # vertex objects (the common case), else ids or a mix
        flat = [v._id for o in objs for v in o._vertices]
    except AttributeError:
        flat = [v._id if isinstance(v, BaseVertex) else v for o in objs for v in o._vertices]
    vids = np.array(flat)
    if vids.dtype.kind not in "iu" or vids.shape != (m * group.k,):
        for o in objs:
            for pos, v in enumerate(o._vertices):
                vid = v._id if isinstance(v, BaseVertex) else v
                if not isinstance(vid, int | np.integer) or isinstance(vid, bool):
                    raise BatchError(f"{o!r}: vertex {pos} is not a vertex with an id or an "
                                     f"integer id: {v!r}", o)
    vids = vids.astype(np.int64, copy=False).reshape(m, group.k)

    def blame(i: int, what: str) -> BatchError:
        return BatchError(f"{et.__name__} on vertices {vids[i].tolist()}: {what}", objs[i])

    meas = _stack(list(map(attrgetter("_measurement"), objs)), group.mshape)
    if meas is None:
        for i, o in enumerate(objs):
            got = _shape_of(o._measurement)
            if got != group.mshape:
                raise blame(i, "measurement is not numeric" if got is None else
                            f"measurement has shape {got}, expected {group.mshape}")
    infos = list(map(attrgetter("_information"), objs))
    if all(map(_is_none, infos)):
        info = np.eye(e)
    else:
        eye = np.eye(e)
        info = _stack([eye if x is None else x for x in infos], (e, e))
        if info is None:
            for i, x in enumerate(infos):
                got = (e, e) if x is None else _shape_of(x)
                if got != (e, e):
                    raise blame(i, "information is not numeric" if got is None else
                                f"information has shape {got}, expected {(e, e)}")
    # Kernel slots: one lookup per distinct kernel value (ORB-SLAM gives every edge its own
    # kernel object, with a few distinct widths).
    kernels = list(map(attrgetter("_robust_kernel"), objs))
    kern: list[int] | int
    if kernels.count(kernels[0]) == m:  # one kernel object (or none) for all (kernels
        # compare by identity)
        kern = _kernel_slot(group, kernels[0], blame, 0)
    else:  # by value (type and parameters; inline: a function call per kernel costs more)
        keys = [None if k is None else (k.__class__, *k.__dict__.values()) for k in kernels]
        try:
            first = dict.fromkeys(keys)
        except TypeError:  # a kernel with unhashable parameters: by identity
            keys = [None if k is None else kernel_key(k) for k in kernels]
            first = dict.fromkeys(keys)
        where = {key: i for i, key in reversed(list(enumerate(keys)))}
        slot_of = {key: -1 if key is None else _kernel_slot(group, kernels[where[key]], blame,
                                                              where[key]) for key in first}
        kern = list(map(slot_of.__getitem__, keys))
        # Every object filed under its value's slot, so that a width changed on one of them
        # later is caught (EdgeGroup._check_members) instead of reaching the others' edges.
        members: dict[int, list[RobustKernel]] = {}
        for slot, k in zip(kern, kernels, strict=True):
            if slot >= 0:
                members.setdefault(slot, []).append(k)
        for slot, same in members.items():
            group.add_kernel_members(slot, same)
        if min(kern) == max(kern):
            kern = kern[0]
    levels = list(map(attrgetter("_level"), objs))
    keys = objs[0].data.keys()
    data: dict[str, np.ndarray] = {}
    if any(map(attrgetter("data"), objs)):
        for i, o in enumerate(objs):
            if o.data.keys() != keys:
                raise blame(i, f"data keys {sorted(o.data)}, the batch's first edge has "
                               f"{sorted(keys)}")
        for key in keys:
            try:
                data[key] = np.array([o.data[key] for o in objs])
            except ValueError:
                first = np.shape(objs[0].data[key])
                i = next(i for i, o in enumerate(objs) if np.shape(o.data[key]) != first)
                raise blame(i, f"data[{key!r}] has shape {np.shape(objs[i].data[key])}, the "
                               f"batch's first edge {first}") from None
    return {"vids": vids, "meas": meas, "info": info,
            "kernel": kern if isinstance(kern, int) else np.array(kern),
            "levels": levels[0] if min(levels) == max(levels) else np.array(levels),
            "data": data}


def checked_information(et: type[BaseEdge], vids: np.ndarray, info: np.ndarray) -> np.ndarray:
    """Information matrices checked (finite, symmetric, positive semi-definite); one matrix
    repeated for every edge comes back as one ``(e, e)`` matrix (every edge of w10000 and
    Victoria Park: the weighting is then a broadcast, not ``m`` products).

    Args:
        et: The edge type.
        vids: ``(m, k)`` the edges' vertex ids (to name one).
        info: ``(e, e)`` shared or ``(m, e, e)``.

    Raises:
        BatchError: naming the first edge whose own matrix fails (its index as culprit);
            a ``GraphError`` for a shared matrix.
    """
    m, e = len(vids), et.dimension
    infos = info.reshape(-1, e, e)
    if len(infos) == 1 and infos[0].tobytes() in _CHECKED_INFO:
        return info  # one matrix checked before (an online loop adds a few edges at a time)

    def bad_info(ok: np.ndarray, what: str) -> GraphError:
        if len(infos) == m:
            i = int(np.flatnonzero(~ok)[0])
            return BatchError(f"{et.__name__} on vertices {vids[i].tolist()}: {what}", i)
        return GraphError(f"{et.__name__} (one matrix for all {m} edges): {what}")

    if not np.isfinite(infos).all():  # per matrix only to name one
        raise bad_info(np.isfinite(infos).all(axis=(1, 2)), "non-finite information matrix")
    diag = infos.diagonal(axis1=1, axis2=2)
    if len(infos) > 1 and np.count_nonzero(infos) == np.count_nonzero(diag):
        # Diagonal matrices (σ⁻²·I per observation, a SLAM system's edges): symmetric, and
        # their eigenvalues are their diagonals (the test below, without eigvalsh and isclose;
        # per matrix only when a diagonal is negative, as its bound is never positive).
        if diag.min() < 0.0:
            ok = diag.min(axis=1) >= -1e-9 * np.maximum(np.abs(diag.max(axis=1)), 1.0)
            if not ok.all():
                raise bad_info(ok, "information matrix is not positive semi-definite")
        return infos[0].copy() if bool((infos == infos[0]).all()) else info
    sym = np.isclose(infos, np.swapaxes(infos, 1, 2), rtol=1e-9, atol=1e-12).all(axis=(1, 2))
    if not sym.all():
        raise bad_info(sym, "information matrix is not symmetric")

    def psd(mats: np.ndarray) -> np.ndarray:
        low = np.linalg.eigvalsh(mats)
        return low[:, 0] >= -1e-9 * np.maximum(np.abs(low[:, -1]), 1.0)

    # Distinct matrices only (most files share a few, often one: a comparison is 30x cheaper
    # than finding the distinct rows); per edge only to name a failure.
    if len(infos) > 1 and bool((infos == infos[0]).all()):
        distinct = infos[:1]
        info = infos[0].copy()
    elif len(infos) <= 1 or e <= 3:  # eigenvalues of all: cheaper than finding distinct
        distinct = infos
    else:  # distinct rows as bytes: 13x faster than np.unique(axis=0) on 6x6 matrices
        rows = np.ascontiguousarray(infos).reshape(len(infos), -1)
        keys = rows.view(np.dtype((np.void, rows.itemsize * rows.shape[1]))).ravel()
        distinct = infos[np.unique(keys, return_index=True)[1]]
    if not psd(distinct).all():
        raise bad_info(psd(infos), "information matrix is not positive semi-definite")
    if len(infos) == 1:
        if len(_CHECKED_INFO) >= 256:
            _CHECKED_INFO.clear()
        _CHECKED_INFO.add(infos[0].tobytes())
    return info


#: Single information matrices (as bytes) that passed the checks: an online loop adds one edge
#: at a time, nearly always with a matrix seen before (the checks cost 60 µs a call).
_CHECKED_INFO: set[bytes] = set()
