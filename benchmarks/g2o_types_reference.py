"""g2o's own per-edge chi2 for the g2o types graphopt added for the g2o API (sba, slam2d,
slam3d, icp), recorded in ``tests/data/g2o_types_reference.json`` for
``tests/test_g2o_types.py`` (which then needs no g2opy).

For every type: a few edges on random inputs (seeded), each edge with its own vertices, built
with the official wheel's objects (g2opy 2.3.0, ``pip install g2opy==2.3.0``; not a test
dependency), ``initialize_optimization``, ``compute_active_errors``, then each edge's
``chi2()``. The inputs are written in graphopt's layouts next to g2o's numbers. The depth and
disparity edges go through a ``.g2o`` file (``ParameterCamera`` cannot be configured from
Python in the wheel); ``SBACam``s are built from ``SE3Quat(R, t)`` (the wheel's
``Quaternion`` constructors fail). Also recorded: graphopt's existing ``EdgeProjectXYZ2UV`` and
``EdgeSE3ProjectXYZ`` on g2o's numbers, and ``SBACam::update`` (``VertexCam``'s ``oplus``).

Usage::

    .venv/bin/python -P benchmarks/g2o_types_reference.py [OUT.json]
"""

from __future__ import annotations

import json
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from graphopt.lie import quat_to_rot, so3_exp
from graphopt.types.isometry3 import matrix_to_quat

OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "g2o_types_reference.json"
M = 5  # edges per type


def _rot(rng: np.random.Generator, m: int, scale: float = 1.5) -> np.ndarray:
    return so3_exp(rng.normal(0.0, scale, (m, 3)))


def _pose34(rng: np.random.Generator, m: int) -> np.ndarray:
    T = np.empty((m, 3, 4))
    T[:, :, :3] = _rot(rng, m)
    T[:, :, 3] = rng.normal(0.0, 2.0, (m, 3))
    return T


def _se2(rng: np.random.Generator, m: int) -> np.ndarray:
    x = rng.normal(0.0, 2.0, (m, 3))
    x[:, 2] = rng.uniform(-np.pi, np.pi, m)
    return x


def _info(rng: np.random.Generator, m: int, e: int) -> np.ndarray:
    A = rng.normal(size=(m, e, e))
    return A @ np.swapaxes(A, 1, 2) + e * np.eye(e)


