"""g2o's other file tags (slam2d, slam3d, sba, sim3, sclam2d, icp): files written by g2opy 2.3.0
read with g2opy's chi2, round trips, the line layouts and errors naming file and line.

The files and g2opy's chi2 on them are recorded in ``tests/data/g2o_files_reference.json`` by
``benchmarks/g2o_files_reference.py`` (g2opy is not needed here).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from graphopt.errors import GraphError
from graphopt.io.g2o import GraphFormatError, read_graph, write_g2o
from graphopt.io.g2o_layouts import LAYOUTS
from graphopt.types.slam_graph import build_graph, graph_file

REFERENCE = json.loads((Path(__file__).parent / "data" / "g2o_files_reference.json").read_text())
FILES = REFERENCE["files"]
#: What cannot be built, and why.
UNBUILDABLE = {"EdgeSE3ProjectXYZ": "writes no intrinsics"}
#: graphopt's SBACam types normalise the quaternions g2o uses as written (6 digits in the file);
#: g2o's EdgeSE3Expmap mixes both (SE3Quat products normalise, its inverse does not).
LOOSE = {"EdgeSBACam": 2e-6, "EdgeProjectP2MC": 1e-8, "EdgeProjectP2SC": 1e-8,
         "EdgeSE3Expmap": 1e-6}


def _file(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / f"{name}.g2o"
    path.write_text(text)
    return path


def _build(path: Path):  # noqa: ANN202
    """The built graph."""
    return build_graph(read_graph(path))


def _chi2(path: Path) -> float:
    slam = _build(path)
    slam.optimizer.compute_active_errors()
    return slam.optimizer.chi2()


@pytest.mark.parametrize("name", sorted(set(FILES) - set(UNBUILDABLE)))
def test_g2opy_files_give_g2opys_chi2(tmp_path: Path, name: str) -> None:
    rec = FILES[name]
    path = _file(tmp_path, name, rec["file"])
    assert sum(len(b.ids) for b in read_graph(path).edges.values()) == rec["edges"]
    assert _chi2(path) == pytest.approx(rec["chi2"], rel=LOOSE.get(name, 1e-9))


@pytest.mark.parametrize("name", sorted(UNBUILDABLE))
def test_unbuildable_tags_are_read_and_refused_clearly(tmp_path: Path, name: str) -> None:
    path = _file(tmp_path, name, FILES[name]["file"])
    graph = read_graph(path)
    with pytest.raises(GraphError, match=rf"{name}\.g2o:\d+: .*{UNBUILDABLE[name]}"):
        build_graph(graph)


def _same_graph(a, b) -> None:  # noqa: ANN001
    assert set(a.vertices) == set(b.vertices) and set(a.edges) == set(b.edges)
    for tag, block in a.vertices.items():
        np.testing.assert_array_equal(block.ids, b.vertices[tag].ids)
        np.testing.assert_array_equal(block.values, b.vertices[tag].values)
    for tag, block in a.edges.items():
        other = b.edges[tag]
        for field in ("ids", "measurements", "information", "params"):
            np.testing.assert_array_equal(getattr(block, field), getattr(other, field))
    assert set(a.parameters) == set(b.parameters)
    for pid, (tag, values) in a.parameters.items():
        assert b.parameters[pid][0] == tag
        np.testing.assert_array_equal(values, b.parameters[pid][1])
    for pid, values in a.offsets.items():
        np.testing.assert_array_equal(values, b.offsets[pid])


@pytest.mark.parametrize("name", sorted(FILES))
def test_write_read_round_trip_gives_the_same_arrays(tmp_path: Path, name: str) -> None:
    graph = read_graph(_file(tmp_path, name, FILES[name]["file"]))
    write_g2o(tmp_path / "again.g2o", graph)
    _same_graph(graph, read_graph(tmp_path / "again.g2o"))


@pytest.mark.parametrize("name", sorted(set(FILES) - set(UNBUILDABLE)))
def test_built_graph_written_back_keeps_estimates_and_chi2(tmp_path: Path, name: str) -> None:
    path = _file(tmp_path, name, FILES[name]["file"])
    slam = _build(path)
    slam.optimizer.compute_active_errors()
    chi2 = slam.optimizer.chi2()
    write_g2o(tmp_path / "out.g2o", graph_file(slam))
    # (the 6-digit quaternions of the file are written normalised, as g2o's toVectorQT does)
    assert _chi2(tmp_path / "out.g2o") == pytest.approx(chi2, rel=1e-5)


def test_edge_line_layout_is_g2os(tmp_path: Path) -> None:
    """Ids, parameter ids, measurement, then the information's upper triangle row by row."""
    text = ("PARAMS_SE2OFFSET 7 0.1 0.2 0.3\nPARAMS_SE2OFFSET 8 0 0 0\n"
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
            "EDGE_SE2_OFFSET 0 1 7 8 1 2 0.5 10 1 2 20 3 30\n")
    graph = read_graph(_file(tmp_path, "layout", text))
    e = graph.edges["EDGE_SE2_OFFSET"]
    np.testing.assert_array_equal(e.ids, [[0, 1]])
    np.testing.assert_array_equal(e.params, [[7, 8]])
    np.testing.assert_array_equal(e.measurements, [[1, 2, 0.5]])
    np.testing.assert_array_equal(e.information[0], [[10, 1, 2], [1, 20, 3], [2, 3, 30]])
    write_g2o(tmp_path / "out.g2o", graph)
    lines = (tmp_path / "out.g2o").read_text().splitlines()
    assert "EDGE_SE2_OFFSET 0 1 7 8 1 2 0.5 10 1 2 20 3 30" in lines
    assert lines[:2] == ["PARAMS_SE2OFFSET 7 0.10000000000000001 0.20000000000000001 "
                         "0.29999999999999999", "PARAMS_SE2OFFSET 8 0 0 0"]


