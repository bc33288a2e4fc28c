"""g2o/TORO/GTSAM graph files: every shared data set, conventions, round trips, bad input."""

from __future__ import annotations

import bz2
import gzip
import re
from pathlib import Path

import numpy as np
import pytest

from graphopt.io.g2o import GraphFormatError, read_graph, write_g2o
from graphopt.io.g2o_records import EdgeBlock, GraphFile, VertexBlock
from graphopt.lie import quat_to_rot, rot_to_quat, so3_exp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"data folder {DATA} is absent")

# File → (raw tag → canonical tag, count per canonical tag (the README's table)).
FILES = {
    "pose2example.txt": {"VERTEX_SE2": 11, "EDGE_SE2": 12},
    "pose3example.txt": {"VERTEX_SE3:QUAT": 5, "EDGE_SE3:QUAT": 6},
    "Klaus3.g2o": {"VERTEX_SE3:QUAT": 3, "EDGE_SE3:QUAT": 3},
    "known_landmark_localization_20.g2o": {"VERTEX_SE3:QUAT": 20, "VERTEX_TRACKXYZ": 4,
                                           "EDGE_SE3:QUAT": 19, "EDGE_SE3_TRACKXYZ": 80},
    "victoriaPark_reduced_1k.g2o": {"EDGE_SE2": 999, "EDGE_SE2_XY": 606},
    "w100.graph": {"VERTEX_SE2": 100, "EDGE_SE2": 300},
    "w10000.graph": {"VERTEX_SE2": 10000, "EDGE_SE2": 64311},
    "sphere_smallnoise.graph": {"VERTEX_SE3:QUAT": 2200, "EDGE_SE3:QUAT": 8647},
}
RAW = {"VERTEX2": "VERTEX_SE2", "EDGE2": "EDGE_SE2", "VERTEX3": "VERTEX_SE3:QUAT",
       "EDGE3": "EDGE_SE3:QUAT", "LANDMARK2": "EDGE_SE2_XY"}


def _counts(graph: GraphFile) -> dict[str, int]:
    blocks = {**graph.vertices, **graph.edges}
    return {tag: len(block.ids) for tag, block in blocks.items()}


def _grep_counts(path: Path) -> dict[str, int]:
    """What ``grep -c '^TAG '`` says per tag, mapped to the canonical tags."""
    out: dict[str, int] = {}
    for line in path.read_text().splitlines():
        if line.strip():
            tag = RAW.get(line.split()[0], line.split()[0])
            out[tag] = out.get(tag, 0) + 1
    return out


def _write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _assert_same(a: GraphFile, b: GraphFile) -> None:
    """Bit-identical arrays (line numbers aside)."""
    assert a.vertices.keys() == b.vertices.keys() and a.edges.keys() == b.edges.keys()
    for tag in a.vertices:
        assert np.array_equal(a.vertices[tag].ids, b.vertices[tag].ids)
        assert np.array_equal(a.vertices[tag].values, b.vertices[tag].values)
    for tag in a.edges:
        x, y = a.edges[tag], b.edges[tag]
        for name in ("ids", "measurements", "information"):
            assert np.array_equal(getattr(x, name), getattr(y, name)), (tag, name)
        assert (x.params is None and y.params is None) or np.array_equal(x.params, y.params)
    assert a.offsets.keys() == b.offsets.keys()
    assert all(np.array_equal(a.offsets[k], b.offsets[k]) for k in a.offsets)
    assert np.array_equal(a.fixed, b.fixed)


# --------------------------------------------------------------------------------------------
# The shared data sets
# --------------------------------------------------------------------------------------------


@needs_data
@pytest.mark.parametrize("name", sorted(FILES))
def test_every_data_file_loads_with_the_readme_counts(name: str) -> None:
    graph = read_graph(DATA / name)
    assert _counts(graph) == FILES[name]
    grep = _grep_counts(DATA / name)
    assert {t: grep[t] for t in FILES[name]} == FILES[name]
    for block in (*graph.vertices.values(), *graph.edges.values()):
        assert (np.diff(block.lines) > 0).all() and block.lines.min() >= 1
    for edges in graph.edges.values():
        assert (np.linalg.eigvalsh(edges.information)[:, 0] > 0).all()
        assert np.array_equal(edges.information, np.swapaxes(edges.information, 1, 2))


