"""g2o's edge classes as thin records, and the g2o types graphopt does not support.

An edge is its vertices, measurement, information, kernel, level and parameter ids until
``initialize_optimization``; then it is an index into a *batch* (all edges of its class and
parameters, as arrays) and its getters read the batch: ``chi2()`` and ``error()`` evaluate the
whole batch once per state and index it, ``set_level`` and ``set_robust_kernel`` write one
entry. Each class maps g2o's vertex order onto the graphopt type's (``_perm``: graphopt position
``p`` takes g2o vertex ``_perm[p]``).
"""

from __future__ import annotations

from math import prod
from typing import Any

import numpy as np

from graphopt.errors import GraphError

from .raw import joined, unbytes
from .vertices import BaseVertex

__all__ = ["UNSUPPORTED", "BaseEdge", "unsupported"]

#: The parameter ids of an edge whose ``set_parameter_id`` was not called, by slot count.
_ZEROS: tuple[tuple[int, ...], ...] = tuple((0,) * n for n in range(8))
_F8 = np.dtype(np.float64)
#: One-slot parameter-id tuples of small ids, shared (no tuple per edge for the collector to
#: scan: g2o programs give every edge ``set_parameter_id(0, 0)``).
_PIDS1: tuple[tuple[int], ...] = tuple((i,) for i in range(64))
#: The information matrices set, by value (bytes, rows): their shared read-only copies.
_INFOS: dict[tuple[bytes, int], np.ndarray] = {}
#: Most values _INFOS keeps (ORB-SLAM's σ⁻² per pyramid level: 8; it starts again when full).
_INFOS_KEPT = 64
#: Per class, its compiled :meth:`BaseEdge._keys_of` and :meth:`BaseEdge._shared_key`.
_KEYS: dict[type, Any] = {}


