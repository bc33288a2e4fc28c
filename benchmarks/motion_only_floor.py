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

With ``--g2o-semantics`` it compares what a g2opy program gets instead: the ORB-SLAM program of
``bench_slam_backend.py``'s g2opy side, run by g2opy and by ``graphopt.g2o`` (the same calls),
and ``bare_g2o``, the bare loop doing g2o's iterations and trials (``optimize(10)`` runs 10
iterations unless one finds no step in 10 trials or a trial leaves chi2 unchanged to rounding,
``StoppingConfig.g2o``: about 18 iterations and trials over the four rounds, where graphopt's
own stopping tests end after 13 iterations). It is the floor of any numpy implementation of
those semantics. The same program run on objects that do nothing (``null_g2o.py``) is what the
program costs by itself; with bare numpy's optimisation it is the floor of any implementation
of g2o's API in Python (*floor / g2opy*).

Method: one thread a side, interleaved, CPU time, medians of ``--runs`` batches of 50 calls.

Usage::

    .venv/bin/python -P benchmarks/motion_only_floor.py [--runs 5] [--matches 100,500]
        [--g2o-semantics]
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
from graphopt.stopping import ROUNDING_CHANGE  # noqa: E402
from graphopt.types import CameraParameters  # noqa: E402

CHI2_MONO = 5.991


DELTA = float(np.sqrt(CHI2_MONO))  # the Huber width of the procedure