@needs_data
def test_equiv_fix_offsets_and_landmarks_of_the_data_sets() -> None:
    assert len(read_graph(DATA / "w100.graph").equiv) == 40
    w = read_graph(DATA / "w10000.graph")
    assert len(w.equiv) == 5875 and w.equiv[0].tolist() == [21, 1]
    kl = read_graph(DATA / "known_landmark_localization_20.g2o")
    assert list(kl.offsets) == [0] and kl.offsets[0].tolist() == [0, 0, 0, 0, 0, 0, 1]
    track = kl.edges["EDGE_SE3_TRACKXYZ"]
    assert (track.params == 0).all()
    np.testing.assert_array_equal(track.measurements[0], [4.05886375959, 1.0120915115,
                                                          2.03342519441])
    assert track.information[0, 0].tolist() == [2457.14285714, -1885.71428571, -3771.42857143]
    assert track.information[0, 2, 2] == 8114.28571429
    # Victoria Park: no vertex lines (legal), 1000 poses named by the odometry, LANDMARK2 read
    # as EDGE_SE2_XY (pose 4 sees landmark 5 at 11.5387 -3.2007, information xx xy yy).
    vp = read_graph(DATA / "victoriaPark_reduced_1k.g2o")
    assert vp.vertices == {} and len(np.unique(vp.edges["EDGE_SE2"].ids)) == 1000
    lm = vp.edges["EDGE_SE2_XY"]
    assert lm.ids[0].tolist() == [4, 5]
    assert lm.measurements[0].tolist() == [11.5387, -3.2007]
    assert lm.information[0].tolist() == [[1.581139, 0.0], [0.0, 1.581139]]
    assert any("LANDMARK2" in note for note in vp.notes)


@needs_data
@pytest.mark.parametrize("name", ["w100.graph", "w10000.graph"])
def test_edge2_information_order_detected_as_toro(name: str) -> None:
    # Every EDGE2 line ends "1 0 1 1 0 0": identity in TORO's order I11 I12 I22 I33 I13 I23,
    # singular (I33 = 0) in g2o's I11 I12 I13 I22 I23 I33. The reader must pick TORO's.
    graph = read_graph(DATA / name)
    info = graph.edges["EDGE_SE2"].information
    assert np.array_equal(info, np.broadcast_to(np.eye(3), info.shape))
    notes = [n for n in graph.notes if n.startswith("EDGE2")]
    assert len(notes) == 1 and "TORO's (I11 I12 I22 I33 I13 I23)" in notes[0]
    assert f"all {len(info)} lines (the other order on 0)" in notes[0]


def test_edge2_order_g2o_both_and_neither(tmp_path: Path) -> None:
    head = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\n"
    # g2o's order: diag(1, 2, 3); in TORO's order I22 = 0.
    g = read_graph(_write(tmp_path, head + "EDGE2 0 1 1 0 0 1 0 0 2 0 3\n"))
    assert g.edges["EDGE_SE2"].information[0].tolist() == [[1, 0, 0], [0, 2, 0], [0, 0, 3]]
    assert "g2o's" in g.notes[0] and "(the other order on 0)" in g.notes[0]
    # Both orders positive definite: TORO's, the format's own.
    g = read_graph(_write(tmp_path, head + "EDGE2 0 1 1 0 0 10 0 1 10 0 0.5\n"))
    assert g.edges["EDGE_SE2"].information[0].tolist() == [[10, 0, 0], [0, 1, 0.5],
                                                           [0, 0.5, 10]]
    assert "TORO's" in g.notes[0] and "(the other order on 1)" in g.notes[0]
    # One line fits only TORO's, the next only g2o's: an error on the first misfit.
    bad = head + "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 0 1 1 0 0 1 0 0 2 0 3\n"
    with pytest.raises(GraphFormatError, match="not positive definite in either order") as e:
        read_graph(_write(tmp_path, bad))
    assert e.value.line == 4


# --------------------------------------------------------------------------------------------
# TORO 3D: roll-pitch-yaw and the information conversion
# --------------------------------------------------------------------------------------------


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """``Rz(y) Ry(p) Rx(r)`` written out."""
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _rpy_of(R: np.ndarray) -> np.ndarray:
    return np.array([np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(R[2, 0]),
                     np.arctan2(R[1, 0], R[0, 0])])


