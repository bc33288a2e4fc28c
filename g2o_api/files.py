"""``SparseOptimizer.load`` / ``save`` through graphopt's g2o/TORO/GTSAM reader and writer
(:mod:`graphopt.io.g2o`, the builder :mod:`graphopt.types.slam_graph`).

``load`` builds the graph with graphopt's builder (one array call per tag) and adopts its arrays
as banks and batches, creating one record per vertex and edge for ``vertices()`` and
``edges()``. ``save`` writes the banks and batches with the current estimates; landmark
numbers that a GTSAM file shared with poses are written renumbered (the load says so, once).
"""

from __future__ import annotations

import gc
import os
import warnings
from typing import Any

import numpy as np

from graphopt.errors import GraphError
from graphopt.io.g2o import read_graph, write_g2o
from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock
from graphopt.optimizer import SparseOptimizer as CoreOptimizer
from graphopt.types import slam_tags
from graphopt.types.isometry3 import pose_from_qt, pose_to_qt
from graphopt.types.slam_graph import build_graph

from .batch import Batch
from .edges_icp import ICP_EDGES, EdgeGICP
from .edges_sba import SBA_EDGES
from .edges_slam import SLAM_EDGES
from .params import CameraParameters, ParameterCamera, ParameterSE2Offset, ParameterSE3Offset
from .sba_cam import SBA_CAM_CLASSES
from .vertices import VERTEX_CLASSES, Bank

__all__ = ["load", "save"]

#: graphopt vertex type name → (g2o class name, file tag).
_VERTICES = {"VertexSE2": ("VertexSE2", "VERTEX_SE2"), "VertexPointXY": ("VertexPointXY",
             "VERTEX_XY"), "VertexSE3": ("VertexSE3", "VERTEX_SE3:QUAT"),
             "VertexPointXYZ": ("VertexPointXYZ", "VERTEX_TRACKXYZ")}
_VERTEX_TAGS = {tag for _, tag in _VERTICES.values()}
#: The g2o classes load() may create (the file's types), by kind.
_VERTEX_CLASSES = [*VERTEX_CLASSES.values(), SBA_CAM_CLASSES["VertexCam"],
                   SBA_CAM_CLASSES["VertexIntrinsics"]]
_EDGE_CLASSES = [c for c in (*SLAM_EDGES.values(), *SBA_EDGES.values(), *ICP_EDGES.values(),
                             *SBA_CAM_CLASSES.values()) if hasattr(c, "_perm")]
_GICP = "EDGE_V_V_GICP"
_GICP_TYPES = ("EdgeVVGicp", "EdgeVVGicpPlaneToPlane")
#: graphopt edge type name → (g2o class name, file tag).
_EDGES = {"EdgeSE2": ("EdgeSE2", "EDGE_SE2"), "EdgeSE2PointXY": ("EdgeSE2PointXY", "EDGE_SE2_XY"),
          "EdgeSE3": ("EdgeSE3", "EDGE_SE3:QUAT"),
          "EdgeSE3PointXYZ": ("EdgeSE3PointXYZ", "EDGE_SE3_TRACKXYZ")}


def load(opt: Any, filename: str | os.PathLike[str]) -> None:
    """Add a graph file's vertices, edges and parameters to ``opt``.

    Args:
        opt: The g2o optimizer (must be empty).
        filename: The file.

    Raises:
        GraphError: a malformed file (one line naming file and line), or ``opt`` not empty.
    """
    if opt._vertices or opt._edges:
        raise GraphError("load: graphopt.g2o loads into an empty optimizer only")
    enabled = gc.isenabled()
    gc.disable()  # one record per vertex and edge: see SparseOptimizer._prepare
    try:
        _load(opt, filename)
    finally:
        if enabled:
            gc.enable()


