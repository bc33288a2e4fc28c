"""Edge types: a vectorised error, optional analytic Jacobians, information and robust kernel.

An edge *type* (a subclass of :class:`BaseEdge`) declares its error dimension, the types of its
vertices and a batched :meth:`BaseEdge.error` over **all edges of a group at once** (arrays
whose first axis runs over edges). Analytic Jacobians are optional: without them a vectorised
central-difference Jacobian is used (:func:`graphopt.numeric.numeric_jacobians`).

Which Jacobians a type's default :meth:`BaseEdge.linearize` uses is its ``differentiation``:
``"auto"`` (analytic ones when the type defines them, else automatic differentiation of
``error`` on jets, :mod:`graphopt.autodiff`), ``"analytic"``, ``"autodiff"`` or ``"numeric"``
(central differences).

Instances are the per-object front of g2o's API (:class:`~graphopt.edge_object.EdgeObject`);
the optimizer takes them into arrays in bulk.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import numpy as np

from graphopt.autodiff import (
    JetError,
    autodiff_linearize,
    check_independent_edges,
    jet_error_message,
)
from graphopt.compiled import CompiledUnary
from graphopt.edge_object import EdgeObject
from graphopt.errors import GraphError
from graphopt.numeric import numeric_jacobians
from graphopt.vertex import BaseVertex

#: The values of ``BaseEdge.differentiation``.
DIFFERENTIATION = ("auto", "analytic", "autodiff", "numeric")

# Edge types whose batched error was seen to treat each edge on its own (checked once).
_INDEPENDENT: set[type] = set()


def _analytic_twin(cls: type) -> type:
    """A subclass of ``cls``'s nearest parent with analytic Jacobians, keeping them."""
    parent = next(c for c in cls.__mro__[1:] if issubclass(c, BaseEdge)
                  and c.has_analytic_jacobians())
    return parent


class Linearization(NamedTuple):
    """What :meth:`BaseEdge.linearize` returns — and :meth:`BaseEdge.evaluate`, without
    Jacobians. All arrays run over the ``m`` edges of the call.

    Args:
        error: ``(m, dimension)`` errors; rows of inactive edges are zero.
        jacobians: One ``(m, rows, d_i)`` array per vertex position, ``rows`` being
            ``dimension`` (or ``linearization_rows`` for a reduced linearisation); ``()`` from
            :meth:`BaseEdge.evaluate`.
        reduced_error: For a reduced linearisation (``linearization_rows = r``), ``e_lin``
            ``(m, r)`` with ``J̃ᵀJ̃ = JᵀJ`` and ``J̃ᵀe_lin = Jᵀe``; else ``None``.
        active: ``(m,)`` boolean mask of the edges active in this evaluation (e.g. a projection
            inside the image), or ``None`` when all are. Inactive edges have zero error and
            zero Jacobians; the optimizer counts the active ones.
    """

    error: np.ndarray
    jacobians: tuple[np.ndarray, ...] = ()
    reduced_error: np.ndarray | None = None
    active: np.ndarray | None = None


@dataclass
class EdgeContext:
    """What a batched ``error``/``jacobians`` call sees besides estimates and measurements.

    Args:
        params: Shared parameters of the edge group (camera intrinsics, images, ...), as given to
            ``add_edges(..., params=...)``; ``None`` by default.
        data: Per-edge auxiliary arrays (first axis over the edges of the call), as given to
            ``add_edges(..., data={...})``.
        derived: For edge types with ``uses_derived``: per vertex position, the vertex type's
            :meth:`~graphopt.vertex.BaseVertex.derived` values of each edge's vertex
            (``(m, k)``), or ``None``. A cache of functions of the estimates in ``x``: numeric
            differentiation, which perturbs ``x``, calls without it.
        measured: The edge type's :meth:`~BaseEdge.measurement_derived` values of the call's
            edges (``(m, k)``), or ``None``: constants of the measurements, computed when the
            group is finalised.
        vertices: Per vertex position, ``(first (k,), inverse (m,))`` of the call's edges'
            vertices — ``first`` one edge of each distinct vertex, ``inverse`` each edge's
            entry in ``first`` — or ``None``. Structure the optimizer knows (edges that share
            a vertex), given to automatically differentiated types: they run ``oplus`` once
            per vertex without comparing estimates to find the shared ones.
    """

    params: Any = None
    data: dict[str, np.ndarray] = field(default_factory=dict)
    derived: tuple[np.ndarray | None, ...] | None = None
    measured: np.ndarray | None = None
    vertices: tuple[tuple[np.ndarray, np.ndarray], ...] | None = None

    def subset(self, index: np.ndarray | slice) -> EdgeContext:
        """A context restricted to some edges (without ``vertices``: a structure of all).

        Args:
            index: Edge indices or slice.
        """
        derived = (None if self.derived is None
                   else tuple(None if d is None else d[index] for d in self.derived))
        return EdgeContext(self.params, {k: v[index] for k, v in self.data.items()},
                           derived=derived,
                           measured=None if self.measured is None else self.measured[index])