def test_vertex3_and_edge3_rotations(tmp_path: Path) -> None:
    rpy = [(0.3, -0.2, 2.5), (-2.9, 1.2, -3.0), (0.0, 0.0, np.pi)]
    text = "".join(f"VERTEX3 {i} 1 2 3 {r!r} {p!r} {y!r}\n" for i, (r, p, y) in enumerate(rpy))
    text += "EDGE3 0 1 0.5 -1 2 0.1 0.2 -0.3\n"
    g = read_graph(_write(tmp_path, text))
    v = g.vertices["VERTEX_SE3:QUAT"].values
    assert (v[:, 3] >= 0).all() and np.allclose(np.linalg.norm(v[:, 3:], axis=1), 1, atol=1e-15)
    for k, angles in enumerate(rpy):
        np.testing.assert_allclose(quat_to_rot(v[k:k + 1, 3:])[0], _rpy_matrix(*angles),
                                   atol=5e-16)
    e = g.edges["EDGE_SE3:QUAT"]
    np.testing.assert_allclose(quat_to_rot(e.measurements[:, 3:])[0],
                               _rpy_matrix(0.1, 0.2, -0.3), atol=5e-16)
    assert e.measurements[0, :3].tolist() == [0.5, -1, 2]
    # No information values: the identity in roll-pitch-yaw space, converted.
    assert np.array_equal(e.information[0], np.diag([1.0, 1, 1, 4, 4, 4]))
    assert any("EDGE3" in n and "1 of 1 EDGE3 lines had none" in n for n in g.notes)


