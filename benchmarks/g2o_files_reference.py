"""g2o files written by g2opy 2.3.0 for every g2o type graphopt reads, with the chi2 g2opy
computes after loading each file back, recorded in ``tests/data/g2o_files_reference.json`` for
``tests/test_g2o_tags.py`` (which then needs no g2opy).

The graphs are those of ``benchmarks/g2o_types_reference.py`` (a few edges per type on seeded
random inputs, each edge with its own vertices), built with the official wheel's objects and
written by its ``SparseOptimizer.save``; the reference chi2 is what a fresh g2opy optimizer
gets from ``load`` of that text (``initialize_optimization``, ``compute_active_errors``,
``active_chi2``), so both sides read the same 6-digit numbers. (After the load every vertex's
estimate is set again: g2opy 2.3.0's load leaves ``VertexCam``'s cached world-to-camera
transform stale, which moves its projections by up to 0.03 px.) Types whose lines g2opy does
not write (no registered tag) are left out.

Usage (needs ``pip install g2opy==2.3.0``)::

    .venv/bin/python -P benchmarks/g2o_files_reference.py [OUT.json]
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import g2o_types_reference as ref  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "g2o_files_reference.json"


def _chi2_of_file(g2o: Any, text: str) -> tuple[float, int]:
    """g2opy's chi2 and edge count after loading ``text``."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "graph.g2o"
        path.write_text(text)
        opt = g2o.SparseOptimizer()
        assert opt.load(str(path)), "g2opy failed to load its own file"
    for v in opt.vertices().values():
        # g2opy's load leaves an SBACam's cached transform (w2n) stale; setting the estimate
        # again computes it, as any program that builds its cameras does.
        v.set_estimate(v.estimate())
    opt.initialize_optimization()
    opt.compute_active_errors()
    return float(opt.active_chi2()), len(opt.edges())


def _priors(rng: np.random.Generator) -> list[tuple[ref.Case, Any]]:
    """``EdgeSE3Prior`` (through an offset) and ``EdgeSE2Prior``, which the types reference
    does not build."""
    m = ref.M
    X, Z, P = ref._pose34(rng, m), ref._pose34(rng, m), ref._pose34(rng, 1)[0]
    se3 = ref.Case("EdgeSE3Prior", [X], Z, ref._info(rng, m, 6))

    def b_se3(g2o: Any, opt: Any, i: int) -> Any:
        if i == 0:
            ref._param(g2o, opt, "ParameterSE3Offset", 3, ref._iso(g2o, P))
        v = ref._vertex(g2o, opt, "VertexSE3", i, ref._iso(g2o, X[i]))
        return ref._edge(g2o, opt, "EdgeSE3Prior", [v], ref._iso(g2o, Z[i]), se3.info[i], (3,))

    x, z = ref._se2(rng, m), ref._se2(rng, m)
    se2 = ref.Case("EdgeSE2Prior", [x], z, ref._info(rng, m, 3))

    def b_se2(g2o: Any, opt: Any, i: int) -> Any:
        v = ref._vertex(g2o, opt, "VertexSE2", i, g2o.SE2(*map(float, x[i])))
        return ref._edge(g2o, opt, "EdgeSE2Prior", [v], g2o.SE2(*map(float, z[i])), se2.info[i])
    return [(se3, b_se3), (se2, b_se2)]