class BaseEdge:
    """A g2o edge record."""

    # Vertices 0 and 1 in slots, any further ones in ``_vn`` (``None`` for one- and two-vertex
    # edges): no list per edge for the cyclic collector to scan (``_v`` gives them as a list).
    __slots__ = ("_v0", "_v1", "_vn", "_meas", "_info", "_kernel", "_level", "_pids", "_id",
                 "_opt", "_batch", "_idx", "__weakref__")
    _k = 2
    _dim = 2
    _gname = ""
    _perm: tuple[int, ...] = (0, 1)
    _mshape: tuple[int, ...] = (2,)
    #: g2o vertex position → graphopt vertex type name, where it differs from the vertex class's.
    _vertex_as: dict[int, str] = {}
    #: Parameter slots (``set_parameter_id``) and what they hold.
    _nparams = 0
    #: graphopt.types parameter class built from ``_params_key()`` (intrinsics on the edge).
    _param_type = ""
    #: The parameter ids of a new edge (``_ZEROS[_nparams]``, set per class).
    _zero_pids: tuple[int, ...] = ()
    #: Whether the measurement is a plain float vector (the base class's conversion): an array
    #: given to ``set_measurement`` is then kept as its bytes (a third of a copy's cost), which
    #: ``initialize_optimization`` joins into the batch's array in one step.
    _raw_vector = True
    #: Attributes a class adds to its records, with their defaults (fx, ..., Xw): a class
    #: without an ``__init__`` of its own gets one that stores these and the base's (see
    #: :func:`_flat_init`).
    _defaults: dict[str, Any] = {}

    def __init__(self) -> None:
        # The base's fields, for classes with an __init__ of their own (they call this
        # directly, not through super(): one object less per record); the others have one flat
        # body from _flat_init. A program makes one record per edge: each step here is paid
        # thousands of times.
        self._v0: BaseVertex | None = None
        self._v1: BaseVertex | None = None
        # Vertices 2, 3, ... (see _v): a list only for types of more than two.
        self._vn: list[BaseVertex | None] | None = None
        self._meas = self._info = self._kernel = self._opt = self._batch = None
        self._level = 0
        self._pids = self._zero_pids  # a shared tuple: no container per edge
        self._id = self._idx = -1
        if self._k > 2:
            self._vn = [None] * (self._k - 2)

    # --- building ----------------------------------------------------------------------------

    def set_vertex(self, i: int, vertex: BaseVertex | None) -> None:
        """Connect vertex ``i``.

        Args:
            i: Position (g2o's order).
            vertex: The vertex.
        """
        if i == 0:
            self._v0 = vertex
        elif i == 1 and self._k != 1:
            self._v1 = vertex
        else:  # further vertices, negative or bad positions
            vs = self._v
            vs[i] = vertex
            self._v = vs
        if self._batch is not None:
            self._structure_changed()

    def vertex(self, i: int) -> BaseVertex | None:
        """Vertex ``i``.

        Args:
            i: Position.
        """
        if i == 0:
            return self._v0
        if i == 1 and self._k != 1:
            return self._v1
        return self._v[i]

    @property
    def _v(self) -> list[BaseVertex | None]:
        """The vertices in g2o's order, as a new list (the type's count, or ``resize``'s)."""
        vn = self._vn
        if vn is None:
            return [self._v0] if self._k == 1 else [self._v0, self._v1]
        return [self._v0, self._v1, *vn]

    @_v.setter
    def _v(self, vertices: list[BaseVertex | None]) -> None:
        n = len(vertices)
        self._v0 = vertices[0] if n else None
        self._v1 = vertices[1] if n > 1 else None
        # A list for more than two vertices, or for a count that is not the class's (resize).
        self._vn = list(vertices[2:]) if n > 2 or n != self._k else None

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
        if type(measurement) is np.ndarray:
            self._meas = (measurement.tobytes() if self._raw_vector and measurement.dtype is _F8
                          else measurement.copy())
        else:
            self._meas = measurement
        if self._batch is not None:
            self._structure_changed()

    def measurement(self) -> Any:
        """The measurement."""
        if self._batch is not None:
            return self._from_measurement(self._batch.meas[self._idx])
        m = self._meas
        if type(m) is bytes:  # a float vector kept as its bytes (see _raw_vector)
            a = np.frombuffer(m).copy()
            return a.reshape(self._mshape) if a.size == prod(self._mshape) else a
        return m

    def set_information(self, information: Any) -> None:
        """Set the information matrix (copied).

        Args:
            information: ``(d, d)`` (nested lists accepted).
        """
        if type(information) is np.ndarray and information.dtype is _F8 and information.ndim == 2:
            # Programs give every edge one of a few matrices (one, or σ⁻²·I per pyramid level):
            # equal values share one read-only copy, which initialize_optimization recognises
            # by identity (equal bytes and row counts of two matrices: equal shapes).
            key = (information.tobytes(), len(information))
            info = _INFOS.get(key)
            if info is None:
                if len(_INFOS) >= _INFOS_KEPT:
                    _INFOS.clear()
                info = _INFOS[key] = information.copy()
                info.flags.writeable = False
            self._info = info
        else:
            self._info = np.array(information, dtype=float)
        if self._batch is not None:
            self._structure_changed()

    def information(self) -> np.ndarray:
        """The information matrix (identity when unset)."""
        if self._batch is not None:
            return self._batch.information_of(self._idx)
        return self._info.copy() if self._info is not None else np.eye(self._dim)

    def set_robust_kernel(self, kernel: Any) -> None:
        """Set (or with ``None`` drop) the robust kernel; after initialisation the change reaches
        the optimizer's arrays at once.

        Args:
            kernel: A ``RobustKernel*`` object or ``None``.
        """
        self._kernel = kernel
        b = self._batch
        if b is not None:  # Batch.set_kernel inlined (outlier passes call this per edge)
            b.kcodes[self._idx] = -1 if kernel is None else b.code(kernel)
            if not b.kernels_dirty and b.group is not None:
                b.kernels_dirty = True
                b._notify()

    def robust_kernel(self) -> Any:
        """The robust kernel or ``None``."""
        return self._kernel

    def set_level(self, level: int) -> None:
        """Set the level (``initialize_optimization(level)`` takes the edges of that level).

        Args:
            level: An integer.
        """
        if level == self._level and type(level) is int:  # unchanged (outlier loops): nothing
            return
        self._level = level = int(level)
        b = self._batch
        if b is not None:
            if level < 0:
                b.set_level(self._idx, level)  # its error
            else:  # Batch.set_level inlined (outlier passes call this per edge)
                b.levels[self._idx] = level
                if not b.levels_dirty and b.group is not None:
                    b.levels_dirty = True
                    b._notify()

    def level(self) -> int:
        """The level."""
        return self._level

    def set_parameter_id(self, slot: int, pid: int) -> None:
        """Name the parameter (``optimizer.add_parameter``) of a slot.

        Args:
            slot: The parameter slot (0).
            pid: The parameter's id.
        """
        n = self._nparams
        if n == 1 and slot == 0:  # the usual call: set_parameter_id(0, pid)
            self._pids = _PIDS1[pid] if type(pid) is int and 0 <= pid < 64 else (int(pid),)
        elif not 0 <= int(slot) < max(n, 1):
            raise ValueError(f"{type(self).__name__} has {n} parameter slots")
        elif n:
            pids = list(self._pids)
            pids[int(slot)] = int(pid)
            self._pids = tuple(pids)
        if self._batch is not None:
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

    def _detach(self) -> None:
        """Leave the optimizer (removed, or the optimizer is gone)."""
        self._opt = self._batch = None

    def _structure_changed(self) -> None:
        if self._batch is not None:
            opt = self._opt()  # the optimizer, unless it is gone
            if opt is not None:
                opt._structure_changed()
            self._batch = None

    # --- evaluation (batched) ----------------------------------------------------------------

    def compute_error(self) -> None:
        """Compute the error at the current estimates (evaluated lazily, for the whole batch)."""
        if self._batch is None:
            self._need_batch()

    def chi2(self) -> float:
        """``eᵀΩe`` at the current estimates, without the kernel (g2o's ``chi2()``)."""
        b = self._batch
        if b is not None:
            c = b._fchi2  # the batch's chi2s while both stores' estimates are unchanged
            if c is not None and b._st0.version == b._fv0 and b._st1.version == b._fv1:
                return c[self._idx]
            return b.chi2_of(self._idx)
        return self._need_batch().chi2_of(self._idx)

    def error(self) -> np.ndarray:
        """The error at the current estimates."""
        return self._need_batch().errors()[self._idx].copy()

    def is_depth_positive(self) -> bool:
        """Whether the observed point is in front of the camera(s)."""
        b = self._batch
        if b is None:
            b = self._need_batch()
        else:
            d = b._fdepth  # as chi2()
            if d is not None and b._st0.version == b._fv0 and b._st1.version == b._fv1:
                return d[self._idx]
        return b.depth_positive_of(self._idx)

    def _need_batch(self) -> Any:
        if self._batch is None:
            if self._opt is None:
                raise RuntimeError(f"{type(self).__name__}: add the edge to an optimizer first")
            opt = self._opt()
            if opt is None:
                raise GraphError(f"{type(self).__name__} on vertices "
                                 f"{[v._id if v is not None else None for v in self._v]}: its "
                                 "optimizer was deleted after the edge changed; add it to an "
                                 "optimizer again")
            opt._prepare()
        return self._batch

    # --- conversion (overridden per type) ----------------------------------------------------

    def _params_key(self) -> tuple[Any, ...]:
        return self._pids

    #: The attributes :meth:`_params_key` returns (its tuple), for a C-level getter over many
    #: records; ``None`` where a class computes its key otherwise.
    _key_attrs: tuple[str, ...] | None = ("_pids",)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "_params_key" in cls.__dict__ and "_key_attrs" not in cls.__dict__:
            cls._key_attrs = None
        cls._zero_pids = _ZEROS[cls._nparams]
        # Plain vectors (the base class's conversions) are kept as their bytes until filing.
        cls._raw_vector = (cls._measurements.__func__ is BaseEdge._measurements.__func__  # type: ignore
                           and cls.set_measurement is BaseEdge.set_measurement)
        if getattr(cls.__init__, "_flat", False) or cls.__init__ is BaseEdge.__init__:
            cls.__init__ = _flat_init(cls)  # type: ignore[method-assign]

    @classmethod
    def _keys_of(cls, recs: list[BaseEdge]) -> list[Any]:
        """Every record's :meth:`_params_key`.

        One list comprehension compiled per class from ``_key_attrs``: a comprehension reads
        slots twice as fast as ``map`` with an ``attrgetter`` (Python 3.11 specialises the
        attribute reads), 15 against 32 µs for the 4 intrinsics of 500 records.

        Args:
            recs: Records of this class.
        """
        return cls._key_functions()[0](recs)

    @classmethod
    def _shared_key(cls, recs: list[BaseEdge]) -> Any:
        """The key every record has (the usual batch: one camera's intrinsics), else ``None``:
        compared attribute by attribute, no tuple per record (12 against 21 µs for 500).

        Args:
            recs: Records of this class (at least one).
        """
        return cls._key_functions()[1](recs)

    @classmethod
    def _key_functions(cls) -> tuple[Any, Any]:
        """:meth:`_keys_of` and :meth:`_shared_key`, compiled for this class."""
        f = _KEYS.get(cls)
        if f is None:
            a = cls._key_attrs
            expr = ("r._params_key()" if not a else f"r.{a[0]}" if len(a) == 1
                    else "(" + ", ".join(f"r.{n}" for n in a) + ")")
            names = [f"_k{i}" for i in range(len(a or ()))]
            differs = " or ".join(f"r.{n} != {k}" for n, k in zip(a or (), names, strict=True))
            src = f"def keys(recs):\n    return [{expr} for r in recs]\n"
            src += ("def shared(recs):\n    return None\n" if not a else
                    f"def shared(recs):\n    r = recs[0]\n    key = {expr}\n"
                    f"    {', '.join(names)}{',' if len(a) == 1 else ''} = "
                    f"{'(key,)' if len(a) == 1 else 'key'}\n"
                    f"    for r in recs:\n        if {differs}:\n            return None\n"
                    "    return key\n")
            ns: dict[str, Any] = {}
            exec(src, ns)  # noqa: S102 - source from class attribute names
            f = _KEYS[cls] = (ns["keys"], ns["shared"])
        return f

    @classmethod
    def _core_name(cls, key: tuple[Any, ...]) -> str:
        """graphopt's type (name in graphopt.types) for the batch of this parameter key."""
        return cls._gname

    @classmethod
    def _core_type(cls, key: tuple[Any, ...]) -> type:
        """graphopt's type for the batch of this parameter key."""
        from .vertices import core_type

        return core_type(cls._core_name(key))

    @classmethod
    def _measurements(cls, raws: list[Any]) -> np.ndarray:
        arr = joined(raws, cls._mshape)  # set_measurement's bytes (_raw_vector): one join
        if arr is not None:
            return arr
        return np.array(unbytes(raws), dtype=float).reshape(len(raws), *cls._mshape)

    @classmethod
    def _from_measurement(cls, row: np.ndarray) -> Any:
        return row.copy()

    @classmethod
    def _data(cls, recs: list[BaseEdge]) -> dict[str, np.ndarray]:
        """Per-edge arrays graphopt's type reads (``Xw`` of the pose-only edges)."""
        return {}

    @staticmethod
    def _depth(x: list[np.ndarray], data: dict[str, np.ndarray], params: Any) -> np.ndarray:
        """``(m,)`` depth tests of a batch (this default defers to graphopt's type)."""
        raise NotImplementedError


