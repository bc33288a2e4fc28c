"""g2o's SLAM edges (``types/slam2d``, ``types/slam3d``, ``EdgeSE3Expmap``, ``EdgeSim3``): their
measurements are g2o's geometry objects, converted to graphopt's arrays in one pass per batch
(see :mod:`graphopt.g2o.edges` for the record)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .edges import BaseEdge
from .geometry import SE2, _RigidBase
from .sim3 import Sim3

__all__ = ["SLAM_EDGES"]


def _rigid_measurements(raws: list[Any], rows: int) -> np.ndarray:
    out = np.zeros((len(raws), rows, 4))
    for i, r in enumerate(raws):
        if isinstance(r, _RigidBase):
            out[i, :3, :3], out[i, :3, 3] = r._R, r._t
        elif isinstance(r, Sim3):
            out[i, :3, :3], out[i, :3, 3] = r._s * r._R, r._t
        else:
            out[i, :3] = np.asarray(r, dtype=float)[:3]
    if rows == 4:
        out[:, 3, 3] = 1.0
    return out


class EdgeSE2(BaseEdge):
    """g2o's ``EdgeSE2`` (measurement ``SE2``)."""

    __slots__ = ()
    _dim = 3
    _gname = "EdgeSE2"
    _mshape = (3,)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return BaseEdge._measurements.__func__(cls, [r._v if type(r) is SE2 else r
                                                     for r in raws])

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        return SE2._of(row.copy())


class EdgeSE2Prior(EdgeSE2):
    """g2o's ``EdgeSE2Prior`` (unary, measurement ``SE2``)."""

    __slots__ = ()
    _k = 1
    _gname = "EdgeSE2Prior"
    _perm = (0,)


class EdgeSE2PointXY(BaseEdge):
    """g2o's ``EdgeSE2PointXY``: the point in the pose's frame."""

    __slots__ = ()
    _gname = "EdgeSE2PointXY"


class EdgeSE3(BaseEdge):
    """g2o's ``EdgeSE3`` (measurement ``Isometry3d``)."""

    __slots__ = ()
    _dim = 6
    _gname = "EdgeSE3"
    _mshape = (3, 4)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return _rigid_measurements(raws, 3)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        from .geometry import Isometry3d

        return Isometry3d(row)


class EdgeSE3Prior(EdgeSE3):
    """g2o's ``EdgeSE3Prior`` (unary, measurement ``Isometry3d``, a ``ParameterSE3Offset``)."""

    __slots__ = ()
    _k = 1
    _gname = "EdgeSE3Prior"
    _perm = (0,)
    _nparams = 1


class EdgeSE3PointXYZ(BaseEdge):
    """g2o's ``EdgeSE3PointXYZ`` (a ``ParameterSE3Offset``)."""

    __slots__ = ()
    _dim = 3
    _gname = "EdgeSE3PointXYZ"
    _mshape = (3,)
    _nparams = 1


class EdgeSE3Expmap(BaseEdge):
    """g2o's ``EdgeSE3Expmap`` (measurement ``SE3Quat``)."""

    __slots__ = ()
    _dim = 6
    _gname = "EdgeSE3Expmap"
    _mshape = (4, 4)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return _rigid_measurements(raws, 4)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        from .geometry import SE3Quat

        m = row.copy()  # one copy; the record holds views of it
        return SE3Quat._of(m[:3, :3], m[:3, 3])


class EdgeSim3(EdgeSE3Expmap):
    """g2o's ``EdgeSim3`` (measurement ``Sim3``)."""

    __slots__ = ()
    _dim = 7
    _gname = "EdgeSim3"

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        sR = row[:3, :3]
        s = float(np.cbrt(np.linalg.det(sR)))
        return Sim3._of(sR / s, row[:3, 3].copy(), s)


def _simple(name: str, k: int, dim: int, base: type = BaseEdge, nparams: int = 0,
            mshape: tuple[int, ...] | None = None) -> type:
    """A g2o edge class whose graphopt type has g2o's name, vertex order and a vector (or
    ``SE2``) measurement."""
    return type(name, (base,), {
        "__slots__": (), "__module__": __name__, "_k": k, "_dim": dim, "_gname": name,
        "_perm": tuple(range(k)), "_mshape": mshape or (dim,), "_nparams": nparams,
        "__doc__": f"g2o's ``{name}``."})


#: g2o types with a vector measurement (or an ``SE2`` one, through ``EdgeSE2``) whose graphopt
#: types keep g2o's vertex order (``types/slam2d_sensors``, ``slam3d_sensors``, ``sclam2d``).
SIMPLE = [_simple("EdgePointXY", 2, 2), _simple("EdgeXYPrior", 1, 2),
          _simple("EdgeSE2XYPrior", 1, 2), _simple("EdgeSE2PointXYBearing", 2, 1),
          _simple("EdgeSE2PointXYCalib", 3, 2), _simple("EdgePointXYZ", 2, 3),
          _simple("EdgeXYZPrior", 1, 3), _simple("EdgeSE3XYZPrior", 1, 3, nparams=1),
          _simple("EdgeSE2SensorCalib", 3, 3, base=EdgeSE2),
          _simple("EdgeSE2Offset", 2, 3, base=EdgeSE2, nparams=2),
          _simple("EdgeSE2PointXYOffset", 2, 2, nparams=1),
          _simple("EdgeSE3Offset", 2, 6, base=EdgeSE3, nparams=2, mshape=(3, 4)),
          _simple("EdgeSE3PointXYZDepth", 2, 3, nparams=1),
          _simple("EdgeSE3PointXYZDisparity", 2, 3, nparams=1)]