def test_every_layout_counts_its_values() -> None:
    lay = LAYOUTS["EDGE_SE3_OFFSET"]
    assert lay.count == 2 + 2 + 7 + 21
    assert LAYOUTS["EDGE_V_V_GICP"].count == 2 + 12 + 6
    assert LAYOUTS["PARAMS_CAMERACALIB"].count == 12


def test_pose_only_and_stereo_lines_are_read_and_refused(tmp_path: Path) -> None:
    """As g2opy 2.3.0 writes them (its save of one edge of each)."""
    text = ("VERTEX_SE3:EXPMAP 0 0 0 0 0 0 0 1\nVERTEX_TRACKXYZ 1 0.1 0.2 5\n"
            "EDGE_SE3_PROJECT_XYZONLYPOSE:EXPMAP 0 1 2 2 0 2\n"
            "EDGE_STEREO_SE3_PROJECT_XYZ:EXPMAP 1 0 1 2 3 2 0 0 2 0 2\n"
            "EDGE_STEREO_SE3_PROJECT_XYZONLYPOSE:EXPMAP 0 1 2 3 2 0 0 2 0 2\n")
    graph = read_graph(_file(tmp_path, "mono", text))
    np.testing.assert_array_equal(graph.edges["EDGE_STEREO_SE3_PROJECT_XYZ:EXPMAP"].ids, [[1, 0]])
    np.testing.assert_array_equal(
        graph.edges["EDGE_STEREO_SE3_PROJECT_XYZONLYPOSE:EXPMAP"].information, [2 * np.eye(3)])
    with pytest.raises(GraphError, match=r"mono\.g2o:3: .*cannot be built: g2o writes neither"):
        build_graph(graph)


def test_camera_without_intrinsics_gets_g2os_defaults(tmp_path: Path) -> None:
    text = ("VERTEX_CAM 0 1 2 3 0 0 0 1\nVERTEX_CAM 1 1 2 3 0 0 0 1 500 510 320 240 0.1\n")
    graph = read_graph(_file(tmp_path, "cam", text))
    np.testing.assert_array_equal(graph.vertices["VERTEX_CAM"].values[:, 7:],
                                  [[1, 1, 0.5, 0.5, 0], [500, 510, 320, 240, 0.1]])


