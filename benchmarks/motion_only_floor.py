"""How fast can numpy run ORB-SLAM's ``PoseOptimization``? A framework-free floor, graphopt and
g2opy on the same scenes, same run.

``bare`` is the procedure of ``docs/slam_backend.md`` §1 written straight in numpy for this one
problem: the projections, g2o's closed-form pose Jacobian, Huber weights, ``JᵀWJ`` by one
product, LM with g2o's λ rules and graphopt's stopping test (relative chi2 change below 1e-6),
SciPy's Cholesky, the SE(3) exponential; no vertex or edge objects, no structure, no checks.
It runs the same iterations as graphopt (printed) and ends at the same chi2 and inliers. It is
what graphopt's per-call overhead is measured against: the time graphopt spends above it is
its framework (building, validation, caches, the general assembly and solver interface), the
time bare numpy spends above g2o's is numpy's per-call floor.

Method: one thread a side, interleaved, CPU time, medians of ``--runs`` batches of 50 calls.

Usage::

    .venv/bin/python -P benchmarks/motion_only_floor.py [--runs 5] [--matches 100,500]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import slam_backend_scenes as scenes  # noqa: E402

from graphopt.lie import se3_exp  # noqa: E402
from graphopt.types import CameraParameters  # noqa: E402

CHI2_MONO = 5.991


def bare(T_init: np.ndarray, Xw: np.ndarray, z: np.ndarray, inv_sigma2: np.ndarray,
         cam: CameraParameters, count: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """Mono ``PoseOptimization`` in plain numpy: ``(T, inliers, last round's chi2)``;
    ``count[0]`` is increased by the iterations run."""
    fx, fy = cam.fx, cam.fy
    f, c = np.array([fx, fy]), np.array([cam.cx, cam.cy])
    delta = np.sqrt(CHI2_MONO)
    m = len(z)
    outlier = np.zeros(m, dtype=bool)
    kernel = True

    def evaluate(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        P = Xw @ T[:3, :3].T + T[:3, 3]
        iz = 1.0 / P[:, 2]
        uv = P[:, :2] * iz[:, None]
        e = z - (uv * f + c)
        u, v = uv[:, 0], uv[:, 1]
        J = np.zeros((m, 2, 6))                  # g2o's EdgeSE3ProjectXYZOnlyPose rows
        J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = fx * u * v, -fx * (1 + u * u), fx * v
        J[:, 0, 3], J[:, 0, 5] = -fx * iz, fx * u * iz
        J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = fy * (1 + v * v), -fy * u * v, -fy * u
        J[:, 1, 4], J[:, 1, 5] = -fy * iz, fy * v * iz
        return e, inv_sigma2 * np.einsum("mi,mi->m", e, e), J

    def robust(s: np.ndarray, active: np.ndarray) -> tuple[float, np.ndarray]:
        if not kernel:
            return float(s[active].sum()), active.astype(float)
        r = np.sqrt(s)
        rho = np.where(s <= CHI2_MONO, s, 2 * delta * r - CHI2_MONO)
        return float(rho[active].sum()), delta / np.maximum(r, delta) * active

    T = T_init
    for round_ in range(4):
        T = T_init.copy()
        active = ~outlier
        e, s, J = evaluate(T)
        chi, w = robust(s, active)
        lam = -1.0
        for _ in range(10):
            count[0] += 1
            wi = w * inv_sigma2
            J2 = J.reshape(-1, 6)
            H = (J * wi[:, None, None]).reshape(-1, 6).T @ J2
            b = -(e * wi[:, None]).reshape(-1) @ J2
            if lam < 0:
                lam = 1e-5 * H.diagonal().max()
            nu = 2.0
            for _ in range(10):
                dx = sla.cho_solve(sla.cho_factor(H + lam * np.eye(6), check_finite=False), b,
                                   check_finite=False)
                Tn = se3_exp(dx[None])[0] @ T
                en, sn, Jn = evaluate(Tn)
                chin, wn = robust(sn, active)
                rho = (chi - chin) / (dx @ (lam * dx + b) + 1e-3)
                if rho > 0:
                    lam *= max(1 / 3, min(2 / 3, 1 - (2 * rho - 1) ** 3))
                    break
                lam, nu = lam * nu, 2 * nu
            else:
                break
            converged = abs(chi - chin) <= 1e-6 * chi
            T, e, s, J, chi, w = Tn, en, sn, Jn, chin, wn
            if converged:
                break
        last = float(s[active].sum())
        outlier = s > CHI2_MONO
        if round_ == 2:
            kernel = False
    return T, ~outlier, last


def _graphopt() -> Callable[..., Any]:
    """``pose_optimization`` of ``docs/slam_backend.md`` (its Python blocks executed)."""
    doc = (HERE.parent / "docs" / "slam_backend.md").read_text()
    ns: dict[str, Any] = {"__name__": "slam_backend_doc"}
    for block in re.findall(r"```python\n(.*?)```", doc, flags=re.S):
        if "slam_backend_scenes" not in block:
            exec(compile(block, "slam_backend.md", "exec"), ns)  # noqa: S102
    return ns["pose_optimization"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--matches", default="100,500")
    args = ap.parse_args()
    try:
        import slam_backend_g2o as g2o_side
    except ImportError:
        g2o_side = None
    gopt = _graphopt()
    print("motion-only BA (mono), CPU ms per call, medians of "
          f"{args.runs} batches of 50; one thread")
    print("| matches | g2opy | bare numpy | graphopt | bare / g2opy | graphopt / g2opy | "
          "bare's iterations | last round's chi2 (bare, graphopt) |")
    print("|---|---|---|---|---|---|---|---|")
    for m in (int(x) for x in args.matches.split(",")):
        s = scenes.motion_only(m, False)
        count = [0]
        calls: dict[str, Callable[[], Any]] = {
            "bare": lambda s=s, count=count: bare(s.T_init, s.Xw, s.z, s.inv_sigma2,
                                                  scenes.CAM, count),
            "graphopt": lambda s=s: gopt(s.T_init, s.Xw, s.z, s.inv_sigma2, scenes.CAM),
        }
        if g2o_side is not None:
            calls["g2opy"] = lambda s=s: g2o_side.pose_optimization(
                s.T_init, s.Xw, s.z, s.inv_sigma2, lambda: None)
        _, inl_b, chi_b = calls["bare"]()
        iters = count[0]
        res = gopt(s.T_init, s.Xw, s.z, s.inv_sigma2, scenes.CAM)
        times: dict[str, list[float]] = {k: [] for k in calls}
        for _ in range(args.runs):
            for k, fn in calls.items():
                t = time.process_time()
                for _ in range(50):
                    fn()
                times[k].append((time.process_time() - t) / 50 * 1e3)
        med = {k: float(np.median(v)) for k, v in times.items()}
        g2o_ms = med.get("g2opy", float("nan"))
        assert np.array_equal(inl_b, res[1]), "bare and graphopt disagree on the inliers"
        print(f"| {m} | {g2o_ms:.2f} | {med['bare']:.2f} | {med['graphopt']:.2f} | "
              f"{med['bare'] / g2o_ms:.2f} | {med['graphopt'] / g2o_ms:.2f} | "
              f"{iters} | {chi_b:.6g}, {res[2]:.6g} |")


if __name__ == "__main__":
    main()
