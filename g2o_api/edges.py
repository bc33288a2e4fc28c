"""g2o's edge classes as thin records, and the g2o types graphopt does not support.

An edge is its vertices, measurement, information, kernel, level and parameter ids until
``initialize_optimization``; then it is an index into a *batch* (all edges of its class and
parameters, as arrays) and its getters read the batch: ``chi2()`` and ``error()`` evaluate the
whole batch once per state and index it, ``set_level`` and ``set_robust_kernel`` write one
entry. Each class maps g2o's vertex order onto the graphopt type's (``_perm``: graphopt position
``p`` takes g2o vertex ``_perm[p]``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .geometry import SE2, _RigidBase
from .sim3 import Sim3
from .vertices import BaseVertex

__all__ = ["EDGE_CLASSES", "UNSUPPORTED", "BaseEdge"]


class BaseEdge:
    """A g2o edge record."""

    __slots__ = ("_v", "_meas", "_info", "_kernel", "_level", "_pids", "_id", "_opt",
                 "_batch", "_idx", "__weakref__")
    _k = 2
    _dim = 2
    _gname = ""
    _perm: tuple[int, ...] = (0, 1)
    _mshape: tuple[int, ...] = (2,)
    #: g2o vertex position → graphopt vertex type name, where it differs from the vertex class's.
    _vertex_as: dict[int, str] = {}
    #: Parameter slots (``set_parameter_id``) and what they hold.
    _nparams = 0

    def __init__(self) -> None:
        self._v: list[BaseVertex | None] = [None] * self._k
        self._meas: Any = None
        self._info: Any = None
        self._kernel: Any = None
        self._level = 0
        self._pids = [0] * self._nparams
        self._id = -1
        self._opt: Any = None
        self._batch: Any = None
        self._idx = -1

    # --- building ----------------------------------------------------------------------------

    def set_vertex(self, i: int, vertex: BaseVertex | None) -> None:
        """Connect vertex ``i``.

        Args:
            i: Position (g2o's order).
            vertex: The vertex.
        """
        self._v[i] = vertex
        self._structure_changed()

    def vertex(self, i: int) -> BaseVertex | None:
        """Vertex ``i``.

        Args:
            i: Position.
        """
        return self._v[i]

    def vertices(self) -> list[BaseVertex | None]:
        """The vertices in g2o's order."""
        return list(self._v)

    def resize(self, k: int) -> None:
        """Accepted for g2o's multi-edges (the vertex count is the type's).

        Args:
            k: Must equal the type's vertex count.
        """
        if int(k) != self._k:
            raise ValueError(f"{type(self).__name__} has {self._k} vertices, not {k}")

    def set_measurement(self, measurement: Any) -> None:
        """Set the measurement (copied).

        Args:
            measurement: A vector (list, tuple, array) or the type's geometry object.
        """
        self._meas = measurement.copy() if type(measurement) is np.ndarray else measurement
        self._structure_changed()

    def measurement(self) -> Any:
        """The measurement."""
        if self._batch is not None:
            return self._from_measurement(self._batch.meas[self._idx])
        return self._meas

    def set_information(self, information: Any) -> None:
        """Set the information matrix (copied).

        Args:
            information: ``(d, d)`` (nested lists accepted).
        """
        self._info = np.array(information, dtype=float)
        self._structure_changed()

    def information(self) -> np.ndarray:
        """The information matrix (identity when unset)."""
        if self._batch is not None:
            return self._batch.information_of(self._idx)
        return self._info if self._info is not None else np.eye(self._dim)

    def set_robust_kernel(self, kernel: Any) -> None:
        """Set (or with ``None`` drop) the robust kernel; after initialisation the change reaches
        the optimizer's arrays at once.

        Args:
            kernel: A ``RobustKernel*`` object or ``None``.
        """
        self._kernel = kernel
        if self._batch is not None:
            self._batch.set_kernel(self._idx, kernel)

    def robust_kernel(self) -> Any:
        """The robust kernel or ``None``."""
        return self._kernel

    def set_level(self, level: int) -> None:
        """Set the level (``initialize_optimization(level)`` takes the edges of that level).

        Args:
            level: An integer.
        """
        self._level = int(level)
        if self._batch is not None:
            self._batch.set_level(self._idx, self._level)

    def level(self) -> int:
        """The level."""
        return self._level

    def set_parameter_id(self, slot: int, pid: int) -> None:
        """Name the parameter (``optimizer.add_parameter``) of a slot.

        Args:
            slot: The parameter slot (0).
            pid: The parameter's id.
        """
        if not 0 <= int(slot) < max(self._nparams, 1):
            raise ValueError(f"{type(self).__name__} has {self._nparams} parameter slots")
        if self._nparams:
            self._pids[int(slot)] = int(pid)
        self._structure_changed()

    def set_id(self, eid: int) -> None:
        """Set the edge's id.

        Args:
            eid: The id.
        """
        self._id = int(eid)

    def id(self) -> int:
        """The id (-1 when unset)."""
        return self._id

    def dimension(self) -> int:
        """The error's dimension."""
        return self._dim

    def _structure_changed(self) -> None:
        if self._batch is not None:
            self._opt._structure_changed()
            self._batch = None

    # --- evaluation (batched) ----------------------------------------------------------------

    def compute_error(self) -> None:
        """Compute the error at the current estimates (evaluated lazily, for the whole batch)."""
        self._need_batch()

    def chi2(self) -> float:
        """``eᵀΩe`` at the current estimates, without the kernel (g2o's ``chi2()``)."""
        return float(self._need_batch().chi2()[self._idx])

    def error(self) -> np.ndarray:
        """The error at the current estimates."""
        return self._need_batch().errors()[self._idx].copy()

    def is_depth_positive(self) -> bool:
        """Whether the observed point is in front of the camera(s)."""
        return bool(self._need_batch().depth_positive()[self._idx])

    def _need_batch(self) -> Any:
        if self._batch is None:
            if self._opt is None:
                raise RuntimeError(f"{type(self).__name__}: add the edge to an optimizer first")
            self._opt._prepare()
        return self._batch

    # --- conversion (overridden per type) ----------------------------------------------------

    def _params_key(self) -> tuple[Any, ...]:
        return tuple(self._pids)

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        m = len(raws)
        arr = np.array(raws, dtype=float)
        return arr.reshape(m, *cls._mshape)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        return row.copy()

    @staticmethod
    def _depth(x: list[np.ndarray], data: dict[str, np.ndarray], params: Any) -> np.ndarray:
        raise NotImplementedError("is_depth_positive: not a projection edge")


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


def _depth_pose_point(x: list[np.ndarray], data: dict[str, np.ndarray], params: Any
                      ) -> np.ndarray:
    T, X = x
    return np.einsum("mj,mj->m", T[:, 2, :3], X) + T[:, 2, 3] > 0


class EdgeSE3ProjectXYZ(BaseEdge):
    """g2o's ``EdgeSE3ProjectXYZ``: vertices ``(point, pose)``, intrinsics in ``fx, fy, cx,
    cy``."""

    __slots__ = ("fx", "fy", "cx", "cy")
    _gname = "EdgeSE3ProjectXYZ"
    _perm = (1, 0)

    def __init__(self) -> None:
        super().__init__()
        self.fx = self.fy = self.cx = self.cy = 0.0

    def _params_key(self) -> tuple[Any, ...]:
        return (self.fx, self.fy, self.cx, self.cy)

    def cam_project(self, p: Any) -> np.ndarray:
        """Pixel of a camera-frame point.

        Args:
            p: ``(3,)`` point.
        """
        p = np.asarray(p, dtype=float).reshape(3)
        return np.array([self.fx * p[0] / p[2] + self.cx, self.fy * p[1] / p[2] + self.cy])

    _depth = staticmethod(_depth_pose_point)


class EdgeProjectXYZ2UV(BaseEdge):
    """g2o's ``EdgeProjectXYZ2UV``: vertices ``(point, pose)``, a ``CameraParameters``
    parameter."""

    __slots__ = ()
    _gname = "EdgeProjectXYZ2UV"
    _perm = (1, 0)
    _nparams = 1
    _depth = staticmethod(_depth_pose_point)


class EdgeProjectPSI2UV(BaseEdge):
    """g2o's ``EdgeProjectPSI2UV``: vertices ``(inverse-depth point, pose, anchor pose)``, a
    ``CameraParameters`` parameter; the point vertex is a ``VertexPointXYZ`` holding
    ``[u, v, ρ]``."""

    __slots__ = ()
    _k = 3
    _gname = "EdgeInverseDepthProjection"
    _perm = (2, 1, 0)
    _vertex_as = {0: "VertexPointInverseDepth"}
    _nparams = 1


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

        return SE3Quat._of(row[:3, :3].copy(), row[:3, 3].copy())


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


EDGE_CLASSES: dict[str, type[BaseEdge]] = {
    c.__name__: c for c in (EdgeSE3ProjectXYZ, EdgeProjectXYZ2UV, EdgeProjectPSI2UV, EdgeSE2,
                            EdgeSE2Prior, EdgeSE2PointXY, EdgeSE3, EdgeSE3Prior, EdgeSE3PointXYZ,
                            EdgeSE3Expmap, EdgeSim3)}

#: g2o types (of the official wheel or the old bindings) without a graphopt equivalent yet.
UNSUPPORTED = (
    "EdgeGICP", "EdgeVVGicp", "Edge_V_V_GICP", "EdgeXyzVsc", "Edge_XYZ_VSC", "EdgeSBACam",
    "EdgeSBAScale", "EdgeProjectP2MC", "EdgeProjectP2SC", "EdgeProjectXYZ2UVU",
    "EdgeSE3ProjectXYZOnlyPose", "EdgeStereoSE3ProjectXYZ", "EdgeStereoSE3ProjectXYZOnlyPose",
    "EdgeSim3ProjectXYZ", "EdgeInverseSim3ProjectXYZ", "EdgePointXY", "EdgePointXYZ",
    "EdgeSE2LotsOfXY", "EdgeSE2OdomDifferentialCalib", "EdgeSE2Offset",
    "EdgeSE2PointXYBearing", "EdgeSE2PointXYCalib", "EdgeSE2PointXYOffset",
    "EdgeSE2SensorCalib", "EdgeSE2TwoPointsXY", "EdgeSE2XYPrior", "EdgeSE3LotsOfXYZ",
    "EdgeSE3Offset", "EdgeSE3PointXYZDepth", "EdgeSE3PointXYZDisparity", "EdgeSE3XYZPrior",
    "EdgeXYPrior", "EdgeXYZPrior", "VertexCam", "VertexSCam", "VertexIntrinsics",
    "VertexOdomDifferentialParams", "SBACam",
)


def unsupported(name: str) -> type:
    """A class whose construction raises ``NotImplementedError`` naming the g2o type.

    Args:
        name: The g2o type's name.
    """

    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        raise NotImplementedError(
            f"graphopt.g2o: {name} is not supported (graphopt has no batched type for it yet); "
            "see docs/g2o_api.md for the supported types")

    return type(name, (), {"__init__": __init__, "__module__": "graphopt.g2o",
                           "__doc__": f"g2o's {name}: not supported by graphopt."})
