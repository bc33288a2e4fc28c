"""A careful vectorised numpy implementation of direct BA's LM iteration: the benchmark peer.

The same problem as ``graphopt-direct-ba`` with xyz points (``docs/direct_ba.md`` §1–§2): one
photometric 4×4 patch edge per (point, image) pair, bilinear interpolation of float32 images
with central-difference gradients, edges active only inside the 4-pixel margin with ``Z > 1e-6``,
Huber (δ = 0.5) on ``eᵀe`` with g2o's semantics, the first pose fixed, the update
``T ← exp([ω, υ]) T`` and ``p ← p + Δp``, and g2o's Levenberg–Marquardt (``λ₀ = τ max diag H``
with τ = 1e-5, ``λI`` damping, Nielsen's rule capped at 2/3, up to 10 trials), points
eliminated by the Schur complement. Nothing of graphopt runs in :meth:`NumpyDirectBA.run`.

Design (all arrays structure-of-arrays over the ``(image, point)`` grid, no loop over edges):

* One flat ``np.take`` of a 7×7 pixel window per edge, pixel-major ``(49, m)``; the 6×6
  interpolated grid gives the patch and its central-difference gradients ``G`` (16×2).
* The 16 rows collapse into ``M = w GᵀG`` (2×2) and ``r = w Gᵀe``; with ``D = ∂(u,v)/∂P`` the
  whole edge is the 3×3 ``Q = DᵀMD`` and ``q = Dᵀr`` of its camera-frame point ``P``. With
  ``S = [−[P]×, I]`` and ``K = [P]× Q``: pose block ``SᵀQS``, gradient ``Sᵀq``, pose–point block
  ``[K; Q] R``, point block ``RᵀQR``, point gradient ``Rᵀq``; the sums over points are one batched
  gemm per image against ``[P, 1]``, the products with ``R`` gemms too.
* Per damped trial: closed-form 3×3 Cholesky of every ``V + λI``, ``X = W L⁻ᵀ`` (36 × 3N),
  ``S = U + λI − XXᵀ`` (BLAS), a 36×36 Cholesky solve, back-substitution with ``X``.
* A trial point is evaluated with gradients (they cost little beside the gather), so an accepted
  step's linearisation is reused; after a rejection, trials evaluate errors only.

``python -P benchmarks/numpy_direct_ba.py --check`` compares the chi2 with graphopt's from the
same start (initial, after 1, 2 and 5 iterations) and times the peer; ``bench_direct_ba.py``
times it beside graphopt. The data come through graphopt's loader, and ``--check`` builds
graphopt's problem, both outside the timed iterations. Patches are the task's 4×4.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "directba"


def _cross(p: tuple, v: np.ndarray) -> np.ndarray:
    """``p × v`` along axis 1 of ``v`` (``p``: three arrays broadcasting against ``v[:, k]``)."""
    return np.stack([p[1] * v[:, 2] - p[2] * v[:, 1], p[2] * v[:, 0] - p[0] * v[:, 2],
                     p[0] * v[:, 1] - p[1] * v[:, 0]], axis=1)


def _se3_exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``exp([ω, υ])`` as ``(R (n,3,3), t (n,3))``: Rodrigues and the SO(3) left Jacobian, with
    the Taylor series below θ² = 1e-8 (g2o's SE3Quat::exp, graphopt's ``se3_exp``)."""
    w, u = xi[:, :3], xi[:, 3:]
    th2 = np.einsum("ni,ni->n", w, w)
    small = th2 < 1e-8
    t2 = np.where(small, 1.0, th2)
    th = np.sqrt(t2)
    s, c = np.sin(th), np.cos(th)
    a = np.where(small, 1.0 - th2 / 6.0, s / th)[:, None, None]
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - c) / t2)[:, None, None]
    cc = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th - s) / (t2 * th))[:, None, None]
    W = np.zeros((len(xi), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    WW = W @ W
    R = np.eye(3) + a * W + b * WW
    J = np.eye(3) + b * W + cc * WW
    return R, np.einsum("nij,nj->ni", J, u)


class NumpyDirectBA:
    """Direct BA (xyz points) solved by g2o's LM in plain numpy.

    Args:
        images: ``(n, H, W)`` greyscale images.
        intrinsics: ``(fx, fy, cx, cy)``.
        poses: ``(n, 4, 4)`` ``T_cw``; the first is held fixed.
        points: ``(N, 3)`` world points.
        patches: ``(N, 16)`` reference intensities, ``k = 4(dx + 2) + (dy + 2)``.
        delta: Huber width on ``‖e‖``.
        margin: Activity margin in pixels.
        tau: LM's ``λ₀ = τ max diag H``.
        max_trials: Damped solves per iteration.
    """

    def __init__(self, images, intrinsics, poses, points, patches, delta=0.5, margin=4.0,
                 tau=1e-5, max_trials=10):
        images = np.asarray(images)
        self.n, self.H, self.W = images.shape
        self.N = len(points)
        self.flat = np.ascontiguousarray(images, dtype=np.float32).ravel()
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in intrinsics)
        self.delta, self.margin, self.tau, self.max_trials = delta, float(margin), tau, max_trials
        w = np.arange(-3, 4)  # raw window for the value and central gradients, [wx, wy]
        self.off_grad = (w[:, None] + w[None, :] * self.W).ravel()[:, None]
        w = np.arange(-2, 3)  # raw window for the value only
        self.off_val = (w[:, None] + w[None, :] * self.W).ravel()[:, None]
        self.img_base = (np.arange(self.n) * (self.H * self.W))[:, None]
        meas = np.asarray(patches, dtype=np.float64).T.reshape(4, 4, 1, self.N)
        self.meas = np.ascontiguousarray(meas)  # [dx, dy, image, point]
        self.R = np.array(poses[:, :3, :3], dtype=np.float64)
        self.t = np.array(poses[:, :3, 3], dtype=np.float64)
        self.p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)  # (3, N)
        self.lam, self.nu = 0.0, 2.0
        self.trial_grad = True
        self.cache = None  # linearisation inputs at the current state
        self.trials: list[int] = []

    # --- edges -------------------------------------------------------------------------------

    def evaluate(self, R, t, p, grad):
        """Robust chi2 at ``(R, t, p)``; with ``grad`` also what the normal equations need."""
        n, N, mg = self.n, self.N, self.margin
        P = np.matmul(R, p) + t[:, :, None]  # (n, 3, N) camera-frame points
        X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
        ok = Z > 1e-6
        iz = 1.0 / np.where(ok, Z, 1.0)
        with np.errstate(over="ignore", invalid="ignore"):
            u = self.fx * X * iz + self.cx
            v = self.fy * Y * iz + self.cy
            ok &= (u >= mg) & (u <= self.W - mg) & (v >= mg) & (v <= self.H - mg)
        u = np.where(ok, u, mg)
        v = np.where(ok, v, mg)
        u0, v0 = np.floor(u), np.floor(v)
        a = (u - u0).astype(np.float32).ravel()
        b = (v - v0).astype(np.float32).ravel()
        base = (self.img_base + v0.astype(np.int64) * self.W + u0.astype(np.int64)).ravel()
        k = 6 if grad else 4  # side of the interpolated grid
        win = np.take(self.flat, (self.off_grad if grad else self.off_val) + base)
        win = win.reshape(k + 1, k + 1, -1)  # [wx, wy, edge]
        ia, ib = 1.0 - a, 1.0 - b
        val = (ia * ib) * win[:k, :k]  # bilinear, shared weights of the patch
        val += (a * ib) * win[1:, :k]
        val += (ia * b) * win[:k, 1:]
        val += (a * b) * win[1:, 1:]
        val4 = val.reshape(k, k, n, N)
        e = np.subtract(self.meas, val4[1:-1, 1:-1] if grad else val4).reshape(16, -1)
        s = np.einsum("km,km->m", e, e)
        s[~ok.ravel()] = 0.0
        d = self.delta
        lin = s <= d * d
        r = np.sqrt(np.where(lin, 1.0, s))
        chi2 = float(np.where(lin, s, 2.0 * d * r - d * d).sum())
        if not grad:
            return chi2, None
        wgt = np.where(lin, 1.0, d / r) * ok.ravel()
        g = np.empty((2, 4, 4, n * N), dtype=np.float32)  # central differences, float32
        np.subtract(val[2:, 1:-1], val[:-2, 1:-1], out=g[0])
        np.subtract(val[1:-1, 2:], val[1:-1, :-2], out=g[1])
        g *= 0.5
        gu, gv = g.astype(np.float64).reshape(2, 16, -1)
        A = np.einsum("km,km->m", gu, gu) * wgt
        B = np.einsum("km,km->m", gu, gv) * wgt
        C = np.einsum("km,km->m", gv, gv) * wgt
        ru = np.einsum("km,km->m", gu, e) * wgt
        rv = np.einsum("km,km->m", gv, e) * wgt
        return chi2, (P, ok, iz, A, B, C, ru, rv)

    # --- normal equations --------------------------------------------------------------------

    def assemble(self, R, edges):
        """Pose block ``U`` (36×36), its gradient, point blocks ``V`` (3, 3, N), their gradient
        (3, N) and the pose–point blocks ``W`` (36, 3, N), all in ``[ω, υ]`` order."""
        n, N = self.n, self.N
        P, ok, iz, A, B, C, ru, rv = edges
        shape = (n, N)
        al = (self.fx * iz).reshape(shape)  # D = [[α, 0, −αx], [0, β, −βy]]
        be = (self.fy * iz).reshape(shape)
        x = np.where(ok, P[:, 0] * iz, 0.0)
        y = np.where(ok, P[:, 1] * iz, 0.0)
        a2 = A.reshape(shape) * al * al
        ab = B.reshape(shape) * al * be
        b2 = C.reshape(shape) * be * be
        qu = ru.reshape(shape) * al
        qv = rv.reshape(shape) * be
        # Q = DᵀMD and q = Dᵀr in the camera frame, laid out KQ[j, d, a, i] with the rows
        # a = 0..2 of K = [P]× Q, a = 3..5 of Q and a = 6 of q (d: the column).
        q02 = -(x * a2 + y * ab)
        q12 = -(x * ab + y * b2)
        q22 = -(x * q02 + y * q12)
        KQ = np.empty((n, 3, 7, N))  # row 6: q
        KQ[:, 0, 3], KQ[:, 0, 4], KQ[:, 0, 5] = a2, ab, q02
        KQ[:, 1, 3], KQ[:, 1, 4], KQ[:, 1, 5] = ab, b2, q12
        KQ[:, 2, 3], KQ[:, 2, 4], KQ[:, 2, 5] = q02, q12, q22
        KQ[:, 0, 6], KQ[:, 1, 6], KQ[:, 2, 6] = qu, qv, -(x * qu + y * qv)
        pc = (P[:, 0:1], P[:, 1:2], P[:, 2:3])
        KQ[:, :, 0:3] = np.swapaxes(_cross(pc, KQ[:, :, 3:6]), 1, 2)  # K = [P]× Q (Q symmetric)
        # Σ_i [P, 1] ⊗ (K, Q, q): one gemm per image gives U = Σ SᵀQS and Σ Sᵀq.
        P1 = np.concatenate([P, np.ones((n, 1, N))], axis=1)
        F = np.matmul(P1, KQ.reshape(n, 21, N).transpose(0, 2, 1)).reshape(n, 4, 3, 7)
        # F[j, e, d, a] = Σ_i P_e KQ[d, a]; e = 3: Σ_i KQ[d, a]
        cols_w = np.stack([F[:, 1, 2] - F[:, 2, 1], F[:, 2, 0] - F[:, 0, 2],
                           F[:, 0, 1] - F[:, 1, 0]], axis=1)  # Σ P × KQ[:, a] → (n, 3, 7)
        U = np.concatenate([cols_w[:, :, :6], F[:, 3, :, :6]], axis=1)  # [col, row]
        grad_p = np.concatenate([cols_w[:, :, 6], F[:, 3, :, 6]], axis=1)  # Σ Sᵀq (n, 6)
        # Pose–point blocks [K; Q] R_j and point blocks Σ_j RᵀQR, point gradient Σ_j Rᵀq.
        Rt = np.swapaxes(R, 1, 2)
        Wb = np.matmul(Rt, KQ[:, :, :6].reshape(n, 3, 6 * N)).reshape(n, 3, 6, N)  # [j, b, a, i]
        V = np.matmul(Rt[:, None], Wb[:, :, 3:6]).sum(axis=0)  # [b, c, i]
        bp = np.matmul(Rt, KQ[:, :, 6]).sum(axis=0)  # (3, N)
        f = slice(1, n)  # free poses
        Uf = sla.block_diag(*[(U[j] + U[j].T) * 0.5 for j in range(1, n)])
        Wf = np.ascontiguousarray(Wb[f].transpose(0, 2, 1, 3)).reshape(6 * (n - 1), 3, N)
        return Uf, grad_p[f].ravel(), V, bp, Wf

    def solve(self, system, lam):
        """``(H + λI) Δ = b`` by the Schur complement over the points."""
        U, bu, V, bp, W = system
        with np.errstate(invalid="ignore", divide="ignore"):
            return self._solve(U, bu, V, bp, W, lam)

    @staticmethod
    def _solve(U, bu, V, bp, W, lam):
        # Closed-form Cholesky of every V + λI and the entries of L⁻¹.
        l00 = np.sqrt(V[0, 0] + lam)
        l10 = V[0, 1] / l00
        l20 = V[0, 2] / l00
        l11 = np.sqrt(V[1, 1] + lam - l10 * l10)
        l21 = (V[1, 2] - l20 * l10) / l11
        l22 = np.sqrt(V[2, 2] + lam - l20 * l20 - l21 * l21)
        m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
        m10 = -l10 * m00 * m11
        m21 = -l21 * m11 * m22
        m20 = -(l20 * m00 + l21 * m10) * m22
        if not np.isfinite(m20.sum() + m22.sum()):
            raise np.linalg.LinAlgError("a point block is not positive definite")
        # X = W L⁻ᵀ, y = L⁻¹ b_p
        X = np.empty_like(W)
        np.multiply(W[:, 0], m00, out=X[:, 0])
        np.multiply(W[:, 0], m10, out=X[:, 1])
        X[:, 1] += W[:, 1] * m11
        np.multiply(W[:, 0], m20, out=X[:, 2])
        X[:, 2] += W[:, 1] * m21
        X[:, 2] += W[:, 2] * m22
        y = np.stack([bp[0] * m00, bp[0] * m10 + bp[1] * m11,
                      bp[0] * m20 + bp[1] * m21 + bp[2] * m22])
        X2 = X.reshape(len(W), -1)
        S = U - X2 @ X2.T
        S[np.diag_indices_from(S)] += lam
        du = sla.cho_solve(sla.cho_factor(S, lower=True, check_finite=False),
                           bu - X2 @ y.ravel(), check_finite=False)
        z = y - (du @ X2).reshape(3, -1)
        dp = np.stack([z[0] * m00 + z[1] * m10 + z[2] * m20, z[1] * m11 + z[2] * m21, z[2] * m22])
        return du, dp

    # --- Levenberg–Marquardt -----------------------------------------------------------------

    def iterate(self) -> float:
        """One LM iteration (g2o's rules); returns the chi2 after it."""
        if self.cache is None or self.cache[1] is None:
            self.cache = self.evaluate(self.R, self.t, self.p, True)
        chi, edges = self.cache
        system = self.assemble(self.R, edges)
        U, bu, V, bp, _ = system
        if self.lam <= 0.0:
            vmax = max(V[0, 0].max(), V[1, 1].max(), V[2, 2].max())
            self.lam = self.tau * max(float(np.diag(U).max()), float(vmax), 1e-12)
            self.nu = 2.0
        for trial in range(1, self.max_trials + 1):
            try:
                du, dp = self.solve(system, self.lam)
            except np.linalg.LinAlgError:
                self.lam *= self.nu
                self.nu *= 2.0
                continue
            dR, dt = _se3_exp(du.reshape(-1, 6))
            R, t = self.R.copy(), self.t.copy()
            R[1:] = dR @ self.R[1:]
            t[1:] = np.einsum("nij,nj->ni", dR, self.t[1:]) + dt
            p = self.p + dp
            new = self.evaluate(R, t, p, self.trial_grad)
            scale = du @ (self.lam * du + bu) + float(np.vdot(dp, self.lam * dp + bp)) + 1e-3
            rho = (chi - new[0]) / scale
            if rho > 0 and math.isfinite(new[0]):
                self.R, self.t, self.p = R, t, p
                self.cache = new if self.trial_grad else None
                self.lam *= max(1.0 / 3.0, min(2.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
                self.nu = 2.0
                self.trial_grad = True
                self.trials.append(trial)
                return new[0]
            self.trial_grad = False
            self.lam *= self.nu
            self.nu *= 2.0
        self.trials.append(self.max_trials)
        return chi

    def chi2(self) -> float:
        """Robust chi2 at the current state."""
        if self.cache is None:
            self.cache = self.evaluate(self.R, self.t, self.p, True)
        return self.cache[0]

    def run(self, iterations: int) -> list[float]:
        """``iterations`` LM iterations; the chi2 after each."""
        self.chi2()
        return [self.iterate() for _ in range(iterations)]


def load(data_dir):
    """The task's data through graphopt's loader (outside any timing)."""
    from graphopt.io.directba import load_directba

    return load_directba(str(data_dir))


def from_data(data) -> NumpyDirectBA:
    """A fresh peer at the data's initial estimates."""
    return NumpyDirectBA(data.images, data.intrinsics, data.poses, data.points, data.patches)


def time_iterations(data, iterations: int) -> float:
    """Seconds per LM iteration: a fresh problem, one warm-up iteration, then ``iterations``
    timed (what ``bench_direct_ba.py`` does with graphopt's optimizer)."""
    peer = from_data(data)
    peer.run(1)
    t0 = time.perf_counter()
    peer.run(iterations)
    return (time.perf_counter() - t0) / iterations


def check(data, counts: list[int]) -> bool:
    """Chi2 of the peer against graphopt's from the same start; prints a table."""
    import graphopt
    from graphopt.apps.direct_ba_problem import build_problem
    from graphopt.types.vertices import VertexPointXYZ, VertexSE3Expmap

    prob = build_problem(data, "xyz", "huber", 0.5, "cholmod", "lm")
    opt = prob.optimizer
    opt.stopping = graphopt.StoppingConfig.iterations_only()
    opt.compute_active_errors()
    g0 = opt.active_robust_chi2()
    peer = from_data(data)
    c0 = peer.chi2()
    rel0 = abs(c0 - g0) / g0
    ok = rel0 <= 1e-9
    print(f"initial chi2: numpy {c0:.10e}  graphopt {g0:.10e}  rel. diff {rel0:.1e}"
          f"  {'ok' if rel0 <= 1e-9 else 'FAIL'} (tol 1e-9)")
    n = max(counts)
    res = opt.optimize(n)
    chis = peer.run(n)
    print(f"{'iter':>4} {'numpy chi2':>20} {'graphopt chi2':>20} {'rel. diff':>10} "
          f"{'trials numpy/graphopt':>22}")
    for k, (c, info) in enumerate(zip(chis, res.info, strict=False), start=1):
        rel = abs(c - info.chi2) / info.chi2
        flip = peer.trials[k - 1] != info.trials
        if k in counts:
            ok &= rel <= 1e-6 and not flip
        mark = " *" if k in counts else ""
        print(f"{k:>4} {c:>20.10e} {info.chi2:>20.10e} {rel:>10.1e} "
              f"{peer.trials[k - 1]:>11}/{info.trials:<10}{' FLIP' if flip else ''}{mark}")
    if len(res.info) < n:
        print(f"graphopt stopped after {len(res.info)} iterations ({res.stop_reason})")
        ok = False
    poses = opt.estimates_of(VertexSE3Expmap)
    points = opt.estimates_of(VertexPointXYZ)
    dt = np.abs(poses[:, :3, 3] - peer.t).max()
    dr = np.abs(poses[:, :3, :3] - peer.R).max()
    dp = np.abs(points - peer.p.T).max()
    print(f"after {n}: max |Δt| {dt:.1e}, max |ΔR| {dr:.1e}, max |Δp| {dp:.1e} "
          f"(pose translations up to {np.abs(peer.t).max():.2f}, points up to "
          f"{np.abs(peer.p).max():.2f})")
    print("check:", "ok" if ok else "FAILED", f"(chi2 within 1e-6 after {counts})")
    return ok


def main(argv: list[str] | None = None) -> int:
    """Check against graphopt and/or time the peer.

    Args:
        argv: Command-line arguments.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--check", action="store_true",
                    help="compare the chi2 with graphopt's from the same start")
    ap.add_argument("--check-iterations", default="1,2,5",
                    help="iteration counts whose chi2 must match (comma-separated)")
    ap.add_argument("--iterations", type=int, default=10, help="timed iterations per repeat")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats (0: no timing)")
    args = ap.parse_args(argv)
    if not Path(args.data).is_dir():
        print(f"numpy_direct_ba: data folder not found: {args.data}", file=sys.stderr)
        return 1
    data = load(args.data)
    ok = True
    if args.check:
        ok = check(data, sorted({int(c) for c in args.check_iterations.split(",")}))
    if args.repeats > 0:
        times = [time_iterations(data, args.iterations) for _ in range(args.repeats)]
        print(f"numpy peer: {np.median(times):.4f} s per LM iteration (median of "
              f"{args.repeats} × {args.iterations} iterations, one thread)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
