"""Batched Jacobians of an edge type by a chosen method, and a check of analytic ones.

:func:`edge_jacobians` evaluates a type's Jacobians on given edges — analytic, automatic
(:mod:`graphopt.autodiff`) or central differences — outside an optimizer;
:func:`check_jacobians` compares a type's analytic Jacobians with automatic differentiation
and reports the worst relative error per vertex position. A type with a reduced
linearisation (``linearization_rows``) is compared through what the normal equations see:
``J_iᵀJ_j`` and ``J_iᵀe``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from graphopt.autodiff import JetError, autodiff_linearize, jet_error_message
from graphopt.edge import BaseEdge, EdgeContext
from graphopt.errors import GraphError
from graphopt.numeric import numeric_jacobians

__all__ = ["JacobianCheck", "check_jacobians", "edge_jacobians"]

METHODS = ("autodiff", "numeric", "analytic")


def _inputs(edge_type: type[BaseEdge], x: Sequence[Any], measurement: Any, params: Any,
            data: dict[str, Any] | None) -> tuple[list[np.ndarray], np.ndarray, EdgeContext]:
    """Checked arrays and the context the optimizer would give (derived values included)."""
    name = edge_type.__name__
    vts = edge_type.vertex_types
    if len(x) != len(vts):
        raise GraphError(f"{name} has {len(vts)} vertex positions, got {len(x)} estimate arrays")
    z = np.asarray(measurement, dtype=float)
    m = len(z)
    if z.shape[1:] != edge_type.get_measurement_shape():
        raise GraphError(f"{name}: measurements of shape {z.shape}, expected "
                         f"(m, {', '.join(map(str, edge_type.get_measurement_shape()))})")
    xs = []
    for i, (xi, vt) in enumerate(zip(x, vts, strict=True)):
        a = np.asarray(xi, dtype=float)
        if a.shape != (m, *vt.estimate_shape):
            raise GraphError(f"{name}: position {i} ({vt.__name__}) estimates of shape "
                             f"{a.shape}, expected {(m, *vt.estimate_shape)}")
        xs.append(a)
    ctx = EdgeContext(params, {k: np.asarray(v) for k, v in (data or {}).items()},
                      measured=edge_type.measurement_derived(z))
    if edge_type.uses_derived:
        ctx.derived = tuple(vt.derived(a) for vt, a in zip(vts, xs, strict=True))
    return xs, z, ctx


def _analytic(edge_type: type[BaseEdge]) -> type[BaseEdge]:
    t = edge_type.analytic_type or edge_type
    if not t.has_analytic_jacobians():
        raise GraphError(f"{edge_type.__name__} has no analytic Jacobians")
    return t


def edge_jacobians(
    edge_type: type[BaseEdge], x: Sequence[Any], measurement: Any, params: Any = None,
    data: dict[str, Any] | None = None, method: str = "autodiff",
) -> tuple[np.ndarray, ...]:
    """The Jacobians of ``m`` edges of a type w.r.t. each vertex's tangent increment.

    Args:
        edge_type: The edge class.
        x: Per vertex position, ``(m, *estimate_shape)`` estimates.
        measurement: ``(m, *measurement_shape)`` measurements.
        params: The group's shared parameters (``add_edges(..., params=)``).
        data: Per-edge arrays (``add_edges(..., data=)``).
        method: ``"autodiff"``, ``"numeric"`` (central differences, the type's
            ``numeric_step``) or ``"analytic"`` (the type's own, full rows).

    Returns:
        One ``(m, dimension, d_i)`` array per vertex position.

    Raises:
        GraphError: bad shapes, an unknown method, no analytic Jacobians, or an operation
            automatic differentiation does not support (naming the type and the function).
    """
    if method not in METHODS:
        raise GraphError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    xs, z, ctx = _inputs(edge_type, x, measurement, params, data)
    if method == "autodiff":
        try:
            return autodiff_linearize(edge_type, xs, z, ctx)[1]
        except JetError as exc:
            raise GraphError(jet_error_message(edge_type, exc)) from exc
    if method == "numeric":
        return numeric_jacobians(edge_type, xs, z, ctx)
    t = _analytic(edge_type)
    return tuple(t.jacobians(xs, z, ctx))


@dataclass(frozen=True)
class JacobianCheck:
    """What :func:`check_jacobians` found.

    Args:
        edge_type: The type's name.
        errors: Per vertex position, the worst relative difference over the edges
            (``max |A − B| / max |B|`` per edge and position; for a reduced linearisation,
            of that position's ``J_iᵀJ_j`` blocks and ``J_iᵀe``).
        compared: ``"jacobians"``, or ``"normal equations"`` for a reduced linearisation.
    """

    edge_type: str
    errors: tuple[float, ...]
    compared: str = "jacobians"

    @property
    def worst(self) -> float:
        """The largest relative error over the positions."""
        return max(self.errors, default=0.0)

    def __str__(self) -> str:
        per = ", ".join(f"position {i}: {e:.2e}" for i, e in enumerate(self.errors))
        return f"{self.edge_type}: analytic vs autodiff {self.compared}, worst relative ({per})"


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    """Worst per-edge ``max|a − b| / max(|a|, |b|)`` (0 where both are 0)."""
    m = len(a)
    a, b = a.reshape(m, -1), b.reshape(m, -1)
    scale = np.maximum(np.abs(a).max(axis=1, initial=0.0), np.abs(b).max(axis=1, initial=0.0))
    diff = np.abs(a - b).max(axis=1, initial=0.0)
    rel = np.where(scale > 0, diff / np.where(scale > 0, scale, 1.0), 0.0)
    return float(rel.max(initial=0.0))


def check_jacobians(
    edge_type: type[BaseEdge], x: Sequence[Any], measurement: Any, params: Any = None,
    data: dict[str, Any] | None = None,
) -> JacobianCheck:
    """Compare a type's analytic Jacobians with automatic differentiation of its ``error``.

    Args:
        edge_type: The edge class (with analytic Jacobians; a subclass switched to
            ``"autodiff"``/``"numeric"`` is checked against its parent's).
        x: Per vertex position, ``(m, *estimate_shape)`` estimates.
        measurement: ``(m, *measurement_shape)`` measurements.
        params: The group's shared parameters.
        data: Per-edge arrays.

    Returns:
        A :class:`JacobianCheck`: the worst relative error per vertex position (print it, or
        assert ``check.worst < 1e-8``).

    Raises:
        GraphError: as :func:`edge_jacobians`.
    """
    t = _analytic(edge_type)
    xs, z, ctx = _inputs(t, x, measurement, params, data)
    try:
        e, auto, active = autodiff_linearize(t, xs, z, ctx)
    except JetError as exc:
        raise GraphError(jet_error_message(t, exc)) from exc
    if t.linearization_rows is None:
        ana = tuple(t.jacobians(xs, z, ctx))
        errs = tuple(_relative(a, b) for a, b in zip(ana, auto, strict=True))
        return JacobianCheck(t.__name__, errs)
    lin = t.linearize(xs, z, ctx)
    assert lin.reduced_error is not None
    red, e_lin = lin.jacobians, lin.reduced_error
    errs = []
    for i in range(len(auto)):
        worst = _relative(np.einsum("mri,mr->mi", red[i], e_lin),
                          np.einsum("mri,mr->mi", auto[i], e))
        for j in range(len(auto)):
            worst = max(worst, _relative(np.einsum("mri,mrj->mij", red[i], red[j]),
                                         np.einsum("mri,mrj->mij", auto[i], auto[j])))
        errs.append(worst)
    return JacobianCheck(t.__name__, tuple(errs), "normal equations")
