"""Vectorised central-difference Jacobians over a whole edge group."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Protocol

import numpy as np


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
    """
    h = edge_type.numeric_step if step is None else step
    # Derived vertex values belong to the unperturbed x: the perturbed errors must not see them.
    ctx = replace(ctx, derived=None) if ctx is not None and ctx.derived is not None else ctx
    m = len(measurement)
    out = []
    for pos, vtype in enumerate(edge_type.vertex_types):
        d = vtype.dimension
        jac = np.zeros((m, edge_type.dimension, d))
        delta = np.zeros((m, d))
        for k in range(d):
            delta[:, k] = h
            xp = list(x)
            xp[pos] = vtype.oplus(x[pos], delta)
            ep = edge_type.error(xp, measurement, ctx)
            xp[pos] = vtype.oplus(x[pos], -delta)
            em = edge_type.error(xp, measurement, ctx)
            jac[:, :, k] = (ep - em) / (2.0 * h)
            delta[:, k] = 0.0
        out.append(jac)
    return tuple(out)
