"""g2o's own per-edge chi2 of the SBA/Sim3 types on the inputs of ``tests/sba_sim3_cases.py``,
for the constants in ``tests/test_sba_sim3_types.py``: run with g2opy 2.3.0
(``pip install g2opy==2.3.0``; not a test dependency) and paste the printed dictionary.

What g2opy 2.3.0 cannot set is emulated with an equal g2o computation:

* ``EdgeStereoSE3ProjectXYZOnlyPose`` exposes neither ``Xw`` nor its intrinsics: its reference
  is g2o's ``EdgeStereoSE3ProjectXYZ`` with the point vertex at ``Xw`` (the same formula;
  g2o's only-pose edge rounds ``1/z`` to a float, the binary one does not).
* ``VertexSim3Expmap``'s intrinsics stay ``f = 1, c = 0``: the Sim3 projections get normalised
  measurements ``(z − c)/f`` and the information ``f²Ω`` (``fx = fy = f``), which is the chi2 of
  pixel measurements with information ``Ω`` through ``(f, f, cx, cy)``.

Usage::

    .venv/bin/python -P benchmarks/g2o_sba_sim3_reference.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import g2opy as g2o  # noqa: E402
import sba_sim3_cases as C  # noqa: E402


def _se3(T: np.ndarray) -> g2o.SE3Quat:
    return g2o.SE3Quat(np.asfortranarray(T[:3, :3]), T[:3, 3].copy())


def _sim3(S: np.ndarray) -> g2o.Sim3:
    sR = S[:3, :3]
    s = float(np.sqrt((sR * sR).sum() / 3.0))
    return g2o.Sim3(np.asfortranarray(sR / s), S[:3, 3].copy(), s)


def _vertex(cls: type, vid: int, est: object, fixed: bool = False) -> object:
    v = cls()
    v.set_id(vid)
    v.set_estimate(est)
    v.set_fixed(fixed)
    return v


def _chi2(edge: object) -> float:
    edge.compute_error()
    return float(edge.chi2())


def _intrinsics(e: object, stereo: bool = False) -> None:
    e.fx, e.fy, e.cx, e.cy = C.FX, C.FY, C.CX, C.CY
    if stereo:
        e.bf = C.BF


def _point_pose_chi2(e: object, pt: object, pose: object, z: np.ndarray, info: np.ndarray,
                     stereo: bool = False) -> float:
    """g2o's chi2 of a (point, pose) projection edge ``e`` with the cases' intrinsics.

    Args:
        e: A new ``EdgeSE3ProjectXYZ`` or ``EdgeStereoSE3ProjectXYZ``.
        pt: The point vertex.
        pose: The pose vertex.
        z: ``(2,)`` or ``(3,)`` measurement.
        info: Information matrix.
        stereo: Set ``bf`` too.
    """
    e.set_vertex(0, pt)
    e.set_vertex(1, pose)
    e.set_measurement(z.copy())
    e.set_information(info.copy())
    _intrinsics(e, stereo)
    return _chi2(e)


def _pair_chi2(scaled: bool, Xi: np.ndarray, Xj: np.ndarray, Z: np.ndarray) -> list[float]:
    """g2o's chi2 of ``EdgeSim3`` (``scaled``) or ``EdgeSE3Expmap`` edges, one per ``k``.

    Args:
        scaled: Sim(3) (information ``C.INFO7``) or SE(3) (the identity).
        Xi: ``(M, 4, 4)`` first vertices.
        Xj: ``(M, 4, 4)`` second vertices.
        Z: ``(M, 4, 4)`` measurements.
    """
    vt, conv = (g2o.VertexSim3Expmap, _sim3) if scaled else (g2o.VertexSE3Expmap, _se3)
    out = []
    for k in range(C.M):
        e = g2o.EdgeSim3() if scaled else g2o.EdgeSE3Expmap()
        e.set_vertex(0, _vertex(vt, 0, conv(Xi[k])))
        e.set_vertex(1, _vertex(vt, 1, conv(Xj[k])))
        e.set_measurement(conv(Z[k]))
        e.set_information(C.INFO7.copy() if scaled else np.eye(6))
        out.append(_chi2(e))
    return out


def reference() -> dict[str, list[float]]:
    """Per-edge chi2 of every type, as g2o computes it."""
    X, T, z2, z3 = C.points(), C.pose(), C.pixels(), C.stereo()
    out: dict[str, list[float]] = {k: [] for k in (
        "EdgeSE3ProjectXYZ", "EdgeSE3ProjectXYZOnlyPose", "EdgeStereoSE3ProjectXYZ",
        "EdgeStereoSE3ProjectXYZOnlyPose", "EdgeSE3Expmap", "EdgeSim3",
        "EdgeSim3ProjectXYZ", "EdgeInverseSim3ProjectXYZ")}
    pose = _vertex(g2o.VertexSE3Expmap, 0, _se3(T))
    for k in range(C.M):
        pt = _vertex(g2o.VertexPointXYZ, 1, X[k].copy())
        out["EdgeSE3ProjectXYZ"].append(_point_pose_chi2(g2o.EdgeSE3ProjectXYZ(), pt, pose,
                                                         z2[k], C.INFO2))
        e = g2o.EdgeSE3ProjectXYZOnlyPose()
        e.set_vertex(0, pose)
        e.set_measurement(z2[k].copy())
        e.set_information(C.INFO2.copy())
        e.Xw = X[k].copy()
        _intrinsics(e)
        out["EdgeSE3ProjectXYZOnlyPose"].append(_chi2(e))
        out["EdgeStereoSE3ProjectXYZ"].append(_point_pose_chi2(
            g2o.EdgeStereoSE3ProjectXYZ(), pt, pose, z3[k], C.INFO3, stereo=True))
        out["EdgeStereoSE3ProjectXYZOnlyPose"].append(out["EdgeStereoSE3ProjectXYZ"][-1])
    out["EdgeSE3Expmap"] = _pair_chi2(False, *C.pose_pairs())
    out["EdgeSim3"] = _pair_chi2(True, *C.sim3_pairs())
    for name, scaled in (("EdgeSE3Expmap near optimum", False), ("EdgeSim3 near optimum", True)):
        out[name] = _pair_chi2(scaled, *C.near_optimum(scaled))
    S, zs = C.sim3_projection()
    f, c = C.F_SIM3, np.array([C.CX, C.CY])
    sim = _vertex(g2o.VertexSim3Expmap, 0, _sim3(S))
    for k in range(C.M):
        pt = _vertex(g2o.VertexPointXYZ, 1, X[k].copy())
        for name, cls in (("EdgeSim3ProjectXYZ", g2o.EdgeSim3ProjectXYZ),
                          ("EdgeInverseSim3ProjectXYZ", g2o.EdgeInverseSim3ProjectXYZ)):
            e = cls()
            e.set_vertex(0, pt)
            e.set_vertex(1, sim)
            e.set_measurement((zs[k] - c) / f)
            e.set_information(C.INFO2 * f * f)
            out[name].append(_chi2(e))
    return out


def main() -> None:
    print("G2O_CHI2 = {")
    for name, vals in reference().items():
        print(f"    {name!r}: [")
        for i in range(0, len(vals), 3):
            print("        " + " ".join(f"{v!r}," for v in vals[i:i + 3]))
        print("    ],")
    print("}")


if __name__ == "__main__":
    main()
