"""g2o and TORO graph files: :func:`read_graph`, :func:`write_g2o` and :class:`GraphFormatError`.

Read tags (plain, ``.gz`` or ``.bz2``; blank lines and ``#`` comments skipped), each converted to
its canonical g2o tag (see :mod:`graphopt.io.g2o_records`):

- g2o: ``VERTEX_SE2``, ``EDGE_SE2``, ``VERTEX_XY``, ``EDGE_SE2_XY``, ``VERTEX_SE3:QUAT``,
  ``EDGE_SE3:QUAT``, ``VERTEX_TRACKXYZ``, ``EDGE_SE3_TRACKXYZ``, ``PARAMS_SE3OFFSET``, ``FIX``.
- GTSAM: ``LANDMARK2 pose landmark x y Ixx Ixy Iyy`` → ``EDGE_SE2_XY`` (same columns).
- g2o's other slam2d, slam3d, sba, sim3, sclam2d and icp tags, as the g2opy 2.3.0 wheel writes
  them (:mod:`graphopt.io.g2o_layouts`): parameters go to :attr:`GraphFile.parameters`, vertex and
  edge lines to blocks under their own tag (sized ``LOTSOF`` lines under ``TAG#k``), ids in
  g2o's order, the information from its upper triangle.
- TORO: ``VERTEX2``/``EDGE2`` → ``VERTEX_SE2``/``EDGE_SE2``; ``VERTEX3``/``EDGE3`` (roll, pitch,
  yaw with ``R = Rz(yaw) Ry(pitch) Rx(roll)``) → ``VERTEX_SE3:QUAT``/``EDGE_SE3:QUAT``;
  ``EQUIV a b`` → :attr:`GraphFile.equiv` (merging is the builder's job).

Conventions that differ between the formats:

- ``EDGE2`` information comes in TORO's order ``I11 I12 I22 I33 I13 I23`` in some files and in
  g2o's ``I11 I12 I13 I22 I23 I33`` in others. Per file, the order that makes every ``EDGE2``
  matrix positive definite is used (TORO's when both do) and named once in
  :attr:`GraphFile.notes`; when neither does, the first failing line is an error.
- ``EDGE3`` information weighs the roll-pitch-yaw error, which is the rotation angle to first
  order, whereas g2o's ``EDGE_SE3:QUAT`` weighs the quaternion's vector part, half the angle:
  ``Ω_g2o = D Ω_toro D`` with ``D = diag(1, 1, 1, 2, 2, 2)`` (rotation block ×4, mixed ×2), so
  chi2 is g2o's. An ``EDGE3`` without information gets the identity in roll-pitch-yaw space.

Vertex ids are per tag, as GTSAM keeps them (g2o's own ``known_landmark`` files number
``VERTEX_TRACKXYZ`` from 0 beside ``VERTEX_SE3:QUAT`` 0…): an id may appear once per tag. An edge
naming an id of a vertex tag that has lines in the file must name one of them; a file without
lines of that tag (GTSAM's Victoria Park) is legal, its estimates are for the builder to guess.

The reader groups the lines by tag and converts each tag with a few numpy calls; every error is a
one-line :class:`GraphFormatError` naming the file and the 1-based line.
"""

from __future__ import annotations

import bz2
import gzip
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from graphopt.io import g2o_layouts as gl
from graphopt.io.atomic import atomic_path
from graphopt.io.g2o_lines import GraphFormatError, parse_ids, positive_definite, symmetric
from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock
from graphopt.io.text import WHITESPACE, read_bytes, token_layout
from graphopt.linear.indexing import concat_ranges

__all__ = ["GraphFormatError", "read_graph", "write_g2o"]


