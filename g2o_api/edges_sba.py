"""g2o's bundle-adjustment edges (``types/sba``): the pinhole projection edges, their pose-only
and stereo variants and the anchored inverse-depth edge, mapped onto graphopt's types (see
:mod:`graphopt.g2o.edges` for the record)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .edges import BaseEdge

__all__ = ["SBA_EDGES"]

_ORIGIN = np.zeros(3)
_ORIGIN.flags.writeable = False
_F8 = np.dtype(np.float64)


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
    _param_type = "CameraParameters"

    _defaults = {"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0}

    def _params_key(self) -> tuple[Any, ...]:
        return (self.fx, self.fy, self.cx, self.cy)

    _key_attrs = ("fx", "fy", "cx", "cy")

    def cam_project(self, p: Any) -> np.ndarray:
        """Pixel of a camera-frame point.

        Args:
            p: ``(3,)`` point.
        """
        p = np.asarray(p, dtype=float).reshape(3)
        return np.array([self.fx * p[0] / p[2] + self.cx, self.fy * p[1] / p[2] + self.cy])

    _depth = staticmethod(_depth_pose_point)


def _depth_pose_only(x: list[np.ndarray], data: dict[str, np.ndarray], params: Any
                     ) -> np.ndarray:
    T = x[0]
    return np.einsum("mj,mj->m", T[:, 2, :3], data["Xw"]) + T[:, 2, 3] > 0


class EdgeSE3ProjectXYZOnlyPose(EdgeSE3ProjectXYZ):
    """g2o's ``EdgeSE3ProjectXYZOnlyPose``: one pose vertex, the world point in ``Xw``."""

    __slots__ = ("Xw",)
    _k = 1
    _gname = "EdgeSE3ProjectXYZOnlyPose"
    _perm = (0,)

    _defaults = {"Xw": _ORIGIN}  # g2o's default; programs assign their point

    @classmethod
    def _data(cls, recs: list[BaseEdge]) -> dict[str, np.ndarray]:
        xw = [r.Xw for r in recs]
        lengths = set(map(len, xw))
        try:  # float arrays of 3 (programs copy a point in): one join of their bytes
            buf = b"".join(xw)  # (each at least 3 floats: 24 bytes each, exactly 3)
            if lengths == {3} and len(buf) == 24 * len(xw) and {x.dtype for x in xw} == {_F8}:
                return {"Xw": np.frombuffer(buf).reshape(-1, 3).copy()}
        except (TypeError, AttributeError):  # lists, tuples, strided views
            pass
        if lengths == {3}:
            return {"Xw": np.asarray(np.concatenate(xw, axis=None), dtype=float).reshape(-1, 3)}
        return {"Xw": np.array(xw, dtype=float).reshape(len(recs), 3)}

    _depth = staticmethod(_depth_pose_only)


class EdgeStereoSE3ProjectXYZ(EdgeSE3ProjectXYZ):
    """g2o's ``EdgeStereoSE3ProjectXYZ``: measurement ``(u, v, u_r)``, ``bf`` on the edge."""

    __slots__ = ("bf",)
    _dim = 3
    _mshape = (3,)
    _gname = "EdgeStereoSE3ProjectXYZ"
    _param_type = "StereoCameraParameters"

    _defaults = {"bf": 0.0}

    def _params_key(self) -> tuple[Any, ...]:
        return (self.fx, self.fy, self.cx, self.cy, self.bf)

    _key_attrs = ("fx", "fy", "cx", "cy", "bf")


class EdgeStereoSE3ProjectXYZOnlyPose(EdgeStereoSE3ProjectXYZ):
    """g2o's ``EdgeStereoSE3ProjectXYZOnlyPose``: one pose vertex, the point in ``Xw``."""

    __slots__ = ("Xw",)
    _k = 1
    _gname = "EdgeStereoSE3ProjectXYZOnlyPose"
    _perm = (0,)

    _defaults = {"Xw": _ORIGIN}  # g2o's default; programs assign their point

    _data = EdgeSE3ProjectXYZOnlyPose._data
    _depth = staticmethod(_depth_pose_only)


class EdgeProjectXYZ2UV(BaseEdge):
    """g2o's ``EdgeProjectXYZ2UV``: vertices ``(point, pose)``, a ``CameraParameters``
    parameter."""

    __slots__ = ()
    _gname = "EdgeProjectXYZ2UV"
    _perm = (1, 0)
    _nparams = 1
    _depth = staticmethod(_depth_pose_point)


class EdgeProjectXYZ2UVU(BaseEdge):
    """g2o's ``EdgeProjectXYZ2UVU``: stereo ``(u, v, u_right)`` of ``(point, pose)``, a
    ``CameraParameters`` parameter (its baseline)."""

    __slots__ = ()
    _dim = 3
    _mshape = (3,)
    _gname = "EdgeProjectXYZ2UVU"
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


class EdgeSim3ProjectXYZ(BaseEdge):
    """g2o's ``EdgeSim3ProjectXYZ``: vertices ``(point, sim3)``, camera 1 of the Sim3 vertex
    (``_focal_length1``, ``_principle_point1``) as the intrinsics."""

    __slots__ = ()
    _gname = "EdgeSim3ProjectXYZ"
    _param_type = "CameraParameters"
    _camera = 1

    def _params_key(self) -> tuple[Any, ...]:
        return self._v1.camera(self._camera)  # type: ignore[union-attr]


class EdgeInverseSim3ProjectXYZ(EdgeSim3ProjectXYZ):
    """g2o's ``EdgeInverseSim3ProjectXYZ``: camera 2 of the Sim3 vertex."""

    __slots__ = ()
    _gname = "EdgeInverseSim3ProjectXYZ"
    _camera = 2


SBA_EDGES: dict[str, type[BaseEdge]] = {c.__name__: c for c in (
    EdgeSE3ProjectXYZ, EdgeSE3ProjectXYZOnlyPose, EdgeStereoSE3ProjectXYZ,
    EdgeStereoSE3ProjectXYZOnlyPose, EdgeProjectXYZ2UV, EdgeProjectXYZ2UVU, EdgeProjectPSI2UV,
    EdgeSim3ProjectXYZ, EdgeInverseSim3ProjectXYZ)}