def _load(opt: Any, filename: str | os.PathLike[str]) -> None:
    """:func:`load`'s work (with the collector paused)."""
    graph = read_graph(filename)
    try:
        slam = build_graph(graph, optimizer=CoreOptimizer())
    except GraphError as exc:
        if "has no vertex line" not in str(exc):
            raise
        # GTSAM files name landmarks (or poses) without vertex lines: estimate those from the
        # edges, keep the file's estimates of the others (g2o's load would leave them at 0).
        slam = build_graph(graph, optimizer=CoreOptimizer(), guess=True)
        _restore_vertex_lines(slam, graph)
    for note in slam.notes:
        if "point j is vertex" in note:
            warnings.warn(f"{filename}: {note}; save() writes them renumbered", stacklevel=4)
    core = slam.optimizer
    banks: dict[type, Bank] = {}
    for gtype, store in core.graph.stores.items():
        cls = _api_class(gtype.__name__, _VERTEX_CLASSES, "vertices")
        recs = []
        for vid, fixed in zip(store.ids.tolist(), store.fixed.tolist(), strict=True):
            r = cls()
            r._id, r._fixed, r._opt = vid, fixed, opt._ref
            opt._vertices[vid] = r
            recs.append(r)
        banks[gtype] = Bank(gtype, recs, store.estimates.copy())
    offsets = {}
    for pid, p in slam.offsets.items():
        par = ParameterSE3Offset()
        par.set_id(pid)
        par.set_offset(np.vstack([p.offset, [0, 0, 0, 1]]))
        opt._parameters[pid] = par
        offsets[id(p)] = pid
    for pid, (tag, v) in graph.parameters.items():
        opt._parameters[pid] = _parameter(pid, tag, np.asarray(v, float))
    batches: dict[Batch, list[Any]] = {}
    for g in core.edge_groups():
        g.finalize()
        cls = _api_class(g.etype.__name__, _EDGE_CLASSES, "edges")
        if cls._nparams == 0 and cls._param_type and g.params is not None:
            # Intrinsics on the edge (or, for the Sim3 projections, on g2o's Sim3 vertex): the
            # batch's key is their numbers, no parameter ids.
            p, pids = g.params, []
            key = (p.fx, p.fy, p.cx, p.cy, *((p.bf,) if hasattr(p, "bf") else ()))
        else:
            pids = _param_ids(g.params, offsets, opt._parameters)
            key = tuple(pids)
        info = g.information
        meas = g.measurements.copy()  # the records keep row views of it
        infos = [info] * len(meas) if info.ndim == 2 else list(info)
        vmap, edges = opt._vertices, opt._edges
        k = g.vertex_ids.shape[1]  # the class's count, or the edges' own (the LotsOf edges)
        where = [cls._perm.index(q) for q in range(k)] if len(cls._perm) == k else range(k)
        raws = (_gicp_measurements(graph, g.vertex_ids, meas) if cls._gname == "EdgeVVGicp"
                else list(meas))
        recs = []
        for row, z, inf in zip(g.vertex_ids.tolist(), raws, infos, strict=True):
            e = cls()
            e._v = [vmap[row[p]] for p in where]
            e._meas, e._info, e._opt = z, inf, opt._ref
            if pids:
                e._pids = tuple(pids)
            edges[e] = None
            recs.append(e)
        banks_of = [opt._vertices[v]._bank for v in g.vertex_ids[0].tolist()]
        batch = Batch(opt, cls, g.etype, opt._core_param(cls, key), recs, g.vertex_ids.copy(),
                      banks_of, meas, None if g.info_is_identity else info.copy(), {})
        batches[batch] = recs
    opt._banks, opt._batches = banks, batches
    opt._records_dirty, opt._core = False, None


def _parameter(pid: int, tag: str, v: np.ndarray) -> Any:
    """The g2o parameter record of a parameter line (the values as the builder reads them).

    Args:
        pid: The id.
        tag: ``PARAMS_CAMERAPARAMETERS``, ``PARAMS_SE2OFFSET`` or ``PARAMS_CAMERACALIB``.
        v: The line's values after the id.
    """
    if tag == "PARAMS_CAMERAPARAMETERS":
        par: Any = CameraParameters(v[0], v[1:3], v[3])
    elif tag == "PARAMS_SE2OFFSET":
        par = ParameterSE2Offset()
        par.set_offset(v[:3])
    elif tag == "PARAMS_CAMERACALIB":
        par = ParameterCamera()
        par.set_offset(np.vstack([pose_from_qt(v[None, :7])[0], [0, 0, 0, 1]]))
        par.set_kcam(*v[7:11].tolist())
    else:
        raise NotImplementedError(f"load: graphopt.g2o has no class for {tag} parameters")
    par.set_id(pid)
    return par