@pytest.mark.parametrize(("text", "line", "match"), [
    ("VERTEX_SE2 0 0 0 0\nEDGE_PRIOR_SE2 0 1 2\n", 2,
     r"EDGE_PRIOR_SE2 needs 10 values \(id0 x y theta 6 information values\), found 3"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_XY 1 0 0\nEDGE_SE2_POINTXY_OFFSET 0 1 4 1 2 1 0 1\n", 3,
     "EDGE_SE2_POINTXY_OFFSET names parameter 4, which no PARAMS_ line defines"),
    ("VERTEX_XY 0 0 0\nVERTEX_XY 1 0 0\nEDGE_POINTXY 0 1 1 2 1 2 1\n", 3,
     "EDGE_POINTXY: information matrix is not positive definite"),
    ("VERTEX_XY 0 0 0\nEDGE_POINTXY 0 5 1 2 1 0 1\n", 2,
     "EDGE_POINTXY names vertex 5, which has no VERTEX_XY line"),
    ("PARAMS_SE2OFFSET 1 0 0 0\nPARAMS_CAMERAPARAMETERS 1 1 0 0 0\n", 2,
     r"duplicate parameter id 1 \(PARAMS_CAMERAPARAMETERS\)"),
    ("VERTEX_SE3:EXPMAP 0 0 0 0 0 0 0 x\n", 1, "not a number: 'x'"),
    ("VERTEX_SE2 0 0 0 0\nVERTEX_XY 1 0 0\nEDGE_SE2_LOTSOFXY 2 0 1 3 1 2 3 1 0 1\n", 3,
     r"EDGE_SE2_LOTSOFXY needs n id_1..id_n d z_1..z_d N I_1..I_N with d = 2\(n-1\)"),
])
def test_malformed_lines_name_file_and_line(tmp_path: Path, text: str, line: int,
                                            match: str) -> None:
    path = _file(tmp_path, "bad", text)
    with pytest.raises(GraphFormatError, match=rf"bad\.g2o:{line}: {match}"):
        read_graph(path)


def test_parameter_of_the_wrong_kind_names_file_and_line(tmp_path: Path) -> None:
    text = ("PARAMS_SE2OFFSET 0 0 0 0\nVERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
            "VERTEX_TRACKXYZ 1 0 0 5\nEDGE_PROJECT_DEPTH 0 1 0 1 2 3 1 0 0 1 0 1\n")
    with pytest.raises(GraphError, match=r"wrong\.g2o:4: EDGE_PROJECT_DEPTH names parameter 0, "
                                         "which is a PARAMS_SE2OFFSET; it needs a "
                                         "PARAMS_CAMERACALIB"):
        build_graph(read_graph(_file(tmp_path, "wrong", text)))


@pytest.mark.parametrize("name", sorted(set(FILES) - set(UNBUILDABLE)))
def test_g2o_api_load_and_save_of_every_tag(tmp_path: Path, name: str) -> None:
    """``graphopt.g2o``'s load gives g2opy's chi2 for every tag graphopt builds (the LotsOf and
    GICP edges, VertexCam, the SE2-offset and camera-calibration parameters included); save
    writes the same lines back (parameters, GICP normals) and they load to the same chi2."""
    import graphopt.g2o as g2o

    rec = FILES[name]
    opt = g2o.SparseOptimizer()
    opt.load(str(_file(tmp_path, name, rec["file"])))
    opt.initialize_optimization()
    opt.compute_active_errors()
    chi2 = opt.active_chi2()
    assert chi2 == pytest.approx(rec["chi2"], rel=LOOSE.get(name, 1e-9))
    # the records are g2o's classes, and their own chi2() add up to the optimizer's
    assert all(getattr(g2o, type(r).__name__) is type(r)
               for r in [*opt.edges(), *opt.vertices().values()])
    assert sum(e.chi2() for e in opt.edges()) == pytest.approx(chi2, rel=1e-12)
    opt.save(str(tmp_path / "saved.g2o"))
    a, b = read_graph(tmp_path / f"{name}.g2o"), read_graph(tmp_path / "saved.g2o")
    assert set(a.edges) == set(b.edges) and set(a.vertices) == set(b.vertices)
    for tag, block in a.edges.items():
        order_a, order_b = np.lexsort(block.ids.T), np.lexsort(b.edges[tag].ids.T)
        np.testing.assert_array_equal(block.ids[order_a], b.edges[tag].ids[order_b])
        np.testing.assert_allclose(block.measurements[order_a],
                                   b.edges[tag].measurements[order_b], rtol=1e-5, atol=1e-6)
    assert {k: t for k, (t, _) in a.parameters.items()} == {
        k: t for k, (t, _) in b.parameters.items()}
    for pid, (_, values) in a.parameters.items():
        np.testing.assert_allclose(b.parameters[pid][1], values, rtol=1e-5, atol=1e-6)
    again = g2o.SparseOptimizer()
    again.load(str(tmp_path / "saved.g2o"))
    again.initialize_optimization()
    again.compute_active_errors()
    assert again.active_chi2() == pytest.approx(chi2, rel=1e-5)


