"""2D SLAM types after g2o's ``types/slam2d``: the SE(2) pose, the 2D point, odometry/loop
edges, point observations and a pose prior, with analytic Jacobians.

Conventions (g2o's, so that chi2 values agree with g2o's):

* A pose is ``(x, y, θ)``; composition ``a·b = (t_a + R(θ_a) t_b, θ_a + θ_b)`` and inverse
  ``(−R(−θ) t, −θ)`` (g2o's ``SE2``), angles wrapped with :func:`normalize_theta`.
* :class:`VertexSE2` updates additively, ``(x + δx, y + δy, normalize(θ + δθ))`` (g2o's
  ``VertexSE2::oplusImpl``): the increment's translation is in the *world* frame.
* Errors: ``EdgeSE2`` ``t2v(Z⁻¹·(Xi⁻¹·Xj))``, ``EdgeSE2PointXY`` ``Xi⁻¹·p − z`` (the point in
  the pose's frame), ``EdgeSE2Prior`` ``t2v(Z⁻¹·X)``; the angle of an error is wrapped.

Every function works on all edges of a type at once on columns of ``(m, 3)`` arrays
(element-wise arithmetic: no per-edge 2x2 matrix products). In the optimizer the trigonometry
is not per edge: the poses' ``cos θ``/``sin θ`` come once per state from
:meth:`VertexSE2.derived`, a relative pose's from ``EdgeSE2.measurement_derived`` once, and
``cos(θ_i + θ_z)`` by the angle sum; called alone, the edges compute them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from graphopt.edge import BaseEdge, EdgeContext, Linearization
from graphopt.vertex import BaseVertex, VertexVector

__all__ = [
    "EdgeFromParts",
    "EdgeSE2",
    "EdgeSE2PointXY",
    "EdgeSE2Prior",
    "VertexPointXY",
    "VertexSE2",
    "normalize_theta",
]

_TWO_PI = 2.0 * np.pi


def normalize_theta(theta: np.ndarray) -> np.ndarray:
    """Wrap angles into ``(−π, π]`` exactly as g2o's ``normalize_theta`` does
    (``fmod(θ + π, 2π)``, then ``+π`` if ``≤ 0`` else ``−π``).

    Args:
        theta: Angles (any shape), radians.

    Returns:
        The wrapped angles, same shape.
    """
    r = np.fmod(theta + np.pi, _TWO_PI)
    return r - np.pi + (r <= 0.0) * _TWO_PI


class VertexSE2(BaseVertex):
    """A 2D pose ``[x, y, θ]`` (g2o's ``VertexSE2``).

    Estimate layout: ``(n, 3)`` rows ``[x, y, θ]`` (θ in radians; wrapped to ``(−π, π]`` by
    every update, taken as given from files, as g2o does).

    Update (g2o's): ``[x + δx, y + δy, normalize_theta(θ + δθ)]``, ``δ`` ``(n, 3)``.

    Args:
        id: Vertex id.
        estimate: ``(3,)`` pose.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 3
    estimate_shape: ClassVar[tuple[int, ...]] = (3,)

    @classmethod
    def derived(cls, estimates: np.ndarray) -> np.ndarray:
        """``[cos θ, sin θ]`` per pose ``(n, 2)``: the edges read them per edge instead of
        taking a cosine and a sine per edge (a pose has about 13 edges in w10000).

        Args:
            estimates: ``(n, 3)`` poses.
        """
        theta = estimates[:, 2]
        return np.column_stack([np.cos(theta), np.sin(theta)])

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """Additive update with the angle wrapped.

        Args:
            estimates: ``(n, 3)`` poses.
            deltas: ``(n, 3)`` increments ``[δx, δy, δθ]``.

        Returns:
            ``(n, 3)`` updated poses.
        """
        out = estimates + deltas
        out[:, 2] = normalize_theta(out[:, 2])
        return out


class VertexPointXY(VertexVector):
    """A 2D point ``[x, y]`` in the world frame (g2o's ``VertexPointXY``); the update is
    addition.

    Estimate layout: ``(n, 2)``.

    Args:
        id: Vertex id.
        estimate: ``(2,)`` point.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 2


def _pose_frame(
    xi: np.ndarray, p: np.ndarray, extra_angle: np.ndarray | None = None,
    cs: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``R(−a)(p − t_i)`` with ``a = θ_i (+ extra_angle)``, column-wise.

    Args:
        xi: ``(m, 3)`` poses.
        p: ``(m, 2+)`` points (their first two columns).
        extra_angle: Added to ``θ_i``.
        cs: ``(cos a, sin a)`` when the caller has them (then ``extra_angle`` is not read).

    Returns:
        ``(u, v, c, s)``: the rotated difference, ``cos a`` and ``sin a``, each ``(m,)``.
    """
    if cs is not None:
        c, s = cs
    else:
        a = xi[:, 2] if extra_angle is None else xi[:, 2] + extra_angle
        c, s = np.cos(a), np.sin(a)
    dx = p[:, 0] - xi[:, 0]
    dy = p[:, 1] - xi[:, 1]
    return c * dx + s * dy, c * dy - s * dx, c, s


def _pose_entries(c: np.ndarray, s: np.ndarray, u: np.ndarray, v: np.ndarray
                  ) -> tuple[np.ndarray, ...]:
    """The first two rows of ``∂(R(−a)(p − t_i))/∂x_i``, row-major: ``[−c, −s, v]`` and
    ``[s, −c, −u]`` (``c·d_y − s·d_x`` and ``−s·d_y − c·d_x`` are the rotated difference's
    ``v`` and ``−u``)."""
    nc = np.negative(c)
    return nc, np.negative(s), v, s, nc, np.negative(u)


def _rows(rows: int, *entries: np.ndarray | float | None) -> np.ndarray:
    """Per-edge matrices ``(m, rows, len(entries) // rows)`` from their entries, row-major
    (``None`` for a zero): one zeroed allocation, the non-zero columns written into it."""
    m = next(len(e) for e in entries if isinstance(e, np.ndarray))
    out = np.zeros((m, len(entries)))
    for k, e in enumerate(entries):
        if e is not None:
            out[:, k] = e
    return out.reshape(m, rows, len(entries) // rows)


def _rotate_back(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R(−θ_z) t_z`` for ``(m, 3)`` measurements ``[x, y, θ]``: the translation part of
    ``−Z⁻¹``."""
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    return cz * z[:, 0] + sz * z[:, 1], cz * z[:, 1] - sz * z[:, 0]


def _sensor_pose(X: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sensor poses ``X·L`` ``(m, 3)`` of poses ``X`` with sensor offsets ``L`` ``(m, 3)``,
    and ``R(θ_X) t_L`` ``(m, 2)`` (whose perpendicular is the derivative of the sensor position
    by ``θ_X``: :func:`_by_pose`)."""
    c, s = np.cos(X[:, 2]), np.sin(X[:, 2])
    rt = np.column_stack([c * L[:, 0] - s * L[:, 1], s * L[:, 0] + c * L[:, 1]])
    return np.column_stack([X[:, :2] + rt, normalize_theta(X[:, 2] + L[:, 2])]), rt


def _by_pose(J: np.ndarray, rt: np.ndarray) -> np.ndarray:
    """``J·∂(X·L)/∂X`` ``(m, r, 3)`` for the additive update: the sensor's position turns with
    ``θ_X`` (``∂t_S/∂θ = [−(R t_L)_y, (R t_L)_x]``, ``rt`` from :func:`_sensor_pose`)."""
    out = J.copy()
    out[:, :, 2] += -J[:, :, 0] * rt[:, None, 1] + J[:, :, 1] * rt[:, None, 0]
    return out


def _by_offset(J: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``J·∂(X·L)/∂L = J·diag(R(θ_X), 1)`` ``(m, r, 3)``."""
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    out = J.copy()
    out[:, :, 0] = J[:, :, 0] * c + J[:, :, 1] * s
    out[:, :, 1] = -J[:, :, 0] * s + J[:, :, 1] * c
    return out


class EdgeFromParts(BaseEdge):
    """Base of the SLAM edge types: ``error`` and ``linearize`` share one batched computation,
    :meth:`_parts`, which returns the ``(m, dimension)`` errors first and then what the
    Jacobians need. Subclasses implement ``_parts`` and ``linearize``.
    """

    # Their Jacobians cost a third more than their errors, and LM with GTSAM's schedule (the
    # pose graphs' default) accepts nearly every step: a trial that linearises spares the next
    # linearisation its errors (w10000: 3.7 ms an iteration of about 70).
    linearize_on_trial: ClassVar[bool] = True

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        raise NotImplementedError

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """Errors of all edges (the first result of :meth:`_parts`).

        Args:
            x: One ``(m, *estimate_shape)`` array per vertex position.
            measurement: ``(m, *measurement_shape)`` measurements.
            ctx: ``ctx.params`` for the types that take a parameter.

        Returns:
            ``(m, dimension)`` errors.
        """
        return cls._parts(x, measurement, ctx)[0]


class EdgeSE2(EdgeFromParts):
    """Relative pose between two :class:`VertexSE2` (g2o's ``EdgeSE2``).

    Error ``e = t2v(Z⁻¹·(Xi⁻¹·Xj))`` ``(m, 3)``, i.e. with ``a = θ_i + θ_z``:
    ``e_xy = R(−a)(t_j − t_i) − R(−θ_z) t_z`` and ``e_θ = normalize(θ_j − θ_i − θ_z)``.

    Jacobians (g2o's ``linearizeOplus``, for the additive update): with ``c, s = cos a, sin a``
    and ``d = t_j − t_i``, ``∂e/∂x_j = [[c, s, 0], [−s, c, 0], [0, 0, 1]]`` and
    ``∂e/∂x_i = [[−c, −s, c·d_y − s·d_x], [s, −c, −s·d_y − c·d_x], [0, 0, −1]]``.

    Args:
        vertices: ``(from, to)`` vertices or ids.
        measurement: ``(3,)`` ``[x, y, θ]`` of ``to`` in the frame of ``from``.
        information: ``(3, 3)`` information matrix.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexSE2)
    uses_derived: ClassVar[bool] = True

    @classmethod
    def measurement_derived(cls, measurements: np.ndarray) -> np.ndarray:
        """``[cos θ_z, sin θ_z, R(−θ_z) t_z]`` per edge ``(m, 4)``: the measurement's part of
        every error, computed once (w10000: 1.3 ms of each 5.6 ms linearisation).

        Args:
            measurements: ``(m, 3)`` relative poses.
        """
        zx, zy = _rotate_back(measurements)
        return np.column_stack([np.cos(measurements[:, 2]), np.sin(measurements[:, 2]), zx, zy])

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        xi, xj = x
        if ctx.measured is not None and ctx.derived is not None and ctx.derived[0] is not None:
            # cos/sin of θ_i + θ_z by the angle sum, from the pose's and the measurement's
            ci, si = ctx.derived[0][:, 0], ctx.derived[0][:, 1]
            m = ctx.measured
            cz, sz = m[:, 0], m[:, 1]
            cs = (ci * cz - si * sz, si * cz + ci * sz)
            u, v, c, s = _pose_frame(xi, xj, cs=cs)
            zx, zy = m[:, 2], m[:, 3]
        else:
            u, v, c, s = _pose_frame(xi, xj, z[:, 2])
            zx, zy = _rotate_back(z)
        e = np.empty((len(z), 3), like=u)  # like=: jets stay jets (graphopt.autodiff)
        np.subtract(u, zx, out=e[:, 0])
        np.subtract(v, zy, out=e[:, 1])
        e[:, 2] = normalize_theta(xj[:, 2] - xi[:, 2] - z[:, 2])
        return e, c, s, u, v

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(Xi (m, 3), Xj (m, 3))`` poses.
            measurement: ``(m, 3)`` relative poses.
            ctx: ``derived`` (the poses' cos/sin) and ``measured`` when the optimizer has them;
                the result is the same without.

        Returns:
            ``(e (m, 3), (J_i (m, 3, 3), J_j (m, 3, 3)))``.
        """
        e, c, s, u, v = cls._parts(x, measurement, ctx)
        Ji = _rows(3, *_pose_entries(c, s, u, v), None, None, -1.0)
        Jj = _rows(3, c, s, None, -s, c, None, None, None, 1.0)
        return Linearization(e, (Ji, Jj))


class EdgeSE2PointXY(EdgeFromParts):
    """A 2D point observed from a pose, in the pose's frame (g2o's ``EdgeSE2PointXY``).

    Error ``e = Xi⁻¹·p − z = R(−θ_i)(p − t_i) − z`` ``(m, 2)``. Jacobians, with
    ``c, s = cos θ_i, sin θ_i`` and ``d = p − t_i``:
    ``∂e/∂x_i = [[−c, −s, c·d_y − s·d_x], [s, −c, −s·d_y − c·d_x]]``,
    ``∂e/∂p = [[c, s], [−s, c]]``.

    Args:
        vertices: ``(pose, point)`` vertices or ids.
        measurement: ``(2,)`` the point in the pose's frame.
        information: ``(2, 2)`` information matrix.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 2
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2, VertexPointXY)
    uses_derived: ClassVar[bool] = True

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        d = ctx.derived[0] if ctx.derived is not None else None
        u, v, c, s = _pose_frame(x[0], x[1], cs=None if d is None else (d[:, 0], d[:, 1]))
        e = np.empty((len(z), 2), like=u)
        np.subtract(u, z[:, 0], out=e[:, 0])
        np.subtract(v, z[:, 1], out=e[:, 1])
        return e, c, s, u, v

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and analytic Jacobians.

        Args:
            x: ``(poses (m, 3), points (m, 2))``.
            measurement: ``(m, 2)`` points in the pose frames.
            ctx: ``derived`` (the poses' cos/sin) when the optimizer has it; the result is the
                same without.

        Returns:
            ``(e (m, 2), (J_pose (m, 2, 3), J_point (m, 2, 2)))``.
        """
        e, c, s, u, v = cls._parts(x, measurement, ctx)
        return Linearization(e, (_rows(2, *_pose_entries(c, s, u, v)), _rows(2, c, s, -s, c)))


class EdgeSE2Prior(EdgeFromParts):
    """A prior on a pose (g2o's ``EdgeSE2Prior``).

    Error ``e = t2v(Z⁻¹·X)`` ``(m, 3)``: ``e_xy = R(−θ_z)(t − t_z)``,
    ``e_θ = normalize(θ − θ_z)``. Jacobian ``[[R(−θ_z), 0], [0, 1]]``.

    Args:
        vertices: ``(pose,)`` vertex or id.
        measurement: ``(3,)`` the prior pose ``[x, y, θ]``.
        information: ``(3, 3)`` information matrix.
        robust_kernel: Optional robust kernel.
    """

    dimension: ClassVar[int] = 3
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = (VertexSE2,)

    @classmethod
    def _parts(
        cls, x: Sequence[np.ndarray], z: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        u, v, c, s = _pose_frame(z, x[0])
        e = np.empty((len(z), 3), like=u)
        e[:, 0] = u
        e[:, 1] = v
        e[:, 2] = normalize_theta(x[0][:, 2] - z[:, 2])
        return e, c, s

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and the analytic Jacobian.

        Args:
            x: ``(poses (m, 3),)``.
            measurement: ``(m, 3)`` prior poses.
            ctx: Unused.

        Returns:
            ``(e (m, 3), (J (m, 3, 3),))``.
        """
        e, c, s = cls._parts(x, measurement, ctx)
        return Linearization(e, (_rows(3, c, s, None, -s, c, None, None, None, 1.0),))