# Tag → (canonical tag, allowed numbers of values after the tag (empty: one or more), layout).
_TAGS: dict[str, tuple[str, tuple[int, ...], str]] = {
    "VERTEX_SE2": ("VERTEX_SE2", (4,), "id x y theta"),
    "VERTEX2": ("VERTEX_SE2", (4,), "id x y theta"),
    "VERTEX_XY": ("VERTEX_XY", (3,), "id x y"),
    "VERTEX_SE3:QUAT": ("VERTEX_SE3:QUAT", (8,), "id x y z qx qy qz qw"),
    "VERTEX3": ("VERTEX_SE3:QUAT", (7,), "id x y z roll pitch yaw"),
    "VERTEX_TRACKXYZ": ("VERTEX_TRACKXYZ", (4,), "id x y z"),
    "EDGE_SE2": ("EDGE_SE2", (11,), "i j x y theta and 6 information values"),
    "EDGE2": ("EDGE_SE2", (11,), "i j x y theta and 6 information values"),
    "EDGE_SE2_XY": ("EDGE_SE2_XY", (7,), "i j x y and 3 information values"),
    "LANDMARK2": ("EDGE_SE2_XY", (7,), "pose landmark x y Ixx Ixy Iyy"),
    "EDGE_SE3:QUAT": ("EDGE_SE3:QUAT", (30,), "i j x y z qx qy qz qw and 21 information values"),
    "EDGE3": ("EDGE_SE3:QUAT", (8, 29), "i j x y z roll pitch yaw [and 21 information values]"),
    "EDGE_SE3_TRACKXYZ": ("EDGE_SE3_TRACKXYZ", (12,), "i j param x y z and 6 information values"),
    "PARAMS_SE3OFFSET": ("PARAMS_SE3OFFSET", (8,), "id x y z qx qy qz qw"),
    "FIX": ("FIX", (), "one or more vertex ids"),
    "EQUIV": ("EQUIV", (2,), "id id"),
}
_POSE_GRAPH_TAGS = tuple(_TAGS)  # named one by one in an unknown tag's error
_TAGS.update({tag: (tag, (lay.count, *gl.CLASSIC.get(tag, ())), lay.text)
              for tag, lay in gl.LAYOUTS.items()})
_TAGS.update({tag: (tag, (), "n id_1..id_n d z_1..z_d N I_1..I_N") for tag in gl.DYNAMIC})
_VERTEX_TAGS = ("VERTEX_SE2", "VERTEX_XY", "VERTEX_SE3:QUAT", "VERTEX_TRACKXYZ")
_ALL_VERTEX_TAGS = (*_VERTEX_TAGS, *(t for t, lay in gl.LAYOUTS.items() if lay.kind == "vertex"))
# Canonical edge tag → (vertex tags of its two ends, measurement columns, information size).
_EDGES = {
    "EDGE_SE2": (("VERTEX_SE2", "VERTEX_SE2"), 3, 3),
    "EDGE_SE2_XY": (("VERTEX_SE2", "VERTEX_XY"), 2, 2),
    "EDGE_SE3:QUAT": (("VERTEX_SE3:QUAT", "VERTEX_SE3:QUAT"), 7, 6),
    "EDGE_SE3_TRACKXYZ": (("VERTEX_SE3:QUAT", "VERTEX_TRACKXYZ"), 3, 3),
}
_ALL_EDGE_TAGS = (*_EDGES, *(t for t, lay in gl.LAYOUTS.items() if lay.kind == "edge"))
_TORO_EDGE2 = ([0, 0, 1, 2, 0, 1], [0, 1, 1, 2, 2, 2])  # I11 I12 I22 I33 I13 I23
_RPY_TO_QVEC = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])  # error scale: rpy ≈ 2 q_vec


def _rpy_to_quat(rpy: np.ndarray) -> np.ndarray:
    """Quaternions ``[qx, qy, qz, qw]`` (``qw >= 0``) of ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    c, s = np.cos(0.5 * rpy).T, np.sin(0.5 * rpy).T
    q = np.stack([
        s[0] * c[1] * c[2] - c[0] * s[1] * s[2],
        c[0] * s[1] * c[2] + s[0] * c[1] * s[2],
        c[0] * c[1] * s[2] - s[0] * s[1] * c[2],
        c[0] * c[1] * c[2] + s[0] * s[1] * s[2],
    ], axis=1)
    return np.where(q[:, 3:] < 0, -q, q)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


_TAG_WIDTH = max(map(len, _TAGS))  # no known tag is longer (g2o's longest: 42 characters)


def _tag_codes(tags: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(tags, return_inverse=True)`` through runs of equal tags (files come in long
    runs of one tag: sorting only the runs' tags is much quicker than sorting every line's)."""
    new = np.ones(len(tags), dtype=bool)
    new[1:] = tags[1:] != tags[:-1]
    runs = np.flatnonzero(new)
    names, run_code = np.unique(tags[runs], return_inverse=True)
    return names, np.repeat(run_code.ravel(), np.diff(np.append(runs, len(tags))))


