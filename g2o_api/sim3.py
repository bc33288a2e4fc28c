"""g2o's ``Sim3`` (a similarity ``p ↦ s R p + t``) and its exponential and logarithm in g2o's
``[ω, υ, σ]`` order (``types/sim3/sim3.h``)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from graphopt.lie import hat, so3_exp, so3_log
from graphopt.types.isometry3 import matrix_to_quat, quat_to_matrix

from .rotations import Quaternion, _rotation, vector

__all__ = ["Sim3", "sim3_exp", "sim3_log"]

_EPS = 1e-5


def _w_matrix(omega: np.ndarray, sigma: float) -> np.ndarray:
    """g2o's ``W = A Ω + B Ω² + c I`` of a Sim3 twist (maps ``υ`` to the translation)."""
    theta = float(np.linalg.norm(omega))
    Om = hat(omega[None])[0]
    s = math.exp(sigma)
    if abs(sigma) < _EPS:
        c = 1.0
        if theta < _EPS:
            A, B = 0.5, 1.0 / 6.0
        else:
            A = (1 - math.cos(theta)) / theta**2
            B = (theta - math.sin(theta)) / theta**3
    else:
        c = (s - 1) / sigma
        if theta < _EPS:
            A = ((sigma - 1) * s + 1) / sigma**2
            B = ((0.5 * sigma**2 - sigma + 1) * s - 1) / sigma**3
        else:
            a, b = s * math.sin(theta), s * math.cos(theta)
            A = (a * sigma + (1 - b) * theta) / (theta * (sigma**2 + theta**2))
            B = (c - ((b - 1) * sigma + a * theta) / (sigma**2 + theta**2)) / theta**2
    return A * Om + B * (Om @ Om) + c * np.eye(3)


def sim3_exp(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` of g2o's ``Sim3(update)``.

    Args:
        v: ``(7,)`` ``[ω, υ, σ]``.
    """
    omega, upsilon, sigma = v[:3], v[3:6], float(v[6])
    return so3_exp(omega[None])[0], _w_matrix(omega, sigma) @ upsilon, math.exp(sigma)


def sim3_log(R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """``[ω, υ, σ]`` with ``sim3_exp`` of it giving ``(R, t, s)``.

    Args:
        R: 3x3 rotation.
        t: ``(3,)`` translation.
        s: Scale (positive).
    """
    sigma = math.log(s)
    omega = so3_log(R[None])[0]
    upsilon = np.linalg.solve(_w_matrix(omega, sigma), t)
    return np.concatenate([omega, upsilon, [sigma]])


class Sim3:
    """g2o's ``Sim3``: ``p ↦ s R p + t``.

    Args:
        args: Nothing (identity), ``(R, t, s)`` with ``R`` a 3x3 matrix or a
            :class:`Quaternion`, or a 7-vector ``[ω, υ, σ]`` (the exponential of g2o's
            ``Sim3(update)``).
    """

    __slots__ = ("_R", "_t", "_s")

    def __init__(self, *args: Any) -> None:
        if not args:
            self._R, self._t, self._s = np.eye(3), np.zeros(3), 1.0
        elif len(args) == 3:
            self._R, self._t = _rotation(args[0]), vector(args[1], 3, "translation")
            self._s = float(args[2])
        elif isinstance(args[0], Sim3):
            self._R, self._t, self._s = args[0]._R.copy(), args[0]._t.copy(), args[0]._s
        else:
            self._R, self._t, self._s = sim3_exp(vector(args[0], 7, "Sim3"))

    @classmethod
    def _of(cls, R: np.ndarray, t: np.ndarray, s: float) -> Sim3:
        obj = cls.__new__(cls)
        obj._R, obj._t, obj._s = R, t, s
        return obj

    def rotation(self) -> Quaternion:
        """The rotation as a quaternion."""
        return Quaternion._of(matrix_to_quat(self._R[None])[0])

    def rotation_matrix(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return self._R.copy()

    def translation(self) -> np.ndarray:
        """The translation."""
        return self._t.copy()

    def scale(self) -> float:
        """The scale ``s``."""
        return self._s

    def matrix(self) -> np.ndarray:
        """``[[sR, t], [0, 0, 0, 1]]``."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self._s * self._R, self._t
        return m

    def inverse(self) -> Sim3:
        """``p ↦ (Rᵀ p − Rᵀ t) / s``."""
        Rt = self._R.T
        return Sim3._of(Rt, -(Rt @ self._t) / self._s, 1.0 / self._s)

    def map(self, p: Any) -> np.ndarray:
        """``s R p + t``.

        Args:
            p: ``(3,)`` point.
        """
        return self._s * (self._R @ vector(p, 3, "point")) + self._t

    def log(self) -> np.ndarray:
        """``[ω, υ, σ]`` (g2o's ``Sim3::log``)."""
        return sim3_log(self._R, self._t, self._s)

    def normalize_rotation(self) -> None:
        """Re-orthonormalise the rotation."""
        self._R = quat_to_matrix(matrix_to_quat(self._R[None]))[0]

    def __mul__(self, other: Any) -> Any:
        if isinstance(other, Sim3):
            return Sim3._of(self._R @ other._R, self._s * (self._R @ other._t) + self._t,
                            self._s * other._s)
        return self.map(other)

    def __repr__(self) -> str:
        return f"Sim3(s={self._s:.6g}, t={self._t.tolist()})"
