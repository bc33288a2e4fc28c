"""graphopt's types for g2o's other file tags (:data:`graphopt.io.g2o_layouts.LAYOUTS`): what
:func:`~graphopt.types.slam_graph.build_graph` adds for each, and how the file's columns become
graphopt's estimates, measurements and parameters (and estimates go back, for the writer).

===================================  ===============================  =========================
tag                                  graphopt type                    notes
===================================  ===============================  =========================
``PARAMS_SE2OFFSET``                 ``ParameterSE2Offset``
``PARAMS_CAMERACALIB``               ``ParameterCamera``              offset quaternion as
                                                                      written
``PARAMS_CAMERAPARAMETERS``          ``SBACameraParameters``          ``fx = fy = focal``
``VERTEX_SE3:EXPMAP``                ``VertexSE3Expmap``              ``T_cw`` from its
                                                                      ``x y z q`` (as written)
``VERTEX_SIM3:EXPMAP``               ``VertexSim3Expmap``             when graphopt has it
``VERTEX_CAM``                       ``VertexCam``
``VERTEX_INTRINSICS``                ``VertexIntrinsics``
``VERTEX_ODOM_DIFFERENTIAL``         ``VertexOdomDifferentialParams``
``EDGE_PRIOR_SE2``                   ``EdgeSE2Prior``
``EDGE_PRIOR_SE2_XY``                ``EdgeSE2XYPrior``
``EDGE_PRIOR_XY``                    ``EdgeXYPrior``
``EDGE_POINTXY``                     ``EdgePointXY``
``EDGE_BEARING_SE2_XY``              ``EdgeSE2PointXYBearing``
``EDGE_SE2_XY_CALIB``                ``EdgeSE2PointXYCalib``
``EDGE_SE2_OFFSET``                  ``EdgeSE2Offset``                params ``(from, to)``
``EDGE_SE2_POINTXY_OFFSET``          ``EdgeSE2PointXYOffset``
``EDGE_SE2_TWOPOINTSXY``             ``EdgeSE2TwoPointsXY``
``EDGE_SE2_CALIB``                   ``EdgeSE2SensorCalib``
``EDGE_SE2_ODOM_DIFFERENTIAL_CALIB`` ``EdgeSE2OdomDifferentialCalib``
``EDGE_SE3_PRIOR``                   ``EdgeSE3Prior``
``EDGE_SE3_XYZ_PRIOR``               ``EdgeSE3XYZPrior``
``EDGE_SE3_OFFSET``                  ``EdgeSE3Offset``                params ``(from, to)``
``EDGE_POINTXYZ``                    ``EdgePointXYZ``
``EDGE_POINTXYZ_PRIOR``              ``EdgeXYZPrior``
``EDGE_PROJECT_DEPTH``               ``EdgeSE3PointXYZDepth``
``EDGE_PROJECT_DISPARITY``           ``EdgeSE3PointXYZDisparity``
``EDGE_V_V_GICP``                    ``EdgeVVGicp``                   normals unused (point to
                                                                      point; g2o's ``pl_pl``
                                                                      is not in the file)
``EDGE_SE3:EXPMAP``                  ``EdgeSE3Expmap``                when graphopt has it
``EDGE_PROJECT_XYZ2UV:EXPMAP``       ``EdgeProjectXYZ2UV``            (point, pose) → (pose,
                                                                      point)
``EDGE_PROJECT_XYZ2UVU:EXPMAP``      ``EdgeProjectXYZ2UVU``           likewise
``EDGE_SIM3:EXPMAP`` …               ``EdgeSim3`` …                   when graphopt has them
``EDGE_PROJECT_P2MC``/``P2SC``       ``EdgeProjectP2MC``/``P2SC``     (point, camera) →
                                                                      (camera, point)
``EDGE_CAM``                         ``EdgeSBACam``
``EDGE_SCALE``                       ``EdgeSBAScale``
``EDGE_SE2_LOTSOFXY``                ``EdgeSE2LotsOfXY.of(k)``        records key ``TAG#k``
``EDGE_SE3_LOTSOF_XYZ``              ``EdgeSE3LotsOfXYZ.of(k)``       likewise
===================================  ===============================  =========================

``EDGE_SE3_PROJECT_XYZ:EXPMAP`` lines (and the ``…ONLYPOSE`` and ``STEREO…`` ones) are read but
cannot be built: g2o writes no intrinsics for them (its ``fx fy cx cy [bf]`` and the only-pose
edges' world point ``Xw`` are attributes of the edge object, lost in the file).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from graphopt.errors import GraphError
from graphopt.io.g2o_layouts import edge_params
from graphopt.io.g2o_records import EdgeBlock, GraphFile
from graphopt.lie import quat_to_rot, rot_to_quat
from graphopt.optimizer import SparseOptimizer
from graphopt.types.isometry3 import pose_from_qt, pose_to_qt, quat_to_matrix

__all__ = ["EDGE_TAGS", "TAG_OF_TYPE", "VERTEX_TAGS", "add_edges", "edge_block", "edge_type",
           "estimates", "known",
           "parameters", "spec", "values", "vertex_type"]


def _same(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float).copy()


def _expmap_in(v: np.ndarray) -> np.ndarray:
    """``x y z q`` → ``(4, 4)``, the quaternion as written (g2o's ``SE3Quat::fromVector``)."""
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = quat_to_matrix(v[:, 3:7])
    T[:, :3, 3] = v[:, :3]
    return T


def _expmap_out(T: np.ndarray) -> np.ndarray:
    return np.column_stack([T[:, :3, 3], rot_to_quat(T[:, :3, :3])])


def _sim3_in(v: np.ndarray) -> np.ndarray:
    """g2o's ``Sim3`` vector ``qx qy qz qw x y z s`` → ``[[sR, t], [0, 0, 0, 1]]``."""
    S = np.tile(np.eye(4), (len(v), 1, 1))
    S[:, :3, :3] = v[:, 7, None, None] * quat_to_rot(v[:, :4])
    S[:, :3, 3] = v[:, 4:7]
    return S


def _sim3_out(S: np.ndarray) -> np.ndarray:
    s = np.cbrt(np.linalg.det(S[:, :3, :3]))
    return np.column_stack([rot_to_quat(S[:, :3, :3] / s[:, None, None]), S[:, :3, 3], s])


@dataclass(frozen=True)
class VertexTag:
    """A vertex tag's graphopt type and conversions.

    Args:
        type_name: The type's name in :mod:`graphopt.types`.
        to_estimate: ``(n, w)`` file values → ``(n, *estimate_shape)``.
        to_values: The inverse, for the writer.
    """

    type_name: str
    to_estimate: Callable[[np.ndarray], np.ndarray] = _same
    to_values: Callable[[np.ndarray], np.ndarray] = _same


def _flat(z: np.ndarray) -> np.ndarray:
    return np.asarray(z, float).reshape(len(z), -1).copy()


@dataclass(frozen=True)
class EdgeTag:
    """An edge tag's graphopt type and conversions.

    Args:
        type_name: The type's name in :mod:`graphopt.types`.
        order: graphopt's vertex position ``k`` is g2o's position ``order[k]``.
        to_measurement: ``(m, w)`` file values → graphopt's measurements.
        params: The parameter tag each parameter id must name.
        why_not: Why such lines cannot be built (``None``: they can).
        to_values: graphopt's measurements → ``(m, w)`` file values (``None``: not writable).
    """

    type_name: str
    order: tuple[int, ...] = (0, 1)
    to_measurement: Callable[[np.ndarray], np.ndarray] = _same
    params: tuple[str, ...] = ()
    why_not: str | None = None
    to_values: Callable[[np.ndarray], np.ndarray] | None = _flat


VERTEX_TAGS: dict[str, VertexTag] = {
    "VERTEX_SE3:EXPMAP": VertexTag("VertexSE3Expmap", _expmap_in, _expmap_out),
    "VERTEX_SIM3:EXPMAP": VertexTag("VertexSim3Expmap", _sim3_in, _sim3_out),
    "VERTEX_CAM": VertexTag("VertexCam"),
    "VERTEX_INTRINSICS": VertexTag("VertexIntrinsics"),
    "VERTEX_ODOM_DIFFERENTIAL": VertexTag("VertexOdomDifferentialParams"),
}

_SE3O, _SE2O = ("PARAMS_SE3OFFSET",), ("PARAMS_SE2OFFSET",)
_KCAM, _SBA = ("PARAMS_CAMERACALIB",), ("PARAMS_CAMERAPARAMETERS",)
EDGE_TAGS: dict[str, EdgeTag] = {
    "EDGE_PRIOR_SE2": EdgeTag("EdgeSE2Prior", (0,)),
    "EDGE_PRIOR_SE2_XY": EdgeTag("EdgeSE2XYPrior", (0,)),
    "EDGE_PRIOR_XY": EdgeTag("EdgeXYPrior", (0,)),
    "EDGE_POINTXY": EdgeTag("EdgePointXY"),
    "EDGE_BEARING_SE2_XY": EdgeTag("EdgeSE2PointXYBearing"),
    "EDGE_SE2_XY_CALIB": EdgeTag("EdgeSE2PointXYCalib", (0, 1, 2)),
    "EDGE_SE2_OFFSET": EdgeTag("EdgeSE2Offset", params=_SE2O * 2),
    "EDGE_SE2_POINTXY_OFFSET": EdgeTag("EdgeSE2PointXYOffset", params=_SE2O),
    "EDGE_SE2_TWOPOINTSXY": EdgeTag("EdgeSE2TwoPointsXY", (0, 1, 2)),
    "EDGE_SE2_CALIB": EdgeTag("EdgeSE2SensorCalib", (0, 1, 2)),
    "EDGE_SE2_ODOM_DIFFERENTIAL_CALIB": EdgeTag("EdgeSE2OdomDifferentialCalib", (0, 1, 2)),
    "EDGE_SE3_PRIOR": EdgeTag("EdgeSE3Prior", (0,), pose_from_qt, _SE3O, None, pose_to_qt),
    "EDGE_SE3_XYZ_PRIOR": EdgeTag("EdgeSE3XYZPrior", (0,), params=_SE3O),
    "EDGE_SE3_OFFSET": EdgeTag("EdgeSE3Offset", (0, 1), pose_from_qt, _SE3O * 2, None,
                               pose_to_qt),
    "EDGE_POINTXYZ": EdgeTag("EdgePointXYZ"),
    "EDGE_POINTXYZ_PRIOR": EdgeTag("EdgeXYZPrior", (0,)),
    "EDGE_PROJECT_DEPTH": EdgeTag("EdgeSE3PointXYZDepth", params=_KCAM),
    "EDGE_PROJECT_DISPARITY": EdgeTag("EdgeSE3PointXYZDisparity", params=_KCAM),
    "EDGE_V_V_GICP": EdgeTag("EdgeVVGicp", to_measurement=lambda v: v[:, [0, 1, 2, 6, 7, 8]]
                             .reshape(len(v), 2, 3), to_values=None),  # (no normals to write)
    "EDGE_SE3:EXPMAP": EdgeTag("EdgeSE3Expmap", to_measurement=_expmap_in,
                               to_values=_expmap_out),
    "EDGE_PROJECT_XYZ2UV:EXPMAP": EdgeTag("EdgeProjectXYZ2UV", (1, 0), params=_SBA),
    "EDGE_PROJECT_XYZ2UVU:EXPMAP": EdgeTag("EdgeProjectXYZ2UVU", (1, 0), params=_SBA),
    "EDGE_SE3_PROJECT_XYZ:EXPMAP": EdgeTag(
        "EdgeSE3ProjectXYZ", (1, 0), why_not="g2o writes no intrinsics (fx fy cx cy) for it"),
    "EDGE_SE3_PROJECT_XYZONLYPOSE:EXPMAP": EdgeTag(
        "EdgeSE3ProjectXYZOnlyPose", (0,),
        why_not="g2o writes neither its intrinsics nor its world point Xw"),
    "EDGE_STEREO_SE3_PROJECT_XYZ:EXPMAP": EdgeTag(
        "EdgeStereoSE3ProjectXYZ", (1, 0),
        why_not="g2o writes no intrinsics (fx fy cx cy bf) for it"),
    "EDGE_STEREO_SE3_PROJECT_XYZONLYPOSE:EXPMAP": EdgeTag(
        "EdgeStereoSE3ProjectXYZOnlyPose", (0,),
        why_not="g2o writes neither its intrinsics nor its world point Xw"),
    "EDGE_SIM3:EXPMAP": EdgeTag("EdgeSim3", to_measurement=_sim3_in, to_values=_sim3_out),
    "EDGE_PROJECT_SIM3_XYZ:EXPMAP": EdgeTag("EdgeSim3ProjectXYZ", params=("unit camera",)),
    "EDGE_PROJECT_INVERSE_SIM3_XYZ:EXPMAP": EdgeTag("EdgeInverseSim3ProjectXYZ",
                                                    params=("unit camera",)),
    "EDGE_PROJECT_P2MC": EdgeTag("EdgeProjectP2MC", (1, 0)),
    "EDGE_PROJECT_P2SC": EdgeTag("EdgeProjectP2SC", (1, 0)),
    "EDGE_CAM": EdgeTag("EdgeSBACam"),
    "EDGE_SCALE": EdgeTag("EdgeSBAScale"),
    # sized lines, keyed ``TAG#k`` (k points): the type is ``.of(k)``, vertex order as g2o's
    "EDGE_SE2_LOTSOFXY": EdgeTag("EdgeSE2LotsOfXY"),
    "EDGE_SE3_LOTSOF_XYZ": EdgeTag("EdgeSE3LotsOfXYZ"),
}


def spec(key: str) -> EdgeTag:
    """The :class:`EdgeTag` of an edge key (``TAG``, or ``TAG#k`` for the sized tags).

    Args:
        key: The key of the edge block.
    """
    tag, _, k = key.partition("#")
    if not k:
        return EDGE_TAGS[tag]
    return EdgeTag(EDGE_TAGS[tag].type_name, tuple(range(int(k) + 1)))


def _type(name: str, tag: str) -> Any:
    import graphopt.types as gt  # noqa: PLC0415 (lazy, like the package)

    try:
        return getattr(gt, name)
    except (AttributeError, ImportError):
        raise GraphError(f"graphopt has no {name} type yet, so {tag} lines cannot be "
                         "built") from None


def vertex_type(tag: str) -> Any:
    """The graphopt vertex type of a vertex tag of :data:`VERTEX_TAGS`.

    Args:
        tag: The tag.
    """
    return _type(VERTEX_TAGS[tag].type_name, tag)


def edge_type(key: str) -> Any:
    """The graphopt edge type of an edge key (a tag of :data:`EDGE_TAGS`, or ``TAG#k``).

    Args:
        key: The key.
    """
    tag, _, k = key.partition("#")
    etype = _type(EDGE_TAGS[tag].type_name, tag)
    return etype.of(int(k)) if k else etype


def estimates(tag: str, values: np.ndarray) -> np.ndarray:
    """Estimates from a vertex tag's file values.

    Args:
        tag: A tag of :data:`VERTEX_TAGS`.
        values: ``(n, w)``.
    """
    return VERTEX_TAGS[tag].to_estimate(np.asarray(values, float))


def values(tag: str, est: np.ndarray) -> np.ndarray:
    """A vertex tag's file values from estimates (the writer's side of :func:`estimates`).

    Args:
        tag: A tag of :data:`VERTEX_TAGS`.
        est: ``(n, *estimate_shape)``.
    """
    return VERTEX_TAGS[tag].to_values(np.asarray(est, float))


def parameters(graph: GraphFile) -> dict[int, Any]:
    """The parameter objects of ``graph.parameters`` (id → object).

    Args:
        graph: The records.
    """
    out: dict[int, Any] = {}
    for pid, (tag, v) in graph.parameters.items():
        v = np.asarray(v, float)
        if not np.isfinite(v).all():
            raise GraphError(f"{graph.path}: {tag} {pid} has non-finite values")
        if tag == "PARAMS_SE2OFFSET":
            out[pid] = _type("ParameterSE2Offset", tag)(v, int(pid))
        elif tag == "PARAMS_CAMERACALIB":
            out[pid] = _type("ParameterCamera", tag)(pose_from_qt(v[None, :7])[0], int(pid),
                                                     *map(float, v[7:11]))
        else:  # PARAMS_CAMERAPARAMETERS: focal cx cy baseline
            out[pid] = _type("SBACameraParameters", tag).from_g2o(v[0], v[1:3], v[3])
    return out


def _where(graph: GraphFile, block: EdgeBlock, i: int) -> str:
    line = int(block.lines[i]) if len(block.lines) > i else 0
    return f"{graph.path}:{line}" if line > 0 else graph.path


def add_edges(opt: SparseOptimizer, graph: GraphFile, tag: str, ids: np.ndarray,
              objects: dict[int, Any], kinds: dict[int, str]) -> None:
    """Add one tag's edges: one ``add_edges`` call per distinct row of parameter ids.

    Args:
        opt: The optimizer.
        graph: The records (for messages).
        tag: A tag of :data:`EDGE_TAGS`, or ``TAG#k`` for the sized ones.
        ids: ``(m, k)`` optimizer vertex ids in g2o's order.
        objects: Parameter id → object (offsets and :func:`parameters`).
        kinds: Parameter id → its tag.
    """
    info_of, block = spec(tag), graph.edges[tag]
    if info_of.why_not is not None:
        raise GraphError(f"{_where(graph, block, 0)}: {tag} cannot be built: {info_of.why_not}")
    try:
        etype = edge_type(tag)
    except GraphError as exc:
        raise GraphError(f"{_where(graph, block, 0)}: {exc}") from None
    meas = np.asarray(block.measurements, float)
    info = np.asarray(block.information, float)
    bad = ~(np.isfinite(meas).all(axis=1) & np.isfinite(info).reshape(len(info), -1).all(axis=1))
    if bad.any():
        raise GraphError(f"{_where(graph, block, int(np.flatnonzero(bad)[0]))}: {tag} has "
                         "non-finite values")
    meas = info_of.to_measurement(meas)
    pids = edge_params(block)
    if info_of.params == ("unit camera",):
        # g2opy 2.3.0 keeps the Sim3 vertex's intrinsics out of the file (and its API): f = 1,
        # c = 0, which is what its loaded edges project with.
        objects, kinds = {-1: _type("CameraParameters", tag)(1.0, 1.0, 0.0, 0.0)}, {}
        pids = np.full((len(ids), 1), -1, np.int64)
    for k, want in enumerate(info_of.params if info_of.params != ("unit camera",) else ()):
        wrong = np.array([kinds.get(p) != want for p in pids[:, k].tolist()], dtype=bool)
        if wrong.any():
            i = int(np.flatnonzero(wrong)[0])
            raise GraphError(f"{_where(graph, block, i)}: {tag} names parameter {pids[i, k]}, "
                             f"which is a {kinds.get(int(pids[i, k]))}; it needs a {want}")
    rows, group = np.unique(pids, axis=0, return_inverse=True) if pids.shape[1] else (
        np.zeros((1, 0), np.int64), np.zeros(len(ids), np.int64))
    ordered = ids[:, list(info_of.order)]
    for g, row in enumerate(rows.tolist()):
        sel = np.flatnonzero(np.asarray(group).ravel() == g)
        objs = [objects[p] for p in row]
        params = None if not objs else objs[0] if len(objs) == 1 else tuple(objs)
        try:
            opt.add_edges(etype, ordered[sel], meas[sel], info[sel], params=params)
        except GraphError as exc:
            raise GraphError(f"{_where(graph, block, int(sel[0]))}: {tag}: {exc}") from None


#: graphopt type name → tag, for writers (the first tag naming the type).
TAG_OF_TYPE: dict[str, str] = {}
for _tag, _spec in [*VERTEX_TAGS.items(), *EDGE_TAGS.items()]:
    TAG_OF_TYPE.setdefault(_spec.type_name, _tag)


def edge_block(type_name: str, vids: np.ndarray, meas: np.ndarray, info: np.ndarray,
               pids: np.ndarray) -> tuple[str, EdgeBlock]:
    """The file key and records of edges held in graphopt's layout (a writer's side of
    :func:`add_edges`).

    Args:
        type_name: The graphopt edge type's name (``EdgeSE3LotsOfXYZ_3`` for ``.of(3)``).
        vids: ``(m, k)`` vertex ids in graphopt's order.
        meas: ``(m, …)`` graphopt's measurements.
        info: ``(m, d, d)`` information matrices.
        pids: ``(m, p)`` parameter ids in g2o's order.

    Raises:
        NotImplementedError: No g2o line holds such edges.
    """
    base, _, k = type_name.partition("_")
    tag = TAG_OF_TYPE.get(type_name) or (TAG_OF_TYPE.get(base) if k.isdigit() else None)
    spec_ = EDGE_TAGS.get(tag or "")
    if spec_ is None or spec_.to_values is None:
        raise NotImplementedError(f"no g2o file line holds {type_name} edges")
    key = f"{tag}#{k}" if k.isdigit() else tag
    order = list(spec(key).order)
    ids = np.empty_like(vids)
    ids[:, order] = vids
    return key, EdgeBlock(ids, spec_.to_values(np.asarray(meas, float)), np.asarray(info, float),
                          np.zeros(len(vids), np.int64), np.asarray(pids, np.int64))


def known(key: str) -> bool:
    """Whether ``key`` (a vertex or edge tag, or ``TAG#k``) is one of this module's.

    Args:
        key: The key.
    """
    return key in VERTEX_TAGS or key.partition("#")[0] in EDGE_TAGS
