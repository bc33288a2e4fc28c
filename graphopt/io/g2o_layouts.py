"""The line layouts of g2o's other file tags (beyond the pose-graph tags of
:mod:`graphopt.io.g2o`): parameters, vertices and edges of g2o's ``slam2d``, ``slam3d``,
``sba``, ``sim3``, ``sclam2d`` and ``icp`` types, as the official ``g2opy`` wheel (2.3.0)
writes and reads them.

g2opy 2.3.0 (g2o's ``pymem`` line) writes every element from its data vector:

- ``PARAMS_… id values…`` (the parameter's vector),
- ``VERTEX_… id estimate…`` (the estimate's vector),
- ``EDGE_… ids… [parameter ids…] measurement… information…`` with the information's upper
  triangle row by row (``I00 I01 … I0d I11 …``), as g2o's ``writeInformationMatrix`` does.

The vectors are those of the estimate's type: a pose ``SE3Quat``/``Isometry3`` is
``x y z qx qy qz qw``, an ``SE2`` ``x y θ``, a ``Sim3`` ``qx qy qz qw x y z s``, an
``SBACam`` its pose ``x y z qx qy qz qw``. Where g2o's older C++ ``read``/``write`` (its
``master`` line) differ and the value count tells them apart, the reader takes those too
(:data:`CLASSIC`); where it cannot (``VERTEX_SE3:EXPMAP`` and ``EDGE_SE3:EXPMAP``, whose
classic lines hold the *inverse* pose), the file is read as g2opy 2.3.0 writes it.

Vertex ids of an edge are in g2o's order (projection edges: point first); graphopt's types
may order them otherwise, which is the builder's business (:mod:`graphopt.types.slam_tags`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TextIO

import numpy as np

from graphopt.io.g2o_lines import GraphFormatError, parse_ids, positive_definite, symmetric
from graphopt.io.g2o_records import EdgeBlock, GraphFile

__all__ = ["CAMERA_DEFAULTS", "CLASSIC", "DIALECTS", "DYNAMIC", "INVERTED_IN_CLASSIC", "LAYOUTS",
           "Layout", "convert", "convert_dynamic", "edge_params", "ends", "invert_qt",
           "to_dialect", "write"]


@dataclass(frozen=True)
class Layout:
    """The columns of one tag's lines after the tag.

    Args:
        kind: ``"param"``, ``"vertex"`` or ``"edge"``.
        values: Parameter values, vertex estimate values or edge measurement values.
        vertices: Edge: the vertex tag at each position (g2o's order).
        params: Edge: number of parameter ids after the vertex ids.
        info: Edge: information dimension (its upper triangle follows the measurement).
        text: The columns, for messages.
    """

    kind: str
    values: int
    vertices: tuple[str, ...] = ()
    params: int = 0
    info: int = 0
    text: str = ""

    @property
    def count(self) -> int:
        """Number of values after the tag."""
        if self.kind != "edge":
            return 1 + self.values
        return len(self.vertices) + self.params + self.values + self.info * (self.info + 1) // 2


def _edge(vertices: tuple[str, ...], values: int, info: int, params: int = 0,
          meas: str = "") -> Layout:
    ids = " ".join(f"id{k}" for k in range(len(vertices)))
    pids = " ".join(f"param{k}" for k in range(params))
    text = " ".join(t for t in (ids, pids, meas or f"{values} measurement values",
                                f"{info * (info + 1) // 2} information values") if t)
    return Layout("edge", values, vertices, params, info, text)


_SE2, _XY, _SE3 = "VERTEX_SE2", "VERTEX_XY", "VERTEX_SE3:QUAT"
_XYZ, _EXP, _SIM3, _CAM = "VERTEX_TRACKXYZ", "VERTEX_SE3:EXPMAP", "VERTEX_SIM3:EXPMAP", "VERTEX_CAM"
_QT = "x y z qx qy qz qw"

#: Tag → layout, for every tag handled generically (the pose-graph tags are not here).
LAYOUTS: dict[str, Layout] = {
    # parameters
    "PARAMS_SE2OFFSET": Layout("param", 3, text="id x y theta"),
    "PARAMS_CAMERACALIB": Layout("param", 11, text=f"id {_QT} fx fy cx cy"),
    "PARAMS_CAMERAPARAMETERS": Layout("param", 4, text="id focal cx cy baseline"),
    # vertices
    "VERTEX_SE3:EXPMAP": Layout("vertex", 7, text=f"id {_QT} (T_cw)"),
    "VERTEX_SIM3:EXPMAP": Layout("vertex", 8, text="id qx qy qz qw x y z s (S_cw)"),
    "VERTEX_CAM": Layout("vertex", 7, text=f"id {_QT} [fx fy cx cy baseline]"),
    "VERTEX_INTRINSICS": Layout("vertex", 5, text="id fx fy cx cy baseline"),
    "VERTEX_ODOM_DIFFERENTIAL": Layout("vertex", 3, text="id k_l k_r b"),
    # slam2d
    "EDGE_PRIOR_SE2": _edge((_SE2,), 3, 3, meas="x y theta"),
    "EDGE_PRIOR_SE2_XY": _edge((_SE2,), 2, 2, meas="x y"),
    "EDGE_PRIOR_XY": _edge((_XY,), 2, 2, meas="x y"),
    "EDGE_POINTXY": _edge((_XY, _XY), 2, 2, meas="x y"),
    "EDGE_BEARING_SE2_XY": _edge((_SE2, _XY), 1, 1, meas="bearing"),
    "EDGE_SE2_XY_CALIB": _edge((_SE2, _XY, _SE2), 2, 2, meas="x y"),
    "EDGE_SE2_OFFSET": _edge((_SE2, _SE2), 3, 3, 2, meas="x y theta"),
    "EDGE_SE2_POINTXY_OFFSET": _edge((_SE2, _XY), 2, 2, 1, meas="x y"),
    "EDGE_SE2_TWOPOINTSXY": _edge((_SE2, _XY, _XY), 4, 4, meas="x1 y1 x2 y2"),
    # sclam2d
    "EDGE_SE2_CALIB": _edge((_SE2, _SE2, _SE2), 3, 3, meas="x y theta"),
    "EDGE_SE2_ODOM_DIFFERENTIAL_CALIB": _edge((_SE2, _SE2, "VERTEX_ODOM_DIFFERENTIAL"), 3, 3,
                                              meas="v_l v_r dt"),
    # slam3d
    "EDGE_SE3_PRIOR": _edge((_SE3,), 7, 6, 1, meas=_QT),
    "EDGE_SE3_XYZ_PRIOR": _edge((_SE3,), 3, 3, 1, meas="x y z"),
    "EDGE_SE3_OFFSET": _edge((_SE3, _SE3), 7, 6, 2, meas=_QT),
    "EDGE_POINTXYZ": _edge((_XYZ, _XYZ), 3, 3, meas="x y z"),
    "EDGE_POINTXYZ_PRIOR": _edge((_XYZ,), 3, 3, meas="x y z"),
    "EDGE_PROJECT_DEPTH": _edge((_SE3, _XYZ), 3, 3, 1, meas="u v depth"),
    "EDGE_PROJECT_DISPARITY": _edge((_SE3, _XYZ), 3, 3, 1, meas="u v disparity"),
    # icp
    "EDGE_V_V_GICP": _edge((_SE3, _SE3), 12, 3,
                           meas="pos0 (3) normal0 (3) pos1 (3) normal1 (3)"),
    # sba (six-dof expmap)
    "EDGE_SE3:EXPMAP": _edge((_EXP, _EXP), 7, 6, meas=_QT),
    "EDGE_PROJECT_XYZ2UV:EXPMAP": _edge((_XYZ, _EXP), 2, 2, 1, meas="u v"),
    "EDGE_PROJECT_XYZ2UVU:EXPMAP": _edge((_XYZ, _EXP), 3, 3, 1, meas="u v u_right"),
    "EDGE_SE3_PROJECT_XYZ:EXPMAP": _edge((_XYZ, _EXP), 2, 2, meas="u v"),
    "EDGE_SE3_PROJECT_XYZONLYPOSE:EXPMAP": _edge((_EXP,), 2, 2, meas="u v"),
    "EDGE_STEREO_SE3_PROJECT_XYZ:EXPMAP": _edge((_XYZ, _EXP), 3, 3, meas="u v u_right"),
    "EDGE_STEREO_SE3_PROJECT_XYZONLYPOSE:EXPMAP": _edge((_EXP,), 3, 3, meas="u v u_right"),
    # sim3
    "EDGE_SIM3:EXPMAP": _edge((_SIM3, _SIM3), 8, 7, meas="qx qy qz qw x y z s"),
    "EDGE_PROJECT_SIM3_XYZ:EXPMAP": _edge((_XYZ, _SIM3), 2, 2, meas="u v"),
    "EDGE_PROJECT_INVERSE_SIM3_XYZ:EXPMAP": _edge((_XYZ, _SIM3), 2, 2, meas="u v"),
    # sba (SBACam)
    "EDGE_PROJECT_P2MC": _edge((_XYZ, _CAM), 2, 2, meas="u v"),
    "EDGE_PROJECT_P2SC": _edge((_XYZ, _CAM), 3, 3, meas="u v u_right"),
    "EDGE_CAM": _edge((_CAM, _CAM), 7, 6, meas=_QT),
    "EDGE_SCALE": _edge((_CAM, _CAM), 1, 1, meas="distance"),
}

#: Tag → other value counts (after the tag) of g2o's classic C++ ``write`` that the reader
#: accepts: ``VERTEX_CAM`` with its intrinsics (``… fx fy cx cy baseline``).
CLASSIC: dict[str, tuple[int, ...]] = {"VERTEX_CAM": (13,)}

#: Tags whose lines carry their sizes, as g2opy 2.3.0 writes them:
#: ``TAG n id_1 … id_n d z_1 … z_d N I_1 … I_N`` (``n = k + 1`` vertices: a pose and ``k``
#: points; ``d = k·dim`` measurement values; ``N = d(d+1)/2`` information values). Tag →
#: (pose tag, point tag, point dimension). Records key them ``TAG#k`` (one block per ``k``).
DYNAMIC: dict[str, tuple[str, str, int]] = {
    "EDGE_SE2_LOTSOFXY": (_SE2, _XY, 2),
    "EDGE_SE3_LOTSOF_XYZ": (_SE3, _XYZ, 3),
}


def ends(key: str) -> tuple[str, ...]:
    """The vertex tag at each position of a generic edge key (``TAG`` or ``TAG#k``).

    Args:
        key: A tag of :data:`LAYOUTS` or a ``TAG#k`` key of :data:`DYNAMIC`.
    """
    if "#" in key:
        tag, k = key.split("#")
        pose, point, _ = DYNAMIC[tag]
        return (pose,) + (point,) * int(k)
    return LAYOUTS[key].vertices


def convert_dynamic(path: Path, tag: str, v: np.ndarray, lines: np.ndarray,
                    pieces: dict[str, list[tuple]]) -> None:
    """Convert the lines of a :data:`DYNAMIC` tag that have ``count`` values each.

    Args:
        path: The file (for messages).
        tag: The tag.
        v: ``(n, count)`` the values after the tag (one count for all rows).
        lines: ``(n,)`` 1-based line numbers.
        pieces: Key ``TAG#k`` → list of ``(ids, measurements, information, lines, params)``.
    """
    dim, count = DYNAMIC[tag][2], v.shape[1]
    # count = 1 + n + 1 + d + 1 + d(d+1)/2 with d = dim·(n − 1): the n that fits, if any
    n = next((n for n in range(2, count) if 3 + n + dim * (n - 1) * (1 + (dim * (n - 1) + 1) / 2)
              == count), 0)
    d = dim * (n - 1)
    want = np.array([n, d, d * (d + 1) // 2])
    got = v[:, [0, 1 + n, 2 + n + d]] if n else np.full((len(v), 3), -1.0)
    bad = np.flatnonzero((got != want).any(axis=1))
    if len(bad):
        raise GraphFormatError(path, f"{tag} needs n id_1..id_n d z_1..z_d N I_1..I_N with "
                                     f"d = {dim}(n-1) and N = d(d+1)/2, found {count} values "
                                     f"starting {' '.join(f'{x:g}' for x in v[bad[0], :3])}",
                               int(lines[bad[0]]))
    ids = parse_ids(path, tag, v[:, 1:1 + n], lines)
    info = symmetric(v[:, 3 + n + d:], *np.triu_indices(d))
    bad = np.flatnonzero(~positive_definite(info))
    if len(bad):
        raise GraphFormatError(path, f"{tag}: information matrix is not positive definite",
                               int(lines[bad[0]]))
    pieces.setdefault(f"{tag}#{n - 1}", []).append(
        (ids, v[:, 2 + n:2 + n + d], info, lines, np.zeros((len(v), 0), np.int64)))


#: What g2o's classic C++ ``read``/``write`` (its ``master`` line) store inverted: the pose of
#: ``VERTEX_SE3:EXPMAP`` and the measurement of ``EDGE_SE3:EXPMAP`` (``T_wc`` for ``T_cw``).
#: ``read_graph``/``write_g2o`` with ``dialect="classic"`` invert them.
INVERTED_IN_CLASSIC = ("VERTEX_SE3:EXPMAP", "EDGE_SE3:EXPMAP")
DIALECTS = ("g2opy", "classic")


def invert_qt(v: np.ndarray) -> np.ndarray:
    """g2o's ``SE3Quat::inverse`` on ``(n, 7)`` ``x y z qx qy qz qw`` rows: the conjugate
    quaternion and ``t' = q̄ (−t)`` (Eigen's quaternion-vector product, as written).

    Args:
        v: ``(n, 7)`` poses.
    """
    u, w = -v[:, 3:6], v[:, 6:7]
    t = -v[:, :3]
    uv = 2.0 * np.cross(u, t)
    return np.column_stack([t + w * uv + np.cross(u, uv), u, w])


def to_dialect(graph: GraphFile, dialect: str) -> GraphFile:
    """``graph`` with the blocks :data:`INVERTED_IN_CLASSIC` inverted when ``dialect`` is
    ``"classic"`` (a shallow copy; ``graph`` itself is not changed). Its own inverse.

    Args:
        graph: The records.
        dialect: ``"g2opy"`` (the layouts above) or ``"classic"``.
    """
    if dialect not in DIALECTS:
        raise ValueError(f"g2o dialect must be one of {', '.join(DIALECTS)}, got {dialect!r}")
    if dialect == "g2opy":
        return graph
    out = replace(graph, vertices=dict(graph.vertices), edges=dict(graph.edges))
    if "VERTEX_SE3:EXPMAP" in out.vertices:
        b = out.vertices["VERTEX_SE3:EXPMAP"]
        out.vertices["VERTEX_SE3:EXPMAP"] = replace(b, values=invert_qt(b.values))
    if "EDGE_SE3:EXPMAP" in out.edges:
        e = out.edges["EDGE_SE3:EXPMAP"]
        out.edges["EDGE_SE3:EXPMAP"] = replace(e, measurements=invert_qt(e.measurements))
    return out


#: The intrinsics ``fx fy cx cy baseline`` of a ``VERTEX_CAM`` line without them: those of
#: g2o's default ``SBACam`` (g2opy 2.3.0 writes the pose only and reads it into a default one).
CAMERA_DEFAULTS = (1.0, 1.0, 0.5, 0.5, 0.0)


def convert(path: Path, tag: str, v: np.ndarray, lines: np.ndarray, out: GraphFile,
            pieces: dict[str, list[tuple]]) -> None:
    """Convert one generic tag's rows; parameters go to ``out``, the rest to ``pieces[tag]``.

    Args:
        path: The file (for messages).
        tag: A tag of :data:`LAYOUTS`.
        v: ``(n, count)`` the values after the tag.
        lines: ``(n,)`` 1-based line numbers.
        out: The graph being read (its parameters are filled).
        pieces: Tag → list of ``(ids, values, lines)`` (vertices) or
            ``(ids, measurements, information, lines, params)`` (edges).
    """
    lay = LAYOUTS[tag]
    if lay.kind == "param":
        for pid, values, line in zip(parse_ids(path, tag, v[:, :1], lines)[:, 0].tolist(),
                                     v[:, 1:], lines.tolist(), strict=True):
            if pid in out.offsets or pid in out.parameters:
                raise GraphFormatError(path, f"duplicate parameter id {pid} ({tag})", line)
            out.parameters[pid] = (tag, values.copy())
        return
    if lay.kind == "vertex":
        values = v[:, 1:]
        if tag == "VERTEX_CAM" and values.shape[1] == lay.values:
            values = np.column_stack([values, np.tile(CAMERA_DEFAULTS, (len(v), 1))])
        pieces[tag].append((parse_ids(path, tag, v[:, :1], lines)[:, 0], values, lines))
        return
    k, p, w = len(lay.vertices), lay.params, lay.values
    ids = parse_ids(path, tag, v[:, :k + p], lines)
    info = symmetric(v[:, k + p + w:], *np.triu_indices(lay.info))
    bad = np.flatnonzero(~positive_definite(info))
    if len(bad):
        raise GraphFormatError(path, f"{tag}: information matrix is not positive definite",
                               int(lines[bad[0]]))
    pieces[tag].append((ids[:, :k], v[:, k + p:k + p + w], info, lines, ids[:, k:]))


def edge_params(block: EdgeBlock) -> np.ndarray:
    """``(m, p)`` parameter ids of an edge block (``p = 0`` without any)."""
    if block.params is None:
        return np.zeros((len(block.ids), 0), np.int64)
    return np.asarray(block.params, np.int64).reshape(len(block.ids), -1)


def write(f: TextIO, graph: GraphFile, kinds: str,
          lines_of: Callable[..., str]) -> None:
    """Write the generic parameters, vertices or edges of ``graph`` in :data:`LAYOUTS` order.

    Args:
        f: The open file.
        graph: The records.
        kinds: ``"param"``, ``"vertex"`` or ``"edge"``.
        lines_of: ``(tag, columns, number of leading integer columns[, other integer
            columns]) -> text``.
    """
    if kinds == "param":
        for pid, (tag, values) in sorted(graph.parameters.items()):
            f.write(lines_of(tag, [np.array([pid]), np.reshape(values, (1, -1))], 1))
        return
    if kinds == "edge":
        for key in sorted(k for k in graph.edges if "#" in k):
            e = graph.edges[key]
            m, n, d = len(e.ids), e.ids.shape[1], e.measurements.shape[1]
            upper = np.asarray(e.information)[:, *np.triu_indices(d)]
            f.write(lines_of(key.split("#")[0], [np.full(m, n), e.ids, np.full(m, d),
                                                 e.measurements, np.full(m, upper.shape[1]),
                                                 upper], n + 1, [n + 1, n + 2 + d]))
    for tag, lay in LAYOUTS.items():
        if lay.kind == "vertex" and kinds == "vertex" and tag in graph.vertices:
            block = graph.vertices[tag]
            f.write(lines_of(tag, [block.ids, block.values], 1))
        elif lay.kind == "edge" and kinds == "edge" and tag in graph.edges:
            e = graph.edges[tag]
            pids = edge_params(e)
            upper = np.asarray(e.information)[:, *np.triu_indices(lay.info)]
            f.write(lines_of(tag, [e.ids, pids, e.measurements, upper],
                             e.ids.shape[1] + pids.shape[1]))
