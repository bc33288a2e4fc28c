"""Group-structured tangents (``graphopt.autodiff.structure``): found where they hold, not
elsewhere, and the Jacobians contracted through them (entry by entry, and through a product
``T[:, :3, :3] @ X`` of a left-structured pose) equal the general contraction's.

Vertex types with a left update (``exp(δ) T``), a right update (``T exp(δ)``) and an
additive angle-axis (no generators fit) are used by many edges each, so that their rows are
gathered from per-vertex jets, as in the optimizer.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from graphopt import BaseEdge, edge_jacobians
from graphopt.autodiff import Jet, structure
from graphopt.autodiff.jacobians import seeded
from graphopt.lie import se3_exp, so3_exp
from graphopt.types import VertexPointXYZ, VertexSE3Expmap
from graphopt.vertex import BaseVertex

RNG = np.random.default_rng(5)


class VertexRightSE3(BaseVertex):
    dimension: ClassVar[int] = 6
    estimate_shape: ClassVar[tuple[int, ...]] = (4, 4)

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        return estimates @ se3_exp(deltas)


class VertexAdditiveRotation(BaseVertex):
    """A rotation matrix updated additively in angle-axis: no fixed generators."""

    dimension: ClassVar[int] = 3
    estimate_shape: ClassVar[tuple[int, ...]] = (3,)
    uses_derived: ClassVar[bool] = True

    @staticmethod
    def oplus(estimates: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        return estimates + deltas

    @classmethod
    def derived(cls, estimates: np.ndarray) -> Any:
        return so3_exp(estimates).reshape(len(estimates), 9)


def _project(T: Any, X: Any) -> Any:
    P = np.matmul(T[:, :3, :3], X[:, :, None])[:, :, 0] + T[:, :3, 3]
    return P[:, :2] / P[:, 2:3]


class EdgeLeft(BaseEdge):
    dimension = 2
    vertex_types = (VertexSE3Expmap, VertexPointXYZ)

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        return _project(x[0], x[1]) - z


class EdgeRight(EdgeLeft):
    vertex_types = (VertexRightSE3, VertexPointXYZ)


class EdgeAdditive(BaseEdge):
    dimension = 2
    vertex_types = (VertexAdditiveRotation, VertexPointXYZ)
    uses_derived = True

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        derived = None if ctx is None or ctx.derived is None else ctx.derived[0]
        r = VertexAdditiveRotation.derived(x[0]) if derived is None else derived
        X = x[1]
        P = [r[:, 3 * i] * X[:, 0] + r[:, 3 * i + 1] * X[:, 1] + r[:, 3 * i + 2] * X[:, 2]
             for i in range(3)]
        return np.stack([P[0] / (P[2] + 5.0), P[1] / (P[2] + 5.0)], axis=1) - z


def _poses(n: int) -> np.ndarray:
    return se3_exp(RNG.normal(0.0, 0.4, (n, 6)))


def _inputs(vt: type, m: int = 300, nv: int = 7) -> tuple[list[np.ndarray], np.ndarray]:
    pick = RNG.integers(0, nv, m)
    if vt is VertexAdditiveRotation:
        est = RNG.normal(0.0, 0.5, (nv, 3))[pick]
    else:
        est = _poses(nv)[pick]
    X = RNG.normal(0.0, 1.0, (m, 3)) + [0.0, 0.0, 6.0]
    return [est, X], RNG.normal(0.0, 0.1, (m, 2))



def _assert_agree(auto, general, numeric) -> None:
    """The structured Jacobians equal the general contraction's to 1e-12 and central
    differences to 1e-6, relative to each Jacobian's largest entry."""
    for a, b, c in zip(auto, general, numeric, strict=True):
        scale = np.max(np.abs(b))
        assert np.max(np.abs(a - b)) <= 1e-12 * scale
        assert np.max(np.abs(a - c)) <= 1e-6 * scale

def test_detect_left_right_and_none() -> None:
    T = _poses(5)
    left = structure.detect(seeded(VertexSE3Expmap, T, 0, 9))
    assert left is not None and left.left
    assert np.count_nonzero(left.G) == 9  # [e_k]x (two entries each) and the unit translations
    right = structure.detect(seeded(VertexRightSE3, T, 0, 6))
    assert right is not None and not right.left
    rot = so3_exp(RNG.normal(0.0, 0.5, (5, 3))).reshape(5, 9)
    d = Jet.seeded(RNG.normal(0.0, 0.5, (5, 3)), 0, 3)
    assert structure.detect(VertexAdditiveRotation.derived(d)) is None
    assert structure.detect(Jet.seeded(rot[:, :4], 0, 4)) is None  # (n, 4): not one matrix