def test_edge3_information_gives_the_same_quadratic_form(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    a = rng.standard_normal((6, 6))
    omega_rpy = a @ a.T + 6 * np.eye(6)  # TORO's information, [x y z roll pitch yaw]
    upper = omega_rpy[np.triu_indices(6)]
    text = ("VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 0 0 0 0 0\n"
            "EDGE3 0 1 1 0 0 0.2 -0.1 0.4 " + " ".join(map(repr, upper.tolist())) + "\n")
    omega_q = read_graph(_write(tmp_path, text)).edges["EDGE_SE3:QUAT"].information[0]
    d = np.array([1, 1, 1, 2, 2, 2.0])
    assert np.array_equal(omega_q, omega_rpy * np.outer(d, d))
    for scale in (1e-3, 1e-5):
        w = scale * np.array([0.6, -0.8, 0.5])  # a small rotation error
        t = scale * np.array([0.3, 0.1, -0.2])
        R = so3_exp(w[None])[0]
        e_rpy = np.concatenate([t, _rpy_of(R)])  # TORO's error
        e_q = np.concatenate([t, rot_to_quat(R[None])[0, :3]])  # g2o's: the quaternion vector
        chi2_rpy, chi2_q = e_rpy @ omega_rpy @ e_rpy, e_q @ omega_q @ e_q
        assert abs(chi2_q / chi2_rpy - 1) < 10 * scale
        # Unconverted, the rotation part would count a quarter: the conversion matters.
        e_half = np.concatenate([t, e_q[3:]])
        assert abs(e_half @ omega_rpy @ e_half / chi2_rpy - 1) > 0.1


# --------------------------------------------------------------------------------------------
# Round trips and the writer
# --------------------------------------------------------------------------------------------


@needs_data
@pytest.mark.parametrize("name", sorted(FILES))
def test_round_trip_is_bit_exact(name: str, tmp_path: Path) -> None:
    graph = read_graph(DATA / name)
    write_g2o(tmp_path / "out.g2o", graph, drop_equiv=True)
    again = read_graph(tmp_path / "out.g2o")
    _assert_same(graph, again)
    assert again.equiv.shape == (0, 2) and not any("EDGE2" in n for n in again.notes)


def test_round_trip_every_writable_tag_and_compression(tmp_path: Path) -> None:
    text = """# a comment, then a blank line

PARAMS_SE3OFFSET 3 0.1 0 0 0 0 0 1
VERTEX_SE2 0 0 0 0
VERTEX_SE2\t1 1 0.5 0.1\r
VERTEX_XY 7 2 3
VERTEX_SE3:QUAT 10 1 2 3 0 0 0.6 0.8
VERTEX_SE3:QUAT 11 1 2 4 0 0 0 1
VERTEX_TRACKXYZ 0 4 5 6
EDGE_SE2 0 1 1 0.5 0.1 10 1 0 10 0 20
EDGE_SE2_XY 1 7 0.3 0.4 5 1 5
EDGE_SE3:QUAT 10 11 0 0 1 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 2 0 0 2 0 2
EDGE_SE3_TRACKXYZ 10 0 3 1 1 1 4 0 0 4 0 4
FIX 0 10
"""
    g = read_graph(_write(tmp_path, text))
    assert g.vertices["VERTEX_SE2"].lines.tolist() == [4, 5]  # comments and blanks counted
    assert g.vertices["VERTEX_SE2"].values[1].tolist() == [1, 0.5, 0.1]  # tab and CR
    assert g.fixed.tolist() == [0, 10]
    assert g.edges["EDGE_SE3_TRACKXYZ"].params.tolist() == [3]
    assert g.edges["EDGE_SE2"].information[0].tolist() == [[10, 1, 0], [1, 10, 0], [0, 0, 20]]
    for name in ("plain.g2o", "packed.g2o.gz", "packed.g2o.bz2"):
        write_g2o(tmp_path / name, g)
        _assert_same(g, read_graph(tmp_path / name))
    raw = (tmp_path / "plain.g2o").read_bytes()
    assert gzip.decompress((tmp_path / "packed.g2o.gz").read_bytes()) == raw
    assert bz2.decompress((tmp_path / "packed.g2o.bz2").read_bytes()) == raw
    lines = raw.decode().splitlines()
    assert lines[0] == "PARAMS_SE3OFFSET 3 0.10000000000000001 0 0 0 0 0 1"
    assert "EDGE_SE2 0 1 1 0.5 0.10000000000000001 10 1 0 10 0 20" in lines
    assert "EDGE_SE3_TRACKXYZ 10 0 3 1 1 1 4 0 0 4 0 4" in lines
    assert lines[-2:] == ["FIX 0", "FIX 10"]


def test_writer_refuses_its_input_and_equiv(tmp_path: Path) -> None:
    src = _write(tmp_path, "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEQUIV 0 1\n")
    g = read_graph(src)
    before = src.read_bytes()
    for target in (src, tmp_path / "." / src.name):
        with pytest.raises(ValueError, match=re.escape(f"overwrite the input file {src}")):
            write_g2o(target, g, drop_equiv=True)
    assert src.read_bytes() == before
    with pytest.raises(ValueError, match="1 EQUIV pairs"):
        write_g2o(tmp_path / "out.g2o", g)
    assert not (tmp_path / "out.g2o").exists()


def test_writer_is_atomic(tmp_path: Path) -> None:
    dest = _write(tmp_path, "old content\n", "dest.g2o")
    graph = GraphFile(
        path="<generated>",
        vertices={"VERTEX_SE2": VertexBlock(np.arange(2), np.zeros((2, 3)), np.zeros(2, int))},
        edges={"EDGE_SE2": EdgeBlock(np.array([[0, 1]]), np.array([[1.0, np.nan, 0]]),
                                     np.eye(3)[None], np.zeros(1, int))},
    )
    with pytest.raises(ValueError, match="EDGE_SE2 contains NaN or inf"):
        write_g2o(dest, graph)  # fails after the vertices went to the temporary file
    assert dest.read_text() == "old content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dest.g2o"]
    with pytest.raises(FileNotFoundError):
        write_g2o(tmp_path / "missing" / "x.g2o", graph)


# --------------------------------------------------------------------------------------------
# Bad input: one line, file and line number
# --------------------------------------------------------------------------------------------

