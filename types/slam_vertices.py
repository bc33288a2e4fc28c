"""The vertex table of a graph being built from a g2o file's records
(:func:`~graphopt.types.slam_graph.build_graph`): per vertex tag, the graphopt type, ids,
estimates and line numbers, with the checks on them."""

from __future__ import annotations

import numpy as np

from graphopt.errors import GraphError
from graphopt.io.g2o_records import GraphFile, VertexBlock
from graphopt.types import slam_tags as st
from graphopt.types.isometry3 import pose_from_qt
from graphopt.types.slam2d import VertexPointXY, VertexSE2
from graphopt.types.slam3d import VertexSE3
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = ["POINT_TAGS", "TAG_ORDER", "VERTEX_TYPES", "VertexTable", "to_estimates", "vtype",
           "where"]

VERTEX_TYPES: dict[str, type[BaseVertex]] = {
    "VERTEX_SE2": VertexSE2, "VERTEX_XY": VertexPointXY,
    "VERTEX_SE3:QUAT": VertexSE3, "VERTEX_TRACKXYZ": VertexPointXYZ,
}
#: The point tags (their ids may live in a key space of their own, GTSAM's).
POINT_TAGS = ("VERTEX_XY", "VERTEX_TRACKXYZ")
#: Every vertex tag, in the order the builder adds them.
TAG_ORDER = [*VERTEX_TYPES, *st.VERTEX_TAGS]


def vtype(tag: str) -> type[BaseVertex]:
    """The graphopt vertex type of ``tag``."""
    return VERTEX_TYPES[tag] if tag in VERTEX_TYPES else st.vertex_type(tag)


def where(path: str, lines: np.ndarray, i: int) -> str:
    """``path:line`` of row ``i`` (``path`` when it has no line)."""
    line = int(lines[i]) if len(lines) > i else 0
    return f"{path}:{line}" if line > 0 else path


def to_estimates(tag: str, values: np.ndarray) -> np.ndarray:
    """Estimates from a vertex tag's file values."""
    if tag in st.VERTEX_TAGS:
        return st.estimates(tag, values)
    return pose_from_qt(values) if tag == "VERTEX_SE3:QUAT" else np.asarray(values, float)


class VertexTable:
    """The vertex table being built: per tag, ids, estimates and line numbers."""

    def __init__(self, graph: GraphFile, shift: int) -> None:
        self.path = graph.path
        self.ids: dict[str, np.ndarray] = {}
        self.est: dict[str, np.ndarray] = {}
        self.lines: dict[str, np.ndarray] = {}
        for tag in TAG_ORDER:
            block = graph.vertices.get(tag)
            if block is None or not len(block.ids):
                continue
            ids = np.asarray(block.ids, np.int64) + (shift if tag in POINT_TAGS else 0)
            self._check_values(tag, block)
            self.ids[tag], self.lines[tag] = ids, np.asarray(block.lines, np.int64)
            self.est[tag] = to_estimates(tag, np.asarray(block.values, float))
        self._check_duplicates()

    def _check_values(self, tag: str, block: VertexBlock) -> None:
        bad = ~np.isfinite(block.values).all(axis=1)
        if tag == "VERTEX_SE3:QUAT" and not bad.any():
            bad = np.abs((block.values[:, 3:] ** 2).sum(axis=1) - 1.0) > 1e-4
            what = "has a quaternion that is not of unit length"
        else:
            what = "has non-finite values"
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise GraphError(f"{where(self.path, block.lines, i)}: {tag} {int(block.ids[i])} "
                             f"{what}")

    def _check_duplicates(self) -> None:
        tags = list(self.ids)
        ids = np.concatenate([self.ids[t] for t in tags]) if tags else np.zeros(0, np.int64)
        uniq, first, counts = np.unique(ids, return_index=True, return_counts=True)
        if np.any(counts > 1):
            dup = int(uniq[counts > 1][0])
            places = [f"{where(self.path, self.lines[t], int(i))} ({t})" for t in tags
                     for i in np.flatnonzero(self.ids[t] == dup)]
            raise GraphError(f"{self.path}: vertex id {dup} is defined twice: "
                             + " and ".join(places[:2]))

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """All ids, sorted, and the index into :data:`TAG_ORDER` of each one's tag."""
        tags = [t for t in TAG_ORDER if t in self.ids]
        ids = np.concatenate([self.ids[t] for t in tags] or [np.zeros(0, np.int64)])
        codes = np.concatenate([np.full(len(self.ids[t]), TAG_ORDER.index(t)) for t in tags]
                               or [np.zeros(0, np.int64)])
        order = np.argsort(ids, kind="stable")
        return ids[order], codes[order]

    def add_missing(self, tag: str, ids: np.ndarray) -> None:
        """Vertices named by edges only: estimates left NaN until the guess fills them."""
        shape = vtype(tag).estimate_shape
        self.ids[tag] = np.concatenate([self.ids.get(tag, np.zeros(0, np.int64)), ids])
        self.lines[tag] = np.concatenate([self.lines.get(tag, np.zeros(0, np.int64)),
                                          np.zeros(len(ids), np.int64)])
        self.est[tag] = np.concatenate([self.est.get(tag, np.zeros((0, *shape))),
                                        np.full((len(ids), *shape), np.nan)])
