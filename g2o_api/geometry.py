"""g2o's geometry classes: ``Quaternion``, ``AngleAxis``, ``Isometry3d``, ``SE3Quat``, ``Sim3``,
``SE2``, with g2o's (Eigen's) conventions.

Conventions a port must keep:

* ``Quaternion(w, x, y, z)`` takes the scalar first (Eigen's constructor), but ``coeffs()`` and
  ``Quaternion(array4)`` use Eigen's storage order ``[x, y, z, w]``.
* ``SE3Quat.to_vector()`` is ``[t, qx, qy, qz, qw]``, ``to_minimal_vector()`` ``[t, qx, qy, qz]``,
  ``log()`` ``[ω, υ]`` (rotation first) and ``exp`` its inverse.
* ``Sim3.log()`` is ``[ω, υ, σ]`` (7 values, ``σ = ln s``); ``Sim3 * p = s R p + t``.

Every constructor accepts lists, tuples, integers and column vectors where the old bindings
did. The objects are plain records (a rotation matrix and a translation): converting thousands
of them to graphopt's arrays is one stacking operation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from graphopt.lie import se3_exp, so3_log
from graphopt.types.isometry3 import matrix_to_quat, quat_to_matrix

from .rotations import Quaternion, _rotation, vector

__all__ = ["Isometry3d", "SE2", "SE3Quat"]


class _RigidBase:
    """Shared by :class:`Isometry3d` and :class:`SE3Quat`: a rotation ``_R`` and translation
    ``_t``."""

    __slots__ = ("_R", "_t")

    @classmethod
    def _of(cls, R: np.ndarray, t: np.ndarray) -> Any:
        obj = cls.__new__(cls)
        obj._R, obj._t = R, t
        return obj

    def _set_common(self, args: tuple[Any, ...]) -> bool:
        """Set from the forms both constructors take: nothing (identity), ``(R, t)`` or another
        rigid transform (copied). ``False`` for a single other argument, left to the subclass.

        Args:
            args: The constructor's arguments.
        """
        if not args:
            self._R, self._t = np.eye(3), np.zeros(3)
        elif len(args) == 2:
            self._R, self._t = _rotation(args[0]), vector(args[1], 3, "translation")
        elif isinstance(args[0], _RigidBase):
            self._R, self._t = args[0]._R.copy(), args[0]._t.copy()
        else:
            return False
        return True

    def rotation_matrix(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return self._R.copy()

    def translation(self) -> np.ndarray:
        """The translation ``(3,)``."""
        return self._t.copy()

    position = translation

    def orientation(self) -> Quaternion:
        """The rotation as a quaternion."""
        return Quaternion._of(matrix_to_quat(self._R[None])[0])

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self._R, self._t
        return m

    to_homogeneous_matrix = matrix

    def set_rotation(self, R: Any) -> None:
        """Replace the rotation.

        Args:
            R: A 3x3 matrix or a :class:`Quaternion`.
        """
        self._R = _rotation(R)

    def set_translation(self, t: Any) -> None:
        """Replace the translation.

        Args:
            t: ``(3,)``.
        """
        self._t = vector(t, 3, "translation")

    def inverse(self) -> Any:
        """The inverse transform."""
        Rt = self._R.T
        return type(self)._of(Rt, -(Rt @ self._t))

    def map(self, p: Any) -> np.ndarray:
        """``R p + t``.

        Args:
            p: ``(3,)`` point.
        """
        return self._R @ vector(p, 3, "point") + self._t

    def __mul__(self, other: Any) -> Any:
        if type(other) is np.ndarray and other.shape == (3,):  # the common case, first
            out = self._R.dot(other)  # (dot: matmul's result, 0.5 us sooner)
            out += self._t  # in place: the same sum without a second array
            return out
        if isinstance(other, _RigidBase):
            return type(self)._of(self._R @ other._R, self._R @ other._t + self._t)
        arr = np.asarray(other, dtype=float)
        if arr.ndim == 2 and arr.shape[0] == 3 and arr.shape[1] != 1:  # 3xN points
            return self._R @ arr + self._t[:, None]
        return self.map(arr)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(t={self._t.tolist()}, q={self.orientation().coeffs()})"


class Isometry3d(_RigidBase):
    """A rigid transform (Eigen's ``Isometry3d``, g2o's ``VertexSE3`` estimate).

    Args:
        args: Nothing (identity), a 4x4 or 3x4 matrix, ``(R, t)`` with ``R`` a 3x3 matrix or a
            :class:`Quaternion`, or another ``Isometry3d``/``SE3Quat``.
    """

    __slots__ = ()

    def __init__(self, *args: Any) -> None:
        if self._set_common(args):
            return
        m = np.array(args[0], dtype=float)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"Isometry3d: expected a 4x4 or 3x4 matrix, got {m.shape}")
        self._R, self._t = m[:3, :3].copy(), m[:3, 3].copy()

    def rotation(self) -> np.ndarray:
        """The 3x3 rotation matrix (Eigen's ``rotation()``)."""
        return self._R.copy()

    def linear(self) -> np.ndarray:
        """The 3x3 linear part."""
        return self._R.copy()

    @property
    def R(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return self._R.copy()

    @property
    def t(self) -> np.ndarray:
        """The translation."""
        return self._t.copy()

    @property
    def Quaternion(self) -> Quaternion:  # noqa: N802 - g2o's attribute name
        """The rotation as a quaternion."""
        return self.orientation()

    def set_identity(self) -> None:
        """Make this the identity."""
        self._R, self._t = np.eye(3), np.zeros(3)

    @staticmethod
    def identity() -> Isometry3d:
        """The identity transform."""
        return Isometry3d()


class SE3Quat(_RigidBase):
    """g2o's ``SE3Quat``: a rigid transform stored as a rotation and a translation.

    Args:
        args: Nothing (identity), ``(R, t)`` with ``R`` a 3x3 matrix or a :class:`Quaternion`,
            a 7-vector ``[t, qx, qy, qz, qw]``, a 6-vector ``[t, qx, qy, qz]`` (minimal, ``qw ≥
            0``), or another ``SE3Quat``/``Isometry3d``.
    """

    __slots__ = ()

    def __init__(self, *args: Any) -> None:
        if self._set_common(args):
            return
        v = np.array(args[0], dtype=float).ravel()
        if v.size == 7:
            self._R, self._t = quat_to_matrix(v[None, 3:] / np.linalg.norm(v[3:]))[0], v[:3]
        elif v.size == 6:
            w = math.sqrt(max(0.0, 1.0 - float(v[3:] @ v[3:])))
            self._R, self._t = quat_to_matrix(np.append(v[3:], w)[None])[0], v[:3]
        else:
            raise ValueError(f"SE3Quat: expected (R, t), 6 or 7 values, got {v.size}")

    def rotation(self) -> Quaternion:
        """The rotation as a quaternion (g2o's ``rotation()``)."""
        return self.orientation()

    Quaternion = rotation

    def to_vector(self) -> np.ndarray:
        """``[x, y, z, qx, qy, qz, qw]``."""
        return np.concatenate([self._t, matrix_to_quat(self._R[None])[0]])

    vector = to_vector

    def to_minimal_vector(self) -> np.ndarray:
        """``[x, y, z, qx, qy, qz]`` with ``qw ≥ 0``."""
        q = matrix_to_quat(self._R[None])[0]
        return np.concatenate([self._t, q[:3] if q[3] >= 0 else -q[:3]])

    def from_vector(self, v: Any) -> None:
        """Set from ``[t, qx, qy, qz, qw]``.

        Args:
            v: 7 values.
        """
        other = SE3Quat(vector(v, 7, "SE3Quat.from_vector"))
        self._R, self._t = other._R, other._t

    def from_minimal_vector(self, v: Any) -> None:
        """Set from ``[t, qx, qy, qz]``.

        Args:
            v: 6 values.
        """
        other = SE3Quat(vector(v, 6, "SE3Quat.from_minimal_vector"))
        self._R, self._t = other._R, other._t

    def log(self) -> np.ndarray:
        """``[ω, υ]`` with ``exp(log(T)) = T`` (g2o's ``SE3Quat::log``)."""
        from graphopt.lie import so3_left_jacobian

        w = so3_log(self._R[None])
        V = so3_left_jacobian(w)[0]
        return np.concatenate([w[0], np.linalg.solve(V, self._t)])

    @staticmethod
    def exp(xi: Any) -> SE3Quat:
        """The transform of a twist ``[ω, υ]``.

        Args:
            xi: 6 values.
        """
        T = se3_exp(vector(xi, 6, "SE3Quat.exp")[None])[0]
        return SE3Quat._of(T[:3, :3], T[:3, 3].copy())

    def adj(self) -> np.ndarray:
        """The 6x6 adjoint in g2o's ``[ω, υ]`` order."""
        A = np.zeros((6, 6))
        t = self._t
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        A[:3, :3] = A[3:, 3:] = self._R
        A[3:, :3] = tx @ self._R
        return A

    def normalize_rotation(self) -> None:
        """Re-orthonormalise the rotation (through its quaternion)."""
        self._R = quat_to_matrix(matrix_to_quat(self._R[None]))[0]

    def to_isometry3d(self) -> Isometry3d:
        """The same transform as an :class:`Isometry3d`."""
        return Isometry3d._of(self._R.copy(), self._t.copy())


class SE2:
    """g2o's ``SE2``: ``[x, y, θ]``.

    Args:
        args: Nothing (identity), ``(x, y, θ)`` or a 3-vector.
    """

    __slots__ = ("_v",)

    def __init__(self, *args: Any) -> None:
        if not args:
            self._v = np.zeros(3)
        elif len(args) == 3:
            self._v = np.array([float(a) for a in args])
        elif isinstance(args[0], SE2):
            self._v = args[0]._v.copy()
        else:
            self._v = vector(args[0], 3, "SE2")
        self._v[2] = math.remainder(self._v[2], 2 * math.pi)

    @classmethod
    def _of(cls, v: np.ndarray) -> SE2:
        obj = cls.__new__(cls)
        obj._v = v
        return obj

    def translation(self) -> np.ndarray:
        """``[x, y]``."""
        return self._v[:2].copy()

    def rotation(self) -> float:
        """The angle θ (g2o returns a ``Rotation2d``; its angle)."""
        return float(self._v[2])

    def to_vector(self) -> np.ndarray:
        """``[x, y, θ]``."""
        return self._v.copy()

    vector = to_vector

    def from_vector(self, v: Any) -> None:
        """Set from ``[x, y, θ]``.

        Args:
            v: 3 values.
        """
        self._v = vector(v, 3, "SE2")

    def inverse(self) -> SE2:
        """The inverse pose."""
        x, y, th = self._v
        c, s = math.cos(th), math.sin(th)
        return SE2._of(np.array([-(c * x + s * y), s * x - c * y, -th]))

    def __mul__(self, other: Any) -> Any:
        x, y, th = self._v
        c, s = math.cos(th), math.sin(th)
        if isinstance(other, SE2):
            ox, oy, oth = other._v
            return SE2(x + c * ox - s * oy, y + s * ox + c * oy, th + oth)
        p = vector(other, 2, "SE2 * point")
        return np.array([x + c * p[0] - s * p[1], y + s * p[0] + c * p[1]])

    def __repr__(self) -> str:
        return f"SE2({self._v[0]:.6g}, {self._v[1]:.6g}, {self._v[2]:.6g})"
