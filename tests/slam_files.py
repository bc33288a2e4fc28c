"""A tiny reader of the g2o/TORO files in ``shared/data/posegraph`` into canonical
:class:`~graphopt.io.g2o_records.GraphFile` records, for the SLAM tests (the project's reader,
``graphopt.io.g2o``, is written elsewhere). Only what those files contain."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph"

_VERTEX = {"VERTEX_SE2": 3, "VERTEX2": 3, "VERTEX_SE3:QUAT": 7, "VERTEX_TRACKXYZ": 3,
           "VERTEX_XY": 2}
#: tag → (canonical tag, measurement size, information size, has a parameter id)
_EDGE = {"EDGE_SE2": ("EDGE_SE2", 3, 3, False), "EDGE2": ("EDGE_SE2", 3, 3, False),
         "EDGE_SE3:QUAT": ("EDGE_SE3:QUAT", 7, 6, False),
         "EDGE_SE3_TRACKXYZ": ("EDGE_SE3_TRACKXYZ", 3, 3, True),
         "LANDMARK2": ("EDGE_SE2_XY", 2, 2, False)}
_TORO_INFO = [0, 1, 4, 2, 5, 3]  # TORO I11 I12 I22 I33 I13 I23 → g2o I11 I12 I13 I22 I23 I33


def _information(values: list[float], n: int) -> np.ndarray:
    info = np.zeros((n, n))
    info[np.triu_indices(n)] = values
    return info + np.triu(info, 1).T


def read_graph(path: Path) -> GraphFile:
    """Parse one file (VERTEX2/EDGE2 → VERTEX_SE2/EDGE_SE2, LANDMARK2 → EDGE_SE2_XY).

    Args:
        path: The file.
    """
    verts: dict[str, list] = {}
    edges: dict[str, list] = {}
    out = GraphFile(str(path))
    fixed, equiv = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        tok = line.split()
        if not tok:
            continue
        tag = tok[0]
        if tag in _VERTEX:
            canon = "VERTEX_SE2" if tag == "VERTEX2" else tag
            verts.setdefault(canon, []).append((int(tok[1]), tok[2:2 + _VERTEX[tag]], lineno))
        elif tag in _EDGE:
            canon, k, n, has_param = _EDGE[tag]
            vals = [float(v) for v in tok[4 if has_param else 3:]]
            info = vals[k:]
            if tag == "EDGE2":
                info = [info[i] for i in _TORO_INFO]
            param = int(tok[3]) if has_param else 0
            edges.setdefault(canon, []).append(((int(tok[1]), int(tok[2])), vals[:k],
                                                _information(info, n), lineno, param))
        elif tag == "PARAMS_SE3OFFSET":
            out.offsets[int(tok[1])] = np.array(tok[2:9], float)
        elif tag == "FIX":
            fixed += [int(t) for t in tok[1:]]
        elif tag == "EQUIV":
            equiv.append((int(tok[1]), int(tok[2])))
    for tag, rows in verts.items():
        out.vertices[tag] = VertexBlock(np.array([r[0] for r in rows]),
                                        np.array([r[1] for r in rows], float),
                                        np.array([r[2] for r in rows]))
    for tag, rows in edges.items():
        params = np.array([r[4] for r in rows]) if tag == "EDGE_SE3_TRACKXYZ" else None
        out.edges[tag] = EdgeBlock(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                                   np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                                   params)
    out.fixed = np.array(fixed, dtype=np.int64)
    out.equiv = np.array(equiv, dtype=np.int64).reshape(-1, 2)
    return out
