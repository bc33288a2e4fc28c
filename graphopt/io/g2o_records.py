"""The contents of a g2o or TORO graph file as arrays, in g2o's conventions.

Readers (:mod:`graphopt.io.g2o`) convert every supported line to the *canonical* g2o tag and
convention (TORO's ``VERTEX2``/``EDGE2``/``VERTEX3``/``EDGE3``, GTSAM's ``LANDMARK2``, …), so that
whoever builds an optimizer from a file — the SLAM types' builder — handles one convention per
tag. Nothing here knows vertex or edge types.

Canonical tags and their columns:

======================  ======  =========================================================
tag                     ids     values
======================  ======  =========================================================
``VERTEX_SE2``          1       ``x y θ``
``VERTEX_XY``           1       ``x y``
``VERTEX_SE3:QUAT``     1       ``x y z qx qy qz qw``
``VERTEX_TRACKXYZ``     1       ``x y z``
``EDGE_SE2``            2       measurement ``x y θ``; information 3x3
``EDGE_SE2_XY``         2       measurement ``x y`` (point in the pose frame); information 2x2
``EDGE_SE3:QUAT``       2       measurement ``x y z qx qy qz qw``; information 6x6 ([t, q_vec])
``EDGE_SE3_TRACKXYZ``   2       measurement ``x y z``; information 3x3; a parameter id per edge
======================  ======  =========================================================

g2o's other tags (:data:`graphopt.io.g2o_layouts.LAYOUTS`) keep their own tag and the columns
of the g2opy 2.3.0 wheel's lines; their parameters are in :attr:`GraphFile.parameters`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class VertexBlock:
    """All vertex lines of one canonical tag.

    Args:
        ids: ``(n,)`` vertex ids.
        values: ``(n, k)`` estimates in the tag's canonical columns.
        lines: ``(n,)`` 1-based line numbers in the file (0 for generated vertices).
    """

    ids: np.ndarray
    values: np.ndarray
    lines: np.ndarray


@dataclass
class EdgeBlock:
    """All edge lines of one canonical tag.

    Args:
        ids: ``(m, k)`` vertex ids in g2o's order (``k = 2`` for the pose-graph tags).
        measurements: ``(m, k)`` measurements in the tag's canonical columns.
        information: ``(m, e, e)`` information matrices, in g2o's convention for the tag.
        lines: ``(m,)`` 1-based line numbers (0 for generated edges).
        params: ``(m,)`` parameter id per edge (``EDGE_SE3_TRACKXYZ``), ``(m, p)`` for the other
            tags with parameters (``p`` may be 0), else ``None``.
    """

    ids: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    lines: np.ndarray
    params: np.ndarray | None = None


@dataclass
class GraphFile:
    """A graph file's contents.

    Args:
        path: Where it was read from (or ``"<generated>"``).
        vertices: Canonical vertex tag → its lines.
        edges: Canonical edge tag → its lines.
        offsets: ``PARAMS_SE3OFFSET`` id → ``(7,)`` offset ``x y z qx qy qz qw``.
        parameters: The other parameter lines: id → ``(tag, values)``
            (:data:`graphopt.io.g2o_layouts.LAYOUTS`; g2o's parameter ids are global).
        fixed: ``(k,)`` ids named by ``FIX`` lines.
        equiv: ``(k, 2)`` id pairs of TORO ``EQUIV`` lines.
        skipped: Unknown tag → number of lines skipped (when the reader was told to skip).
        notes: One-line remarks a reader made (e.g. which information order it detected).
        separate_landmarks: Whether landmark numbers live in a key space of their own
            (GTSAM's ``LANDMARK2``).
    """

    path: str
    vertices: dict[str, VertexBlock] = field(default_factory=dict)
    edges: dict[str, EdgeBlock] = field(default_factory=dict)
    offsets: dict[int, np.ndarray] = field(default_factory=dict)
    parameters: dict[int, tuple[str, np.ndarray]] = field(default_factory=dict)
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    equiv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    skipped: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    #: GTSAM ``LANDMARK2`` lines were read: their landmark numbers are GTSAM's ``L(j)`` keys,
    #: a key space of their own that may reuse pose numbers.
    separate_landmarks: bool = False
