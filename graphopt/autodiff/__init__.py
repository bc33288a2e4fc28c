"""Forward-mode automatic differentiation of batched NumPy code.

:class:`Jet` carries every edge's derivatives through ``error(x, z, ctx)`` written with plain
``np.`` calls; :func:`autodiff_linearize` returns a group's errors and exact Jacobians from one
call. What works and what does not: ``docs/autodiff.md``.
"""

from graphopt.autodiff import functions, lie_rules, linalg, selection, ufuncs  # noqa: F401 - rules
from graphopt.autodiff.jacobians import (
    autodiff_linearize,
    check_independent_edges,
    jet_error_message,
    seeded,
)
from graphopt.autodiff.jet import Jet, JetError

__all__ = [
    "Jet",
    "JetError",
    "autodiff_linearize",
    "check_independent_edges",
    "jet_error_message",
    "seeded",
]