def _flat_init(cls: type[BaseEdge]) -> Any:
    """An ``__init__`` for ``cls`` that stores every field of a new record in one body: the
    base's fields and the ``_defaults`` of each class along the MRO (``fx``, ``Xw``, ...).

    Written as source and compiled (as :mod:`dataclasses` writes ``__init__``): a chain of
    ``__init__`` calls costs 40–50 ns a record more, about 5 % of a record's making.

    Args:
        cls: A class that does not define ``__init__`` by hand (nor do its bases below
            :class:`BaseEdge`).
    """
    fields: dict[str, Any] = {"_v0": None, "_v1": None, "_vn": None, "_meas": None,
                              "_info": None, "_kernel": None, "_opt": None, "_batch": None,
                              "_level": 0, "_pids": cls._zero_pids, "_id": -1, "_idx": -1}
    for c in reversed(cls.__mro__):
        fields.update(c.__dict__.get("_defaults", {}))
    # One chained store per distinct value (``self.fx = self.fy = ... = _d1``: cheaper than a
    # load per field).
    groups: dict[int, list[str]] = {}
    values: dict[int, Any] = {}
    for name, value in fields.items():
        groups.setdefault(id(value), []).append(name)
        values[id(value)] = value
    ns: dict[str, Any] = {f"_d{i}": values[k] for i, k in enumerate(groups)}
    body = ["    " + " = ".join(f"self.{n}" for n in names) + f" = _d{i}"
            for i, names in enumerate(groups.values())]
    if cls._k > 2:  # vertices 2, 3, ...: a list of the record's own
        body.append(f"    self._vn = [None] * {cls._k - 2}")
    exec("def __init__(self):\n" + "\n".join(body), ns)  # noqa: S102 - fixed source, no input
    init = ns["__init__"]
    init._flat = True
    init.__qualname__ = f"{cls.__name__}.__init__"
    return init


