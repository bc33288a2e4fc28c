"""Every built-in edge type: automatic differentiation of its ``error`` equals its analytic
Jacobians to 1e-10 relative (``graphopt.check_jacobians``).

The types are enumerated from ``graphopt.types``; their inputs come from
``tests/autodiff_samples.py``. A new edge type without a sample fails here, by name: add one
there (a function of ``(rng, m)``, see that module's docstring). A type without analytic
Jacobians, or whose analytic ones approximate on purpose (``APPROXIMATE`` there), is compared
with central differences instead.
"""

from __future__ import annotations

import numpy as np
import pytest
from autodiff_samples import APPROXIMATE, PENDING, SAMPLES

import graphopt.types
from graphopt import BaseEdge, check_jacobians, edge_jacobians

EDGE_TYPES = sorted(
    name for name in graphopt.types.__all__
    if isinstance(getattr(graphopt.types, name), type)
    and issubclass(getattr(graphopt.types, name), BaseEdge)
)


def test_every_edge_type_has_a_sample() -> None:
    missing = [name for name in EDGE_TYPES if name not in SAMPLES]
    assert not missing, f"add samples to tests/autodiff_samples.py for {missing}"


@pytest.mark.parametrize("name", EDGE_TYPES)
def test_autodiff_equals_analytic(name: str) -> None:
    if name not in SAMPLES:
        pytest.fail(f"{name} has no sample in tests/autodiff_samples.py")
    if name in PENDING:
        pytest.xfail(PENDING[name])
    out = SAMPLES[name](np.random.default_rng(3), 40)
    x, z, params, data = out[:4]
    etype = out[4] if len(out) > 4 else getattr(graphopt.types, name)  # e.g. a LotsOf.of(3)
    if not etype.has_analytic_jacobians() or name in APPROXIMATE:  # central differences
        auto = edge_jacobians(etype, x, z, params, data)
        num = edge_jacobians(etype, x, z, params, data, method="numeric")
        for a, b in zip(auto, num, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * np.abs(b).max())
        return
    check = check_jacobians(etype, x, z, params, data)
    assert len(check.errors) == len(etype.vertex_types)
    assert check.worst < 1e-10, str(check)