def _gicp_measurements(graph: GraphFile, vids: np.ndarray, meas: np.ndarray) -> list[Any]:
    """``EdgeGICP`` measurements of the file's GICP lines, with their normals (graphopt's
    type reads the points only; save() writes the normals back)."""
    block = graph.edges[_GICP]
    if block.ids.shape != vids.shape or not np.array_equal(block.ids, vids):
        raise GraphError(f"{graph.path}: {_GICP} edges were built in another order")
    out = []
    for row in np.asarray(block.measurements, float):
        m = EdgeGICP()
        m.pos0, m.normal0, m.pos1, m.normal1 = row[0:3], row[3:6], row[6:9], row[9:12]
        out.append(m)
    return out


def _api_class(name: str, classes: Any, what: str) -> Any:
    """The g2o class of a graphopt type (by its ``_gname``; ``EdgeSE2LotsOfXY_3`` is
    ``EdgeSE2LotsOfXY``'s); a clear error when there is none."""
    name = _VERTICES.get(name, _EDGES.get(name, (name,)))[0]
    base, _, k = name.rpartition("_")
    if base and k.isdigit():
        name = base
    found = next((c for c in classes if getattr(c, "_gname", None) == name), None)
    if found is None:
        raise NotImplementedError(f"load: graphopt.g2o has no class for {name} {what} yet")
    return found


def _param_ids(params: Any, offsets: dict[int, int], known: dict[int, Any]) -> list[int]:
    """The parameter ids of an edge group's graphopt parameter object(s)."""
    if params is None:
        return []
    objs = params if isinstance(params, tuple) else (params,)
    out = []
    for p in objs:
        pid = offsets.get(id(p))
        if pid is None and getattr(p, "id", None) in known:  # SE2 offsets, cameras on a pose
            pid = p.id
        if pid is None:  # a camera (PARAMS_CAMERAPARAMETERS): the one with its numbers
            pid = next(k for k, c in known.items() if isinstance(c, CameraParameters)
                       and (c.focal_length, *c.principle_point.tolist(), c.baseline)
                       == (p.fx, p.cx, p.cy, p.baseline))
        out.append(pid)
    return out


def _restore_vertex_lines(slam: Any, graph: GraphFile) -> None:
    """Put back the estimates of the vertices that have vertex lines (after a guess)."""
    for tag, block in graph.vertices.items():
        if tag not in _VERTEX_TAGS:  # the guess sets the pose-graph tags' vertices only
            continue
        ids = slam.vertex_ids[tag][: len(block.ids)]
        store = next(st for gt, st in slam.optimizer.graph.stores.items()
                     if _VERTICES.get(gt.__name__, ("", ""))[1] == tag)
        order = np.argsort(store.ids)
        rows = order[np.searchsorted(store.ids[order], ids)]
        values = np.asarray(block.values, float)
        est = store.estimates.copy()
        est[rows] = pose_from_qt(values) if tag == "VERTEX_SE3:QUAT" else values
        store.estimates = est


