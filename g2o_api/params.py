"""g2o's parameters: ``CameraParameters`` (one focal length, a principal point, a baseline),
``StereoCameraParameters`` and ``ParameterSE3Offset``, registered with
``optimizer.add_parameter`` and named by edges through ``set_parameter_id``."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.types.slam3d import ParameterSE3Offset as CoreOffset

from .geometry import SE2, Isometry3d, _RigidBase
from .rotations import vector

__all__ = ["CameraParameters", "Parameter", "ParameterCamera", "ParameterSE2Offset",
           "ParameterSE3Offset", "StereoCameraParameters"]


class Parameter:
    """A g2o parameter with an id."""

    def __init__(self) -> None:
        self._id = -1

    def set_id(self, pid: int) -> None:
        """Set the id edges name it by.

        Args:
            pid: The id.
        """
        self._id = int(pid)

    def id(self) -> int:
        """The id (-1 when unset)."""
        return self._id

    def _core(self) -> Any:
        raise NotImplementedError


class CameraParameters(Parameter):
    """g2o's ``CameraParameters(focal_length, principal_point, baseline)``.

    Args:
        focal_length: ``f`` (both axes).
        principal_point: ``(cx, cy)``.
        baseline: Stereo baseline (used by ``stereocam_uvu_map``).
    """

    def __init__(self, focal_length: float = 1.0, principal_point: Any = (0.0, 0.0),
                 baseline: float = 0.5) -> None:
        super().__init__()
        self.focal_length = float(focal_length)
        self.principle_point = vector(principal_point, 2, "principal_point")
        self.baseline = float(baseline)
        self._cached: Any = None

    def cam_map(self, p: Any) -> np.ndarray:
        """Pixel of a camera-frame point: ``f · (x, y) / z + (cx, cy)``.

        Args:
            p: ``(3,)`` point in the camera frame.
        """
        if type(p) is not np.ndarray or p.shape != (3,):
            p = vector(p, 3, "cam_map")
        x, y, z = p.tolist()
        c = self.principle_point
        if z == 0.0 or type(c) is not np.ndarray or c.shape != (2,):
            return p[:2] * (self.focal_length / p[2]) + c
        # Python floats: the numpy expression's operations in its order (the same bits) without
        # its four array temporaries — called once per point and pose by g2o's demos.
        s = self.focal_length / z
        cx, cy = c.tolist()
        return np.array((x * s + cx, y * s + cy))

    def stereocam_uvu_map(self, p: Any) -> np.ndarray:
        """``(u, v, u − f·b / z)``.

        Args:
            p: ``(3,)`` point in the camera frame.
        """
        uv = self.cam_map(p)
        p = vector(p, 3, "stereocam_uvu_map")
        return np.array([uv[0], uv[1], uv[0] - self.baseline * self.focal_length / p[2]])

    def _core(self) -> Any:
        # graphopt's SBACameraParameters is a CameraParameters with the baseline: it serves
        # the monocular and the stereo (EdgeProjectXYZ2UVU) edges alike.
        from graphopt.types import SBACameraParameters as Core

        key = (self.focal_length, *self.principle_point.tolist(), self.baseline)
        if self._cached is None or self._cached[0] != key:
            self._cached = (key, Core.from_g2o(key[0], key[1:3], key[3]))
        return self._cached[1]


class StereoCameraParameters(CameraParameters):
    """g2o's ``StereoCameraParameters`` (same fields as :class:`CameraParameters`)."""


class ParameterSE3Offset(Parameter):
    """g2o's ``ParameterSE3Offset``: a sensor's pose on its vertex (identity by default)."""

    def __init__(self) -> None:
        super().__init__()
        self._offset = Isometry3d()

    def set_offset(self, offset: Any = None) -> None:
        """Set the offset.

        Args:
            offset: An :class:`Isometry3d` (or 4x4 / 3x4 matrix); ``None``: identity.
        """
        self._offset = Isometry3d() if offset is None else (
            Isometry3d(offset) if not isinstance(offset, _RigidBase) else Isometry3d(offset))

    def offset(self) -> Isometry3d:
        """The offset."""
        return Isometry3d(self._offset)

    param = offset
    set_param = set_offset

    def _core(self) -> Any:
        return CoreOffset(self._offset.matrix()[:3], max(self._id, 0))


class ParameterSE2Offset(Parameter):
    """g2o's ``ParameterSE2Offset``: a sensor's ``SE2`` pose on its vertex (zero by default)."""

    def __init__(self) -> None:
        super().__init__()
        self._offset = SE2()

    def set_offset(self, offset: Any = None) -> None:
        """Set the offset.

        Args:
            offset: An :class:`SE2` or ``[x, y, θ]``; ``None``: zero.
        """
        self._offset = SE2() if offset is None else (
            SE2(offset) if not isinstance(offset, SE2) else SE2(offset.to_vector()))

    def offset(self) -> SE2:
        """The offset."""
        return SE2(self._offset.to_vector())

    param = offset
    set_param = set_offset

    def _core(self) -> Any:
        from graphopt.types import ParameterSE2Offset as Core

        return Core(self._offset.to_vector(), max(self._id, 0))


class ParameterCamera(ParameterSE3Offset):
    """g2o's ``ParameterCamera``: an ``Isometry3d`` offset and pinhole intrinsics (g2o's
    defaults ``fx = fy = 1``, ``cx = cy = 0.5``)."""

    def __init__(self) -> None:
        super().__init__()
        self._k = (1.0, 1.0, 0.5, 0.5)

    def set_kcam(self, fx: float, fy: float, cx: float, cy: float) -> None:
        """Set the intrinsics.

        Args:
            fx: Focal length x.
            fy: Focal length y.
            cx: Principal point x.
            cy: Principal point y.
        """
        self._k = (float(fx), float(fy), float(cx), float(cy))

    setKcam = set_kcam  # noqa: N815 - the old bindings' name
    setOffset = ParameterSE3Offset.set_offset  # noqa: N815

    def Kcam(self) -> np.ndarray:  # noqa: N802 - g2o's name
        """The 3x3 camera matrix."""
        fx, fy, cx, cy = self._k
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def _core(self) -> Any:
        from graphopt.types import ParameterCamera as Core

        return Core(self._offset.matrix()[:3], max(self._id, 0), *self._k)
