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
    key = (tuple(parts), tuple([g.activity_version for g in p.groups]), type(algorithm),
           algorithm.config, stopping, iterations)
    try:
        hash(key)
    except TypeError:  # a configuration with an unhashable field
        return None
    return key


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
    ends, res = kept
    for st, end in zip(p.stores, ends, strict=True):
        if end is not None:  # the stores with free vertices
            st.estimates = end.copy()  # a copy: set_estimate writes into the live array
    p.evaluate(linearize=False)  # the last evaluation at the end state, as after the run
    return OptimizationResult(initial_chi2=res.initial_chi2, final_chi2=res.final_chi2,
                              seconds=time.perf_counter() - t_start,
                              stop_reason=res.stop_reason, info=[copy(i) for i in res.info],
                              replayed=True)


def keep(p: Problem, key: tuple[Any, ...], res: OptimizationResult) -> None:
    """Keep a finished run's result and end state under its inputs.

    Args:
        p: The problem.
        key: From :func:`run_key`, taken before the run.
        res: The run's result (copied: the caller may change it).
    """
    if res.stop_reason in _NOT_KEPT:
        return
    free = set(p._free)
    ends = [np.array(st.estimates) if si in free else None for si, st in enumerate(p.stores)]
    runs = p.runs
    runs[key] = (ends, OptimizationResult(initial_chi2=res.initial_chi2,
                                          final_chi2=res.final_chi2, seconds=res.seconds,
                                          stop_reason=res.stop_reason,
                                          info=[copy(i) for i in res.info]))
    while len(runs) > MEMO_RUNS:
        del runs[next(iter(runs))]
