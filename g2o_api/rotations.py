"""g2o's rotations: ``Quaternion`` (Eigen's conventions: ``Quaternion(w, x, y, z)`` takes the
scalar first, ``coeffs()`` and ``Quaternion(array4)`` use the storage order ``[x, y, z, w]``) and
``AngleAxis``; and the input coercion every g2o class shares (lists, tuples, ints, column
vectors)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from graphopt.lie import so3_exp, so3_log
from graphopt.types.isometry3 import matrix_to_quat, quat_to_matrix

__all__ = ["AngleAxis", "Quaternion", "vector"]


def vector(value: Any, n: int, what: str = "vector") -> np.ndarray:
    """``value`` as a float ``(n,)`` array (lists, tuples, column or row vectors).

    Args:
        value: The input.
        n: Its length.
        what: Named in the error.
    """
    arr = np.array(value, dtype=float)
    if arr.size != n:
        raise ValueError(f"{what}: expected {n} values, got shape {arr.shape}")
    return arr.reshape(n)


def _matrix3(value: Any) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.shape != (3, 3):
        raise ValueError(f"expected a 3x3 rotation matrix, got shape {arr.shape}")
    return arr


class Quaternion:
    """A rotation quaternion (g2o's / Eigen's ``Quaternion``).

    Args:
        args: Nothing (identity), ``(w, x, y, z)``, a ``[x, y, z, w]`` array (Eigen's storage
            order), a 3x3 rotation matrix, an :class:`AngleAxis` or another quaternion.
    """

    __slots__ = ("_q",)

    def __init__(self, *args: Any) -> None:
        if not args:
            self._q = np.array([0.0, 0.0, 0.0, 1.0])
        elif len(args) == 4:
            w, x, y, z = (float(a) for a in args)
            self._q = np.array([x, y, z, w])
        elif isinstance(args[0], Quaternion):
            self._q = args[0]._q.copy()
        elif isinstance(args[0], AngleAxis):
            self._q = args[0].quaternion()._q
        else:
            arr = np.array(args[0], dtype=float)
            if arr.shape == (3, 3):
                self._q = matrix_to_quat(arr[None])[0]
            else:
                self._q = vector(arr, 4, "Quaternion")

    @classmethod
    def _of(cls, xyzw: np.ndarray) -> Quaternion:
        q = cls.__new__(cls)
        q._q = xyzw
        return q

    def w(self) -> float:
        """The scalar part."""
        return float(self._q[3])

    def x(self) -> float:
        """The first vector coefficient."""
        return float(self._q[0])

    def y(self) -> float:
        """The second vector coefficient."""
        return float(self._q[1])

    def z(self) -> float:
        """The third vector coefficient."""
        return float(self._q[2])

    def vec(self) -> np.ndarray:
        """``[x, y, z]``."""
        return self._q[:3].copy()

    def coeffs(self) -> np.ndarray:
        """``[x, y, z, w]`` (Eigen's storage order)."""
        return self._q.copy()

    def matrix(self) -> np.ndarray:
        """The 3x3 rotation matrix (Eigen's ``toRotationMatrix``)."""
        return quat_to_matrix(self._q[None])[0]

    rotation_matrix = matrix
    to_rotation_matrix = matrix

    @property
    def R(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return self.matrix()

    def norm(self) -> float:
        """Euclidean norm of the coefficients."""
        return float(np.linalg.norm(self._q))

    def squared_norm(self) -> float:
        """Squared norm of the coefficients."""
        return float(self._q @ self._q)

    def normalize(self) -> None:
        """Scale to unit norm in place."""
        self._q = self._q / np.linalg.norm(self._q)

    def normalized(self) -> Quaternion:
        """A unit-norm copy."""
        return Quaternion._of(self._q / np.linalg.norm(self._q))

    def conjugate(self) -> Quaternion:
        """``[−x, −y, −z, w]``."""
        return Quaternion._of(self._q * [-1.0, -1.0, -1.0, 1.0])

    def inverse(self) -> Quaternion:
        """The conjugate divided by the squared norm."""
        return Quaternion._of(self._q * [-1.0, -1.0, -1.0, 1.0] / (self._q @ self._q))

    def dot(self, other: Quaternion) -> float:
        """Dot product of the coefficients.

        Args:
            other: The other quaternion.
        """
        return float(self._q @ other._q)

    def angular_distance(self, other: Quaternion) -> float:
        """Angle of the rotation between the two (Eigen's ``angularDistance``).

        Args:
            other: The other quaternion.
        """
        d = abs((self.conjugate() * other)._q[3])
        return 2.0 * math.acos(min(1.0, d))

    def set_identity(self) -> None:
        """Make this the identity."""
        self._q = np.array([0.0, 0.0, 0.0, 1.0])

    @staticmethod
    def identity() -> Quaternion:
        """The identity rotation."""
        return Quaternion()

    def __mul__(self, other: Any) -> Any:
        if isinstance(other, Quaternion):
            x1, y1, z1, w1 = self._q
            x2, y2, z2, w2 = other._q
            return Quaternion._of(np.array([
                w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]))
        return self.matrix() @ vector(other, 3, "Quaternion * point")

    def __repr__(self) -> str:
        x, y, z, w = self._q
        return f"Quaternion(w={w:.6g}, x={x:.6g}, y={y:.6g}, z={z:.6g})"


class AngleAxis:
    """A rotation by ``angle`` about a unit ``axis`` (Eigen's ``AngleAxisd``).

    Args:
        args: Nothing (identity), ``(angle, axis)``, a :class:`Quaternion`, a 3x3 matrix or
            another ``AngleAxis``.
    """

    __slots__ = ("_angle", "_axis")

    def __init__(self, *args: Any) -> None:
        if not args:
            self._angle, self._axis = 0.0, np.array([1.0, 0.0, 0.0])
        elif len(args) == 2:
            self._angle, self._axis = float(args[0]), vector(args[1], 3, "AngleAxis axis")
        elif isinstance(args[0], AngleAxis):
            self._angle, self._axis = args[0]._angle, args[0]._axis.copy()
        else:
            R = args[0].matrix() if isinstance(args[0], Quaternion) else _matrix3(args[0])
            w = so3_log(R[None])[0]
            theta = float(np.linalg.norm(w))
            self._angle = theta
            self._axis = w / theta if theta > 0 else np.array([1.0, 0.0, 0.0])

    def angle(self) -> float:
        """The angle in radians."""
        return self._angle

    def axis(self) -> np.ndarray:
        """The unit axis."""
        return self._axis.copy()

    def matrix(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return so3_exp((self._angle * self._axis)[None])[0]

    rotation_matrix = matrix
    to_rotation_matrix = matrix

    @property
    def R(self) -> np.ndarray:
        """The 3x3 rotation matrix."""
        return self.matrix()

    def quaternion(self) -> Quaternion:
        """The same rotation as a quaternion."""
        h = 0.5 * self._angle
        return Quaternion._of(np.append(math.sin(h) * self._axis, math.cos(h)))

    def inverse(self) -> AngleAxis:
        """The opposite rotation."""
        return AngleAxis(-self._angle, self._axis)

    def from_rotation_matrix(self, R: Any) -> AngleAxis:
        """Set from a rotation matrix; returns ``self``.

        Args:
            R: 3x3 rotation.
        """
        other = AngleAxis(R)
        self._angle, self._axis = other._angle, other._axis
        return self

    @staticmethod
    def identity() -> AngleAxis:
        """The identity rotation."""
        return AngleAxis()

    def __mul__(self, other: Any) -> Any:
        return self.matrix() @ vector(other, 3, "AngleAxis * point")


def _rotation(value: Any) -> np.ndarray:
    """A 3x3 rotation from a matrix, :class:`Quaternion` or :class:`AngleAxis`."""
    if isinstance(value, Quaternion | AngleAxis):
        return value.matrix()
    return _matrix3(value)
