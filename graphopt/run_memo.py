"""Runs answered from memory: an ``optimize`` whose inputs equal an earlier run's.

ORB-SLAM's ``PoseOptimization`` starts every round from the same predicted pose. A round whose
outliers did not change (most of them after the first) repeats the previous round exactly: the
same start, levels, kernels, structure and settings give the same iterations and the same end,
which g2o computes again. A problem that allows it (:attr:`~graphopt.problem.Problem.
replayable`: one free vertex, a few hundred bytes of estimates) keeps its last
:data:`MEMO_RUNS` runs by those inputs; a run with the inputs of a kept one sets the estimates
that run ended at and returns its result, marked :attr:`~graphopt.result.OptimizationResult.
replayed`, without iterating.

The inputs: every store's estimates (bytes), every group's
:attr:`~graphopt.edge_group.EdgeGroup.activity_version` (levels, the initialised level, kernels,
kernel widths), the algorithm's class and configuration, the stopping tests and the iteration
cap; the structure (vertices, edges, measurements, fixed flags, parameters) is the problem's
own, which a change replaces. Like :mod:`~graphopt.evaluation_memo`, it assumes what every
built-in type is: an edge type's outputs depend on its inputs only. Runs with callbacks or
verbose lines, and runs that were interrupted or stopped, are neither kept nor replayed.
"""

from __future__ import annotations

import time
from copy import copy
from typing import TYPE_CHECKING, Any

import numpy as np

from graphopt.result import OptimizationResult, StopReason

if TYPE_CHECKING:
    from graphopt.problem import Problem

#: Runs kept per problem at most (the oldest goes first).
MEMO_RUNS = 8

#: Estimate bytes (all stores) above which runs are not kept: a few poses' worth.
MAX_STATE_BYTES = 4096

_NOT_KEPT = (StopReason.INTERRUPTED, StopReason.STOPPED)


def run_key(p: Problem, algorithm: Any, stopping: Any, iterations: int, plain: bool
            ) -> tuple[Any, ...] | None:
    """The inputs of a run on ``p``, or ``None`` if it is not to be kept or replayed.

    Args:
        p: The problem.
        algorithm: The optimizer's algorithm (its class and frozen ``config`` count).
        stopping: The frozen stopping configuration.
        iterations: The cap.
        plain: No callbacks and no verbose lines.
    """
    if not (plain and p.replayable):
        return None
    parts = []
    size = 0
    for st in p.stores:
        est = st.estimates
        size += est.nbytes
        if size > MAX_STATE_BYTES:
            return None
        parts.append(est.tobytes())
    # The frozen configurations by identity (hashing them costs more than the rest of the key;
    # an equal copy only misses): the entry holds them, so that no other object takes an id.
    return (tuple(parts), tuple([g.activity_version for g in p.groups]), type(algorithm),
            id(algorithm.config), id(stopping), iterations)


def replay(p: Problem, key: tuple[Any, ...], t_start: float) -> OptimizationResult | None:
    """The kept run with inputs ``key``, its end state set on ``p``'s stores, or ``None``.

    Args:
        p: The problem.
        key: From :func:`run_key`.
        t_start: ``perf_counter`` at the call's start (the result's ``seconds``).
    """
    kept = p.runs.get(key)
    if kept is None:
        return None
    ends, (initial, final, reason, infos), _ = kept
    for st, end in zip(p.stores, ends, strict=True):
        if end is not None:  # the stores with free vertices
            st.estimates = end.copy()  # a copy: set_estimate writes into the live array
    p.evaluate(linearize=False)  # the last evaluation at the end state, as after the run
    return OptimizationResult(initial_chi2=initial, final_chi2=final,
                              seconds=time.perf_counter() - t_start, stop_reason=reason,
                              info=[copy(i) for i in infos], replayed=True)


def keep(p: Problem, key: tuple[Any, ...], res: OptimizationResult, algorithm: Any,
         stopping: Any) -> None:
    """Keep a finished run's result and end state under its inputs.

    Args:
        p: The problem.
        key: From :func:`run_key`, taken before the run.
        res: The run's result (its list is copied; its records are copied when replayed).
        algorithm: The algorithm whose configuration the key names.
        stopping: The stopping configuration the key names.
    """
    if res.stop_reason in _NOT_KEPT:
        return
    p.keep_last_outputs()  # the end state's evaluation, which replay makes again
    ends = [None] * len(p.stores)
    for si in p.free_stores:
        ends[si] = np.array(p.stores[si].estimates)
    runs = p.runs
    runs[key] = (ends, (res.initial_chi2, res.final_chi2, res.stop_reason, tuple(res.info)),
                 (algorithm.config, stopping))
    if len(runs) > MEMO_RUNS:
        del runs[next(iter(runs))]