def test_g2o_api_gicp_normals_and_parameters_survive_load(tmp_path: Path) -> None:
    """A loaded GICP edge's measurement carries the file's normals; the parameter records are
    g2o's classes with the file's numbers."""
    import graphopt.g2o as g2o

    text = ("PARAMS_SE2OFFSET 3 0.5 -0.25 0.1\n"
            "PARAMS_CAMERACALIB 4 1 2 3 0 0 0 1 500 510 320 240\n"
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
            "EDGE_V_V_GICP 0 1 1 2 3 0 0.6 0.8 0.5 2 3 0.8 0.6 0 1 0 0 1 0 1\n")
    opt = g2o.SparseOptimizer()
    opt.load(str(_file(tmp_path, "gicp", text)))
    (edge,) = opt.edges()
    m = edge.measurement()
    np.testing.assert_array_equal(m.pos0, [1, 2, 3])
    np.testing.assert_array_equal(m.normal0, [0, 0.6, 0.8])
    np.testing.assert_array_equal(m.pos1, [0.5, 2, 3])
    np.testing.assert_array_equal(m.normal1, [0.8, 0.6, 0])
    # e = X0⁻¹ X1 pos1 − pos0 = (0.5 + 1, 2, 3) − (1, 2, 3)
    assert edge.chi2() == pytest.approx(0.25, rel=1e-12)
    se2, cam = opt.parameter(3), opt.parameter(4)
    assert isinstance(se2, g2o.ParameterSE2Offset) and isinstance(cam, g2o.ParameterCamera)
    np.testing.assert_array_equal(se2.offset().to_vector(), [0.5, -0.25, 0.1])
    np.testing.assert_array_equal(cam.Kcam(), [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    np.testing.assert_array_equal(cam.offset().translation(), [1, 2, 3])


def test_classic_dialect_inverts_the_expmap_poses(tmp_path: Path) -> None:
    """g2o's C++ write stores VERTEX_SE3:EXPMAP and EDGE_SE3:EXPMAP as the inverse pose;
    ``invert_qt`` is g2opy's ``SE3Quat.inverse()`` (numbers from g2opy 2.3.0)."""
    from graphopt.io.g2o_layouts import invert_qt

    v = np.array([[0.691168, 1.643236, 0.660874, 0.305234, 0.029495, 0.567347, -0.764251],
                  [-2.606314, 1.810712, 0.892749, -0.207034, -0.612701, 0.761042, 0.050481]])
    g2opy_inverse = [[0.89171016, -0.60479084, -1.56645237, -0.305234, -0.029495, -0.567347,
                      -0.764251],
                     [-2.74200024, 1.75417227, 0.5223178, 0.207034, 0.612701, -0.761042,
                      0.050481]]
    np.testing.assert_allclose(invert_qt(v), g2opy_inverse, atol=5e-9)
    unit = v.copy()
    unit[:, 3:] /= np.linalg.norm(unit[:, 3:], axis=1, keepdims=True)
    np.testing.assert_allclose(invert_qt(invert_qt(unit)), unit, atol=1e-12)
    name = "EdgeProjectXYZ2UV"
    graph = read_graph(_file(tmp_path, name, FILES[name]["file"]))
    write_g2o(tmp_path / "classic.g2o", graph, dialect="classic")
    first = next(line for line in (tmp_path / "classic.g2o").read_text().splitlines()
                 if line.startswith("VERTEX_SE3:EXPMAP"))
    block = graph.vertices["VERTEX_SE3:EXPMAP"]
    np.testing.assert_allclose([float(x) for x in first.split()[2:]],
                               invert_qt(block.values[:1])[0], rtol=1e-15)
    back = read_graph(tmp_path / "classic.g2o", dialect="classic")
    # (an involution only for unit quaternions: the file's 6-digit ones are off by ~1e-6)
    np.testing.assert_allclose(back.vertices["VERTEX_SE3:EXPMAP"].values, block.values,
                               atol=1e-4)
    with pytest.raises(ValueError, match="dialect"):
        read_graph(tmp_path / "classic.g2o", dialect="c++")


def test_vertex_only_tags_round_trip_through_the_builder(tmp_path: Path) -> None:
    text = ("VERTEX_INTRINSICS 3 500 510 320 240 0.1\nVERTEX_ODOM_DIFFERENTIAL 4 1 0.9 0.5\n"
            "VERTEX_CAM 5 1 2 3 0 0 0 1 500 510 320 240 0.1\n")
    graph = read_graph(_file(tmp_path, "v", text))
    write_g2o(tmp_path / "out.g2o", graph_file(build_graph(graph)))
    _same_graph(graph, read_graph(tmp_path / "out.g2o"))
