"""g2o's ``types/icp``: the GICP correspondence ``Edge_V_V_GICP`` (the wheel's ``EdgeVVGicp``)
between two ``VertexSE3``, with its measurement object ``EdgeGICP``; ``pl_pl`` (plane to plane)
selects graphopt's :class:`~graphopt.types.icp.EdgeVVGicpPlaneToPlane`."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphopt.types.icp import gicp_covariance, gicp_normal_frame, gicp_precision

from .edges import BaseEdge

__all__ = ["ICP_EDGES"]


class EdgeGICP:
    """g2o's ``EdgeGICP``: a point correspondence ``pos0`` ↔ ``pos1`` with surface normals."""

    def __init__(self) -> None:
        self.pos0 = np.zeros(3)
        self.pos1 = np.zeros(3)
        self.normal0 = np.array([0.0, 0.0, 1.0])
        self.normal1 = np.array([0.0, 0.0, 1.0])
        self.R0 = np.eye(3)
        self.R1 = np.eye(3)

    def copy(self) -> EdgeGICP:
        """A copy (g2o copies the measurement into the edge)."""
        m = EdgeGICP()
        for name in ("pos0", "pos1", "normal0", "normal1", "R0", "R1"):
            setattr(m, name, np.array(getattr(self, name), dtype=float))
        return m

    @staticmethod
    def _n(normal: Any) -> np.ndarray:
        return np.asarray(normal, dtype=float).reshape(1, 3)

    def make_rot0(self) -> None:
        """``R0``: rows two tangent directions and ``normal0``."""
        self.R0 = gicp_normal_frame(self._n(self.normal0))[0]

    def make_rot1(self) -> None:
        """``R1``: rows two tangent directions and ``normal1``."""
        self.R1 = gicp_normal_frame(self._n(self.normal1))[0]

    def prec0(self, e: float) -> np.ndarray:
        """Information tight along ``normal0``: ``R0ᵀ diag(e, e, 1) R0``.

        Args:
            e: Weight of the tangent directions.
        """
        self.make_rot0()
        return gicp_precision(self._n(self.normal0), float(e))[0]

    def prec1(self, e: float) -> np.ndarray:
        """Information tight along ``normal1``.

        Args:
            e: Weight of the tangent directions.
        """
        self.make_rot1()
        return gicp_precision(self._n(self.normal1), float(e))[0]

    def cov0(self, e: float) -> np.ndarray:
        """Covariance small along ``normal0``: ``R0ᵀ diag(1, 1, e) R0``.

        Args:
            e: Variance along the normal.
        """
        self.make_rot0()
        return gicp_covariance(self._n(self.normal0), float(e))[0]

    def cov1(self, e: float) -> np.ndarray:
        """Covariance small along ``normal1``.

        Args:
            e: Variance along the normal.
        """
        self.make_rot1()
        return gicp_covariance(self._n(self.normal1), float(e))[0]


class EdgeVVGicp(BaseEdge):
    """g2o's ``Edge_V_V_GICP``: ``e = X0⁻¹·X1·pos1 − pos0``; with ``pl_pl`` the information is
    ``(cov0 + R cov1 Rᵀ)⁻¹`` at every evaluation (set ``cov0``/``cov1``)."""

    __slots__ = ("pl_pl", "cov0", "cov1")
    _dim = 3
    _mshape = (2, 3)
    _gname = "EdgeVVGicp"

    def __init__(self) -> None:
        super().__init__()
        self.pl_pl = False
        self.cov0 = np.eye(3)
        self.cov1 = np.eye(3)

    def set_measurement(self, measurement: Any) -> None:
        """Set the measurement (copied).

        Args:
            measurement: An :class:`EdgeGICP` (or ``(2, 3)`` ``[pos0, pos1]``).
        """
        super().set_measurement(measurement.copy() if isinstance(measurement, EdgeGICP)
                                else measurement)

    def measurement(self) -> Any:
        """The measurement: an :class:`EdgeGICP` with its normals (``load`` keeps the file's)."""
        m = self._meas
        return m.copy() if isinstance(m, EdgeGICP) else super().measurement()

    def _params_key(self) -> tuple[Any, ...]:
        return (bool(self.pl_pl),)

    @classmethod
    def _core_name(cls, key: tuple[Any, ...]) -> str:
        return "EdgeVVGicpPlaneToPlane" if key and key[0] else cls._gname

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        return np.array([[r.pos0, r.pos1] if isinstance(r, EdgeGICP) else r for r in raws],
                        dtype=float).reshape(len(raws), 2, 3)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        m = EdgeGICP()
        m.pos0, m.pos1 = row[0].copy(), row[1].copy()
        return m

    @classmethod
    def _data(cls, recs: list[BaseEdge]) -> dict[str, np.ndarray]:
        if not recs or not recs[0].pl_pl:  # type: ignore[attr-defined]
            return {}
        return {"cov0": np.array([r.cov0 for r in recs], dtype=float),  # type: ignore
                "cov1": np.array([r.cov1 for r in recs], dtype=float)}  # type: ignore


class EdgeXyzVsc(BaseEdge):
    """g2o's ``Edge_XYZ_VSC`` (``EdgeXyzVsc``): stereo ``(u, v, u_right)`` of ``(point,
    VertexSCam)``, the intrinsics ``VertexSCam``'s static ones."""

    __slots__ = ()
    _dim = 3
    _mshape = (3,)
    _gname = "EdgeXyzVsc"
    _perm = (1, 0)
    _param_type = "SCamParameters"

    def _params_key(self) -> tuple[Any, ...]:
        from .vertices import VertexSCam

        return VertexSCam._cam


ICP_EDGES: dict[str, type] = {"EdgeVVGicp": EdgeVVGicp, "Edge_V_V_GICP": EdgeVVGicp,
                              "EdgeGICP": EdgeGICP, "EdgeXyzVsc": EdgeXyzVsc,
                              "Edge_XYZ_VSC": EdgeXyzVsc}
