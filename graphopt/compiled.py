"""Compiled evaluations (numba) of the groups of a single-vertex problem.

ORB-SLAM's motion-only BA evaluates one group of 100–500 edges on one pose about 23 times a
frame. In numpy each evaluation is some 40 calls — projection, Jacobian rows, robust weights,
``JᵀWJ`` — at about 1 µs each whatever the size: 28.7 µs at 100 edges, 46.7 at 500. One
compiled loop over the edges does all of it in 3.9 and 11.8 µs. An edge type offers such a loop with
:meth:`~graphopt.edge.BaseEdge.compiled_unary` (a :class:`CompiledUnary`);
:class:`~graphopt.single_vertex.SingleVertexProblem` calls it where the group's weighing is
one a loop can do (no kernel or Huber, a diagonal information, levels), else the numpy path.
The numbers are the same function of the same inputs, summed edge by edge instead of by BLAS:
equal to rounding, not to the bit.

numba is imported on first use (0.2 s; most runs never need it): :func:`available` only looks
for it. Loops are compiled on their first call and cached on disk beside their module (about
0.8 s once, then milliseconds). ``GRAPHOPT_JIT=0`` in the environment turns them off.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
from collections.abc import Callable
from types import ModuleType
from typing import Any, NamedTuple

from graphopt.robust_kernel import RobustKernel, RobustKernelHuber

__all__ = ["CompiledUnary", "Lazy", "available", "kernel_code", "load"]

#: Robust kernels a compiled loop applies, by code (``kernel_code``): none, Huber.
KERNEL_NONE, KERNEL_HUBER = 0, 1

_available: bool | None = None


def available() -> bool:
    """Whether compiled loops may run: numba is installed and ``GRAPHOPT_JIT`` is not ``0``
    (read once; tests switch it with :func:`set_enabled`)."""
    global _available
    if _available is None:
        _available = (os.environ.get("GRAPHOPT_JIT", "1") != "0"
                      and importlib.util.find_spec("numba") is not None)
    return _available


def set_enabled(on: bool) -> None:
    """Turn compiled loops on (if numba is installed) or off, for this process.

    Args:
        on: Whether they may run.
    """
    global _available
    _available = None if on else False
    if on:
        available()


def load(module: str) -> ModuleType | None:
    """Import a module of compiled loops (which imports numba), or ``None`` when compiled
    loops are off or the import fails (numba missing or too old for this numpy).

    Args:
        module: Its dotted name.
    """
    if not available():
        return None
    try:
        return importlib.import_module(module)
    except ImportError:
        return None


class Lazy:
    """One function of a module of compiled loops, loaded at its first use.

    Args:
        module: The module's dotted name.
        name: The function's name in it.
    """

    __slots__ = ("_fn", "module", "name")

    def __init__(self, module: str, name: str) -> None:
        self.module, self.name = module, name
        self._fn: Any = None  # False: the module does not load

    def get(self) -> Callable[..., Any] | None:
        """The compiled function, or ``None`` (no numba, or loops off)."""
        if not available():
            return None
        fn = self._fn
        if fn is None:
            mod = load(self.module)
            fn = self._fn = False if mod is None else getattr(mod, self.name)
        return fn or None


def kernel_code(kernel: RobustKernel | None) -> tuple[int, float] | None:
    """``(code, δ)`` of a robust kernel a compiled loop applies, else ``None``.

    Args:
        kernel: The group's one kernel, or ``None`` for none.
    """
    if kernel is None:
        return KERNEL_NONE, 0.0
    if type(kernel) is RobustKernelHuber:
        return KERNEL_HUBER, kernel.delta
    return None


class CompiledUnary(NamedTuple):
    """A type's compiled evaluation of a group whose edges all act on one vertex.

    ``fn(x, *args, info, active, code, delta, lin) -> (e, every, s, H, b, chi2, robust)``
    with ``x`` the vertex's estimate (one row of its store), ``info`` ``(m|1, rows)`` the
    information's diagonal (one row: shared), ``active`` ``(m,)`` (or ``(0,)``: all),
    ``code``/``delta`` from :func:`kernel_code`: the errors ``e`` ``(m, rows)``, every edge's
    ``e'Ωe`` (``every``), the active ones' (``s``, 0 elsewhere), with ``lin``
    ``H = Σ ρ'JᵀΩJ`` ``(d, d)`` and ``b = Σ ρ'JᵀΩe`` ``(d,)`` over the active edges (else
    zeros), the active edges' chi2 and robust chi2 (what
    :func:`~graphopt.unary_terms.unary_terms` returns from numpy arrays). The Jacobians are
    not kept: the type's ``linearize`` gives them where they are wanted (naming an edge whose
    values are not finite).

    Attributes:
        fn: The compiled loop.
        args: The type's inputs after ``x`` (measurements, per-edge data, parameters).
        rows: The error dimension.
    """

    fn: Callable[..., tuple[Any, ...]]
    args: tuple[Any, ...]
    rows: int