def _expmap_sim3(rng: np.random.Generator) -> list[tuple[ref.Case, Any]]:
    """``EdgeSE3Expmap``, ``EdgeSim3`` and the two Sim3 projections (ORB-SLAM's loop closing),
    which the types reference does not build (graphopt's types for them come from the sba_pose
    and sim3 modules)."""
    from graphopt.lie import se3_exp

    m = ref.M
    Ti, Tj, Z = (se3_exp(rng.normal(0, 0.5, (m, 6))) for _ in range(3))
    exp = ref.Case("EdgeSE3Expmap", [Ti, Tj], Z, ref._info(rng, m, 6))

    def se3q(g2o: Any, T: np.ndarray) -> Any:
        return g2o.SE3Quat(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))

    def b_exp(g2o: Any, opt: Any, i: int) -> Any:
        v = [ref._vertex(g2o, opt, "VertexSE3Expmap", 10 * i + k, se3q(g2o, a[i]))
             for k, a in enumerate(exp.x)]
        return ref._edge(g2o, opt, "EdgeSE3Expmap", v, se3q(g2o, Z[i]), exp.info[i])

    scale = rng.uniform(0.5, 2.0, (3, m))
    sim = ref.Case("EdgeSim3", [Ti, Tj], Z, ref._info(rng, m, 7))

    def sim3(g2o: Any, T: np.ndarray, s: float) -> Any:
        return g2o.Sim3(np.asfortranarray(T[:3, :3]), T[:3, 3].copy(), float(s))

    def b_sim(g2o: Any, opt: Any, i: int) -> Any:
        v = [ref._vertex(g2o, opt, "VertexSim3Expmap", 10 * i + k, sim3(g2o, a[i], scale[k, i]))
             for k, a in enumerate(sim.x)]
        return ref._edge(g2o, opt, "EdgeSim3", v, sim3(g2o, Z[i], scale[2, i]), sim.info[i])

    out = [(exp, b_exp), (sim, b_sim)]
    p = ref._in_front(rng, Ti[:, :3, :3], Ti[:, :3, 3])
    for name in ("EdgeSim3ProjectXYZ", "EdgeInverseSim3ProjectXYZ"):
        case = ref.Case(name, [p, Ti], rng.normal(0, 0.5, (m, 2)), ref._info(rng, m, 2))

        def b_proj(g2o: Any, opt: Any, i: int, case: ref.Case = case) -> Any:
            v = [ref._vertex(g2o, opt, "VertexPointXYZ", 10 * i, p[i]),
                 ref._vertex(g2o, opt, "VertexSim3Expmap", 10 * i + 1,
                             sim3(g2o, Ti[i], scale[0, i]))]
            return ref._edge(g2o, opt, case.name, v, case.z[i], case.info[i])
        out.append((case, b_proj))
    return out


def _camera_files(g2o: Any, rng: np.random.Generator) -> dict[str, str]:
    """Depth and disparity graphs: g2opy cannot configure a ``ParameterCamera`` from Python,
    so the graph is loaded from lines like the types reference's and saved again."""
    files = {}
    real_load = g2o.SparseOptimizer.load

    def load_and_keep(opt: Any, path: str) -> bool:
        ok = real_load(opt, path)
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "saved.g2o"
            opt.save(str(out))
            text = out.read_text()
        tag = next(t for t in ("DEPTH", "DISPARITY") if f"EDGE_PROJECT_{t} " in text)
        files["EdgeSE3PointXYZ" + tag.capitalize()] = text
        return ok

    g2o.SparseOptimizer.load = load_and_keep
    try:
        ref._camera_edges(rng, ref._pose34(rng, ref.M))
    finally:
        g2o.SparseOptimizer.load = real_load
    return files


def main() -> None:
    import g2opy as g2o

    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    files: dict[str, dict[str, Any]] = {}

    def save(case: ref.Case, build: Any) -> list[float]:
        opt = g2o.SparseOptimizer()
        for i in range(len(case.z)):
            build(g2o, opt, i)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "graph.g2o"
            opt.save(str(path))  # False when a type has no tag (its lines are left out)
            text = path.read_text()
        if any(line.startswith("EDGE") for line in text.splitlines()):
            chi2, edges = _chi2_of_file(g2o, text)
            files[case.name] = {"file": text, "chi2": chi2, "edges": edges}
        return [0.0] * len(case.z)

    ref._g2o_chi2 = save  # build each case's graph, but save it instead
    rng = np.random.default_rng(23)
    ref.slam3d(rng)
    ref.slam2d(rng)
    ref.sba(rng)
    ref.icp(rng)
    for case, build in _priors(rng) + _expmap_sim3(rng):
        save(case, build)
    for name, text in _camera_files(g2o, rng).items():
        chi2, edges = _chi2_of_file(g2o, text)
        files[name] = {"file": text, "chi2": chi2, "edges": edges}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"g2opy": "2.3.0", "files": files}, indent=1) + "\n")
    for name, rec in files.items():
        print(f"{name:30s} {rec['edges']} edges, chi2 {rec['chi2']:.10g}")


if __name__ == "__main__":
    main()
