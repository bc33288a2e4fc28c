"""Bundle adjustment types for BAL ("Bundle Adjustment in the Large") problems.

BAL's camera has 9 parameters ``[ω (angle-axis), t, f, k1, k2]`` and maps a world point ``X`` to
the image by (Snavely's Bundler model)::

    P  = R(ω) X + t                       # camera frame; the camera looks down −z
    p  = −P_xy / P_z                      # normalised image coordinates
    p' = f (1 + k1 |p|² + k2 |p|⁴) p      # radial distortion and focal length (pixels)

The edge error is ``p' − measurement`` (Ceres' residual). The camera vertex updates the rotation
on the LEFT, ``R ← exp([δω]×) R``, and ``t, f, k1, k2`` additively; the stored angle-axis stays a
minimal 3-vector (``ω ← log(exp(δω) exp(ω))``). The derivation of the Jacobians is in
``docs/bal.md``. Everything is elementwise over ``(m,)`` arrays. The camera type hands its
rotation matrices to the edge as *derived* values (computed once per camera and state, not once
per observation); without them the edge builds ``R`` per edge with
:func:`graphopt.lie.so3_exp` (graphopt's one Rodrigues formula).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.io.bal import BALProblem
from graphopt.lie import so3_exp, so3_log
from graphopt.types.vertices import VertexPointXYZ
from graphopt.vertex import BaseVertex

__all__ = [
    "EdgeBALProjection",
    "VertexCameraBAL",
    "bal_cost",
    "bal_project",
    "count_behind_camera",
    "reprojection_errors",
]


class VertexCameraBAL(BaseVertex):
    """A BAL camera: ``[ω0, ω1, ω2, t0, t1, t2, f, k1, k2]``.

    ``ω`` is the angle-axis of ``R`` (world to camera). Update: ``R ← exp([δ0:3]×) R`` (left
    perturbation, so the rotation's tangent space is the same at every ``R`` — unlike additive
    angle-axis updates, whose Jacobian degrades near θ = π), ``t ← t + δ3:6``, ``f ← f + δ6``,
    ``k1 ← k1 + δ7``, ``k2 ← k2 + δ8``.

    Args:
        id: Vertex id.
        estimate: ``(9,)`` camera parameters.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 9
    estimate_shape: ClassVar[tuple[int, ...]] = (9,)

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """Left SO(3) update of the angle-axis, additive for ``t, f, k1, k2``.

        Args:
            estimates: ``(n, 9)`` cameras.
            deltas: ``(n, 9)`` increments ``[δω, δt, δf, δk1, δk2]``.
        """
        out = estimates + deltas
        out[:, :3] = so3_log(so3_exp(deltas[:, :3]) @ so3_exp(estimates[:, :3]))
        return out

    @classmethod
    def derived(cls, estimates: np.ndarray) -> np.ndarray:
        """Row-major rotation matrices ``R(ω)``, ``(n, 9)``: shared by all of a camera's edges.

        Args:
            estimates: ``(n, 9)`` cameras.
        """
        return _rotation_entries(estimates[:, :3])  # the edge's own formula, once per camera


def _rotation_entries(w: np.ndarray) -> np.ndarray:
    """Row-major entries of ``R = exp([w]×)``, ``(m, 9)`` (a view of :func:`so3_exp`'s result)."""
    return so3_exp(w).reshape(len(w), 9)


