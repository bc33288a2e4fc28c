"""g2o's SBA camera family (``types/sba``): ``SBACam`` (a pose with its own intrinsics and
baseline), ``VertexCam``, ``VertexIntrinsics`` and the edges ``EdgeProjectP2MC`` /
``EdgeProjectP2SC`` (mono / stereo projections, ``(point, camera)``), ``EdgeSBACam``
(relative pose, an ``SE3Quat``) and ``EdgeSBAScale`` (distance), onto
:mod:`graphopt.types.sba_cam`."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.types.isometry3 import matrix_to_quat, quat_to_matrix

from .edges import BaseEdge
from .geometry import SE3Quat, _RigidBase
from .vertices import BaseVertex

__all__ = ["SBA_CAM_CLASSES"]


class SBACam(SE3Quat):
    """g2o's ``SBACam``: the camera's pose in the world (camera → world) and its intrinsics
    ``(fx, fy, cx, cy)`` and stereo baseline (g2o's defaults 1, 1, 0.5, 0.5, 0)."""

    __slots__ = ("_k",)

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        src = args[0] if len(args) == 1 else None
        self._k = src._k if isinstance(src, SBACam) else (1.0, 1.0, 0.5, 0.5, 0.0)

    @classmethod
    def _of(cls, R: np.ndarray, t: np.ndarray, k: tuple[float, ...] = (1.0, 1.0, 0.5, 0.5, 0.0)
            ) -> SBACam:
        obj = cls.__new__(cls)
        obj._R, obj._t, obj._k = R, t, k
        return obj

    def set_cam(self, fx: float, fy: float, cx: float, cy: float, tx: float) -> None:
        """Set the intrinsics and the baseline.

        Args:
            fx: Focal length x.
            fy: Focal length y.
            cx: Principal point x.
            cy: Principal point y.
            tx: Stereo baseline.
        """
        self._k = (float(fx), float(fy), float(cx), float(cy), float(tx))

    @property
    def Kcam(self) -> np.ndarray:  # noqa: N802 - g2o's name
        """The 3x3 camera matrix."""
        fx, fy, cx, cy, _ = self._k
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def baseline(self) -> float:
        """The stereo baseline."""
        return self._k[4]

    def w2n(self, p: Any) -> np.ndarray:
        """A world point in the camera frame.

        Args:
            p: ``(3,)``.
        """
        return self._R.T @ (np.asarray(p, dtype=float).reshape(3) - self._t)

    def w2i(self, p: Any) -> np.ndarray:
        """A world point's pixel.

        Args:
            p: ``(3,)``.
        """
        h = self.Kcam @ self.w2n(p)
        return h[:2] / h[2]


class VertexCam(BaseVertex):
    """g2o's ``VertexCam`` (estimate ``SBACam``)."""

    __slots__ = ()
    _gname = "VertexCam"
    _shape = (12,)

    @classmethod
    def _default(cls) -> Any:
        return SBACam()

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        out = np.zeros((len(raws), 12))
        for i, r in enumerate(raws):
            if isinstance(r, _RigidBase):
                out[i, :3] = r._t
                out[i, 3:7] = matrix_to_quat(r._R[None])[0]
                out[i, 7:] = r._k if isinstance(r, SBACam) else (1.0, 1.0, 0.5, 0.5, 0.0)
            else:
                out[i] = np.asarray(r, dtype=float).reshape(12)
        return out

    @classmethod
    def _from_row(cls, row: np.ndarray) -> SBACam:
        R = quat_to_matrix(row[None, 3:7] / np.linalg.norm(row[3:7]))[0]
        return SBACam._of(R, row[:3].copy(), tuple(float(v) for v in row[7:]))


class VertexIntrinsics(BaseVertex):
    """g2o's ``VertexIntrinsics``: ``[fx, fy, cx, cy, baseline]``."""

    __slots__ = ()
    _gname = "VertexIntrinsics"
    _shape = (5,)

    @classmethod
    def _default(cls) -> Any:
        return np.array([1.0, 1.0, 0.5, 0.5, 0.1])


def _edge(name: str, k: int, dim: int, perm: tuple[int, ...]) -> type:
    return type(name, (BaseEdge,), {"__slots__": (), "__module__": __name__, "_k": k,
                                    "_dim": dim, "_gname": name, "_perm": perm,
                                    "_mshape": (dim,), "__doc__": f"g2o's ``{name}``."})


class EdgeSBACam(BaseEdge):
    """g2o's ``EdgeSBACam``: the relative pose of two cameras (measurement ``SE3Quat``)."""

    __slots__ = ()
    _dim = 6
    _mshape = (7,)
    _gname = "EdgeSBACam"

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return np.array([r.to_vector() if isinstance(r, SE3Quat) else r for r in raws],
                        dtype=float).reshape(len(raws), 7)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        return SE3Quat(row)


SBA_CAM_CLASSES: dict[str, type] = {
    "SBACam": SBACam, "VertexCam": VertexCam, "VertexIntrinsics": VertexIntrinsics,
    "EdgeProjectP2MC": _edge("EdgeProjectP2MC", 2, 2, (1, 0)),
    "EdgeProjectP2SC": _edge("EdgeProjectP2SC", 2, 3, (1, 0)),
    "EdgeSBAScale": _edge("EdgeSBAScale", 2, 1, (0, 1)), "EdgeSBACam": EdgeSBACam}