def save(opt: Any, filename: str | os.PathLike[str]) -> None:
    """Write ``opt``'s graph with the current estimates as a g2o file, atomically.

    Args:
        opt: The g2o optimizer.
        filename: The destination.

    Raises:
        NotImplementedError: a vertex or edge type the g2o writer has no line for.
    """
    opt._prepare()
    vertices, fixed = {}, []
    for gtype, bank in opt._banks.items():
        name = gtype.__name__
        tag = _VERTICES[name][1] if name in _VERTICES else slam_tags.TAG_OF_TYPE.get(name, "")
        if tag not in _VERTEX_TAGS and tag not in slam_tags.VERTEX_TAGS:
            raise NotImplementedError(f"save: no g2o file line for {name} vertices")
        est = np.asarray(bank.estimates())
        values = (pose_to_qt(est) if tag == "VERTEX_SE3:QUAT" else slam_tags.values(tag, est)
                  if tag in slam_tags.VERTEX_TAGS else est.copy())
        vertices[tag] = VertexBlock(bank.ids.copy(), values, np.zeros(len(bank.ids), np.int64))
        fixed.append(bank.ids[bank.user_fixed])
    edges = {}
    for b, recs in opt._batches.items():
        name = b.gtype.__name__
        m, d = len(recs), b.gtype.dimension
        info = np.broadcast_to(np.eye(d) if b.info is None else b.info, (m, d, d)).copy()
        if name not in _EDGES:
            pids = np.array([list(r._pids) for r in recs], np.int64).reshape(m, -1)
            try:
                if name in _GICP_TYPES:
                    key, block = _GICP, _gicp_block(b, recs, info)
                else:
                    key, block = slam_tags.edge_block(name, b.vids, b.meas, info, pids)
            except NotImplementedError:
                raise NotImplementedError(f"save: no g2o file line for {b.cls.__name__} "
                                          "edges") from None
            if key in edges:
                old = edges[key]
                block = EdgeBlock(*(np.concatenate([getattr(old, f), getattr(block, f)])
                                    for f in ("ids", "measurements", "information", "lines",
                                              "params")))
            edges[key] = block
            continue
        tag = _EDGES[name][1]
        meas = pose_to_qt(b.meas) if tag == "EDGE_SE3:QUAT" else b.meas.copy()
        params = None
        if tag == "EDGE_SE3_TRACKXYZ":
            params = np.full(m, recs[0]._pids[0] if recs else 0, np.int64)
        block = EdgeBlock(b.vids.copy(), meas, info, np.zeros(m, np.int64), params)
        if tag in edges:  # several batches of one tag (parameters): one block
            old = edges[tag]
            block = EdgeBlock(*(np.concatenate([getattr(old, f), getattr(block, f)])
                                for f in ("ids", "measurements", "information", "lines")),
                              None if params is None else np.concatenate([old.params, params]))
        edges[tag] = block
    offsets = {pid: pose_to_qt(p.offset().matrix()[None, :3])[0]
               for pid, p in opt._parameters.items() if type(p) is ParameterSE3Offset}
    others = {pid: _parameter_line(p) for pid, p in opt._parameters.items()
              if type(p) is not ParameterSE3Offset}
    graph = GraphFile(path="<generated>", vertices=vertices, edges=edges, offsets=offsets,
                      parameters={pid: v for pid, v in others.items() if v is not None},
                      fixed=np.concatenate(fixed) if fixed else np.zeros(0, np.int64))
    write_g2o(filename, graph)



def _parameter_line(p: Any) -> tuple[str, np.ndarray] | None:
    """A parameter's file line: ``(tag, values after the id)``; ``None`` for a parameter g2o
    files have no line for."""
    if isinstance(p, CameraParameters):
        return "PARAMS_CAMERAPARAMETERS", np.array([p.focal_length, *p.principle_point,
                                                    p.baseline])
    if isinstance(p, ParameterSE2Offset):
        return "PARAMS_SE2OFFSET", p.offset().to_vector()
    if isinstance(p, ParameterCamera):
        qt = pose_to_qt(p.offset().matrix()[None, :3])[0]
        return "PARAMS_CAMERACALIB", np.concatenate([qt, p._k])
    return None


def _gicp_block(b: Batch, recs: list[Any], info: np.ndarray) -> EdgeBlock:
    """The ``EDGE_V_V_GICP`` lines of a GICP batch: ``pos0 normal0 pos1 normal1`` (the
    normals the records hold; g2o's defaults ``(0, 0, 1)`` where a vector was given)."""
    m = len(recs)
    normals = np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 1.0], (m, 1))
    for i, r in enumerate(recs):
        if isinstance(r._meas, EdgeGICP):
            normals[i] = [*np.ravel(r._meas.normal0), *np.ravel(r._meas.normal1)]
    pos = np.asarray(b.meas, float).reshape(m, 6)
    values = np.column_stack([pos[:, :3], normals[:, :3], pos[:, 3:], normals[:, 3:]])
    return EdgeBlock(b.vids.copy(), values, info, np.zeros(m, np.int64), np.zeros((m, 0),
                                                                                  np.int64))