def _in_front(rng: np.random.Generator, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """World points in front of cameras ``p_c = R_cw p + t_cw``."""
    pc = np.column_stack([rng.normal(0, 1, (len(R_cw), 2)), rng.uniform(3, 8, len(R_cw))])
    return np.einsum("nji,nj->ni", R_cw, pc - t_cw)


class Case:
    """One type's inputs (graphopt's layout) and how to build them in g2opy."""

    def __init__(self, name: str, x: list[np.ndarray], z: np.ndarray, info: np.ndarray,
                 params: dict[str, Any] | None = None, data: dict[str, np.ndarray] | None = None
                 ) -> None:
        self.name, self.x, self.z, self.info = name, x, z, info
        self.params, self.data = params, data or {}

    def record(self, chi2: list[float]) -> dict[str, Any]:
        return {"type": self.name, "x": [a.tolist() for a in self.x], "z": self.z.tolist(),
                "information": self.info.tolist(), "params": self.params,
                "data": {k: v.tolist() for k, v in self.data.items()}, "chi2": chi2}


def _g2o_chi2(case: Case, build: Callable[[Any, Any, int], Any]) -> list[float]:
    """Per-edge chi2: ``build(g2o, optimizer, i)`` adds edge ``i`` (and its vertices)."""
    import g2opy as g2o

    opt = g2o.SparseOptimizer()
    edges = [build(g2o, opt, i) for i in range(len(case.z))]
    opt.initialize_optimization()
    opt.compute_active_errors()
    return [float(e.chi2()) for e in edges]


def _vertex(g2o: Any, opt: Any, cls: str, vid: int, est: Any) -> Any:
    v = getattr(g2o, cls)()
    v.set_id(vid)
    v.set_estimate(est)
    opt.add_vertex(v)
    return v


def _edge(g2o: Any, opt: Any, cls: str, verts: list[Any], z: Any, info: np.ndarray,
          pids: tuple[int, ...] = ()) -> Any:
    e = getattr(g2o, cls)()
    for k, v in enumerate(verts):
        e.set_vertex(k, v)
    e.set_measurement(z)
    e.set_information(info)
    for k, p in enumerate(pids):
        e.set_parameter_id(k, p)
    assert opt.add_edge(e), cls
    return e


def _lots_edge(g2o: Any, opt: Any, cls: str, d: int, verts: list[Any], z: np.ndarray,
               info: np.ndarray) -> Any:
    """A variable-arity edge (one pose, ``k`` points of dimension ``d``): g2o wants its
    dimension and vertex count set before the vertices."""
    e = getattr(g2o, cls)()
    e.set_dimension(d * (len(verts) - 1))
    e.resize(len(verts))
    for j, v in enumerate(verts):
        e.set_vertex(j, v)
    e.set_measurement(z)
    e.set_information(info)
    assert opt.add_edge(e), cls
    return e


def _lots_case(rng: np.random.Generator, name: str, vertices: tuple[str, str], d: int,
               poses: np.ndarray, pose: Callable[[Any, np.ndarray], Any]) -> dict[str, Any]:
    """The record of ``M`` edges of the variable-arity type ``name`` with ``k = 3`` random
    points each (drawn here, then the measurements and the information).

    Args:
        rng: The generator (its draws continue the caller's sequence).
        name: ``EdgeSE3LotsOfXYZ`` or ``EdgeSE2LotsOfXY``.
        vertices: g2o's pose and point vertex class names.
        d: The point dimension.
        poses: ``(M, ...)`` the poses, in graphopt's layout.
        pose: ``pose(g2o, poses[i])``: the g2o estimate of a pose.
    """
    k = 3
    pts = [rng.normal(0, 3, (M, d)) for _ in range(k)]
    c = Case(name, [poses, *pts], rng.normal(size=(M, d * k)), _info(rng, M, d * k))

    def build(g2o: Any, opt: Any, i: int) -> Any:
        v = [_vertex(g2o, opt, vertices[0], 10 * i, pose(g2o, poses[i]))]
        v += [_vertex(g2o, opt, vertices[1], 10 * i + 1 + j, pts[j][i]) for j in range(k)]
        return _lots_edge(g2o, opt, name, d, v, c.z[i], c.info[i])
    return c.record(_g2o_chi2(c, build))


def _iso(g2o: Any, T: np.ndarray) -> Any:
    return g2o.Isometry3d(np.ascontiguousarray(T))


def _param(g2o: Any, opt: Any, cls: str, pid: int, value: Any) -> None:
    p = getattr(g2o, cls)()
    p.set_id(pid)
    p.set_param(value)
    opt.add_parameter(p)


def slam3d(rng: np.random.Generator) -> list[dict[str, Any]]:
    out = []
    xi, xj, z = _pose34(rng, M), _pose34(rng, M), _pose34(rng, M)
    P = _pose34(rng, 2)
    case = Case("EdgeSE3Offset", [xi, xj], z, _info(rng, M, 6),
                {"kind": "se3_offsets", "offsets": P.tolist()})

    def b_off(g2o: Any, opt: Any, i: int) -> Any:
        if i == 0:
            _param(g2o, opt, "ParameterSE3Offset", 0, _iso(g2o, P[0]))
            _param(g2o, opt, "ParameterSE3Offset", 1, _iso(g2o, P[1]))
        v = [_vertex(g2o, opt, "VertexSE3", 10 * i + k, _iso(g2o, a[i]))
             for k, a in enumerate(case.x)]
        return _edge(g2o, opt, "EdgeSE3Offset", v, _iso(g2o, case.z[i]), case.info[i], (0, 1))
    out.append(case.record(_g2o_chi2(case, b_off)))

    p, q = rng.normal(0, 3, (M, 3)), rng.normal(0, 3, (M, 3))
    for name, x, zz, vcls in (("EdgePointXYZ", [p, q], rng.normal(size=(M, 3)),
                               ("VertexPointXYZ", "VertexPointXYZ")),
                              ("EdgeXYZPrior", [p], rng.normal(size=(M, 3)), ("VertexPointXYZ",))):
        c = Case(name, x, zz, _info(rng, M, 3))

        def b_pt(g2o: Any, opt: Any, i: int, c: Case = c, vcls: tuple = vcls) -> Any:
            v = [_vertex(g2o, opt, vc, 10 * i + k, a[i]) for k, (vc, a) in
                 enumerate(zip(vcls, c.x, strict=True))]
            return _edge(g2o, opt, c.name, v, c.z[i], c.info[i])
        out.append(c.record(_g2o_chi2(c, b_pt)))

    c = Case("EdgeSE3XYZPrior", [xi], rng.normal(0, 2, (M, 3)), _info(rng, M, 3),
             {"kind": "se3_offset", "offset": P[0].tolist()})

    def b_xyzp(g2o: Any, opt: Any, i: int) -> Any:
        if i == 0:
            _param(g2o, opt, "ParameterSE3Offset", 0, _iso(g2o, P[0]))
        v = _vertex(g2o, opt, "VertexSE3", i, _iso(g2o, xi[i]))
        return _edge(g2o, opt, "EdgeSE3XYZPrior", [v], c.z[i], c.info[i], (0,))
    out.append(c.record(_g2o_chi2(c, b_xyzp)))

    out.append(_lots_case(rng, "EdgeSE3LotsOfXYZ", ("VertexSE3", "VertexPointXYZ"), 3, xi, _iso))
    out += _camera_edges(rng, xi)
    return out


def _camera_edges(rng: np.random.Generator, X: np.ndarray) -> list[dict[str, Any]]:
    """Depth and disparity edges, through a .g2o file."""
    import g2opy as g2o

    off = _pose34(rng, 1)[0]
    off[:, :3] = _rot(rng, 1, 0.2)[0]
    K = (500.0, 510.0, 320.0, 240.0)
    N = np.einsum("nij,jk->nik", X[:, :, :3], off[:, :3])
    tN = np.einsum("nij,j->ni", X[:, :, :3], off[:, 3]) + X[:, :, 3]
    NT = np.swapaxes(N, 1, 2)
    p = _in_front(rng, NT, -np.einsum("nij,nj->ni", NT, tN))
    out = []
    for name, tag in (("EdgeSE3PointXYZDepth", "EDGE_PROJECT_DEPTH"),
                      ("EdgeSE3PointXYZDisparity", "EDGE_PROJECT_DISPARITY")):
        z = np.column_stack([rng.normal(320, 50, M), rng.normal(240, 50, M),
                             rng.uniform(0.1, 6, M)])
        info = _info(rng, M, 3)
        qt = lambda T: " ".join(repr(float(v)) for v in  # noqa: E731
                                np.r_[T[:, 3], matrix_to_quat(T[None, :, :3])[0]])
        lines = [f"PARAMS_CAMERACALIB 0 {qt(off)} " + " ".join(repr(v) for v in K)]
        for i in range(M):
            lines.append(f"VERTEX_SE3:QUAT {2 * i} {qt(X[i])}")
            lines.append(f"VERTEX_TRACKXYZ {2 * i + 1} " + " ".join(repr(float(v)) for v in p[i]))
            up = info[i][np.triu_indices(3)]
            lines.append(f"{tag} {2 * i} {2 * i + 1} 0 " + " ".join(
                repr(float(v)) for v in np.r_[z[i], up]))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "cam.g2o"
            path.write_text("\n".join(lines) + "\n")
            opt = g2o.SparseOptimizer()
            assert opt.load(str(path))
        opt.initialize_optimization()
        opt.compute_active_errors()
        edges = sorted(opt.edges(), key=lambda e: e.vertices()[0].id())
        # The file's quaternions, read back as g2o holds them, are the inputs.
        Xr = np.array([opt.vertex(2 * i).estimate().matrix()[:3] for i in range(M)])
        c = Case(name, [Xr, p], z, info,
                 {"kind": "camera", "offset": off.tolist(), "K": list(K)})
        out.append(c.record([float(e.chi2()) for e in edges]))
    return out


def slam2d(rng: np.random.Generator) -> list[dict[str, Any]]:
    out = []
    xi, xj, z = _se2(rng, M), _se2(rng, M), _se2(rng, M)
    P = _se2(rng, 2) * 0.3
    p, q = rng.normal(0, 3, (M, 2)), rng.normal(0, 3, (M, 2))
    se2 = lambda g2o, v: g2o.SE2(*map(float, v))  # noqa: E731
    specs = [
        ("EdgeSE2Offset", [xi, xj], z, 3, ("VertexSE2", "VertexSE2"), "se2", (0, 1)),
        ("EdgePointXY", [p, q], rng.normal(size=(M, 2)), 2,
         ("VertexPointXY", "VertexPointXY"), "vec", ()),
        ("EdgeXYPrior", [p], rng.normal(size=(M, 2)), 2, ("VertexPointXY",), "vec", ()),
        ("EdgeSE2XYPrior", [xi], rng.normal(size=(M, 2)), 2, ("VertexSE2",), "vec", ()),
        ("EdgeSE2PointXYBearing", [xi, p], rng.uniform(-3, 3, (M, 1)), 1,
         ("VertexSE2", "VertexPointXY"), "float", ()),
        ("EdgeSE2PointXYOffset", [xi, p], rng.normal(size=(M, 2)), 2,
         ("VertexSE2", "VertexPointXY"), "vec", (0,)),
        ("EdgeSE2PointXYCalib", [xi, p, xj * 0.2], rng.normal(size=(M, 2)), 2,
         ("VertexSE2", "VertexPointXY", "VertexSE2"), "vec", ()),
        ("EdgeSE2TwoPointsXY", [xi, p, q], rng.normal(size=(M, 4)), 4,
         ("VertexSE2", "VertexPointXY", "VertexPointXY"), "vec", ()),
        ("EdgeSE2SensorCalib", [xi, xj, P[[0, 1, 0, 1, 0]]], z * 0.3, 3,
         ("VertexSE2", "VertexSE2", "VertexSE2"), "se2", ()),
        ("EdgeSE2OdomDifferentialCalib", [xi, xj, np.array([[1.0, 1.0, 0.5], [0.9, 1.1, 0.4],
                                                            [1.05, 0.97, 0.6], [1.0, 1.0, 0.5],
                                                            [0.8, 1.2, 0.3]])],
         np.column_stack([rng.uniform(0.5, 1.5, (M, 2)), rng.uniform(0.1, 1.0, M)]), 3,
         ("VertexSE2", "VertexSE2", "VertexOdomDifferentialParams"), "velocity", ()),
    ]
    specs[-1][2][3, 1] = specs[-1][2][3, 0]  # one straight motion (v_l = v_r)
    for name, x, zz, e, vcls, mkind, pids in specs:
        params = ({"kind": "se2_offsets", "offsets": P.tolist()} if pids else None)
        c = Case(name, x, zz, _info(rng, M, e), params)

        def build(g2o: Any, opt: Any, i: int, c: Case = c, vcls: tuple = vcls,
                  mkind: str = mkind, pids: tuple = pids) -> Any:
            if i == 0:
                for k in pids:
                    _param(g2o, opt, "ParameterSE2Offset", k, se2(g2o, P[k]))
            v = [_vertex(g2o, opt, vc, 10 * i + k, se2(g2o, a[i]) if vc == "VertexSE2" else a[i])
                 for k, (vc, a) in enumerate(zip(vcls, c.x, strict=True))]
            zi = (se2(g2o, c.z[i]) if mkind == "se2" else
                  float(c.z[i, 0]) if mkind == "float" else
                  g2o.VelocityMeasurement(*map(float, c.z[i])) if mkind == "velocity" else c.z[i])
            return _edge(g2o, opt, c.name, v, zi, c.info[i], pids)
        out.append(c.record(_g2o_chi2(c, build)))

    out.append(_lots_case(rng, "EdgeSE2LotsOfXY", ("VertexSE2", "VertexPointXY"), 2, xi, se2))
    return out


def _cams(rng: np.random.Generator, m: int) -> np.ndarray:
    q = rng.normal(size=(m, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    K = np.array([500.0, 510.0, 320.0, 240.0, 0.12])
    return np.column_stack([rng.normal(0, 2, (m, 3)), q, np.tile(K, (m, 1))])


def sba(rng: np.random.Generator) -> list[dict[str, Any]]:
    out = []
    ci, cj = _cams(rng, M), _cams(rng, M)
    R = quat_to_rot(ci[:, 3:7])
    p = _in_front(rng, np.swapaxes(R, 1, 2), -np.einsum("nji,nj->ni", R, ci[:, :3]))

    def sbacam(g2o: Any, c: np.ndarray) -> Any:
        # (the wheel's Quaternion constructors fail: through SE3Quat's matrix one)
        cam = g2o.SBACam(g2o.SE3Quat(quat_to_rot(c[None, 3:7])[0], np.ascontiguousarray(c[:3])))
        cam.set_cam(*map(float, c[7:12]))
        return cam

    def q7(g2o: Any, v: np.ndarray) -> Any:
        return g2o.SE3Quat(quat_to_rot(v[None, 3:7])[0], np.ascontiguousarray(v[:3]))

    zrel = np.column_stack([rng.normal(size=(M, 3)), _cams(rng, M)[:, 3:7]])
    specs = [("EdgeProjectP2MC", [ci, p], rng.normal(300, 80, (M, 2)), 2),
             ("EdgeProjectP2SC", [ci, p], rng.normal(300, 80, (M, 3)), 3),
             ("EdgeSBACam", [ci, cj], zrel, 6),
             ("EdgeSBAScale", [ci, cj], rng.uniform(1, 4, (M, 1)), 1)]
    for name, x, z, e in specs:
        c = Case(name, x, z, _info(rng, M, e))

        def build(g2o: Any, opt: Any, i: int, c: Case = c) -> Any:
            if c.name.startswith("EdgeProject"):  # g2o's order: (point, camera)
                v = [_vertex(g2o, opt, "VertexPointXYZ", 10 * i, c.x[1][i]),
                     _vertex(g2o, opt, "VertexCam", 10 * i + 1, sbacam(g2o, c.x[0][i]))]
            else:
                v = [_vertex(g2o, opt, "VertexCam", 10 * i + k, sbacam(g2o, a[i]))
                     for k, a in enumerate(c.x)]
            zi = (q7(g2o, c.z[i]) if c.name == "EdgeSBACam" else
                  float(c.z[i, 0]) if c.name == "EdgeSBAScale" else c.z[i])
            return _edge(g2o, opt, c.name, v, zi, c.info[i])
        out.append(c.record(_g2o_chi2(c, build)))
    return out + _expmap(rng)


def camera_updates(rng: np.random.Generator) -> dict[str, Any]:
    """``SBACam::update`` (``VertexCam``'s ``oplus``): cameras, increments and g2o's
    resulting ``[t, q]``."""
    import g2opy as g2o

    cams = _cams(rng, M)
    deltas = rng.normal(0, 0.2, (M, 6))
    result = []
    for c, d in zip(cams, deltas, strict=True):
        cam = g2o.SBACam(g2o.SE3Quat(quat_to_rot(c[None, 3:7])[0], np.ascontiguousarray(c[:3])))
        cam.update(d)
        result.append(cam.to_vector().tolist())
    return {"cameras": cams.tolist(), "deltas": deltas.tolist(), "result": result}


def _expmap(rng: np.random.Generator) -> list[dict[str, Any]]:
    from graphopt.lie import se3_exp

    out = []
    T, A = se3_exp(rng.normal(0, 0.4, (M, 6))), se3_exp(rng.normal(0, 0.4, (M, 6)))
    p = _in_front(rng, T[:, :3, :3], T[:, :3, 3])
    f, pp, b = 480.0, (320.0, 240.0), 0.1
    params = {"kind": "sba_camera", "f": f, "pp": list(pp), "baseline": b}
    # ψ of points in front of both cameras: x_a = A·p_w, ψ = [x/z, y/z, 1/z]
    xa = np.einsum("nij,nj->ni", A[:, :3, :3], p) + A[:, :3, 3]
    psi = np.column_stack([xa[:, :2] / xa[:, 2:], 1.0 / xa[:, 2]])
    se3q = lambda g2o, T: g2o.SE3Quat(np.ascontiguousarray(T[:3, :3]),  # noqa: E731
                                      np.ascontiguousarray(T[:3, 3]))
    specs = [("EdgeProjectXYZ2UV", [T, p], rng.normal(300, 50, (M, 2)), 2),
             ("EdgeSE3ProjectXYZ", [T, p], rng.normal(300, 50, (M, 2)), 2),
             ("EdgeProjectXYZ2UVU", [T, p], rng.normal(300, 50, (M, 3)), 3),
             ("EdgeProjectPSI2UV", [A, T, psi], rng.normal(300, 50, (M, 2)), 2)]
    for name, x, z, e in specs:
        c = Case(name, x, z, _info(rng, M, e), params)

        def build(g2o: Any, opt: Any, i: int, c: Case = c) -> Any:
            if i == 0:
                cam = g2o.CameraParameters(f, np.array(pp), b)
                cam.set_id(0)
                opt.add_parameter(cam)
            if c.name == "EdgeSE3ProjectXYZ":  # intrinsics as attributes, no parameter
                v = [_vertex(g2o, opt, "VertexPointXYZ", 10 * i, c.x[1][i]),
                     _vertex(g2o, opt, "VertexSE3Expmap", 10 * i + 1, se3q(g2o, c.x[0][i]))]
                e = _edge(g2o, opt, c.name, v, c.z[i], c.info[i])
                e.fx, e.fy, e.cx, e.cy = f, f, pp[0], pp[1]
                return e
            if c.name != "EdgeProjectPSI2UV":
                v = [_vertex(g2o, opt, "VertexPointXYZ", 10 * i, c.x[1][i]),
                     _vertex(g2o, opt, "VertexSE3Expmap", 10 * i + 1, se3q(g2o, c.x[0][i]))]
            else:  # g2o's order: (ψ, observing, anchor)
                v = [_vertex(g2o, opt, "VertexPointXYZ", 10 * i, c.x[2][i]),
                     _vertex(g2o, opt, "VertexSE3Expmap", 10 * i + 1, se3q(g2o, c.x[1][i])),
                     _vertex(g2o, opt, "VertexSE3Expmap", 10 * i + 2, se3q(g2o, c.x[0][i]))]
            return _edge(g2o, opt, c.name, v, c.z[i], c.info[i], (0,))
        out.append(c.record(_g2o_chi2(c, build)))
    return out


def icp(rng: np.random.Generator) -> list[dict[str, Any]]:
    out = []
    x0, x1 = _pose34(rng, M), _pose34(rng, M)
    z = rng.normal(0, 2, (M, 2, 3))
    n = rng.normal(size=(M, 2, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n[0, 0] = [0.0, 0.99, np.sqrt(1 - 0.99 ** 2)]  # the x-axis branch of makeRot
    for pl_pl in (False, True):
        name = "EdgeVVGicpPlaneToPlane" if pl_pl else "EdgeVVGicp"
        info = np.tile(np.eye(3), (M, 1, 1)) if pl_pl else _info(rng, M, 3)
        c = Case(name, [x0, x1], z, info, None, {"normals": n})

        def build(g2o: Any, opt: Any, i: int, c: Case = c, pl_pl: bool = pl_pl) -> Any:
            v = [_vertex(g2o, opt, "VertexSE3", 10 * i + k, _iso(g2o, a[i]))
                 for k, a in enumerate(c.x)]
            meas = g2o.EdgeGICP()
            meas.pos0, meas.pos1 = c.z[i, 0], c.z[i, 1]
            meas.normal0, meas.normal1 = n[i, 0], n[i, 1]
            e = _edge(g2o, opt, "EdgeVVGicp", v, meas, c.info[i])
            if pl_pl:
                e.pl_pl = True
                e.cov0, e.cov1 = meas.cov0(0.01), meas.cov1(0.01)
            return e
        out.append(c.record(_g2o_chi2(c, build)))

    X = _pose34(rng, M)
    RT = np.swapaxes(X[:, :, :3], 1, 2)
    p = _in_front(rng, RT, -np.einsum("nij,nj->ni", RT, X[:, :, 3]))
    K = (500.0, 505.0, 320.0, 240.0, 0.11)
    c = Case("EdgeXyzVsc", [X, p], rng.normal(300, 50, (M, 3)), _info(rng, M, 3),
             {"kind": "scam", "K": list(K)})

    def b_vsc(g2o: Any, opt: Any, i: int) -> Any:
        g2o.VertexSCam.set_cam(*K)
        v = [_vertex(g2o, opt, "VertexPointXYZ", 10 * i, p[i]),
             _vertex(g2o, opt, "VertexSCam", 10 * i + 1, _iso(g2o, X[i]))]
        v[1].set_all()
        return _edge(g2o, opt, "EdgeXyzVsc", v, c.z[i], c.info[i])
    out.append(c.record(_g2o_chi2(c, b_vsc)))
    return out


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else OUT
    rng = np.random.default_rng(23)
    cases = slam3d(rng) + slam2d(rng) + sba(rng) + icp(rng)
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {"g2opy": "2.3.0", "cases": cases, "camera_updates": camera_updates(rng)}
    out.write_text(json.dumps(record, indent=None) + "\n")
    for c in cases:
        print(f"{c['type']:28s} chi2 {', '.join(f'{v:.6g}' for v in c['chi2'])}")


if __name__ == "__main__":
    main()
