"""Vectorised central-difference Jacobians over a whole edge group."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from graphopt.errors import GraphError


class _VertexType(Protocol):
    dimension: int

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray: ...


class _EdgeType(Protocol):
    """What the differences need of an edge type (a :class:`~graphopt.edge.BaseEdge`)."""

    dimension: int
    numeric_step: float
    vertex_types: Sequence[type[_VertexType]]

    @classmethod
    def error(cls, x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any) -> np.ndarray: ...


def numeric_jacobians(
    edge_type: type[_EdgeType],
    x: Sequence[np.ndarray],
    measurement: np.ndarray,
    ctx: Any,
    step: float | None = None,
) -> tuple[np.ndarray, ...]:
    """Central differences ``(e(x ⊞ hδ) − e(x ⊞ −hδ)) / 2h`` for every edge at once.

    The loop runs over tangent directions (at most the sum of the vertex dimensions), never over
    edges: each direction is one batched ``error`` call on all edges.

    Args:
        edge_type: The edge class (provides ``error``, ``vertex_types``, ``dimension``).
        x: Per-position estimates ``(m, *estimate_shape)``.
        measurement: ``(m, *measurement_shape)``.
        ctx: The :class:`~graphopt.edge.EdgeContext` passed to ``error``.
        step: Difference step; defaults to ``edge_type.numeric_step``.

    Returns:
        One ``(m, dimension, vertex_dimension)`` array per vertex position.

    Raises:
        GraphError: an ``oplus`` or ``error`` result of the wrong shape (naming the type).

    ``oplus`` gets a copy of the estimates each time: one that updates its input in place
    (against its contract) would otherwise move ``x`` between the two sides of the difference
    and halve the Jacobian. The copies cost little next to the ``error`` calls.
    """
    h = edge_type.numeric_step if step is None else step
    # Derived vertex values belong to the unperturbed x: the perturbed errors must not see them.
    ctx = replace(ctx, derived=None) if ctx is not None and ctx.derived is not None else ctx
    m = len(measurement)
    shape = (m, edge_type.dimension)
    out = []
    for pos, vtype in enumerate(edge_type.vertex_types):
        d = vtype.dimension
        jac = np.zeros((m, edge_type.dimension, d))
        delta = np.zeros((m, d))
        xi = x[pos]
        for k in range(d):
            delta[:, k] = h
            xp = list(x)
            xp[pos] = checked_oplus(vtype, xi.copy(), delta)
            ep = edge_type.error(xp, measurement, ctx)
            xp[pos] = checked_oplus(vtype, xi.copy(), -delta)
            em = edge_type.error(xp, measurement, ctx)
            if np.shape(ep) != shape or np.shape(em) != shape:
                raise GraphError(f"{edge_type.__name__}.error returned shape {np.shape(ep)}, "
                                 f"expected {shape}")
            jac[:, :, k] = (ep - em) / (2.0 * h)
            delta[:, k] = 0.0
        out.append(jac)
    return tuple(out)


def checked_oplus(vtype: type[_VertexType], x: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``vtype.oplus(x, delta)``, its result checked to have ``x``'s shape.

    Args:
        vtype: The vertex type.
        x: ``(k, *estimate_shape)`` estimates (``oplus`` may change them: pass a copy).
        delta: ``(k, dimension)`` increments.

    Raises:
        GraphError: a result of another shape (or not an array), naming the type.
    """
    out = vtype.oplus(x, delta)
    if getattr(out, "shape", None) != x.shape:
        got = f"shape {out.shape}" if hasattr(out, "shape") else f"a {type(out).__name__}"
        raise GraphError(f"{getattr(vtype, '__name__', vtype)}.oplus returned {got}, "
                         f"expected {x.shape}")
    return out


def frozen_copy(a: np.ndarray) -> np.ndarray:
    """A read-only copy of ``a`` (what is kept for later readers while its owner may write
    into the original).

    Args:
        a: The array.
    """
    a = np.array(a)
    a.flags.writeable = False
    return a