class BaseEdge(EdgeObject):
    """Base class of all edge types.

    Subclasses set ``dimension`` (error dimension), ``vertex_types`` (one vertex class per
    position) and optionally ``measurement_shape`` (default ``(dimension,)``), and implement
    :meth:`error`; optionally :meth:`jacobians` or :meth:`linearize` (analytic Jacobians).

    Args:
        vertices: The vertices (objects or ids), one per entry of ``vertex_types``.
        measurement: The measurement, shape ``measurement_shape``.
        information: ``(dimension, dimension)`` information matrix (identity by default).
        robust_kernel: A :class:`~graphopt.robust_kernel.RobustKernel` or ``None``.
        params: Shared parameters for the edge's group (see :class:`EdgeContext`).
        data: Per-edge auxiliary values (scalars or arrays), see :class:`EdgeContext`.
    """

    dimension: ClassVar[int] = 0
    vertex_types: ClassVar[tuple[type[BaseVertex], ...]] = ()
    measurement_shape: ClassVar[tuple[int, ...] | None] = None
    #: Central-difference step for the numeric Jacobian.
    numeric_step: ClassVar[float] = 1e-6
    #: Rows of a *reduced linearisation* (see :meth:`linearize`), or ``None``.
    linearization_rows: ClassVar[int | None] = None
    #: Evaluate trial steps with :meth:`linearize` instead of :meth:`error`. Worth it when
    #: ``linearize`` costs little more than ``error`` (they share the expensive part, such as
    #: image sampling): an accepted step then needs no second evaluation at the next
    #: linearisation.
    linearize_on_trial: ClassVar[bool] = False
    #: Receive the vertices' :meth:`~graphopt.vertex.BaseVertex.derived` values in
    #: ``ctx.derived`` (gathered per edge by the optimizer).
    uses_derived: ClassVar[bool] = False
    #: Where the default :meth:`linearize` takes Jacobians from: ``"auto"`` (the type's analytic
    #: ones if it defines :meth:`jacobians` or :meth:`linearize`, else ``"autodiff"``),
    #: ``"analytic"``, ``"autodiff"`` (exact, from one ``error`` call on jets; see
    #: ``docs/autodiff.md``) or ``"numeric"`` (central differences). A subclass that sets
    #: ``"autodiff"`` or ``"numeric"`` under a parent with analytic Jacobians uses the generic
    #: linearisation (full rows); the parent's stays reachable for
    #: :func:`graphopt.check_jacobians`.
    differentiation: ClassVar[str] = "auto"
    #: For a type switched to ``"autodiff"``/``"numeric"``: the parent whose analytic
    #: Jacobians it replaced (else ``None``).
    analytic_type: ClassVar[type | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        mode = cls.differentiation
        if mode not in DIFFERENTIATION:
            raise GraphError(f"{cls.__name__}.differentiation must be one of "
                             f"{', '.join(DIFFERENTIATION)}, got {mode!r}")
        if mode in ("autodiff", "numeric") and cls.has_analytic_jacobians():
            # Keep the analytic linearisation for comparisons, use the generic one.
            cls.analytic_type = _analytic_twin(cls)
            cls.linearize = BaseEdge.__dict__["linearize"]  # type: ignore[assignment]
            cls.jacobians = BaseEdge.__dict__["jacobians"]  # type: ignore[assignment]
            cls.compiled_unary = BaseEdge.__dict__["compiled_unary"]  # type: ignore[assignment]
            cls.linearization_rows = None

    # --- the batched type interface --------------------------------------------------------

    @classmethod
    def measurement_derived(cls, measurements: np.ndarray) -> np.ndarray | None:
        """Per-edge constants of the measurements that ``error``/``linearize`` would otherwise
        recompute at every call (the trigonometry of a relative pose, say), or ``None``.

        Computed once when the group is finalised (measurements do not change after an edge
        is added) and handed to the edge type as ``ctx.measured``. Optional: the type must
        give the same result when ``ctx.measured`` is ``None``.

        Args:
            measurements: ``(m, *measurement_shape)`` measurements.

        Returns:
            ``(m, k)`` values, or ``None`` (the default: nothing to keep).
        """
        return None

    @classmethod
    def error(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """Errors of many edges at once.

        Args:
            x: One array per vertex position: ``(m, *estimate_shape)`` estimates.
            measurement: ``(m, *measurement_shape)`` measurements.
            ctx: Parameters and per-edge data, see :class:`EdgeContext`.

        Returns:
            ``(m, dimension)`` errors.
        """
        raise NotImplementedError

    @classmethod
    def jacobians(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> tuple[np.ndarray, ...]:
        """Analytic Jacobians of the error w.r.t. each vertex's tangent increment.

        By default, a type that overrides :meth:`linearize` (without a reduced linearisation)
        gets its Jacobians from there; any other type has none, which selects the numeric
        Jacobian.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.

        Returns:
            One ``(m, dimension, vertex_type.dimension)`` array per vertex position.
        """
        own_linearize = cls.linearize.__func__ is not BaseEdge.linearize.__func__  # type: ignore[attr-defined]
        if own_linearize and cls.linearization_rows is None:
            return cls.linearize(x, measurement, ctx).jacobians
        raise NotImplementedError

    @classmethod
    def differentiation_method(cls) -> str:
        """The method the default :meth:`linearize` uses: ``"analytic"``, ``"autodiff"`` or
        ``"numeric"`` (``"auto"`` resolved)."""
        if cls.differentiation == "auto":
            return "analytic" if cls.has_analytic_jacobians() else "autodiff"
        return cls.differentiation

    @classmethod
    def depth_positive(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> np.ndarray:
        """``(m,)`` whether each edge's point is in front of its camera(s) (g2o's
        ``isDepthPositive``); projection types implement it.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.

        Raises:
            GraphError: the type has no notion of depth (the default).
        """
        raise GraphError(f"{cls.__name__} has no depth_positive (not a projection edge type)")

    @classmethod
    def compiled_unary(cls, measurement: np.ndarray, ctx: EdgeContext) -> CompiledUnary | None:
        """A compiled loop evaluating a group of these edges when all act on one vertex (a
        single-vertex problem; see :mod:`graphopt.compiled`), or ``None`` (the default: the
        type's numpy methods are used).

        Args:
            measurement: The group's measurements.
            ctx: The group's context.
        """
        return None

    @classmethod
    def has_analytic_jacobians(cls) -> bool:
        """True if the type overrides :meth:`jacobians` or :meth:`linearize`."""
        return (
            cls.jacobians.__func__ is not BaseEdge.jacobians.__func__  # type: ignore[attr-defined]
            or cls.linearize.__func__ is not BaseEdge.linearize.__func__  # type: ignore[attr-defined]
        )

    @classmethod
    def evaluate(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and the activity mask, without Jacobians (what a trial step needs).

        The default wraps :meth:`error` (every edge active). A type whose edges can be
        inactive (a projection outside the image) overrides this and returns the mask.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.

        Returns:
            A :class:`Linearization` with ``jacobians=()``.
        """
        return Linearization(cls.error(x, measurement, ctx))

    @classmethod
    def linearize(
        cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: EdgeContext
    ) -> Linearization:
        """Errors and Jacobians together (override to share intermediate results).

        The default takes :meth:`evaluate` and :meth:`jacobians`, or numeric Jacobians
        (:func:`graphopt.numeric.numeric_jacobians`) when the type has no analytic ones.

        A type that sets ``linearization_rows = r`` returns a *reduced linearisation*: ``r``-row
        Jacobians ``J̃`` and ``reduced_error`` ``e_lin`` ``(m, r)`` such that ``J̃ᵀJ̃ = JᵀJ`` and
        ``J̃ᵀe_lin = Jᵀe`` for the full ``J`` and ``e``. The normal equations are the same, built
        from fewer rows (a 16-pixel patch whose Jacobian factors through a 2-D image gradient
        needs 2). ``error`` still gives the chi2; the information matrix must be the identity.

        Args:
            x: As in :meth:`error`.
            measurement: As in :meth:`error`.
            ctx: As in :meth:`error`.

        Returns:
            A :class:`Linearization`.
        """
        method = cls.differentiation_method()
        if method == "autodiff":
            try:
                e, jac, active = autodiff_linearize(cls, x, measurement, ctx)
                if cls not in _INDEPENDENT:  # once per type: no edge sees another's vertices
                    check_independent_edges(cls, x, measurement, ctx, e, jac)
                    _INDEPENDENT.add(cls)
            except JetError as exc:
                raise GraphError(jet_error_message(cls, exc)) from exc
            return Linearization(e, jac, active=active)
        ev = cls.evaluate(x, measurement, ctx)
        if method == "analytic":
            try:
                jac = cls.jacobians(x, measurement, ctx)
            except NotImplementedError:
                raise GraphError(f"{cls.__name__}: differentiation = 'analytic' but the type "
                                 "defines no jacobians or linearize") from None
        else:
            jac = numeric_jacobians(cls, x, measurement, ctx)
        # One array instead of a tuple stays one array: the linearizer reports it.
        jac = jac if isinstance(jac, np.ndarray) else tuple(jac)
        return Linearization(ev.error, jac, active=ev.active)

    @classmethod
    def jacobian_rows(cls) -> int:
        """Rows of the Jacobians :meth:`linearize` returns."""
        return cls.linearization_rows or cls.dimension

    @classmethod
    def get_measurement_shape(cls) -> tuple[int, ...]:
        """The shape of one measurement."""
        return cls.measurement_shape if cls.measurement_shape is not None else (cls.dimension,)