#: Names of the official wheel that graphopt.g2o does not provide (its machinery, simulators,
#: helpers): constructing one raises ``NotImplementedError`` naming it.
UNSUPPORTED: tuple[str, ...] = (
    "AbstractOptimizationAlgorithmCreator", "Affine", "AffineCompact", "EstimatePropagator",
    "EstimatePropagatorCost", "EstimatePropagatorCostBase", "EstimatePropagatorCostOdometry",
    "Factory", "FactoryTypeInfo", "G2OBatchStatistics", "HyperDijkstra", "HyperGraph",
    "HyperGraphAction", "IoFileFilter", "IoWrapper", "Isometry2d", "JacobianWorkspace",
    "MotionMeasurement", "OdomConvert", "OptimizableGraph", "OptimizationAlgorithmProperty",
    "OptimizationAlgorithmWithHessian", "ParameterContainer", "Projective",
    "RegisterOptimizationAlgorithmProxy", "RobustKernelScaleDelta", "Rotation2d", "Simulator",
    "Simulator2D", "Simulator2DConfig", "Simulator3D", "Simulator3DConfig", "SimulatorConfig",
    "Solver", "SparseBlockMatrixX", "SparseOptimizerTerminateAction", "TransformTraits",
    "UniformCostFunction", "VariableVectorXEdge", "VectorXVertex", "VertexIntrinsicsEstimate",
    "World",
)


def unsupported(name: str) -> type:
    """A class whose construction raises ``NotImplementedError`` naming the g2o type.

    Args:
        name: The g2o type's name.
    """

    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        raise NotImplementedError(
            f"graphopt.g2o: g2o's {name} is not supported; see docs/g2o_api.md for what is")

    return type(name, (), {"__init__": __init__, "__module__": "graphopt.g2o",
                           "__doc__": f"g2o's {name}: not supported by graphopt."})
