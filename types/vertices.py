"""Vertex types for bundle adjustment: SE(3) poses and 3D points (Euclidean, inverse depth)."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from graphopt.lie import se3_exp_left
from graphopt.vertex import BaseVertex, VertexVector

_I3 = np.eye(3)
_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])  # a homogeneous transform's last row


def _valid_one(v: list[float]) -> bool:
    """:meth:`VertexSE3Expmap.validate` of one ``(4, 4)`` transform given row by row."""
    if not all(math.isfinite(x) for x in v):
        return False
    r0, r1, r2 = v[0:3], v[4:7], v[8:11]
    for i, a in enumerate((r0, r1, r2)):  # R Rᵀ = I to 1e-6, entry by entry
        for j, b in enumerate((r0, r1, r2)):
            if abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] - (i == j)) >= 1e-6:
                return False
    det = (r0[0] * (r1[1] * r2[2] - r1[2] * r2[1]) - r0[1] * (r1[0] * r2[2] - r1[2] * r2[0])
           + r0[2] * (r1[0] * r2[1] - r1[1] * r2[0]))
    return det > 0 and max(abs(v[12]), abs(v[13]), abs(v[14]), abs(v[15] - 1.0)) < 1e-12


class VertexSE3Expmap(BaseVertex):
    """A rigid transform ``T`` (world to camera, ``T_cw``) as a ``(4, 4)`` homogeneous matrix.

    Update (g2o's SE3Expmap): ``T ← exp(δ) · T`` with ``δ = [ω, υ]`` — rotation first, then
    translation — and ``exp`` the SE(3) exponential (:func:`graphopt.types.lie.se3_exp`).

    Args:
        id: Vertex id.
        estimate: ``(4, 4)`` rigid transform.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 6
    estimate_shape: ClassVar[tuple[int, ...]] = (4, 4)

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """``exp(δ) · T`` for all poses.

        Args:
            estimates: ``(n, 4, 4)`` transforms.
            deltas: ``(n, 6)`` twists ``[ω, υ]``.
        """
        return se3_exp_left(deltas, estimates)

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Finite, bottom row ``[0, 0, 0, 1]`` and an orthonormal rotation block (1e-6).

        Args:
            estimates: ``(n, 4, 4)`` transforms.
        """
        if len(estimates) == 1 and type(estimates) is np.ndarray:
            # One pose (a motion-only BA resets it every round): Python floats, 2 µs not 11.
            return np.array([_valid_one(estimates[0].ravel().tolist())])
        ok = super().validate(estimates)
        R = estimates[:, :3, :3]
        if not ok.all():  # non-finite rotations checked as the identity (ok is False there)
            R = np.where(ok[:, None, None], R, _I3)
        # Few numpy calls: a motion-only BA checks its pose at every round's set_estimate.
        G = np.matmul(R, np.swapaxes(R, 1, 2))
        G -= _I3
        orth = np.abs(G, out=G).reshape(len(R), 9).max(axis=1, initial=0.0) < 1e-6
        det = np.linalg.det(R) > 0
        bottom = np.abs(estimates[:, 3] - _BOTTOM).max(axis=1, initial=0.0) < 1e-12
        return ok & orth & det & bottom


class VertexPointXYZ(VertexVector):
    """A 3D point ``[x, y, z]`` in the world frame; the update is addition.

    Args:
        id: Vertex id.
        estimate: ``(3,)`` point.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 3


class VertexPointInverseDepth(VertexVector):
    """A 3D point by inverse depth in an anchor camera: ``[a, b, ρ]``.

    The point in the anchor camera's frame is ``[a, b, 1] / ρ`` (``a, b`` are normalised image
    coordinates, ``ρ = 1/z``); in the world it is ``T_aw⁻¹ · [a, b, 1]/ρ``. The anchor pose is
    the first vertex of the edges that observe the point. The update is addition.

    Args:
        id: Vertex id.
        estimate: ``(3,)`` ``[a, b, ρ]``.
        fixed: Hold constant.
        marginalized: Eliminate by the Schur complement.
    """

    dimension: ClassVar[int] = 3

    @classmethod
    def validate(cls, estimates: np.ndarray) -> np.ndarray:
        """Finite with ``ρ > 0``.

        Args:
            estimates: ``(n, 3)``.
        """
        return super().validate(estimates) & (estimates[:, 2] > 0)