def _scan(path: Path, data: bytes, skip_unknown: bool
          ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], dict[str, int]]:
    """Known tag → ``(values (flat), value count per line, line numbers)``; unknown → count.

    One pass over the whole file: the tag of every line from a fixed-width window, then the tags
    (and skipped or comment lines) blanked out and every remaining token parsed by one C call.
    """
    a = np.frombuffer(data, dtype=np.uint8)
    starts, token_line = token_layout(data)
    first = np.ones(len(starts), dtype=bool)
    first[1:] = token_line[1:] != token_line[:-1]
    line_of = np.cumsum(first) - 1  # token → index of its (non-blank) line
    heads, numbers = starts[first], token_line[first]
    # each line's first _TAG_WIDTH + 1 bytes (past the end: spaces), gathered without an index
    # matrix: rows of a strided window view
    padded = np.concatenate([a, np.full(_TAG_WIDTH + 1, 32, np.uint8)])
    chars = sliding_window_view(padded, _TAG_WIDTH + 1)[heads]
    space = WHITESPACE[chars]
    space[:, -1] = True
    width = np.argmax(space, axis=1)
    chars = np.where(np.arange(_TAG_WIDTH + 1) < width[:, None], chars, 0)[:, :_TAG_WIDTH]
    names, code = _tag_codes(np.ascontiguousarray(chars).view(f"S{_TAG_WIDTH}").ravel())
    tags = [n.decode("utf-8", errors="replace") for n in names]
    known = np.array([t in _TAGS for t in tags], dtype=bool)
    keep = known[code] if len(code) else first[:0]
    unknown = np.array([not (t in _TAGS or t.startswith("#")) for t in tags], dtype=bool)
    if unknown.any() and not skip_unknown:
        k = int(np.argmax(unknown[code]))  # the first line with an unknown tag
        shown = tags[code[k]] + ("..." if width[k] >= _TAG_WIDTH else "")
        raise GraphFormatError(
            path, f"unknown tag {shown!r} (known: {' '.join(_POSE_GRAPH_TAGS)}, "
            f"g2o's other slam2d, slam3d, sba, sim3, sclam2d and icp tags, {len(_TAGS)} in all "
            "(docs/slam.md §2); --skip-unknown / skip_unknown=True skips such lines)", numbers[k])
    skipped = {tags[u]: int(np.count_nonzero(code == u)) for u in np.flatnonzero(unknown)}
    counts = np.bincount(line_of, minlength=len(heads)) - 1
    bad = np.zeros(len(heads), dtype=bool)
    for u in np.flatnonzero(known):
        allowed = _TAGS[tags[u]][1]
        lines_u = code == u
        bad |= lines_u & (~np.isin(counts, allowed) if allowed else counts < 1)
    if bad.any():
        k = int(np.argmax(bad))
        tag, (_, allowed, layout) = tags[code[k]], _TAGS[tags[code[k]]]
        expect = " or ".join(map(str, allowed)) or "at least 1"
        raise GraphFormatError(path, f"{tag} needs {expect} values ({layout}), found "
                                     f"{counts[k]}", numbers[k])
    # Blank every tag and every skipped or comment line, then parse what is left in one call.
    newlines = np.flatnonzero(a == 10)
    line_end = np.append(newlines, len(a))[np.searchsorted(newlines, heads)]
    blanked = padded.copy()
    rows = sliding_window_view(blanked, _TAG_WIDTH, writeable=True)  # writes reach blanked
    for w in np.unique(width[keep]).tolist():  # the tags: one assignment per tag width
        rows[heads[keep & (width == w)], :w] = 32
    other = ~keep  # comment and skipped lines: whole lines
    blanked[concat_ranges(heads[other], (line_end - heads)[other])] = 32
    blanked = blanked[:len(a)]
    numeric = keep[line_of] & ~first
    values = _numbers(path, blanked.tobytes(), numbers[line_of[numeric]])
    value_code = code[line_of[numeric]]
    groups = {tags[u]: (values[value_code == u], counts[code == u], numbers[code == u])
              for u in np.flatnonzero(known)}
    return groups, skipped