def bal_project(
    cameras: np.ndarray, points: np.ndarray, rot: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """BAL projection of ``points[i]`` by ``cameras[i]``.

    Args:
        cameras: ``(m, 9)`` camera parameters.
        points: ``(m, 3)`` world points.
        rot: Optional ``(m, 9)`` row-major rotation matrices of the cameras (else computed).

    Returns:
        ``(uv, Pz)``: ``(m, 2)`` predicted pixels and ``(m,)`` camera-frame z (``Pz > 0`` means
        the point is behind the camera, which looks down −z).
    """
    r = _rotation_entries(cameras[:, :3]) if rot is None else rot
    X0, X1, X2 = points[:, 0], points[:, 1], points[:, 2]
    # The same operations, in the same order, as the edge's linearisation.
    Px = r[:, 0] * X0 + r[:, 1] * X1 + r[:, 2] * X2 + cameras[:, 3]
    Py = r[:, 3] * X0 + r[:, 4] * X1 + r[:, 5] * X2 + cameras[:, 4]
    Pz = r[:, 6] * X0 + r[:, 7] * X1 + r[:, 8] * X2 + cameras[:, 5]
    with np.errstate(divide="ignore", invalid="ignore"):
        niz = -1.0 / Pz  # = −(1/Pz) exactly: px = Px·niz is the linearisation's −Px·iz
    px, py = Px * niz, Py * niz
    r2 = px * px + py * py
    f, k1, k2 = cameras[:, 6], cameras[:, 7], cameras[:, 8]
    fd = f * (1.0 + r2 * (k1 + k2 * r2))
    return np.stack([fd * px, fd * py], axis=1), Pz


def count_behind_camera(
    cameras: np.ndarray, points: np.ndarray, camera_index: np.ndarray, point_index: np.ndarray
) -> int:
    """Number of observations whose point lies behind its camera (``P_z ≥ 0``).

    BAL's model projects such points anyway (through the sign flip of ``−P_xy/P_z``); they are
    counted so that the app can report them, not removed.

    Args:
        cameras: ``(c, 9)`` cameras.
        points: ``(n, 3)`` points.
        camera_index: ``(m,)`` camera of each observation.
        point_index: ``(m,)`` point of each observation.
    """
    _, Pz = bal_project(cameras[camera_index], points[point_index])
    return int(np.count_nonzero(Pz >= 0))


def reprojection_errors(
    problem: BALProblem, cameras: np.ndarray | None = None, points: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals ``p' − z`` of every observation of a BAL problem.

    Args:
        problem: The problem (observations and their camera/point indices).
        cameras: ``(c, 9)`` cameras to evaluate at (``problem.cameras`` if None).
        points: ``(n, 3)`` points to evaluate at (``problem.points`` if None).

    Returns:
        ``(r (m, 2), Pz (m,))``: residuals in pixels and camera-frame z (``Pz ≥ 0``: behind).
    """
    cams = problem.cameras if cameras is None else cameras
    pts = problem.points if points is None else points
    uv, Pz = bal_project(cams[problem.camera_index], pts[problem.point_index])
    return uv - problem.observations, Pz


def bal_cost(problem: BALProblem) -> float:
    """Ceres' cost ``½ Σ ‖r‖²`` of a BAL problem at its own estimates (no robust kernel).

    Args:
        problem: The problem.
    """
    r, _ = reprojection_errors(problem)
    return 0.5 * float(np.einsum("ij,ij->", r, r))


class EdgeBALProjection(BaseEdge):
    """Reprojection error of a world point in a BAL camera: ``e = p'(camera, X) − z``.

    Vertices: ``(VertexCameraBAL, VertexPointXYZ)``. Measurement: ``(2,)`` pixels with BAL's
    conventions (origin at the image centre, y up). Analytic Jacobians ``(m, 2, 9)`` for the
    camera (w.r.t. the left rotation increment, ``t``, ``f``, ``k1``, ``k2``) and ``(m, 2, 3)``
    for the point; see ``docs/bal.md`` for the derivation.

    Args:
        vertices: ``(camera, point)`` vertices or ids.
        measurement: ``(2,)`` observed pixel.
        information: ``(2, 2)`` information matrix (identity by default).
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexCameraBAL, VertexPointXYZ)
    # The Jacobians share the projection with the error; linearising trial points lets an
    # accepted LM step skip the next linearisation (≈ 8 % per iteration on Dubrovnik-16).
    linearize_on_trial: ClassVar[bool] = True
    # The camera's rotation matrix, once per camera (see VertexCameraBAL.derived).
    uses_derived: ClassVar[bool] = True

    #: Edges processed per block: the ~150 elementwise temporaries of one block stay in the CPU
    #: cache, which makes the whole evaluation 2-3x faster than one pass over all edges.
    block_size: ClassVar[int] = 4096

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``p'(camera, X) − z`` for all edges.

        Args:
            x: ``(cameras (m, 9), points (m, 3))``.
            measurement: ``(m, 2)`` observed pixels.
            ctx: ``ctx.derived[0]``, when given, holds each edge's camera rotation ``(m, 9)``.
        """
        cam, X = x
        m = len(cam)
        rot = None if ctx is None or ctx.derived is None else ctx.derived[0]
        if type(cam) is not np.ndarray:  # jets come in blocks already (graphopt.autodiff)
            return bal_project(cam, X, rot)[0] - measurement
        e = np.empty((m, 2))
        bs = cls.block_size
        for s in range(0, m, bs):  # blocks of edges, not a loop per edge
            r = None if rot is None else rot[s : s + bs]
            uv, _ = bal_project(cam[s : s + bs], X[s : s + bs], r)
            np.subtract(uv, measurement[s : s + bs], out=e[s : s + bs])
        return e

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Error and analytic Jacobians sharing the rotation and projection terms.

        Args:
            x: ``(cameras (m, 9), points (m, 3))``.
            measurement: ``(m, 2)`` observed pixels.
            ctx: ``ctx.derived[0]``, when given, holds each edge's camera rotation ``(m, 9)``.

        Returns:
            ``(e (m, 2), (J_camera (m, 2, 9), J_point (m, 2, 3)))``.
        """
        cam, X = x
        m = len(cam)
        rot = None if ctx is None or ctx.derived is None else ctx.derived[0]
        e = np.empty((m, 2))
        Jc = np.empty((m, 2, 9))
        Jp = np.empty((m, 2, 3))
        bs = cls.block_size
        for s in range(0, m, bs):  # blocks of edges, not a loop per edge
            sl = slice(s, s + bs)
            r = _rotation_entries(cam[sl, :3]) if rot is None else rot[sl]
            _linearize_block(cam[sl], r, X[sl], measurement[sl], e[sl], Jc[sl], Jp[sl])
        return Linearization(e, (Jc, Jp))


def _rows(a: np.ndarray) -> np.ndarray:
    """``a.T`` with contiguous rows: a view of Fortran-ordered input (the optimizer gathers 2-D
    estimates that way), a transposed copy otherwise."""
    return a.T if a.strides[0] == a.itemsize else np.ascontiguousarray(a.T)


def _linearize_block(
    cam: np.ndarray,
    rot: np.ndarray,
    X: np.ndarray,
    z: np.ndarray,
    e: np.ndarray,
    Jc: np.ndarray,
    Jp: np.ndarray,
) -> None:
    """Fill ``e``, ``Jc``, ``Jp`` for one block of edges (see ``docs/bal.md``).

    ``rot`` holds each edge's row-major ``R``. Every column used below is read as a contiguous
    array (strided columns make each operation slower).
    """
    c = _rows(cam)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rows(rot)
    X0, X1, X2 = _rows(X)
    Qx = r00 * X0 + r01 * X1 + r02 * X2  # Q = R X
    Qy = r10 * X0 + r11 * X1 + r12 * X2
    Qz = r20 * X0 + r21 * X1 + r22 * X2
    Px, Py, Pz = Qx + c[3], Qy + c[4], Qz + c[5]
    f, k1, k2 = c[6], c[7], c[8]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / Pz
    px, py = -Px * iz, -Py * iz
    r2 = px * px + py * py
    d = 1.0 + r2 * (k1 + k2 * r2)
    fd = f * d
    e[:, 0] = fd * px - z[:, 0]
    e[:, 1] = fd * py - z[:, 1]

    # M = ∂p'/∂p = f (d I + g p pᵀ), g = 2 k1 + 4 k2 r²  (symmetric 2×2).
    fg = f * (2.0 * k1 + 4.0 * k2 * r2)
    fgx = fg * px
    m00 = fd + fgx * px
    m01 = fgx * py
    m11 = fd + fg * py * py
    # A = M ∂p/∂P with ∂p/∂P = (1/Pz) [[−1, 0, −px], [0, −1, −py]].
    niz = -iz
    a00, a01 = m00 * niz, m01 * niz
    a11 = m11 * niz
    a10 = a01
    a02 = a00 * px + a01 * py
    a12 = a10 * px + a11 * py

    # Rotation (left): ∂P/∂δω = −[Q]×, so each row is Q × a_row.
    Jc[:, 0, 0] = Qy * a02 - Qz * a01
    Jc[:, 0, 1] = Qz * a00 - Qx * a02
    Jc[:, 0, 2] = Qx * a01 - Qy * a00
    Jc[:, 1, 0] = Qy * a12 - Qz * a11
    Jc[:, 1, 1] = Qz * a10 - Qx * a12
    Jc[:, 1, 2] = Qx * a11 - Qy * a10
    # Translation: ∂P/∂t = I.
    Jc[:, 0, 3], Jc[:, 0, 4], Jc[:, 0, 5] = a00, a01, a02
    Jc[:, 1, 3], Jc[:, 1, 4], Jc[:, 1, 5] = a10, a11, a12
    # Intrinsics: ∂p'/∂f = d p, ∂p'/∂k1 = f r² p, ∂p'/∂k2 = f r⁴ p.
    fr2 = f * r2
    fr4 = fr2 * r2
    Jc[:, 0, 6], Jc[:, 1, 6] = d * px, d * py
    Jc[:, 0, 7], Jc[:, 1, 7] = fr2 * px, fr2 * py
    Jc[:, 0, 8], Jc[:, 1, 8] = fr4 * px, fr4 * py

    # Point: ∂P/∂X = R, so each row is a_row R.
    Jp[:, 0, 0] = a00 * r00 + a01 * r10 + a02 * r20
    Jp[:, 0, 1] = a00 * r01 + a01 * r11 + a02 * r21
    Jp[:, 0, 2] = a00 * r02 + a01 * r12 + a02 * r22
    Jp[:, 1, 0] = a10 * r00 + a11 * r10 + a12 * r20
    Jp[:, 1, 1] = a10 * r01 + a11 * r11 + a12 * r21
    Jp[:, 1, 2] = a10 * r02 + a11 * r12 + a12 * r22