@pytest.mark.parametrize("edge", [EdgeLeft, EdgeRight, EdgeAdditive])
def test_structured_contraction_equals_general(edge: type, monkeypatch: Any) -> None:
    x, z = _inputs(edge.vertex_types[0])
    used: list[bool] = []
    plan = structure.Structure.plan

    def spy(*args: Any) -> Any:
        used.append(plan(*args) is not None)
        return plan(*args)

    products: list[bool] = []
    product_plan = structure.Structure.product_plan

    def spy_product(*args: Any) -> Any:
        products.append(product_plan(*args) is not None)
        return product_plan(*args)

    monkeypatch.setattr(structure.Structure, "plan", spy)
    monkeypatch.setattr(structure.Structure, "product_plan", spy_product)
    auto = edge_jacobians(edge, x, z)
    # The translation column and the rotation block's product (left: rows of exp(δ) T).
    assert any(used) == (edge is not EdgeAdditive)
    assert any(products) == (edge is EdgeLeft)
    monkeypatch.setattr(structure.Structure, "plan", lambda *a: None)
    monkeypatch.setattr(structure.Structure, "product_plan", lambda *a: None)
    general = edge_jacobians(edge, x, z)
    numeric = edge_jacobians(edge, x, z, method="numeric")
    _assert_agree(auto, general, numeric)


class EdgeLeftFormed(EdgeLeft):
    """The rotation block is also read by forward rules (``trace`` of a product forms its
    derivatives) after its product was recorded: the structured product's shortcut must not
    be taken for a block that is no longer a gathered leaf."""

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        R = x[0][:, :3, :3]
        P = np.matmul(R, x[1][:, :, None])[:, :, 0] + x[0][:, :3, 3]
        s = np.trace(R @ R, axis1=1, axis2=2)  # forward rules: R's derivatives formed
        return P[:, :2] / P[:, 2:3] + 0.01 * s[:, None] - z


def test_structured_block_formed_after_its_product() -> None:
    x, z = _inputs(VertexSE3Expmap)
    auto = edge_jacobians(EdgeLeftFormed, x, z)
    numeric = edge_jacobians(EdgeLeftFormed, x, z, method="numeric")
    for a, c in zip(auto, numeric, strict=True):
        assert np.max(np.abs(a - c)) <= 1e-6 * np.max(np.abs(c))


class EdgeLeftEntries(EdgeLeft):
    """``R X + t`` written entry by entry (as BAL's error is): the entries' adjoints are kept
    as products and contracted through the generators (``structure.defer``); one entry is also
    multiplied by a recorded value, another read by a forward rule after its product."""

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        T, X = x
        R = [[T[:, i, j] for j in range(3)] for i in range(3)]
        P = [R[i][1] * X[:, 1] + R[i][0] * X[:, 0] + R[i][2] * X[:, 2] + T[:, i, 3]
             for i in range(3)]
        w = R[0][1] * P[2] + np.arctan2(R[2][0], 1.0)  # (arctan2: a forward rule)
        return np.stack([P[0] / P[2] + 0.1 * w, P[1] / P[2]], axis=1) - z


def test_entries_contracted_as_products(monkeypatch: Any) -> None:
    x, z = _inputs(VertexSE3Expmap)
    kept: list[bool] = []
    defer = structure.defer

    def spy(*args: Any) -> bool:
        kept.append(defer(*args))
        return kept[-1]

    monkeypatch.setattr(structure, "defer", spy)
    auto = edge_jacobians(EdgeLeftEntries, x, z)
    assert any(kept) and not all(kept)  # (T[:, 2, 0] was formed: an ordinary leaf)
    monkeypatch.setattr(structure.Structure, "plan", lambda *a: None)
    general = edge_jacobians(EdgeLeftEntries, x, z)
    numeric = edge_jacobians(EdgeLeftEntries, x, z, method="numeric")
    _assert_agree(auto, general, numeric)


class EdgeLeftRepeated(EdgeLeft):
    """Entry products repeated with the same factor arrays: ``V_i0 x0`` twice in one row's sum
    (its deferred pairs count twice, and that sum is not one the contraction can reuse), and
    a sum of distinct products the contraction reuses (``structure.SUMS``)."""

    @classmethod
    def error(cls, x: Any, z: np.ndarray, ctx: Any) -> Any:
        T, X = x
        R = [[T[:, i, j] for j in range(3)] for i in range(3)]
        x0, x1, x2 = X[:, 0], X[:, 1], X[:, 2]
        P = [(R[i][0] * x0 + R[i][1] * x1) + (R[i][0] * x0 + R[i][2] * x2) + T[:, i, 3]
             for i in range(2)]
        P.append(R[2][0] * x0 + R[2][1] * x1 + R[2][2] * x2 + T[:, 2, 3])
        return np.stack([P[0] / P[2], P[1] / P[2]], axis=1) - z


def test_repeated_entry_products_count_each_time(monkeypatch: Any) -> None:
    x, z = _inputs(VertexSE3Expmap)
    auto = edge_jacobians(EdgeLeftRepeated, x, z)
    monkeypatch.setattr(structure.Structure, "plan", lambda *a: None)
    general = edge_jacobians(EdgeLeftRepeated, x, z)
    numeric = edge_jacobians(EdgeLeftRepeated, x, z, method="numeric")
    _assert_agree(auto, general, numeric)
