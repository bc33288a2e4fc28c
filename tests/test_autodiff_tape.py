"""Reverse accumulation (``graphopt.autodiff.tape``) gives the forward jets' Jacobians.

Each error below runs with recording on (the default) and off (forward jets throughout, the
rules tested against central differences in ``test_autodiff.py``); both must agree to 1e-12.
The errors exercise what the tape records (broadcasting, constant powers, division, ``stack``,
``concatenate``, writes into ``like=`` buffers through views and ``out=``), what forces the
forward path (a jet written in place, a container read before it is complete, a transposed
leaf), and gathered rows of a vertex type with its own ``oplus``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from graphopt import BaseEdge, VertexVector, edge_jacobians
from graphopt.autodiff import tape
from graphopt.types import VertexSE2

RNG = np.random.default_rng(11)


class VertexP3(VertexVector):
    dimension = 3


def _edge(fn: Callable[[Any, Any, Any], Any], dim: int, vtypes: tuple[type, ...]) -> type:
    return type("EdgeT", (BaseEdge,), {
        "dimension": dim, "vertex_types": vtypes, "measurement_shape": (2,),
        "error": classmethod(lambda cls, x, z, ctx: fn(x[0], x[1], z)),
    })


def _broadcast(a: Any, b: Any, z: Any) -> Any:
    s = (a[:, :, None] * b[:, None, :]).sum(axis=2)  # (m, 3)
    q = a ** 2 / (1.0 + b * b) - 2.0 * np.sqrt(b * b + 1.0) + s
    return np.concatenate([q[:, :2] - z, np.stack([np.exp(-q[:, 2]), -a[:, 0] / b[:, 1]], 1)],
                          axis=1)


def _buffers(a: Any, b: Any, z: Any) -> Any:
    e = np.empty((len(z), 4), like=a)
    half = len(z) // 2
    for s in (slice(0, half), slice(half, None)):  # writes through views, out=, a constant
        np.subtract(a[s, :2] * b[s, 2:3], z[s], out=e[s, :2])
        e[s, 2] = np.arctan(a[s, 2]) + b[s, 0] ** 3
    e[:, 3] = 0.5
    e[1:, 3] = a[1:, 1] * b[1:, 1]
    return e


def _in_place(a: Any, b: Any, z: Any) -> Any:
    p = a * b
    q = p + 1.0
    p += a  # a recorded jet written in place: everything is formed forward from here
    return np.stack([p[:, 0] * q[:, 1], p[:, 2] - z[:, 0]], axis=1)


def _read_container(a: Any, b: Any, z: Any) -> Any:
    c = np.zeros_like(a)
    c[:, 0] = a[:, 1] * b[:, 2]
    d = c * 2.0  # read before the next write
    c[:, 1] = b[:, 0]
    return np.stack([d[:, 0] + c[:, 1], c[:, 0] - z[:, 1]], axis=1)


def _transposed(a: Any, b: Any, z: Any) -> Any:
    u = np.transpose(a * b)  # axis 0 is no longer the edges: a forward leaf
    return np.stack([u[0] * u[1], u[2] + z[:, 0]], axis=1)


@pytest.mark.parametrize("fn,dim", [(_broadcast, 4), (_buffers, 4), (_in_place, 2),
                                    (_read_container, 2), (_transposed, 2)])
def test_reverse_equals_forward(fn: Callable[..., Any], dim: int) -> None:
    m = 9
    x = [RNG.uniform(0.5, 1.5, (m, 3)), RNG.uniform(0.5, 1.5, (m, 3))]
    z = RNG.normal(size=(m, 2))
    etype = _edge(fn, dim, (VertexP3, VertexP3))
    rev = edge_jacobians(etype, x, z)
    fwd = _forward_only(etype, x, z)
    num = edge_jacobians(etype, x, z, method="numeric")
    for r, f, n in zip(rev, fwd, num, strict=True):
        np.testing.assert_allclose(r, f, rtol=1e-12, atol=1e-12 * np.abs(f).max())
        np.testing.assert_allclose(r, n, rtol=1e-6, atol=1e-6 * np.abs(n).max())



def _forward_only(etype: type, x: Any, z: Any) -> tuple[np.ndarray, ...]:
    """The Jacobians with the reverse tape switched off (forward jets alone)."""
    tape.ENABLED = False
    try:
        return edge_jacobians(etype, x, z)
    finally:
        tape.ENABLED = True

def test_gathered_rows_of_a_manifold_vertex() -> None:
    """Poses shared by many edges: their ``x ⊞ δ`` is formed once per pose and its rows'
    tangents gathered per edge only as far as used (a column, a row range)."""
    m = 40
    poses = np.c_[RNG.normal(size=(4, 2)), RNG.uniform(-3, 3, 4)]
    x = [poses[RNG.integers(0, 4, m)], RNG.normal(size=(m, 3))]
    z = RNG.normal(size=(m, 2))

    def fn(p: Any, q: Any, z: Any) -> Any:
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        head = p[:5]  # a row range of gathered rows, then its columns
        e = np.empty((len(z), 2), like=q)
        e[:, 0] = c * (q[:, 0] - p[:, 0]) + s * q[:, 1] - z[:, 0]
        e[:, 1] = -s * q[:, 0] + c * (q[:, 1] - p[:, 1]) - z[:, 1]
        e[:5, 1] = e[:5, 1] + head[:, 2] * head[:, 0]
        return e

    etype = _edge(fn, 2, (VertexSE2, VertexP3))
    rev = edge_jacobians(etype, x, z)
    fwd = _forward_only(etype, x, z)
    for r, f in zip(rev, fwd, strict=True):
        np.testing.assert_allclose(r, f, rtol=1e-12, atol=1e-12 * np.abs(f).max())


def _reused_buffer(a: Any, b: Any, z: Any) -> Any:
    buf = z[:, 0] * 2.0
    p = a[:, 0] * buf  # recorded with buf's current values
    e = np.zeros((len(z), 2), like=a)
    e[:, 1] = buf
    buf[:] = 5.0  # reused afterwards: the derivatives must not see it
    e[:, 0] = p / buf + b[:, 1]
    return e


def test_plain_arrays_reused_after_an_operation() -> None:
    m = 6
    x = [RNG.uniform(0.5, 1.5, (m, 3)), RNG.uniform(0.5, 1.5, (m, 3))]
    z = RNG.normal(size=(m, 2))
    etype = _edge(_reused_buffer, 2, (VertexP3, VertexP3))
    rev = edge_jacobians(etype, x, z)
    num = edge_jacobians(etype, x, z, method="numeric")
    for r, n in zip(rev, num, strict=True):
        np.testing.assert_allclose(r, n, rtol=1e-6, atol=1e-6)