def _numbers(path: Path, blanked: bytes, lines: np.ndarray) -> np.ndarray:
    """Every token of ``blanked`` as a float; an error on the first non-numeric or non-finite."""
    if len(lines) == 0:
        return np.zeros(0)
    values = None
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        try:
            values = np.fromstring(blanked, dtype=float, sep=" ")
        except (ValueError, DeprecationWarning):
            pass
    if values is not None and len(values) == len(lines):
        bad = np.flatnonzero(~np.isfinite(values))
        if not len(bad):
            return values
    tokens = blanked.split()  # only for broken files: find the culprit
    for k, token in enumerate(tokens):
        text = token.decode("utf-8", errors="replace")[:40]
        try:
            number = float(token.replace(b"_", b"#"))  # Python reads 1_0, the C parser does not
        except ValueError:
            raise GraphFormatError(path, f"not a number: {text!r}", lines[k]) from None
        if not np.isfinite(number):
            raise GraphFormatError(path, f"non-finite value {text!r}", lines[k])
    raise GraphFormatError(path, "could not parse the numbers")  # pragma: no cover


def _table(path: Path, tag: str, values: np.ndarray, counts: np.ndarray, numbers: np.ndarray
          ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Value count → ``(values (n, count), line numbers (n,))`` for one tag's lines."""
    allowed = _TAGS[tag][1]
    if tag == "FIX":  # any number of ids per line, one row per id
        return {1: (values[:, None], np.repeat(numbers, counts))}
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    out = {}
    for count in allowed or np.unique(counts).tolist():  # (sized lines: per count)
        sel = counts == count
        if sel.any():
            out[count] = (values[offsets[sel][:, None] + np.arange(count)], numbers[sel])
    return out


def _edge2_information(path: Path, values: np.ndarray, lines: np.ndarray,
                       notes: list[str]) -> np.ndarray:
    """EDGE2 information in whichever order (TORO's or g2o's) makes all of it positive definite."""
    orders = {"TORO's (I11 I12 I22 I33 I13 I23)": symmetric(values, *_TORO_EDGE2),
              "g2o's (I11 I12 I13 I22 I23 I33)": symmetric(values, *np.triu_indices(3))}
    fits = {name: positive_definite(info) for name, info in orders.items()}
    score = {name: int(ok.sum()) for name, ok in fits.items()}
    (toro, g2o), m = orders, len(values)
    name = toro if score[toro] >= score[g2o] else g2o
    if score[name] < m:
        k = int(np.flatnonzero(~fits[name])[0])
        raise GraphFormatError(
            path, f"EDGE2: information matrix is not positive definite in either order "
                  f"(TORO's fits {score[toro]} of {m} EDGE2 lines, g2o's {score[g2o]})",
            int(lines[k]))
    other = g2o if name == toro else toro
    notes.append(f"EDGE2 information read in {name} order: positive definite on all {m} lines "
                 f"(the other order on {score[other]})")
    return orders[name]


def _convert(path: Path, tag: str, rows: dict[int, tuple[np.ndarray, np.ndarray]],
             out: GraphFile, pieces: dict[str, list[tuple]]) -> None:
    """Append one tag's rows, converted to the canonical tag, to ``pieces`` (offsets: ``out``)."""
    canonical = _TAGS[tag][0]
    for count, (v, lines) in rows.items():
        if tag in gl.LAYOUTS:
            gl.convert(path, tag, v, lines, out, pieces)
        elif tag in gl.DYNAMIC:
            gl.convert_dynamic(path, tag, v, lines, pieces)
        elif tag in ("FIX", "EQUIV"):
            pieces[tag].append((parse_ids(path, tag, v, lines), lines))
        elif tag == "PARAMS_SE3OFFSET":
            for pid, values, line in zip(parse_ids(path, tag, v[:, :1], lines)[:, 0].tolist(),
                                         v[:, 1:], lines.tolist(), strict=True):
                if pid in out.offsets or pid in out.parameters:
                    raise GraphFormatError(path, f"duplicate PARAMS_SE3OFFSET id {pid}", line)
                out.offsets[pid] = values
        elif canonical in _VERTEX_TAGS:
            values = v[:, 1:]
            if tag == "VERTEX3":
                values = np.column_stack([values[:, :3], _rpy_to_quat(values[:, 3:])])
            pieces[canonical].append((parse_ids(path, tag, v[:, :1], lines)[:, 0], values, lines))
        else:
            nid = 3 if tag == "EDGE_SE3_TRACKXYZ" else 2
            ids = parse_ids(path, tag, v[:, :nid], lines)
            _, cols, dim = _EDGES[canonical]
            cols = 6 if tag == "EDGE3" else cols
            meas, tail = v[:, nid:nid + cols], v[:, nid + cols:]
            if tag == "EDGE2":
                info = _edge2_information(path, tail, lines, out.notes)
            elif tag == "EDGE3":
                meas = np.column_stack([meas[:, :3], _rpy_to_quat(meas[:, 3:])])
                info = symmetric(tail, *np.triu_indices(6)) if count == 29 else np.eye(6)[None]
                info = info * _RPY_TO_QVEC[:, None] * _RPY_TO_QVEC + np.zeros((len(v), 1, 1))
            else:
                info = symmetric(tail, *np.triu_indices(dim))
            loops = np.flatnonzero(ids[:, 0] == ids[:, 1])
            if len(loops) and canonical in ("EDGE_SE2", "EDGE_SE3:QUAT"):
                raise GraphFormatError(path, f"{tag}: edge from vertex {ids[loops[0], 0]} to "
                                             "itself", lines[loops[0]])
            bad = np.flatnonzero(~positive_definite(info))
            if len(bad):
                raise GraphFormatError(path, f"{tag}: information matrix is not positive "
                                             "definite", lines[bad[0]])
            pieces[canonical].append((ids[:, :2], meas, info, lines, ids[:, 2:]))
    if tag == "EDGE3":
        out.notes.append(
            f"EDGE3 information converted from roll-pitch-yaw errors to g2o's quaternion-vector "
            f"errors (rotation block x4, mixed x2; chi2 is g2o's); {len(rows.get(8, [[]])[-1])} "
            f"of {sum(len(r[1]) for r in rows.values())} EDGE3 lines had none: identity in rpy")
    elif tag == "LANDMARK2":
        out.separate_landmarks = True
        out.notes.append("LANDMARK2 (GTSAM: pose landmark x y Ixx Ixy Iyy) read as EDGE_SE2_XY")


def _earliest(bad: np.ndarray, lines: np.ndarray) -> int | None:
    """Index of the earliest line where ``bad`` holds, or ``None``."""
    if not bad.any():
        return None
    return int(np.flatnonzero(bad)[np.argmin(lines[bad])])


def _check_references(path: Path, graph: GraphFile, fix_lines: np.ndarray,
                      equiv_lines: np.ndarray) -> None:
    """Duplicate vertex ids, edges naming missing vertices or parameters, FIX/EQUIV ids."""
    for tag, block in graph.vertices.items():
        order = np.lexsort((block.lines, block.ids))
        ids, lines = block.ids[order], block.lines[order]
        dup = np.zeros(len(ids), dtype=bool)
        dup[1:] = ids[1:] == ids[:-1]
        if (k := _earliest(dup, lines)) is not None:
            first = lines[np.maximum.accumulate(np.where(dup, 0, np.arange(len(ids))))[k]]
            raise GraphFormatError(
                path, f"duplicate {tag} id {ids[k]} (first defined on line {first})", lines[k])
    for tag, edges in graph.edges.items():
        ends = _EDGES[tag][0] if tag in _EDGES else gl.ends(tag)
        for end, vtag in enumerate(ends):
            if vtag not in graph.vertices:
                continue
            missing = ~np.isin(edges.ids[:, end], graph.vertices[vtag].ids)
            if (k := _earliest(missing, edges.lines)) is not None:
                raise GraphFormatError(path, f"{tag} names vertex {edges.ids[k, end]}, which has "
                                             f"no {vtag} line in this file", edges.lines[k])
        if tag not in _EDGES:
            pids = gl.edge_params(edges)
            absent = ~np.isin(pids, [*graph.offsets, *graph.parameters])
            if (k := _earliest(absent.any(axis=1), edges.lines)) is not None:
                raise GraphFormatError(path, f"{tag} names parameter {pids[k][absent[k]][0]}, "
                                             "which no PARAMS_ line defines", edges.lines[k])
        elif edges.params is not None:
            missing = ~np.isin(edges.params, list(graph.offsets))
            if (k := _earliest(missing, edges.lines)) is not None:
                raise GraphFormatError(path, f"{tag} names parameter {edges.params[k]}, which no "
                                             "PARAMS_SE3OFFSET line defines", edges.lines[k])
    blocks = [b.ids for b in graph.vertices.values()] or [
        e.ids.ravel() for e in graph.edges.values()]
    known = np.concatenate(blocks + [np.zeros(0, np.int64)])
    for name, ids, lines in (("FIX", graph.fixed[:, None], fix_lines),
                             ("EQUIV", graph.equiv, equiv_lines)):
        unknown = ~np.isin(ids, known)
        if (k := _earliest(unknown.any(axis=1), lines)) is not None:
            raise GraphFormatError(path, f"{name} names vertex {ids[k][unknown[k]][0]}, which "
                                         "the file never defines", lines[k])


def read_graph(path: str | os.PathLike[str], skip_unknown: bool = False,
               dialect: str = "g2opy") -> GraphFile:
    """Read a g2o, TORO or GTSAM graph file, every line converted to its canonical g2o tag.

    Args:
        path: The file (plain, ``.gz`` or ``.bz2``; detected from the content).
        skip_unknown: Skip lines with unknown tags (counted per tag in
            :attr:`GraphFile.skipped` and noted) instead of failing on the first.
        dialect: ``"g2opy"`` (the official wheel's lines, default) or ``"classic"`` (g2o's C++
            ``read``, which stores ``VERTEX_SE3:EXPMAP`` and ``EDGE_SE3:EXPMAP`` inverted; the
            records are the same either way). The tags where they differ otherwise are told
            apart by their value counts.

    Returns:
        The contents; blocks keep the file's line order and line numbers.

    Raises:
        GraphFormatError: Missing or corrupt file, no graph lines, an unknown tag, a wrong value
            count, a non-numeric or non-finite value, a bad or duplicate id, an information
            matrix that is not positive definite, an edge naming a vertex the file's vertex
            lines lack or a parameter it never defines, ``FIX``/``EQUIV`` naming an unknown
            vertex, an edge from a vertex to itself. One line naming the file and line.
    """
    path = Path(path)
    gl.to_dialect(GraphFile(str(path)), dialect)  # a bad dialect fails before reading
    groups, skipped = _scan(path, read_bytes(path, GraphFormatError), skip_unknown)
    if not groups:
        raise GraphFormatError(path, "no vertex or edge lines" + (
            f" (skipped {sum(skipped.values())} lines with unknown tags)" if skipped else ""))
    graph = GraphFile(path=str(path), skipped=skipped)
    pieces: dict[str, list[tuple]] = {t: [] for t in (*_ALL_VERTEX_TAGS, *_ALL_EDGE_TAGS, "FIX",
                                                      "EQUIV")}
    # tags in the order of their first line: a duplicate parameter id names its later line
    for tag, group in sorted(groups.items(), key=lambda kv: int(kv[1][2][0])):
        _convert(path, tag, _table(path, tag, *group), graph, pieces)
    merged = {}
    for tag, parts in pieces.items():  # each canonical tag's lines in file order
        if not parts:
            merged[tag] = [np.zeros((0, 2), np.int64), np.zeros(0, np.int64)]
            continue
        parts = [np.concatenate(p) for p in zip(*parts, strict=True)]
        order = np.argsort(parts[3 if len(parts) == 5 else -1], kind="stable")
        merged[tag] = [p[order] for p in parts]
        if tag in _ALL_VERTEX_TAGS:
            graph.vertices[tag] = VertexBlock(*merged[tag])
        elif tag in gl.LAYOUTS or "#" in tag:
            graph.edges[tag] = EdgeBlock(*merged[tag])
        elif tag in _EDGES:
            ids, meas, info, lines, extra = merged[tag]
            graph.edges[tag] = EdgeBlock(ids, meas, info, lines, extra[:, 0] if extra.shape[1]
                                         else None)
    (fixed, fix_lines), (equiv, equiv_lines) = merged["FIX"], merged["EQUIV"]
    graph.fixed, graph.equiv = fixed[:, 0].astype(np.int64), equiv.astype(np.int64)
    _check_references(path, graph, fix_lines, equiv_lines)
    graph = gl.to_dialect(graph, dialect)
    if skipped:
        graph.notes.append("skipped lines with unknown tags: " + ", ".join(
            f"{t} x{n}" for t, n in sorted(skipped.items())))
    return graph


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _lines_of(tag: str, columns: list[np.ndarray], n_ids: int,
              sizes: Sequence[int] = ()) -> str:
    """``tag id… v…`` lines: the first ``n_ids`` columns and those at ``sizes`` as integers,
    the other values with ``%.17g``."""
    if len(columns[0]) == 0:
        return ""
    table = np.column_stack([np.asarray(c, dtype=float).reshape(len(c), -1) for c in columns])
    if not np.isfinite(table).all():
        raise ValueError(f"write_g2o: {tag} contains NaN or inf")
    kinds = ["%d" if c < n_ids or c in sizes else "%.17g" for c in range(table.shape[1])]
    fmt = " ".join([tag, *kinds])
    return "\n".join(fmt % tuple(row) for row in table.tolist()) + "\n"


def write_g2o(path: str | os.PathLike[str], graph: GraphFile, drop_equiv: bool = False,
              dialect: str = "g2opy") -> None:
    """Write ``graph`` as a g2o file (canonical tags, ``%.17g``), atomically.

    Parameters come first, then vertices, edges and ``FIX`` lines. A ``.gz``/``.bz2`` suffix
    compresses. g2o itself wants vertex ids unique across tags; GTSAM keeps landmarks apart.

    Args:
        path: Destination; never the file ``graph`` was read from.
        graph: The contents (canonical tags only).
        drop_equiv: Leave out ``EQUIV`` pairs (g2o has no such line) instead of refusing.
        dialect: ``"g2opy"`` (default) or ``"classic"`` (see :func:`read_graph`).

    Raises:
        ValueError: ``path`` is ``graph``'s input file, a block has an unknown tag or NaN/inf,
            or the graph has ``EQUIV`` pairs and ``drop_equiv`` is false. ``path`` is then
            untouched and no temporary file is left.
    """
    graph = gl.to_dialect(graph, dialect)
    source, target = Path(graph.path), Path(path)
    same = source.exists() and target.exists() and os.path.samefile(target, source)
    if same or target.resolve() == source.resolve():
        raise ValueError(f"write_g2o: refusing to overwrite the input file {graph.path}")
    if len(graph.equiv) and not drop_equiv:
        raise ValueError(f"write_g2o: {len(graph.equiv)} EQUIV pairs, which g2o cannot store; "
                         "merge them first or pass drop_equiv=True")
    unknown = ((set(graph.vertices) - set(_ALL_VERTEX_TAGS))
               | {t for t in graph.edges if t not in _ALL_EDGE_TAGS
                  and t.split("#")[0] not in gl.DYNAMIC})
    if unknown:
        raise ValueError(f"write_g2o: no g2o line for {', '.join(sorted(unknown))}")
    track = graph.edges.get("EDGE_SE3_TRACKXYZ")
    if track is not None and track.params is None:
        raise ValueError("write_g2o: EDGE_SE3_TRACKXYZ edges need parameter ids (params)")
    name = str(path)
    opener: Callable = gzip.open if name.endswith(".gz") else (
        bz2.open if name.endswith(".bz2") else open)
    with atomic_path(path) as tmp, opener(tmp, "wt", encoding="ascii") as f:
        for pid, offset in sorted(graph.offsets.items()):
            f.write(_lines_of("PARAMS_SE3OFFSET", [np.array([pid]), np.reshape(offset, (1, 7))], 1))
        gl.write(f, graph, "param", _lines_of)
        for tag in _VERTEX_TAGS:
            if tag in graph.vertices:
                block = graph.vertices[tag]
                f.write(_lines_of(tag, [block.ids, block.values], 1))
        gl.write(f, graph, "vertex", _lines_of)
        for tag, (_, _, dim) in _EDGES.items():
            if tag in graph.edges:
                e = graph.edges[tag]
                ids = [e.ids] + ([e.params] if e.params is not None else [])
                upper = e.information[:, *np.triu_indices(dim)]
                f.write(_lines_of(tag, [*ids, e.measurements, upper], len(ids) + 1))
        gl.write(f, graph, "edge", _lines_of)
        f.write(_lines_of("FIX", [np.asarray(graph.fixed)], 1))
