"""Jacobians of a whole edge group from one evaluation of its ``error`` on jets.

The derivative is taken w.r.t. each vertex's tangent increment ``δ`` at ``δ = 0`` — the
Jacobian of ``e(x ⊞ δ)`` the optimizer needs — by running the vertex type's own ``oplus`` on a
jet ``δ`` (value 0, derivative the identity over that position's directions). Nothing else is
asked of a vertex type: exponential maps, angle-axis updates and their small-angle series are
differentiated as written (a series exact to first order at 0 gives the exact derivative).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from graphopt.autodiff.jet import Jet, JetError
from graphopt.errors import GraphError
from graphopt.vertex import VertexVector

__all__ = ["BLOCK_EDGES", "autodiff_linearize", "check_independent_edges"]

#: Edges per jet evaluation: one block's tangents (``k × block × …`` values per temporary)
#: stay in the CPU cache, and the Python cost per operation is paid once per block.
BLOCK_EDGES = 8192


class _VertexType(Protocol):
    dimension: int
    __name__: str

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray: ...


class _EdgeType(Protocol):
    dimension: int
    vertex_types: Sequence[type[_VertexType]]
    __name__: str

    @classmethod
    def evaluate(cls, x: Sequence[Any], measurement: np.ndarray, ctx: Any) -> Any: ...


def seeded(vtype: type[_VertexType], x: np.ndarray, lo: int, n: int) -> Jet:
    """``x ⊞ δ`` as a jet at ``δ = 0``, its derivative w.r.t. directions ``lo…lo+d−1``.

    Args:
        vtype: The vertex type (its ``oplus`` runs on the jet).
        x: ``(m, *estimate_shape)`` estimates.
        lo: The position's first tangent direction.
        n: Total directions.

    Raises:
        GraphError: an ``oplus`` that drops the derivative or returns another shape.
    """
    m, d = len(x), vtype.dimension
    if vtype.oplus is VertexVector.oplus and x.shape == (m, d):
        return Jet.seeded(x, lo, n)  # x + δ: the derivative is the identity
    # ∂δ/∂δ = I, broadcast over the edges (a read-only view, no m·d² array).
    delta = Jet.seeded(np.zeros((m, d)), lo, n)
    out = vtype.oplus(x.copy(), delta)  # type: ignore[arg-type]
    name = getattr(vtype, "__name__", str(vtype))
    if type(out) is not Jet:
        raise GraphError(f"{name}.oplus returned a {type(out).__name__} without derivatives for "
                         "a jet increment (automatic differentiation needs it to compute with "
                         "NumPy operations on the increment)")
    if out.shape != x.shape:
        raise GraphError(f"{name}.oplus returned shape {out.shape}, expected {x.shape}")
    # The value at δ = 0 is x itself (oplus(x, 0) may differ from it in the last bit).
    out.value = x
    return out


def autodiff_linearize(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray | None]:
    """Errors and exact Jacobians of every edge of a group, from one ``evaluate`` on jets.

    Args:
        edge_type: The edge class (``evaluate``/``error``, ``vertex_types``, ``dimension``).
        x: Per position ``(m, *estimate_shape)`` estimates.
        measurement: ``(m, *measurement_shape)``.
        ctx: The :class:`~graphopt.edge.EdgeContext`; its ``derived`` values (a cache of
            functions of ``x``) are not passed on, as for numeric differences.

    Returns:
        ``(e (m, dimension), (J_i (m, dimension, d_i), …), active (m,) or None)``; rows of
        inactive edges are zero.

    Raises:
        JetError: a NumPy function without a derivative rule (the caller names the type).
        GraphError: an ``oplus`` or ``error`` result of the wrong shape or without derivatives.
    """
    dims = [vt.dimension for vt in edge_type.vertex_types]
    n = int(sum(dims))
    offsets = np.concatenate([[0], np.cumsum(dims)]).astype(int).tolist()
    if ctx is not None and getattr(ctx, "derived", None) is not None:
        ctx = replace(ctx, derived=None)
    m = len(measurement)
    if m > BLOCK_EDGES:
        return _blocks(edge_type, x, measurement, ctx)
    xs = [seeded(vt, np.asarray(xi), offsets[i], n)
          for i, (vt, xi) in enumerate(zip(edge_type.vertex_types, x, strict=True))]
    ev = edge_type.evaluate(xs, measurement, ctx)
    e, active = (ev.error, ev.active) if hasattr(ev, "error") else (ev, None)
    shape = (m, edge_type.dimension)
    if tuple(np.shape(e)) != shape:
        raise GraphError(f"{edge_type.__name__}.error returned shape {np.shape(e)}, "
                         f"expected {shape}")
    jac = []
    if type(e) is not Jet:  # the error does not depend on the estimates
        value = np.asarray(e, dtype=float)
        jac = [np.zeros((m, shape[1], d)) for d in dims]
    else:
        value = np.array(e.value, dtype=float)
        t, lo = e.tangent, e.lo
        for i, d in enumerate(dims):
            a, b = max(offsets[i], lo), min(offsets[i] + d, lo + len(t))
            if a >= b:
                jac.append(np.zeros((m, shape[1], d)))
                continue
            block = np.moveaxis(t[a - lo: b - lo], 0, -1)
            if b - a == d:
                jac.append(np.ascontiguousarray(block))
            else:
                J = np.zeros((m, shape[1], d))
                J[:, :, a - offsets[i]: b - offsets[i]] = block
                jac.append(J)
    if active is not None and not np.all(active):
        for J in jac:
            J[~np.asarray(active)] = 0.0
    return value, tuple(jac), active


def _blocks(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any
) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray | None]:
    """:func:`autodiff_linearize` over blocks of :data:`BLOCK_EDGES` edges (edges are
    independent), so that the ``(k, block, …)`` tangents of one block stay in the CPU cache."""
    m = len(measurement)
    e = np.empty((m, edge_type.dimension))
    jac = [np.empty((m, edge_type.dimension, vt.dimension)) for vt in edge_type.vertex_types]
    active: np.ndarray | None = None
    for s in range(0, m, BLOCK_EDGES):
        sl = slice(s, min(s + BLOCK_EDGES, m))
        sub = ctx.subset(sl) if ctx is not None else None
        eb, jb, ab = autodiff_linearize(edge_type, [xi[sl] for xi in x], measurement[sl], sub)
        e[sl] = eb
        for J, j in zip(jac, jb, strict=True):
            J[sl] = j
        if ab is not None:
            if active is None:
                active = np.ones(m, dtype=bool)
            active[sl] = ab
    return e, tuple(jac), active


def check_independent_edges(
    edge_type: type[_EdgeType], x: Sequence[np.ndarray], measurement: np.ndarray, ctx: Any,
    error: np.ndarray, jacobians: tuple[np.ndarray, ...],
) -> None:
    """Raise if the first edge's error or Jacobian changes when it is evaluated alone.

    A batched error must treat every edge on its own; one that mixes edges (a mean over the
    edge axis) would give each edge the derivative of the others' terms. Evaluating one edge
    again costs little and catches that (once per type, at its first linearisation).

    Args:
        edge_type: The edge class.
        x: As in :func:`autodiff_linearize`.
        measurement: As in :func:`autodiff_linearize`.
        ctx: As in :func:`autodiff_linearize`.
        error: The group's errors from the same estimates.
        jacobians: The group's Jacobians.

    Raises:
        GraphError: the edge's values differ (naming the type).
    """
    if len(measurement) < 2:
        return
    sub = ctx.subset(slice(0, 1)) if ctx is not None and hasattr(ctx, "subset") else ctx
    e1, j1, _ = autodiff_linearize(edge_type, [xi[:1] for xi in x], measurement[:1], sub)
    scale = max(float(np.max(np.abs(error[:1]), initial=0.0)), 1e-300)
    bad = not np.allclose(e1, error[:1], rtol=1e-9, atol=1e-12 * scale)
    for a, b in zip(j1, jacobians, strict=True):
        s = max(float(np.max(np.abs(b[:1]), initial=0.0)), 1e-300)
        bad = bad or not np.allclose(a, b[:1], rtol=1e-9, atol=1e-12 * s)
    if bad:
        raise GraphError(
            f"{edge_type.__name__}: the first edge's error or Jacobian changes when it is "
            "evaluated alone: the batched error mixes edges (a sum, mean or sort over the edge "
            "axis?), which neither automatic nor numeric differentiation supports; each edge's "
            "error must depend on its own vertices only")


def jet_error_message(edge_type: type, exc: JetError) -> str:
    """The message of a :class:`JetError` raised inside ``edge_type``'s error."""
    return (f"{edge_type.__name__}: {exc} (in its error or its vertices' oplus). Write that "
            "step with the supported NumPy operations (docs/autodiff.md), give the type analytic "
            "Jacobians, or set differentiation = 'numeric'")
