"""How ``W V⁻¹ Wᵀ`` is formed: the cost model behind the automatic choice, and the choice.

Three strategies form a W class's share of the Schur complement (``schur_sparse.py``,
``schur_dense.py``, ``schur_gram.py``); the same Gram products may also sum a camera's
diagonal U block (``assembly.py``). The choice is made once, at initialisation, by modelled
seconds: the constants below were fitted on this project's 2-core machine (one thread).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from numbers import Real
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from graphopt.linear.gathered_gram import GatheredGram

SchurStrategyName = Literal["auto", "sparse", "dense", "gram"]
STRATEGIES: tuple[str, ...] = ("auto", "sparse", "dense", "gram")


@dataclass(frozen=True)
class SchurCostModel:
    """Modelled costs (seconds per unit) and the limits of the Schur plans.

    Each strategy's module turns these into its modelled seconds; the gathered Gram's formula
    (:meth:`gram_seconds`) is shared by the Schur Gram and the U blocks' Gram.

    Args:
        gather: Per value gathered in whole rows by ``np.take`` (the sparse pairs' ``Yᵀ``).
        sparse_mac: Per multiply-add in SciPy's sparse product (the contractions).
        small_mac: Per multiply-add in NumPy's loops over small matrices (``Yᵀ = V⁻¹Wᵀ``).
        blas_mac: Per multiply-add in BLAS ``syrk`` at its peak rate (dense panels).
        blas_half: Columns (a count): ``syrk`` on ``n`` columns runs at
            ``n / (n + blas_half)`` of its peak rate.
        place: Per value of ``L⁻¹Wᵀ`` formed and placed in a dense panel.
        area: Per element of a panel (zeroed, read again for the right-hand side).
        dense_element: Per element of a panel's ``n × n`` product (summed into ``S``).
        panel: Per panel (call overheads).
        panel_rows: Most rows of a panel's dense matrix (about 1.6 MB for 100 columns: it
            stays in cache).
        dense_limit: Most elements (all panels of a class together) the automatic choice
            accepts for the dense path; a forced ``"dense"`` beyond it is an error.
        gemm_mac: Per multiply-add in the batched products of a gathered Gram.
        z: Per value of ``Z = L⁻¹Wᵀ`` formed for a Gram (and read again for the right-hand
            side).
        gram_gather: Per value gathered into a Gram's chunk.
        gemm_output: Per output block of a Gram.
        gemm_chunk: Per chunk (one ``np.matmul`` call) of a Gram.
        gram_enabled: Whether the automatic choices consider gathered Gram products at all
            (for the Schur complement and for the U blocks).
        spectral_max: Most U blocks (a count) ordered by the co-visibility graph's Fiedler
            vector before the V blocks are numbered; beyond it their own order is kept.
    """

    gather: float = 0.6e-9
    sparse_mac: float = 0.4e-9
    small_mac: float = 0.7e-9
    blas_mac: float = 3.2e-11
    blas_half: float = 45
    place: float = 2.4e-9
    area: float = 0.8e-9
    dense_element: float = 4.2e-9
    panel: float = 3e-5
    panel_rows: int = 2048
    dense_limit: int = 64_000_000
    gemm_mac: float = 1.35e-10
    z: float = 3.0e-9
    gram_gather: float = 0.8e-9
    gemm_output: float = 5e-7
    gemm_chunk: float = 5e-6
    gram_enabled: bool = True
    spectral_max: int = 600

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "gram_enabled":
                if not isinstance(value, bool):
                    raise TypeError(f"SchurCostModel.gram_enabled must be a bool, got {value!r}")
            elif isinstance(value, bool) or not isinstance(value, Real) or not (
                    math.isfinite(value) and value >= 0):
                raise ValueError(f"SchurCostModel.{f.name} must be a finite number >= 0, "
                                 f"got {value!r}")
        if self.panel_rows < 1:
            raise ValueError(f"SchurCostModel.panel_rows must be >= 1, got {self.panel_rows}")

    def gram_seconds(self, gram: GatheredGram, gathered: int) -> float:
        """One call of a gathered Gram that gathers ``gathered`` blocks.

        Args:
            gram: The Gram.
            gathered: Blocks it gathers (both sides).
        """
        r, d = gram.r, gram.d
        return (self.gram_gather * gathered * r * d
                + self.gemm_mac * gram.padded * r * d * d
                + self.gemm_output * gram.n_out
                + self.gemm_chunk * gram.n_chunks)


@dataclass(frozen=True)
class SchurConfig:
    """Which strategy forms ``W V⁻¹ Wᵀ``, and the cost model of the automatic choice.

    Args:
        strategy: ``"auto"``: per W class, the cheapest by ``cost``. ``"sparse"``,
            ``"dense"`` or ``"gram"``: that strategy for every W class (a forced ``"dense"``
            whose panels exceed ``cost.dense_limit`` raises ``ValueError`` at
            initialisation). The U blocks' Gram products are chosen by ``cost`` either way.
        cost: Constants and limits of the plans.

    Raises:
        ValueError: for an unknown strategy.
    """

    strategy: SchurStrategyName = "auto"
    cost: SchurCostModel = field(default_factory=SchurCostModel)

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ValueError(f"unknown Schur strategy {self.strategy!r}; choose one of "
                             f"{', '.join(STRATEGIES)}")
        if not isinstance(self.cost, SchurCostModel):
            raise TypeError(f"SchurConfig.cost must be a SchurCostModel, got {self.cost!r}")