V2 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
BAD = [
    ("unknown", V2 + "FOO 1 2\n", 3, "unknown tag 'FOO'"),
    ("count", "VERTEX_SE2 0 0 0\n", 1, "VERTEX_SE2 needs 4 values (id x y theta), found 3"),
    ("edge3-count", "EDGE3 0 1 1 2 3 4 5 6 7 8\n", 1, "EDGE3 needs 8 or 29 values"),
    ("fix-empty", V2 + "FIX\n", 3, "FIX needs at least 1 values"),
    ("non-numeric", V2 + "EDGE_SE2 0 1 1 0 abc 1 0 0 1 0 1\n", 3, "not a number: 'abc'"),
    ("nan", V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 nan 0 1\n", 3, "non-finite value 'nan'"),
    ("inf", "VERTEX_XY 0 1 -inf\n", 1, "non-finite value '-inf'"),
    ("duplicate", V2 + "VERTEX_SE2 1 5 5 0\n", 3,
     "duplicate VERTEX_SE2 id 1 (first defined on line 2)"),
    ("fractional-id", "VERTEX_SE2 1.5 0 0 0\n", 1, "id 1.5 is not a non-negative integer"),
    ("negative-id", V2 + "EDGE_SE2 -1 1 1 0 0 1 0 0 1 0 1\n", 3, "id -1 is not"),
    ("not-pd", V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 -1\n", 3,
     "EDGE_SE2: information matrix is not positive definite"),
    ("not-pd-3d", "EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 " + "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 0"
     + "\n", 1, "EDGE_SE3:QUAT: information matrix is not positive definite"),
    ("missing-param", "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n"
     "EDGE_SE3_TRACKXYZ 0 0 2 1 1 1 1 0 0 1 0 1\n", 2,
     "names parameter 2, which no PARAMS_SE3OFFSET line defines"),
    ("duplicate-param", "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\nPARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n",
     2, "duplicate PARAMS_SE3OFFSET id 0"),
    ("missing-vertex", V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 0 2 1 0 0 1 0 0 1 0 1\n",
     4, "EDGE_SE2 names vertex 2, which has no VERTEX_SE2 line in this file"),
    ("self-edge", V2 + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", 3, "edge from vertex 1 to itself"),
    ("fix-unknown", V2 + "FIX 0 9\n", 3, "FIX names vertex 9, which the file never defines"),
    ("equiv-unknown", V2 + "EQUIV 1 4\n", 3, "EQUIV names vertex 4"),
]


@pytest.mark.parametrize(("case", "text", "line", "message"), BAD, ids=[b[0] for b in BAD])
def test_malformed_lines(case: str, text: str, line: int, message: str, tmp_path: Path) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(GraphFormatError) as err:
        read_graph(path)
    assert err.value.line == line and err.value.path == str(path)
    assert str(err.value).startswith(f"{path}:{line}: ") and message in str(err.value)
    assert "\n" not in str(err.value)


def test_files_that_cannot_be_read(tmp_path: Path) -> None:
    cases = [(tmp_path / "missing.g2o", "file not found"),
             (tmp_path, "is a directory"),
             (_write(tmp_path, "# only a comment\n\n", "c.g2o"), "no vertex or edge lines"),
             (_write(tmp_path, "", "empty.g2o"), "no vertex or edge lines"),
             (_write(tmp_path, " \n\t\n", "blank.g2o"), "no vertex or edge lines")]
    broken = tmp_path / "broken.g2o.gz"
    broken.write_bytes(gzip.compress(b"VERTEX_SE2 0 0 0 0\n" * 50)[:30])
    cases.append((broken, "corrupt or truncated compressed file"))
    for path, message in cases:
        with pytest.raises(GraphFormatError, match=message) as err:
            read_graph(path)
        assert err.value.line is None and str(err.value).startswith(f"{path}: ")


def test_skip_unknown_counts_per_tag(tmp_path: Path) -> None:
    text = V2 + "FOO 1\nBAR\nFOO 2 3\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
    with pytest.raises(GraphFormatError, match="unknown tag 'FOO'"):
        read_graph(_write(tmp_path, text))
    g = read_graph(_write(tmp_path, text), skip_unknown=True)
    assert g.skipped == {"FOO": 2, "BAR": 1}
    assert g.notes == ["skipped lines with unknown tags: BAR x1, FOO x2"]
    assert _counts(g) == {"VERTEX_SE2": 2, "EDGE_SE2": 1}
    with pytest.raises(GraphFormatError, match=r"no vertex or edge lines \(skipped 1 lines"):
        read_graph(_write(tmp_path, "FOO 1\n"), skip_unknown=True)


def test_compressed_inputs_and_edges_without_vertices(tmp_path: Path) -> None:
    text = b"EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nLANDMARK2 1 50 3 4 2 0 2\n"
    (tmp_path / "g.gz").write_bytes(gzip.compress(text))
    (tmp_path / "g.bz2").write_bytes(bz2.compress(text))
    for name in ("g.gz", "g.bz2"):
        g = read_graph(tmp_path / name)
        assert g.vertices == {}  # legal: the builder guesses the estimates
        assert g.edges["EDGE_SE2_XY"].ids.tolist() == [[1, 50]]
        assert g.edges["EDGE_SE2_XY"].lines.tolist() == [2]
