"""Build a :class:`~graphopt.optimizer.SparseOptimizer` from a g2o/TORO graph file's canonical
records (:class:`~graphopt.io.g2o_records.GraphFile`) with the SLAM types, and back.

======================  ===================  ============================================
canonical tag           graphopt type        notes
======================  ===================  ============================================
``VERTEX_SE2``          ``VertexSE2``        ``[x, y, θ]``
``VERTEX_XY``           ``VertexPointXY``
``VERTEX_SE3:QUAT``     ``VertexSE3``        ``[x y z qx qy qz qw]`` → ``[R | t]`` as g2o
``VERTEX_TRACKXYZ``     ``VertexPointXYZ``
``EDGE_SE2``            ``EdgeSE2``
``EDGE_SE2_XY``         ``EdgeSE2PointXY``
``EDGE_SE3:QUAT``       ``EdgeSE3``
``EDGE_SE3_TRACKXYZ``   ``EdgeSE3PointXYZ``  one edge group per ``PARAMS_SE3OFFSET`` id
======================  ===================  ============================================

Decisions (each also said in :attr:`SlamGraph.notes` when it applies):

* **Gauge.** ``FIX`` lines fix their vertices. Without any, the pose with the lowest id is
  fixed ("first pose fixed for the gauge"), as g2o's tools do.
* **TORO ``EQUIV a b``** is recorded (:attr:`SlamGraph.equiv`), not applied: both poses and
  all edges stay. In Olson's files every ``EQUIV`` pair is also joined by an ``EDGE2`` whose
  measurement is *not* the identity (``w100``: ``EDGE2 21 1 −0.061 −0.043 0.028``), so merging
  ``b`` into ``a`` would turn that edge into a self-loop and drop it. Keeping both is the graph
  a g2o conversion of the file describes (same vertices, same edges, no ``EQUIV`` tag).
* **Landmark ids.** g2o's ids are global. If the ids of point vertex lines
  (``VERTEX_XY``/``VERTEX_TRACKXYZ``) coincide with those of pose vertex lines — GTSAM writes
  landmarks in a namespace of their own (``known_landmark_localization_20.g2o``: poses 0–19,
  landmarks 0–3) — all point ids (lines and the point column of point edges) are shifted past
  the largest pose id in the optimizer; :func:`graph_file` shifts them back.
* **Initial guess** (``guess=True``; required when edges name vertices without a vertex line):
  poses by composing measurements along a BFS tree from the fixed poses (a fixed pose without
  a vertex line is the origin), landmarks from their first observation
  (:mod:`graphopt.types.slam_guess`); every vertex that is not fixed gets the guess, like g2o's
  ``computeInitialGuess``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graphopt.algorithms import LevenbergConfig
from graphopt.errors import GraphError
from graphopt.io.g2o_layouts import ends
from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock
from graphopt.optimizer import SparseOptimizer
from graphopt.types import slam_guess as sg
from graphopt.types import slam_tags as st
from graphopt.types.isometry3 import pose_from_qt, pose_to_qt
from graphopt.types.slam2d import EdgeSE2, EdgeSE2PointXY
from graphopt.types.slam3d import EdgeSE3, EdgeSE3PointXYZ, ParameterSE3Offset
from graphopt.types.slam_vertices import TAG_ORDER as _TAG_ORDER
from graphopt.types.slam_vertices import VERTEX_TYPES
from graphopt.types.slam_vertices import VertexTable as _Vertices
from graphopt.types.slam_vertices import to_estimates as _to_estimates
from graphopt.types.slam_vertices import vtype as _vtype
from graphopt.types.slam_vertices import where as _where

__all__ = ["POSE_GRAPH_INITIAL_LAMBDA", "SlamGraph", "build_graph", "graph_file",
           "pose_graph_levenberg"]

#: Edge tag → (edge type, vertex tag of each position).
EDGE_TYPES = {
    "EDGE_SE2": (EdgeSE2, ("VERTEX_SE2", "VERTEX_SE2")),
    "EDGE_SE2_XY": (EdgeSE2PointXY, ("VERTEX_SE2", "VERTEX_XY")),
    "EDGE_SE3:QUAT": (EdgeSE3, ("VERTEX_SE3:QUAT", "VERTEX_SE3:QUAT")),
    "EDGE_SE3_TRACKXYZ": (EdgeSE3PointXYZ, ("VERTEX_SE3:QUAT", "VERTEX_TRACKXYZ")),
}
#: LM's initial ``λ`` (identity damping) on pose graphs, with GTSAM's schedule. GTSAM starts at
#: 1e-5; ``benchmarks/bench_schedules.py --family posegraph --initial-lambdas ...`` measured
#: 1e-5 … 1e-9 on the eight graphs it builds (the data folder's four, four generated Manhattan
#: worlds): from 3e-6 LM needs as few or fewer iterations to within 1e-6 of the best chi2 on
#: every one of them — w10000 7 against 8, the sphere 4 against 5, two noisy Manhattan worlds
#: 15 against none in 60 and 27 against 41 — and no smaller value is as good on all (1e-8:
#: w10000 6, but two noisy worlds never reach the best minimum).
POSE_GRAPH_INITIAL_LAMBDA = 3e-6


def pose_graph_levenberg(schedule: str = "gtsam") -> LevenbergConfig:
    """Levenberg–Marquardt as pose graphs run it by default: GTSAM's schedule from
    :data:`POSE_GRAPH_INITIAL_LAMBDA` (other schedules keep their own start).

    Args:
        schedule: ``"gtsam"``, ``"g2o"`` or ``"ceres"`` (see :class:`~graphopt.LevenbergConfig`).
    """
    return LevenbergConfig(schedule=schedule, initial_lambda=(
        POSE_GRAPH_INITIAL_LAMBDA if schedule == "gtsam" else None))


_POSE_EDGES = {"VERTEX_SE2": "EDGE_SE2", "VERTEX_SE3:QUAT": "EDGE_SE3:QUAT"}
_POINT_EDGES = {"VERTEX_XY": "EDGE_SE2_XY", "VERTEX_TRACKXYZ": "EDGE_SE3_TRACKXYZ"}
def _ends(tag: str) -> tuple[str, ...]:
    """The vertex tag at each position of an edge tag (g2o's order)."""
    return EDGE_TYPES[tag][1] if tag in EDGE_TYPES else ends(tag)


@dataclass
class SlamGraph:
    """An optimizer built from a graph file, and what the building decided.

    Args:
        optimizer: The optimizer holding the vertices and edges.
        path: The file the records came from.
        vertex_ids: Vertex tag → ``(n,)`` optimizer ids, in the order they were added.
        vertex_lines: Vertex tag → ``(n,)`` 1-based line numbers (0: no vertex line).
        edges: Edge tag → the :class:`EdgeBlock` as read (file ids).
        vertex_counts: Vertex tag → number of vertices added.
        edge_counts: Edge tag → number of edges added.
        fixed: Fixed optimizer id → why (``"FIX line"`` or ``"first pose fixed for the
            gauge"``).
        point_id_offset: Added to the file's point ids (0 unless they clashed with pose ids).
        offsets: ``PARAMS_SE3OFFSET`` id → its parameter object (one edge group each).
        equiv: ``(k, 2)`` TORO ``EQUIV`` pairs (recorded, not applied).
        guessed: ``(g,)`` optimizer ids whose estimate came from the initial guess.
        notes: One-line remarks on the decisions above.
        parameters: The other parameter lines (id → ``(tag, values)``), as read.
    """

    optimizer: SparseOptimizer
    path: str
    vertex_ids: dict[str, np.ndarray]
    vertex_lines: dict[str, np.ndarray]
    edges: dict[str, EdgeBlock]
    vertex_counts: dict[str, int]
    edge_counts: dict[str, int]
    fixed: dict[int, str]
    point_id_offset: int = 0
    offsets: dict[int, ParameterSE3Offset] = field(default_factory=dict)
    equiv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    guessed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    notes: list[str] = field(default_factory=list)
    parameters: dict[int, tuple[str, np.ndarray]] = field(default_factory=dict)


def _check_tags(graph: GraphFile) -> None:
    for kind, tags, known in (("vertex", graph.vertices, [*VERTEX_TYPES, *st.VERTEX_TAGS]),
                              ("edge", graph.edges, [*EDGE_TYPES, *st.EDGE_TAGS])):
        bad = [t for t in tags if t not in known and not st.known(t)]
        if bad:
            raise GraphError(f"{graph.path}: {kind} tag {bad[0]} is not supported by the SLAM "
                             f"types (supported: {', '.join(known)})")


def _point_offset(graph: GraphFile) -> int:
    """0, or the shift that moves point ids past every pose id when vertex lines of both kinds
    use the same ids (edges alone cannot tell a clash from a wrong id)."""
    pose, point = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for tag, block in graph.vertices.items():
        (point if tag in _POINT_EDGES else pose).append(np.asarray(block.ids, np.int64))
    if graph.separate_landmarks:
        # GTSAM's LANDMARK2 numbers landmarks as L(j), apart from the poses X(i): the ids
        # the edges name count too (such files rarely have vertex lines).
        for tag, block in graph.edges.items():
            for c, vtag in enumerate(_ends(tag)):
                (point if vtag in _POINT_EDGES else pose).append(block.ids[:, c])
    pose_ids, point_ids = np.concatenate(pose), np.concatenate(point)
    if not len(point_ids) or not np.isin(point_ids, pose_ids).any():
        return 0
    for tag, block in graph.edges.items():
        for c, vtag in enumerate(_ends(tag)):
            if vtag not in _POINT_EDGES:
                pose_ids = np.concatenate([pose_ids, block.ids[:, c]])
    return int(pose_ids.max()) + 1 - min(int(point_ids.min()), 0)


def _edge_ids(graph: GraphFile, shift: int) -> dict[str, np.ndarray]:
    out = {}
    for tag, block in graph.edges.items():
        ids = np.asarray(block.ids, np.int64).copy()
        for c, vtag in enumerate(_ends(tag)):
            if vtag in _POINT_EDGES:
                ids[:, c] += shift
        out[tag] = ids
    return out


def _resolve_vertices(graph: GraphFile, verts: _Vertices, eids: dict[str, np.ndarray],
                      guess: bool, shift: int) -> None:
    """Check every edge's vertices (existence and type); add the missing ones if guessing."""
    for tag, ids in eids.items():
        block = graph.edges[tag]
        for c, vtag in enumerate(_ends(tag)):
            known, codes = verts.table()
            col = ids[:, c]
            pos = np.minimum(np.searchsorted(known, col), max(len(known) - 1, 0))
            found = known[pos] == col if len(known) else np.zeros(len(col), bool)
            wrong = found & (codes[pos] != _TAG_ORDER.index(vtag)) if len(known) else found
            file_id = col - (shift if vtag in _POINT_EDGES else 0)
            if wrong.any():
                i = int(np.flatnonzero(wrong)[0])
                raise GraphError(f"{_where(graph.path, block.lines, i)}: {tag} names vertex "
                                 f"{int(file_id[i])} at position {c}, which is a "
                                 f"{_TAG_ORDER[int(codes[pos[i]])]}; it needs a {vtag}")
            if (~found).any():
                if not guess:
                    i = int(np.flatnonzero(~found)[0])
                    raise GraphError(f"{_where(graph.path, block.lines, i)}: {tag} names vertex "
                                     f"{int(file_id[i])}, which has no vertex line (build with "
                                     "guess=True to estimate it from the edges)")
                verts.add_missing(vtag, np.unique(col[~found]))


def _fixed_ids(graph: GraphFile, verts: _Vertices, shift: int) -> dict[int, str]:
    known, codes = verts.table()
    if len(graph.fixed):
        out = {}
        for fid in np.unique(np.asarray(graph.fixed, np.int64)).tolist():
            vid = fid if fid in known or not shift else fid + shift
            if not np.isin(vid, known):
                raise GraphError(f"{graph.path}: FIX {fid} names no vertex")
            out[int(vid)] = "FIX line"
        return out
    poses = known[np.isin(codes, [_TAG_ORDER.index(t) for t in _POSE_EDGES])]
    return {int(poses.min()): "first pose fixed for the gauge"} if len(poses) else {}


def _offsets(graph: GraphFile) -> dict[int, ParameterSE3Offset]:
    out = {}
    for pid, values in graph.offsets.items():
        v = np.asarray(values, float)
        if v.shape != (7,) or not np.isfinite(v).all():
            raise GraphError(f"{graph.path}: PARAMS_SE3OFFSET {pid} is not 7 finite values")
        out[int(pid)] = ParameterSE3Offset.from_qt(v, int(pid))
    return out


def _index_of(ids: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Positions in ``ids`` (unsorted, unique) of the ``query`` ids (all present)."""
    order = np.argsort(ids)
    return order[np.searchsorted(ids, query, sorter=order)]


def _guess(graph: GraphFile, verts: _Vertices, eids: dict[str, np.ndarray],
           fixed: dict[int, str], offsets: dict[int, ParameterSE3Offset]) -> np.ndarray:
    """Fill the estimates by BFS propagation; return the ids that were set."""
    set_ids = []
    for ptag, etag in _POSE_EDGES.items():
        if ptag not in verts.ids:
            continue
        ids, est = verts.ids[ptag], verts.est[ptag]
        group = sg.SE2_GROUP if ptag == "VERTEX_SE2" else sg.SE3_GROUP
        roots = np.flatnonzero(np.isin(ids, list(fixed)))
        unset = np.isnan(est[roots].reshape(len(roots), -1)).any(axis=1)
        est[roots[unset]] = group.identity
        reached = np.zeros(len(ids), bool)
        reached[roots] = True
        if etag in eids:
            meas = _to_estimates(ptag, graph.edges[etag].measurements)
            reached = sg.propagate_poses(group, est, roots, _index_of(ids, eids[etag][:, 0]),
                                         _index_of(ids, eids[etag][:, 1]), meas)
        set_ids.append(ids[reached & ~np.isin(ids, list(fixed))])
        for ltag, letag in _POINT_EDGES.items():
            if EDGE_TYPES[letag][1][0] == ptag and ltag in verts.ids and letag in eids:
                set_ids.append(_guess_points(graph, verts, eids, ltag, letag, ptag, reached,
                                             fixed, offsets))
    out = np.concatenate(set_ids) if set_ids else np.zeros(0, np.int64)
    for tag, est in verts.est.items():
        unset = np.isnan(est.reshape(len(est), -1)).any(axis=1)
        if unset.any():
            vid = int(verts.ids[tag][np.flatnonzero(unset)[0]])
            raise GraphError(f"{graph.path}: {tag} {vid} has no vertex line and no edge path "
                             "from a fixed pose to estimate it from")
    return out


def _guess_points(graph: GraphFile, verts: _Vertices, eids: dict[str, np.ndarray], ltag: str,
                  letag: str, ptag: str, reached: np.ndarray, fixed: dict[int, str],
                  offsets: dict[int, ParameterSE3Offset]) -> np.ndarray:
    lids = verts.ids[ltag]
    pose_idx = _index_of(verts.ids[ptag], eids[letag][:, 0])
    lm_idx = _index_of(lids, eids[letag][:, 1])
    block = graph.edges[letag]
    if letag == "EDGE_SE2_XY":
        def observe(X: np.ndarray, z: np.ndarray, e: np.ndarray) -> np.ndarray:
            return sg.SE2_GROUP.compose(X, np.column_stack([z, np.zeros(len(z))]))[:, :2]
    else:
        P = _edge_offsets(graph, block, offsets)

        def observe(X: np.ndarray, z: np.ndarray, e: np.ndarray) -> np.ndarray:
            Pz = np.einsum("nij,nj->ni", P[e, :, :3], z) + P[e, :, 3]
            return np.einsum("nij,nj->ni", X[:, :, :3], Pz) + X[:, :, 3]
    free = ~np.isin(lids, list(fixed))
    est = verts.est[ltag]
    new = est.copy()
    placed = sg.place_landmarks(observe, verts.est[ptag], reached, pose_idx, lm_idx,
                                np.asarray(block.measurements, float), len(lids), new)
    est[placed & free] = new[placed & free]
    return lids[placed & free]


def _edge_offsets(graph: GraphFile, block: EdgeBlock,
                  offsets: dict[int, ParameterSE3Offset]) -> np.ndarray:
    """``(m, 3, 4)`` offset of each ``EDGE_SE3_TRACKXYZ`` edge (by its parameter id)."""
    pids = np.zeros(len(block.ids), np.int64) if block.params is None else block.params
    out = np.empty((len(pids), 3, 4))
    for pid in np.unique(pids).tolist():
        if pid not in offsets:
            i = int(np.flatnonzero(pids == pid)[0])
            raise GraphError(f"{_where(graph.path, block.lines, i)}: EDGE_SE3_TRACKXYZ uses "
                             f"parameter {pid}, but there is no PARAMS_SE3OFFSET {pid}")
        out[pids == pid] = offsets[pid].offset
    return out


def _add_edges(opt: SparseOptimizer, graph: GraphFile, tag: str, ids: np.ndarray,
               offsets: dict[int, ParameterSE3Offset]) -> None:
    block = graph.edges[tag]
    etype = EDGE_TYPES[tag][0]
    meas = np.asarray(block.measurements, float)
    info = np.asarray(block.information, float)
    bad = ~(np.isfinite(meas).all(axis=1) & np.isfinite(info).reshape(len(info), -1).all(axis=1))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise GraphError(f"{_where(graph.path, block.lines, i)}: {tag} has non-finite values")
    if tag == "EDGE_SE3:QUAT":
        meas = pose_from_qt(meas)
    groups: list[tuple[np.ndarray, ParameterSE3Offset | None]] = [(np.arange(len(ids)), None)]
    if tag == "EDGE_SE3_TRACKXYZ":
        _edge_offsets(graph, block, offsets)  # every parameter id exists
        pids = np.zeros(len(ids), np.int64) if block.params is None else block.params
        groups = [(np.flatnonzero(pids == p), offsets[p]) for p in np.unique(pids).tolist()]
    for sel, params in groups:
        try:
            opt.add_edges(etype, ids[sel], meas[sel], info[sel], params=params)
        except GraphError as exc:
            low = np.linalg.eigvalsh(info[sel])
            scale = np.maximum(np.abs(low[:, -1]), 1.0)
            nonpsd = np.flatnonzero(low[:, 0] < -1e-9 * scale)
            asym = np.flatnonzero(~np.isclose(info[sel], np.swapaxes(info[sel], 1, 2),
                                              rtol=1e-9, atol=1e-12).all(axis=(1, 2)))
            for rows, what in ((nonpsd, "is not positive semi-definite"),
                               (asym, "is not symmetric")):
                if len(rows):
                    raise GraphError(f"{_where(graph.path, block.lines, int(sel[rows[0]]))}: "
                                     f"{tag}: the information matrix {what}") from None
            raise GraphError(f"{graph.path}: {tag}: {exc}") from None


def build_graph(graph: GraphFile, optimizer: SparseOptimizer | None = None,
                guess: bool = False) -> SlamGraph:
    """Build an optimizer from a graph file's canonical records.

    One ``add_vertices`` call per vertex tag and one ``add_edges`` call per edge tag (per
    offset parameter for ``EDGE_SE3_TRACKXYZ``). See the module docstring for the gauge,
    ``EQUIV``, landmark ids and the initial guess.

    Args:
        graph: The records (canonical g2o tags, see :mod:`graphopt.io.g2o_records`).
        optimizer: Add to this optimizer; by default a new ``SparseOptimizer`` with
            :func:`pose_graph_levenberg` (GTSAM's damping schedule, the fastest on pose graphs:
            see ``benchmarks/bench_schedules.py``).
        guess: Replace the estimates of all vertices that are not fixed by the spanning-tree
            guess. Required when edges name vertices that have no vertex line.

    Returns:
        The :class:`SlamGraph`.

    Raises:
        GraphError: One line naming the file and line (or tag and id): unsupported tags,
            duplicate ids, edges naming missing vertices (without ``guess``) or vertices of the
            wrong type, non-finite values, bad information matrices, unknown parameters.
    """
    _check_tags(graph)
    opt = optimizer if optimizer is not None else SparseOptimizer(
        pose_graph_levenberg())  # pose graphs' best schedule (bench_schedules.py)
    notes: list[str] = []
    shift = _point_offset(graph)
    if shift:
        notes.append(f"point ids coincide with pose ids (separate namespaces, as GTSAM writes "
                     f"them): point j is vertex j+{shift} in the optimizer")
    verts = _Vertices(graph, shift)
    eids = _edge_ids(graph, shift)
    _resolve_vertices(graph, verts, eids, guess, shift)
    fixed = _fixed_ids(graph, verts, shift)
    notes += [f"vertex {v} fixed: {why}" for v, why in fixed.items() if why != "FIX line"]
    if len(graph.equiv):
        notes.append(f"{len(graph.equiv)} EQUIV pairs recorded, not merged: both poses and the "
                     "edges between them are kept")
    offsets = _offsets(graph)
    missing = sum(int((verts.lines[t] == 0).sum()) for t in verts.lines)
    guessed = np.zeros(0, np.int64)
    if guess:
        guessed = _guess(graph, verts, eids, fixed, offsets)
        notes.append(f"initial guess for {len(guessed)} vertices by BFS from the fixed poses"
                     + (f" ({missing} had no vertex line)" if missing else ""))
    fixed_arr = np.array(list(fixed), dtype=np.int64)
    for tag in _TAG_ORDER:
        if tag in verts.ids:
            ids = verts.ids[tag]
            try:
                opt.add_vertices(_vtype(tag), ids, verts.est[tag], np.isin(ids, fixed_arr))
            except GraphError as exc:
                raise GraphError(f"{graph.path}: {tag}: {exc}") from None
    objects = {**offsets, **st.parameters(graph)}
    kinds = {**dict.fromkeys(offsets, "PARAMS_SE3OFFSET"),
             **{pid: tag for pid, (tag, _) in graph.parameters.items()}}
    for tag in graph.edges:
        if tag not in EDGE_TYPES:
            st.add_edges(opt, graph, tag, eids[tag], objects, kinds)
        else:
            _add_edges(opt, graph, tag, eids[tag], offsets)
    return SlamGraph(
        optimizer=opt, path=graph.path, vertex_ids=dict(verts.ids),
        vertex_lines=dict(verts.lines), edges=dict(graph.edges),
        vertex_counts={t: len(v) for t, v in verts.ids.items()},
        edge_counts={t: len(b.ids) for t, b in graph.edges.items()}, fixed=fixed,
        point_id_offset=shift, offsets=offsets, equiv=np.asarray(graph.equiv, np.int64),
        guessed=guessed, notes=notes, parameters=dict(graph.parameters))


def graph_file(slam: SlamGraph) -> GraphFile:
    """The current estimates and the edges as canonical records (for the writer).

    Point ids are shifted back to the file's; vertices keep their line numbers (0 for those
    the guess created); ``FIX`` lists the vertices fixed now (the gauge pose included).

    Args:
        slam: What :func:`build_graph` returned (after optimising, say).

    Returns:
        A :class:`GraphFile` with ``path="<generated>"``.
    """
    opt = slam.optimizer
    vertices = {}
    fixed = []
    for tag, ids in slam.vertex_ids.items():
        store = opt.graph.stores[_vtype(tag)]
        rows = _index_of(store.ids, ids)
        est = store.estimates[rows]
        values = (pose_to_qt(est) if tag == "VERTEX_SE3:QUAT" else
                  st.values(tag, est) if tag in st.VERTEX_TAGS else est.copy())
        file_ids = ids - (slam.point_id_offset if tag in _POINT_EDGES else 0)
        vertices[tag] = VertexBlock(file_ids, values, slam.vertex_lines[tag].copy())
        fixed.append(file_ids[store.fixed[rows]])
    offsets = {pid: p.to_qt() for pid, p in slam.offsets.items()}
    return GraphFile(
        path="<generated>", vertices=vertices, edges=dict(slam.edges), offsets=offsets,
        parameters=dict(slam.parameters),
        fixed=np.concatenate(fixed) if fixed else np.zeros(0, np.int64),
        equiv=slam.equiv.copy(), notes=list(slam.notes))
