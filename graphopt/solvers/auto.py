"""The automatic choice between the explicit reduced system and implicit-Schur PCG.

Made once, before ``S``'s pattern is built, from block-level quantities of the
:class:`~graphopt.linear.structure.BlockIndex` (never from the scalar pattern):

* ``n_w``: W blocks (camera–point pairs); ``pairs``: pairs of W blocks sharing a V block,
  ``Σ_v n_v(n_v + 1)/2`` — the work and the index memory of the explicit Schur fill;
* ``nnz_s``: scalar entries of ``S`` (its co-visible U block pairs times their sizes);
* ``nnz_l``, ``flops``: CHOLMOD's factor of ``S`` — predicted by factorising the *block-level*
  co-visibility matrix (``n_u × n_u``, about ``1/d²`` of ``S``'s entries; simplicial, the same
  default ordering): ``nnz(L) ≈ d²·nnz(L_b)``, ``Σ_j c_j² ≈ d³·Σ_j c_bj²``. On 2-D camera
  grids of 900–3600 cameras (``d = 9``) this predicted the scalar factor's entries within 1 %
  and its ``Σ c_j²`` within 7 %, in 1/50 of the factorisation's time.

The explicit path is modelled as ``bytes = 36·nnz_s + 64·pairs + 12·nnz_l`` (the data of
``S``, its copy and pattern; the Schur plans' index arrays — the explicit run's peak RSS
exceeded the implicit one's by 241 MB on the 1M-observation path scene of
``benchmarks/bench_implicit_schur.py``, 3.07 M pairs and 1.05 M entries of ``S``; the factor)
and ``seconds = 8.5e-8·pairs + flops / 1.5e10`` per solve (CHOLMOD ran at 7–28e9 ``Σc²`` per
second on this machine, one thread, on the grids above; the Schur fill and the solve took
0.26 s per iteration on the path scene). Implicit-Schur PCG is modelled as
``(1.5e-7 + cg_iterations · 4e-8) · n_w`` seconds per solve (the operator — V blocks'
inverses, right-hand side — 150 ms and one product with ``S`` 37 ms at 1 M W blocks), with
``cg_iterations = 50``: measured averages per solve were 8–10 (Dubrovnik-16), 19–25
(Ladybug-49), 57 (1M path scene, 2 to 240 as λ falls) and 107 (100k path scene).

The rule: implicit when the explicit path's modelled memory exceeds the budget, or its modelled
seconds per solve exceed the implicit path's; explicit for graphs without marginalised vertices
and below ``min_w_blocks`` (at 100k observations the implicit path measured 8.7x slower per
iteration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp

from graphopt.linear.indexing import unique_ints

if TYPE_CHECKING:
    from graphopt.linear.structure import BlockIndex


@dataclass(frozen=True)
class ReducedCostModel:
    """Measured constants of the choice between the explicit and the implicit reduced system
    (see the module docstring for where they come from).

    Args:
        memory_budget: Bytes the explicit path may take; ``None``: half of the memory
            available (``MemAvailable``) when the structure is built.
        bytes_per_s_entry: Per scalar entry of ``S`` (its data, the reduction's copy, the
            pattern's keys and indices).
        bytes_per_pair: Per pair of W blocks sharing a V block (the Schur plans).
        bytes_per_factor_entry: Per entry of the Cholesky factor (value and index).
        seconds_per_pair: Explicit Schur fill, per pair.
        factor_rate: CHOLMOD's ``Σ_j c_j²`` (column counts of ``L``) per second.
        operator_seconds: Implicit operator per W block (once per solve).
        product_seconds: One product with ``S`` per W block.
        cg_iterations: Typical CG iterations per solve.
        min_w_blocks: Fewest W blocks for which the implicit path is considered.
        max_block_entries: Most block-level entries of ``S`` the factor is predicted for
            (beyond it, memory alone decides: ``S`` alone is then over a few GB).
    """

    memory_budget: float | None = None
    bytes_per_s_entry: float = 36.0
    bytes_per_pair: float = 64.0
    bytes_per_factor_entry: float = 12.0
    seconds_per_pair: float = 8.5e-8
    factor_rate: float = 1.5e10
    operator_seconds: float = 1.5e-7
    product_seconds: float = 4e-8
    cg_iterations: float = 50.0
    min_w_blocks: int = 200_000
    max_block_entries: int = 20_000_000


def available_memory() -> float:
    """``MemAvailable`` from ``/proc/meminfo`` in bytes (8 GB where it cannot be read)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:  # pragma: no cover - not Linux
        pass
    return 8e9  # pragma: no cover


def _factor_of_blocks(index: BlockIndex, keys: np.ndarray) -> tuple[float, float] | None:
    """``(nnz(L_b), Σ_j c_bj²)`` of the block-level co-visibility matrix's Cholesky factor, or
    ``None`` without CHOLMOD."""
    try:
        from sksparse.cholmod import cholesky
    except ImportError:  # pragma: no cover - depends on the machine
        return None
    nb = max(index.n_ublocks, 1)
    rows, cols = keys % nb, keys // nb
    off = rows != cols
    b = sp.csc_matrix((np.ones(int(off.sum())), (rows[off], cols[off])), shape=(nb, nb))
    # Diagonally dominant, so positive definite whatever the pattern.
    b = sp.csc_matrix(b + sp.diags(np.asarray(b.sum(axis=1)).ravel() + 1.0))
    low = cholesky(b, mode="simplicial").L()
    counts = np.diff(low.indptr).astype(np.float64)
    return float(low.nnz), float((counts ** 2).sum())


def choose_implicit(index: BlockIndex, model: ReducedCostModel) -> tuple[bool, dict[str, Any]]:
    """Whether implicit-Schur PCG should solve this graph, and the modelled quantities.

    Args:
        index: The block index, before its pattern is built.
        model: The constants.

    Returns:
        ``(implicit, facts)``: the choice and a dict of what it was made from (``reason``,
        ``n_w``, ``pairs``, ``nnz_s``, ``nnz_l``, ``explicit_bytes``, ``budget``,
        ``explicit_seconds``, ``implicit_seconds``).
    """
    n_w = sum(len(wc.vblock) for wc in index.wclasses)
    facts: dict[str, Any] = {"n_w": n_w}
    if not index.vclasses or n_w < model.min_w_blocks:
        facts["reason"] = "no marginalised vertices" if not index.vclasses else "small"
        return False, facts
    pairs = 0.0
    for vc, c in enumerate(index.vclasses):
        counts = np.zeros(len(c.slots), dtype=np.float64)
        for wc in index.wclasses:
            if wc.vclass == vc:
                counts += np.bincount(wc.vblock, minlength=len(c.slots))
        pairs += float((counts * (counts + 1) / 2).sum())
    budget = model.memory_budget if model.memory_budget is not None else 0.5 * available_memory()
    facts.update(pairs=pairs, budget=budget)
    nb = max(index.n_ublocks, 1)
    d = float(np.mean(index.udims)) if index.n_ublocks else 1.0
    implicit_s = (model.operator_seconds + model.cg_iterations * model.product_seconds) * n_w
    facts["implicit_seconds"] = implicit_s
    # The fill's keys are what the explicit pattern is built from (kept by the index).
    keys = unique_ints(np.concatenate([index.fill_keys(vc)
                                       for vc in range(len(index.vclasses))]), nb * nb)
    nnz_s = float(len(keys)) * d * d
    explicit_b = model.bytes_per_s_entry * nnz_s + model.bytes_per_pair * pairs
    explicit_s = model.seconds_per_pair * pairs
    facts.update(nnz_s=nnz_s)
    factor = _factor_of_blocks(index, keys) if len(keys) <= model.max_block_entries else None
    if factor is not None:
        nnz_l, flops = factor[0] * d * d, factor[1] * d ** 3
        explicit_b += model.bytes_per_factor_entry * nnz_l
        explicit_s += flops / model.factor_rate
        facts.update(nnz_l=nnz_l, flops=flops)
    elif len(keys) > model.max_block_entries:
        explicit_s = math.inf  # S alone is over max_block_entries · d² entries
    facts.update(explicit_bytes=explicit_b, explicit_seconds=explicit_s)
    if explicit_b > budget:
        facts["reason"] = "memory"
        return True, facts
    if explicit_s > implicit_s:
        facts["reason"] = "time"
        return True, facts
    facts["reason"] = "explicit is modelled faster and fits"
    return False, facts
