"""g2o's vertex classes as thin records: an id, an estimate as the program gave it (a float
vector as its bytes) and two flags until ``initialize_optimization``; then a slot in a graphopt
vertex store (a *bank*, one per graphopt type), whose row ``estimate()`` reads. ``add_vertex``
only files the record: each type's estimates become graphopt's array in one step, checked
(shapes, finite values, rotations) once, in bulk, naming the offending vertex's id."""

from __future__ import annotations

import copy as _copy
from importlib import import_module
from math import prod
from typing import Any

import numpy as np

from graphopt.errors import GraphError
from graphopt.linear.indexing import IdLookup
from graphopt.storage import VertexStore

from .geometry import SE2, Isometry3d, SE3Quat, _RigidBase
from .raw import joined, unbytes
from .sim3 import Sim3

__all__ = ["BaseVertex", "VERTEX_CLASSES"]

_F8 = np.dtype(np.float64)


class Bank:
    """The graphopt store behind all records of one graphopt vertex type (replaced when the
    core optimizer is rebuilt; records keep their slot). Records point at their bank, not the
    bank at them (no reference cycle: the optimizer holds the records)."""

    __slots__ = ("gtype", "store", "ids", "user_fixed", "marg", "initial", "_lookup")

    def __init__(self, gtype: type, records: list[BaseVertex], initial: np.ndarray) -> None:
        self.gtype = gtype
        self.store: VertexStore | None = None
        n = len(records)
        self.ids = np.fromiter([r._id for r in records], np.int64, count=n)
        self.user_fixed = np.fromiter([r._fixed for r in records], bool, count=n)
        self.marg = np.fromiter([r._marg for r in records], bool, count=n)
        self.initial = initial  # the estimates until the first core store exists
        self._lookup: IdLookup | None = None  # see slots_of
        for i, r in enumerate(records):  # (one loop: half the cost of two setattr passes)
            r._bank = self
            r._slot = i

    def slots_of(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slots of ``ids`` and whether each is in this bank.

        Args:
            ids: ``(m,)`` vertex ids.
        """
        if self._lookup is None:  # once per bank
            self._lookup = IdLookup(self.ids)
        return self._lookup(ids)

    def estimates(self) -> np.ndarray:
        """The current ``(n, *shape)`` estimates (the store's, or the initial ones)."""
        return self.store.estimates if self.store is not None else self.initial


_CORE_TYPES: dict[str, type] = {}


def core_type(name: str) -> type:
    """``graphopt.types.<name>``, or ``NotImplementedError`` naming it while it is missing."""
    t = _CORE_TYPES.get(name)
    if t is None:  # (the import machinery costs microseconds a call: once per name)
        try:
            t = _CORE_TYPES[name] = getattr(import_module("graphopt.types"), name)
        except AttributeError:
            raise NotImplementedError(f"graphopt.g2o: graphopt.types has no {name} yet; the "
                                      "g2o type that needs it is not supported") from None
    return t


class BaseVertex:
    """A g2o vertex record (``set_id``, ``set_estimate``, ``estimate``, ``set_fixed``,
    ``set_marginalized``)."""

    __slots__ = ("_id", "_est", "_fixed", "_marg", "_opt", "_bank", "_slot", "__weakref__")
    #: graphopt's vertex type (name in graphopt.types) and its estimate shape.
    _gname = ""
    _shape: tuple[int, ...] = ()
    #: Whether the estimate is the plain vector (the base class's conversions).
    _vector = True

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._vector = (cls._to_array.__func__ is BaseVertex._to_array.__func__  # type: ignore
                       and cls._from_row.__func__ is BaseVertex._from_row.__func__  # type: ignore
                       and cls._finish.__func__ is BaseVertex._finish.__func__)  # type: ignore

    def __init__(self) -> None:
        self._id = self._slot = -1
        self._est: Any = None
        self._fixed = self._marg = False
        self._opt: Any = None
        self._bank: Bank | None = None

    # --- g2o's API ---------------------------------------------------------------------------

    def set_id(self, vid: int) -> None:
        """Set the id (unique in the optimizer).

        Args:
            vid: The id.
        """
        self._id = int(vid)

    def id(self) -> int:
        """The id."""
        return self._id

    def set_estimate(self, estimate: Any) -> None:
        """Set the estimate (copied); after ``initialize_optimization`` it goes straight to the
        store.

        Args:
            estimate: The vertex type's estimate (``SE3Quat``, ``Isometry3d``, ``SE2``, ``Sim3``
                or a vector as list, tuple or array).
        """
        bank = self._bank
        if bank is None:
            if type(estimate) is np.ndarray:  # a float vector: its bytes (a third of a copy)
                self._est = (estimate.tobytes() if self._vector and estimate.dtype is _F8
                             else estimate.copy())
            else:
                self._est = (list(estimate) if isinstance(estimate, list | tuple)
                             else self._clone(estimate))
            return
        row = self._to_array([estimate], [self._id])
        self._finish(row, [self])
        row = row[0]
        st = bank.store
        if st is None:
            bank.initial[self._slot] = row
            return
        st.set_estimate(self._slot, row, self._id)  # (a value it validated last is not again)

    def estimate(self) -> Any:
        """The estimate (read from the store after ``initialize_optimization``)."""
        bank = self._bank
        if bank is None:
            est = self._est
            if est is None:
                return None
            if type(est) is bytes:  # set_estimate's bytes of a float vector
                est = np.frombuffer(est).copy()
                if est.size == prod(self._shape):
                    return est.reshape(self._shape)
            return self._from_row(self._to_array([est], [self._id])[0])
        return self._from_row(bank.estimates()[self._slot])

    def set_fixed(self, fixed: bool) -> None:
        """Hold the vertex constant.

        Args:
            fixed: The flag.
        """
        self._fixed = bool(fixed)
        bank = self._bank
        if bank is not None:
            bank.user_fixed[self._slot] = self._fixed
            if bank.store is not None:  # graphopt rebuilds the structure at the next run
                bank.store.set_flag("fixed", self._slot, self._fixed)

    def fixed(self) -> bool:
        """Whether the vertex is held constant."""
        return self._fixed

    def set_marginalized(self, marginalized: bool) -> None:
        """Eliminate the vertex by the Schur complement.

        Args:
            marginalized: The flag.
        """
        self._marg = bool(marginalized)
        bank = self._bank
        if bank is not None:
            bank.marg[self._slot] = self._marg
            if bank.store is not None:  # graphopt rebuilds the structure at the next run
                bank.store.set_flag("marginalized", self._slot, self._marg)

    def marginalized(self) -> bool:
        """Whether the vertex is marginalised."""
        return self._marg

    def dimension(self) -> int:
        """The tangent-space dimension."""
        return core_type(self._gname).dimension

    def __repr__(self) -> str:
        return f"{type(self).__name__}(id={self._id})"

    def _detach(self) -> None:
        """Leave the optimizer (removed, or the optimizer is gone), keeping the current
        estimate in the record."""
        bank = self._bank
        if bank is not None:
            self._est = self._from_row(bank.estimates()[self._slot])
        self._opt = self._bank = None

    # --- conversion (overridden per type) ----------------------------------------------------

    @staticmethod
    def _clone(estimate: Any) -> Any:
        if isinstance(estimate, _RigidBase | Sim3 | SE2):
            return _copy.copy(estimate)  # shallow: their arrays are replaced, never written
        copy = getattr(estimate, "copy", None)
        return copy() if callable(copy) else estimate

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        """``(n, *shape)`` estimates from the raw values (vectors by default)."""
        n, shape = len(raws), cls._shape
        arr = joined(raws, shape)
        if arr is not None:
            return arr
        raws = unbytes(raws)
        try:
            arr = np.array(raws, dtype=float)
            if arr.size == n * int(np.prod(shape)):
                return arr.reshape(n, *shape)
        except (TypeError, ValueError):
            pass
        for vid, raw in zip(ids, raws, strict=True):  # name the first bad one
            try:
                a = np.array(raw, dtype=float)
                if a.size == int(np.prod(shape)):
                    continue
                got = f"shape {a.shape}"
            except (TypeError, ValueError):
                got = type(raw).__name__
            raise GraphError(f"vertex {vid} ({cls.__name__}): estimate has {got}, expected "
                             f"{shape}")
        raise GraphError(f"{cls.__name__}: estimates could not be converted")

    @classmethod
    def _from_row(cls, row: np.ndarray) -> Any:
        return row.copy()

    @classmethod
    def _default(cls) -> Any:
        """g2o's initial estimate (``setToOrigin``)."""
        return np.zeros(cls._shape)

    @classmethod
    def _finish(cls, est: np.ndarray, recs: list[BaseVertex]) -> None:
        """Complete converted estimates with what the records hold besides (in place)."""


def _rigid_rows(cls: type, raws: list[Any], ids: list[int], rows: int) -> np.ndarray:
    """``(n, rows, 4)`` ``[R | t]`` (+ bottom row) from SE3Quat/Isometry3d records or
    matrices."""
    n = len(raws)
    out = np.zeros((n, rows, 4))
    if n == 1 and isinstance(raws[0], _RigidBase):  # set_estimate of a filed vertex
        out[0, :3, :3], out[0, :3, 3] = raws[0]._R, raws[0]._t
    elif all(isinstance(r, _RigidBase) for r in raws):
        out[:, :3, :3] = np.array([r._R for r in raws])
        out[:, :3, 3] = np.array([r._t for r in raws])
    else:
        for i, (vid, r) in enumerate(zip(ids, raws, strict=True)):
            if isinstance(r, _RigidBase):
                out[i, :3, :3], out[i, :3, 3] = r._R, r._t
                continue
            m = np.array(r, dtype=float)
            if m.shape not in ((4, 4), (3, 4)):
                raise GraphError(f"vertex {vid} ({cls.__name__}): estimate must be an SE3Quat, "
                                 f"an Isometry3d or a 4x4 matrix, got {type(r).__name__}")
            out[i, :3] = m[:3]
    if rows == 4:
        out[:, 3, 3] = 1.0
    return out


class VertexSE3Expmap(BaseVertex):
    """g2o's ``VertexSE3Expmap`` (estimate ``SE3Quat``, world to camera)."""

    __slots__ = ()
    _gname = "VertexSE3Expmap"
    _shape = (4, 4)

    @classmethod
    def _default(cls) -> Any:
        return SE3Quat()

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        return _rigid_rows(cls, raws, ids, 4)

    @classmethod
    def _from_row(cls, row: np.ndarray) -> SE3Quat:
        m = row.copy()  # one copy; the record holds views of it
        return SE3Quat._of(m[:3, :3], m[:3, 3])


class VertexSE3(BaseVertex):
    """g2o's ``VertexSE3`` (estimate ``Isometry3d``)."""

    __slots__ = ()
    _gname = "VertexSE3"
    _shape = (3, 4)

    @classmethod
    def _default(cls) -> Any:
        return Isometry3d()

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        return _rigid_rows(cls, raws, ids, 3)

    @classmethod
    def _from_row(cls, row: np.ndarray) -> Isometry3d:
        m = row.copy()
        return Isometry3d._of(m[:, :3], m[:, 3])


class VertexSCam(VertexSE3):
    """g2o's ``VertexSCam``: a stereo camera's pose in the world (an ``Isometry3d``); the
    intrinsics are static, as in g2o (``VertexSCam.set_cam(fx, fy, cx, cy, baseline)``)."""

    __slots__ = ()
    _gname = "VertexSCam"
    _cam = (1.0, 1.0, 0.5, 0.5, 0.1)

    @staticmethod
    def set_cam(fx: float, fy: float, cx: float, cy: float, baseline: float) -> None:
        """Set the intrinsics of every ``VertexSCam`` (g2o's static ``setKcam``).

        Args:
            fx: Focal length x.
            fy: Focal length y.
            cx: Principal point x.
            cy: Principal point y.
            baseline: Stereo baseline.
        """
        VertexSCam._cam = (float(fx), float(fy), float(cx), float(cy), float(baseline))

    set_kcam = set_cam

    def set_all(self) -> None:
        """g2o caches its projection matrices here; nothing to do."""

    def map_point(self, p: Any) -> np.ndarray:
        """``[u, v, u_right]`` of a world point.

        Args:
            p: ``(3,)`` world point.
        """
        from graphopt.types.sba_cam import stereo_projection

        T = self.estimate()
        pc = T._R.T @ (np.asarray(p, dtype=float).reshape(3) - T._t)
        return stereo_projection(pc[None], *self._cam)[0][0]

    def Kcam(self) -> np.ndarray:  # noqa: N802 - g2o's name
        """The 3x3 camera matrix."""
        fx, fy, cx, cy, _ = self._cam
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def baseline(self) -> float:
        """The stereo baseline."""
        return self._cam[4]


class VertexPointXYZ(BaseVertex):
    """g2o's ``VertexPointXYZ`` (the old bindings' ``VertexSBAPointXYZ``): a ``(3,)`` point."""

    __slots__ = ()
    _gname = "VertexPointXYZ"
    _shape = (3,)


class VertexPointXY(BaseVertex):
    """g2o's ``VertexPointXY``: a ``(2,)`` point."""

    __slots__ = ()
    _gname = "VertexPointXY"
    _shape = (2,)


class VertexOdomDifferentialParams(BaseVertex):
    """g2o's ``VertexOdomDifferentialParams``: ``[k_l, k_r, b]``."""

    __slots__ = ()
    _gname = "VertexOdomDifferentialParams"
    _shape = (3,)


class VertexSE2(BaseVertex):
    """g2o's ``VertexSE2`` (estimate ``SE2``)."""

    __slots__ = ()
    _gname = "VertexSE2"
    _shape = (3,)

    @classmethod
    def _default(cls) -> Any:
        return SE2()

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        if all(type(r) is SE2 for r in raws):
            return np.array([r._v for r in raws]).reshape(len(raws), 3)
        return BaseVertex._to_array.__func__(cls, [r._v if type(r) is SE2 else r for r in raws],
                                             ids)

    @classmethod
    def _from_row(cls, row: np.ndarray) -> SE2:
        return SE2._of(row.copy())


class VertexSim3Expmap(BaseVertex):
    """g2o's ``VertexSim3Expmap`` (estimate ``Sim3``). ``_fix_scale`` (set before the first
    ``initialize_optimization``) travels in graphopt's estimate; the two cameras' intrinsics
    (``_focal_length1/2``, ``_principle_point1/2``) become the Sim3 projection edges'
    parameters."""

    __slots__ = ("_fix_scale", "_focal_length1", "_focal_length2", "_principle_point1",
                 "_principle_point2")
    _gname = "VertexSim3Expmap"
    _shape = (4, 4)

    def __init__(self) -> None:
        super().__init__()
        self._fix_scale = False
        self._focal_length1 = np.ones(2)
        self._focal_length2 = np.ones(2)
        self._principle_point1 = np.zeros(2)
        self._principle_point2 = np.zeros(2)

    def cam_map1(self, p: Any) -> np.ndarray:
        """Pixel of a point in camera 1 (``_focal_length1``, ``_principle_point1``).

        Args:
            p: ``(3,)`` camera-frame point.
        """
        p = np.asarray(p, dtype=float).reshape(3)
        return p[:2] / p[2] * np.asarray(self._focal_length1) + self._principle_point1

    def cam_map2(self, p: Any) -> np.ndarray:
        """Pixel of a point in camera 2.

        Args:
            p: ``(3,)`` camera-frame point.
        """
        p = np.asarray(p, dtype=float).reshape(3)
        return p[:2] / p[2] * np.asarray(self._focal_length2) + self._principle_point2

    def camera(self, which: int) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` of camera 1 or 2.

        Args:
            which: 1 or 2.
        """
        f = np.broadcast_to(np.asarray(getattr(self, f"_focal_length{which}"), float), (2,))
        c = np.asarray(getattr(self, f"_principle_point{which}"), float).reshape(2)
        return (float(f[0]), float(f[1]), float(c[0]), float(c[1]))

    @classmethod
    def _default(cls) -> Any:
        return Sim3()

    @classmethod
    def _to_array(cls, raws: list[Any], ids: list[int]) -> np.ndarray:
        out = np.zeros((len(raws), 4, 4))
        for i, (vid, r) in enumerate(zip(ids, raws, strict=True)):
            if not isinstance(r, Sim3):
                raise GraphError(f"vertex {vid} (VertexSim3Expmap): estimate must be a Sim3, "
                                 f"got {type(r).__name__}")
            out[i, :3, :3], out[i, :3, 3] = r._s * r._R, r._t
        out[:, 3, 3] = 1.0
        return out

    @classmethod
    def _finish(cls, est: np.ndarray, recs: list[BaseVertex]) -> None:
        est[:, 3, 0] = [float(r._fix_scale) for r in recs]  # type: ignore[attr-defined]

    @classmethod
    def _from_row(cls, row: np.ndarray) -> Sim3:
        sR = row[:3, :3]
        s = float(np.cbrt(np.linalg.det(sR)))
        return Sim3._of(sR / s, row[:3, 3].copy(), s)


VERTEX_CLASSES: dict[str, type[BaseVertex]] = {
    "VertexSE3Expmap": VertexSE3Expmap, "VertexSE3": VertexSE3,
    "VertexPointXYZ": VertexPointXYZ, "VertexSBAPointXYZ": VertexPointXYZ,
    "VertexPointXY": VertexPointXY, "VertexSE2": VertexSE2,
    "VertexSim3Expmap": VertexSim3Expmap, "VertexSCam": VertexSCam,
    "VertexOdomDifferentialParams": VertexOdomDifferentialParams,
}
