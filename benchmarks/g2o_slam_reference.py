"""g2o's own chi2 values on the pose-graph data, for the constants in
``tests/test_slam_graph.py``: run with g2opy 2.3.0 (``pip install g2opy==2.3.0``; not a test
dependency).

Prints, per file, g2o's chi2 after loading (``load``, ``initialize_optimization``,
``compute_active_errors``, ``chi2``) and after Levenberg–Marquardt (100 iterations at most,
first vertex fixed, Eigen's sparse Cholesky). Two files need a g2o-readable copy first:

* ``known_landmark_localization_20.g2o`` numbers its 4 landmarks 0–3, like poses 0–3 (GTSAM's
  separate landmark namespace); g2o's ids are global, so its load drops the landmark lines and
  its chi2 is meaningless (6.7e66). The copy shifts landmark ids by 20, as graphopt's builder
  does.
* ``victoriaPark_reduced_1k.g2o`` has no vertex lines and GTSAM's ``LANDMARK2`` tag: the copy
  writes ``EDGE_SE2_XY`` and zero vertices, then g2o's ``compute_initial_guess`` (vertex 0
  fixed) sets the initial estimate.
* ``w100.graph`` is TORO: the copy is what a g2o conversion writes, ``VERTEX_SE2``/``EDGE_SE2``
  with the information reordered to g2o's and no ``EQUIV`` lines (graphopt keeps both poses of
  an ``EQUIV`` pair and all edges, so its chi2 must equal g2o's on this copy).

Usage::

    .venv/bin/python -P benchmarks/g2o_slam_reference.py [DATA_DIR]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph"


def _renumber_landmarks(src: Path, dst: Path, shift: int) -> None:
    out = []
    for line in src.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "VERTEX_TRACKXYZ":
            tok[1] = str(int(tok[1]) + shift)
        elif tok and tok[0] == "EDGE_SE3_TRACKXYZ":
            tok[2] = str(int(tok[2]) + shift)
        out.append(" ".join(tok))
    dst.write_text("\n".join(out) + "\n")


def _victoria_as_g2o(src: Path, dst: Path) -> None:
    poses, points, edges = set(), set(), []
    for line in src.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "EDGE_SE2":
            poses |= {int(tok[1]), int(tok[2])}
            edges.append(line.strip())
        elif tok and tok[0] == "LANDMARK2":
            points.add(int(tok[2]))
            edges.append("EDGE_SE2_XY " + " ".join(tok[1:8]))
    head = [f"VERTEX_SE2 {i} 0 0 0" for i in sorted(poses)]
    head += [f"VERTEX_XY {i} 0 0" for i in sorted(points)]
    dst.write_text("\n".join(head + edges) + "\n")


def _toro_as_g2o(src: Path, dst: Path) -> None:
    out = []
    for line in src.read_text().splitlines():
        tok = line.split()
        if tok and tok[0] == "VERTEX2":
            out.append("VERTEX_SE2 " + " ".join(tok[1:5]))
        elif tok and tok[0] == "EDGE2":
            i11, i12, i22, i33, i13, i23 = tok[6:12]  # TORO's information order
            out.append("EDGE_SE2 " + " ".join(tok[1:6] + [i11, i12, i13, i22, i23, i33]))
    dst.write_text("\n".join(out) + "\n")


def main() -> None:
    import g2opy as g2o

    data = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA
    tmp = Path(tempfile.mkdtemp())
    _renumber_landmarks(data / "known_landmark_localization_20.g2o", tmp / "kl20.g2o", 20)
    _victoria_as_g2o(data / "victoriaPark_reduced_1k.g2o", tmp / "victoria.g2o")
    _toro_as_g2o(data / "w100.graph", tmp / "w100.g2o")
    files = [data / "pose2example.txt", data / "pose3example.txt", data / "Klaus3.g2o",
             tmp / "kl20.g2o", tmp / "victoria.g2o", tmp / "w100.g2o"]
    for path in files:
        opt = g2o.SparseOptimizer()
        opt.set_algorithm(g2o.OptimizationAlgorithmLevenberg(
            g2o.BlockSolverX(g2o.LinearSolverEigenX())))
        if not opt.load(str(path)):
            raise SystemExit(f"g2o could not load {path}")
        opt.vertex(0).set_fixed(True)
        opt.initialize_optimization()
        if path.name == "victoria.g2o":
            opt.compute_initial_guess()
        opt.compute_active_errors()
        initial = opt.chi2()
        iterations = opt.optimize(100)
        opt.compute_active_errors()
        print(f"{path.name}: initial chi2 {initial!r}, after LM ({iterations} iterations) "
              f"{opt.chi2()!r}")


if __name__ == "__main__":
    main()