def _project(T: np.ndarray, Xw: np.ndarray, z: np.ndarray, f: np.ndarray, c: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(e (m, 2), iz (m,), uv (m, 2))`` of the world points ``Xw`` seen from ``T``."""
    P = Xw @ T[:3, :3].T + T[:3, 3]
    iz = 1.0 / P[:, 2]
    uv = P[:, :2] * iz[:, None]
    return z - (uv * f + c), iz, uv


def _jacobian(uv: np.ndarray, iz: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """g2o's ``EdgeSE3ProjectXYZOnlyPose`` rows ``(m, 2, 6)``."""
    u, v = uv[:, 0], uv[:, 1]
    J = np.zeros((len(iz), 2, 6))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = fx * u * v, -fx * (1 + u * u), fx * v
    J[:, 0, 3], J[:, 0, 5] = -fx * iz, fx * u * iz
    J[:, 1, 0], J[:, 1, 1], J[:, 1, 2] = fy * (1 + v * v), -fy * u * v, -fy * u
    J[:, 1, 4], J[:, 1, 5] = -fy * iz, fy * v * iz
    return J


def _robust(s: np.ndarray, active: np.ndarray, kernel: bool) -> tuple[float, np.ndarray]:
    """The active edges' robust chi2 and every edge's weight (0 if inactive)."""
    if not kernel:
        return float(s[active].sum()), active.astype(float)
    r = np.sqrt(s)
    rho = np.where(s <= CHI2_MONO, s, 2 * DELTA * r - CHI2_MONO)
    return float(rho[active].sum()), DELTA / np.maximum(r, DELTA) * active


def bare(T_init: np.ndarray, Xw: np.ndarray, z: np.ndarray, inv_sigma2: np.ndarray,
         cam: CameraParameters, count: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """Mono ``PoseOptimization`` in plain numpy: ``(T, inliers, last round's chi2)``;
    ``count[0]`` is increased by the iterations run."""
    fx, fy = cam.fx, cam.fy
    f, c = np.array([fx, fy]), np.array([cam.cx, cam.cy])
    outlier = np.zeros(len(z), dtype=bool)
    kernel = True

    def evaluate(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, iz, uv = _project(T, Xw, z, f, c)
        return e, inv_sigma2 * np.einsum("mi,mi->m", e, e), _jacobian(uv, iz, fx, fy)

    T = T_init
    for round_ in range(4):
        T = T_init.copy()
        active = ~outlier
        e, s, J = evaluate(T)
        chi, w = _robust(s, active, kernel)
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
                chin, wn = _robust(sn, active, kernel)
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


def bare_g2o(T_init: np.ndarray, Xw: np.ndarray, z: np.ndarray, inv_sigma2: np.ndarray,
             cam: CameraParameters, count: list[int]) -> tuple[np.ndarray, np.ndarray, float]:
    """The same procedure with **g2o's semantics** (what ``graphopt.g2o`` must do for a g2opy
    program): every ``optimize(10)`` runs 10 iterations unless an iteration finds no step in 10
    trials or a trial changes chi2 by at most ``ROUNDING_CHANGE`` of it (g2o's ``rho == 0``, as
    ``StoppingConfig.g2o``); λ₀ = 1e-5·max diag(H) at each call; g2o's λ rules; a trial
    evaluates errors only, an accepted one is linearised afresh. LAPACK's Cholesky directly
    (not ``cho_solve``'s checks). ``count`` gets ``[iterations, trials]`` added."""
    fx, fy = cam.fx, cam.fy
    f, c = np.array([fx, fy]), np.array([cam.cx, cam.cy])
    outlier = np.zeros(len(z), dtype=bool)
    kernel = True
    potrf, potrs = sla.lapack.dpotrf, sla.lapack.dpotrs

    def errors(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        e, iz, uv = _project(T, Xw, z, f, c)
        return e, inv_sigma2 * np.einsum("mi,mi->m", e, e), (uv, iz)

    last = 0.0
    for round_ in range(4):
        T = T_init.copy()
        active = ~outlier
        e, s, q = errors(T)
        chi, w = _robust(s, active, kernel)
        done = False
        for it in range(10):
            if done:
                break
            J = _jacobian(*q, fx, fy)
            count[0] += 1
            wi = w * inv_sigma2
            J2 = J.reshape(-1, 6)
            H = (J * wi[:, None, None]).reshape(-1, 6).T @ J2
            b = -(e * wi[:, None]).reshape(-1) @ J2
            if it == 0:
                lam, nu = 1e-5 * H.diagonal().max(), 2.0
            for _ in range(10):
                count[1] += 1
                L, info = potrf(H + lam * np.eye(6), lower=1)
                dx = potrs(L, b, lower=1)[0]
                Tn = se3_exp(dx[None])[0] @ T
                en, sn, qn = errors(Tn)
                chin, wn = _robust(sn, active, kernel)
                rho = (chi - chin) / (dx @ (lam * dx + b) + 1e-3)
                done = abs(chi - chin) <= ROUNDING_CHANGE * chi  # g2o's rho == 0, to rounding
                if rho > 0 and np.isfinite(chin):
                    lam *= max(1 / 3, min(2 / 3, 1 - (2 * rho - 1) ** 3))
                    nu = 2.0
                    T, e, s, q, chi, w = Tn, en, sn, qn, chin, wn
                    break
                if done:
                    break
                lam, nu = lam * nu, 2 * nu
            else:
                break  # no step in 10 trials: g2o's optimize stops
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


def _medians(calls: dict[str, Callable[[], Any]], runs: int) -> dict[str, float]:
    """CPU ms per call of each, the median of ``runs`` batches of 50, the sides interleaved."""
    times: dict[str, list[float]] = {k: [] for k in calls}
    for _ in range(runs):
        for k, fn in calls.items():
            t = time.process_time()
            for _ in range(50):
                fn()
            times[k].append((time.process_time() - t) / 50 * 1e3)
    return {k: float(np.median(v)) for k, v in times.items()}


def _program_on(g2o_side: Any, module: Any, name: str) -> Any:
    """``slam_backend_g2o``'s functions reading ``module`` as their ``g2o``: the same program of
    g2opy calls, run by another module."""
    side = type(g2o_side)(name)
    side.__dict__.update({k: v for k, v in g2o_side.__dict__.items() if not k.startswith("__")})
    side.g2o = module
    side.NO_KERNEL = module.RobustKernelHuber(1e12)
    for key, fn in g2o_side.__dict__.items():  # its functions, reading side's globals
        if getattr(fn, "__module__", None) == g2o_side.__name__ and hasattr(fn, "__code__"):
            side.__dict__[key] = type(fn)(fn.__code__, side.__dict__, key, fn.__defaults__,
                                          fn.__closure__)
    return side


def g2o_semantics(args: argparse.Namespace) -> None:
    """The ``--g2o-semantics`` table (see the module docstring)."""
    import null_g2o
    import slam_backend_g2o as g2o_side

    import graphopt.g2o as go_g2o

    go_side = _program_on(g2o_side, go_g2o, "slam_backend_graphopt_g2o")
    null_side = _program_on(g2o_side, null_g2o, "slam_backend_null_g2o")
    print("motion-only BA (mono) with g2o's semantics, CPU ms per call, medians of "
          f"{args.runs} batches of 50; one thread. *program*: the g2opy program on objects "
          "that do nothing (null_g2o.py); *floor*: program + bare numpy")
    print("| matches | g2opy | graphopt.g2o | bare numpy (g2o's semantics) | program | "
          "graphopt.g2o / g2opy | bare / g2opy | floor / g2opy | iterations, trials (bare) | "
          "last round's chi2 (bare, g2opy) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for m in (int(x) for x in args.matches.split(",")):
        s = scenes.motion_only(m, False)
        count = [0, 0]
        calls: dict[str, Callable[[], Any]] = {
            "g2opy": lambda s=s: g2o_side.pose_optimization(s.T_init, s.Xw, s.z, s.inv_sigma2,
                                                            lambda: None),
            "graphopt.g2o": lambda s=s: go_side.pose_optimization(s.T_init, s.Xw, s.z,
                                                                  s.inv_sigma2, lambda: None),
            "bare": lambda s=s, count=count: bare_g2o(s.T_init, s.Xw, s.z, s.inv_sigma2,
                                                      scenes.CAM, count),
            "program": lambda s=s: null_side.pose_optimization(s.T_init, s.Xw, s.z,
                                                               s.inv_sigma2, lambda: None),
        }
        _, inl_b, chi_b = calls["bare"]()
        counted = list(count)
        _, inl_g, quality = calls["g2opy"]()
        _, inl_go, _ = calls["graphopt.g2o"]()
        assert np.array_equal(inl_b, inl_g) and np.array_equal(inl_go, inl_g), \
            "the inlier sets differ"
        med = _medians(calls, args.runs)
        g = med["g2opy"]
        print(f"| {m} | {g:.2f} | {med['graphopt.g2o']:.2f} | {med['bare']:.2f} | "
              f"{med['program']:.2f} | {med['graphopt.g2o'] / g:.2f} | {med['bare'] / g:.2f} | "
              f"{(med['bare'] + med['program']) / g:.2f} | {counted[0]}, {counted[1]} | "
              f"{chi_b:.6g}, {quality():.6g} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--matches", default="100,500")
    ap.add_argument("--g2o-semantics", action="store_true",
                    help="compare g2o's semantics instead: g2opy, graphopt.g2o running the same "
                         "g2opy program, and bare numpy doing g2o's iterations and trials")
    args = ap.parse_args()
    if args.g2o_semantics:
        g2o_semantics(args)
        return
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
        med = _medians(calls, args.runs)
        g2o_ms = med.get("g2opy", float("nan"))
        assert np.array_equal(inl_b, res[1]), "bare and graphopt disagree on the inliers"
        print(f"| {m} | {g2o_ms:.2f} | {med['bare']:.2f} | {med['graphopt']:.2f} | "
              f"{med['bare'] / g2o_ms:.2f} | {med['graphopt'] / g2o_ms:.2f} | "
              f"{iters} | {chi_b:.6g}, {res[2]:.6g} |")


if __name__ == "__main__":
    main()