class EdgeSE2LotsOfXY(BaseEdge):
    """g2o's ``EdgeSE2LotsOfXY``: one pose and ``k`` points (``resize(k + 1)`` first);
    measurement ``(2k,)``."""

    __slots__ = ()
    _gname = "EdgeSE2LotsOfXY"
    _k = 1
    _perm = ()
    _point = 2

    def resize(self, k: int) -> None:
        """Set the vertex count (the pose and ``k − 1`` points).

        Args:
            k: At least 2.
        """
        if int(k) < 2:
            raise ValueError(f"{type(self).__name__} needs the pose and at least one point")
        self._v = [None] * int(k)

    def dimension(self) -> int:
        """``2k`` (``3k`` in 3D)."""
        return self._point * (len(self._v) - 1)

    def _params_key(self) -> tuple[Any, ...]:
        return (len(self._v),)

    @classmethod
    def _core_type(cls, key: tuple[Any, ...]) -> type:
        from .vertices import core_type

        return core_type(cls._gname).of(key[0] - 1)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return np.array(raws, dtype=float).reshape(len(raws), -1)


class EdgeSE3LotsOfXYZ(EdgeSE2LotsOfXY):
    """g2o's ``EdgeSE3LotsOfXYZ``: one ``VertexSE3`` and ``k`` 3D points; measurement
    ``(3k,)``."""

    __slots__ = ()
    _gname = "EdgeSE3LotsOfXYZ"
    _point = 3


class EdgeSE2TwoPointsXY(BaseEdge):
    """g2o's ``EdgeSE2TwoPointsXY``: a pose and two points; measurement ``(4,)``."""

    __slots__ = ()
    _k = 3
    _dim = 4
    _perm = (0, 1, 2)
    _mshape = (4,)
    _gname = "EdgeSE2TwoPointsXY"


class VelocityMeasurement:
    """g2o's ``VelocityMeasurement``: wheel velocities ``vl``, ``vr`` over ``dt``.

    Args:
        vl: Left wheel velocity.
        vr: Right wheel velocity.
        dt: Time span.
    """

    def __init__(self, vl: float = 0.0, vr: float = 0.0, dt: float = 0.0) -> None:
        self._v = [float(vl), float(vr), float(dt)]

    def vl(self) -> float:
        """Left wheel velocity."""
        return self._v[0]

    def vr(self) -> float:
        """Right wheel velocity."""
        return self._v[1]

    def dt(self) -> float:
        """Time span."""
        return self._v[2]

    def set_vl(self, v: float) -> None:
        """Set the left wheel velocity.

        Args:
            v: The value.
        """
        self._v[0] = float(v)

    def set_vr(self, v: float) -> None:
        """Set the right wheel velocity.

        Args:
            v: The value.
        """
        self._v[1] = float(v)

    def set_dt(self, v: float) -> None:
        """Set the time span.

        Args:
            v: The value.
        """
        self._v[2] = float(v)

    def copy(self) -> VelocityMeasurement:
        """A copy."""
        return VelocityMeasurement(*self._v)


class EdgeSE2OdomDifferentialCalib(BaseEdge):
    """g2o's ``EdgeSE2OdomDifferentialCalib``: ``(X1, X2, VertexOdomDifferentialParams)``,
    measurement a ``VelocityMeasurement``."""

    __slots__ = ()
    _k = 3
    _dim = 3
    _perm = (0, 1, 2)
    _mshape = (3,)
    _gname = "EdgeSE2OdomDifferentialCalib"

    def set_measurement(self, measurement: Any) -> None:
        """Set the measurement (copied).

        Args:
            measurement: A :class:`VelocityMeasurement` or ``[vl, vr, dt]``.
        """
        super().set_measurement(measurement.copy() if isinstance(measurement,
                                                                 VelocityMeasurement)
                                else measurement)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return np.array([r._v if isinstance(r, VelocityMeasurement) else r for r in raws],
                        dtype=float).reshape(len(raws), 3)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        return VelocityMeasurement(*row.tolist())



SLAM_EDGES: dict[str, type[BaseEdge]] = {c.__name__: c for c in (
    EdgeSE2, EdgeSE2Prior, EdgeSE2PointXY, EdgeSE3, EdgeSE3Prior, EdgeSE3PointXYZ,
    EdgeSE3Expmap, EdgeSim3, *SIMPLE, EdgeSE2LotsOfXY, EdgeSE3LotsOfXYZ, EdgeSE2TwoPointsXY,
    EdgeSE2OdomDifferentialCalib, VelocityMeasurement)}
