"""The online replay protocol of a SLAM graph: poses in id order, one step per pose.

Step ``k`` adds pose ``k`` — initialised by composing its odometry edge (an edge joining it to
pose ``k − 1``, either direction) onto the *current* estimate of pose ``k − 1``, or, without
one, from the graph's estimate (the file's, or the spanning-tree guess) — the landmarks first
observed in this step (each from its first observation, by the pose's new estimate) and every
edge whose larger pose endpoint is ``k`` (a landmark observation belongs to its pose's step).
The first pose is fixed and forms step 0 alone. This is the protocol of
``benchmarks/bench_online.py`` and ``graphopt-g2o --online``, both for graphopt and for GTSAM's
iSAM2.

:func:`replay_schedule` computes, once and without a loop per edge, which edges and landmarks
enter at each step (:class:`ReplaySchedule`); :func:`initial_pose` and
:func:`initial_landmarks` compute the new vertices' starting estimates at run time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graphopt.errors import GraphError
from graphopt.online import IncrementalConfig, IncrementalOptimizer, UpdateReport
from graphopt.optimizer import SparseOptimizer
from graphopt.robust_kernel import RobustKernel
from graphopt.types import slam_guess as sg
from graphopt.types.isometry3 import pose_from_qt
from graphopt.types.slam2d import EdgeSE2, EdgeSE2PointXY, VertexPointXY
from graphopt.types.slam3d import EdgeSE3
from graphopt.types.slam_graph import VERTEX_TYPES, SlamGraph
from graphopt.vertex import BaseVertex

__all__ = ["Replay", "ReplaySchedule", "StepEdges", "initial_landmarks", "initial_pose",
           "replay", "replay_schedule"]

#: Edge tags the replay supports: tag → (edge type, is a landmark observation).
ONLINE_EDGES = {"EDGE_SE2": (EdgeSE2, False), "EDGE_SE2_XY": (EdgeSE2PointXY, True),
                "EDGE_SE3:QUAT": (EdgeSE3, False)}


@dataclass
class StepEdges:
    """The edges of one tag, sorted by the step they enter.

    Args:
        tag: The canonical edge tag.
        etype: The edge type.
        ids: ``(m, 2)`` optimizer vertex ids.
        measurements: ``(m, *measurement_shape)`` (poses as ``[R | t]`` for 3-D).
        information: ``(m, e, e)``.
        bounds: ``(n + 1,)``: the edges of step ``k`` are rows ``bounds[k]:bounds[k + 1]``.
    """

    tag: str
    etype: type
    ids: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    bounds: np.ndarray


@dataclass
class ReplaySchedule:
    """What enters at every step of the replay.

    Args:
        pose_type: ``VertexSE2`` or ``VertexSE3``.
        group: How poses compose (:data:`~graphopt.types.slam_guess.SE2_GROUP` or SE3).
        pose_ids: ``(n,)`` pose ids in step order.
        estimates: ``(n, *pose_shape)`` the graph's estimates of the poses (the fallback
            start of a pose without odometry).
        odometry: ``(n,)`` measurement ``Z`` with ``X_k = X_{k-1}·Z`` (already inverted for an
            edge stored backwards), as ``(n, *pose_shape)``; ``has_odometry`` ``(n,)`` tells
            where there is one.
        has_odometry: ``(n,)`` booleans.
        edges: One :class:`StepEdges` per edge tag.
        landmark_type: ``VertexPointXY`` or ``None``.
        landmark_ids: ``(l,)`` landmark ids in order of first observation.
        landmark_first: ``(l,)`` row of the first observation in the landmark tag's
            :class:`StepEdges`.
        landmark_bounds: ``(n + 1,)`` landmarks first seen at step ``k``:
            ``landmark_ids[landmark_bounds[k]:landmark_bounds[k + 1]]``.
    """

    pose_type: type[BaseVertex]
    group: sg.PoseGroup
    pose_ids: np.ndarray
    estimates: np.ndarray
    odometry: np.ndarray
    has_odometry: np.ndarray
    edges: list[StepEdges]
    landmark_type: type[BaseVertex] | None
    landmark_ids: np.ndarray
    landmark_first: np.ndarray
    landmark_bounds: np.ndarray

    @property
    def steps(self) -> int:
        """Number of steps (poses)."""
        return len(self.pose_ids)


def replay_schedule(slam: SlamGraph) -> ReplaySchedule:
    """The replay of a built SLAM graph (:func:`~graphopt.types.slam_graph.build_graph`).

    Args:
        slam: The graph (its optimizer's estimates are the fallback starts).

    Returns:
        The schedule.

    Raises:
        GraphError: a tag the replay does not support, no poses, or an edge whose vertex
            never enters (a landmark-landmark edge, say).
    """
    bad = [t for t in slam.edges if t not in ONLINE_EDGES]
    if bad:
        raise GraphError(f"{slam.path}: the online replay does not support {bad[0]} (it "
                         f"supports {', '.join(ONLINE_EDGES)})")
    ptags = [t for t in ("VERTEX_SE2", "VERTEX_SE3:QUAT") if t in slam.vertex_ids]
    if len(ptags) != 1:
        raise GraphError(f"{slam.path}: the online replay needs poses of one kind, found "
                         f"{ptags or 'none'}")
    ptag = ptags[0]
    pose_type = VERTEX_TYPES[ptag]
    store = slam.optimizer.graph.stores[pose_type]
    order = np.argsort(store.ids)
    pose_ids, estimates = store.ids[order], store.estimates[order]
    n = len(pose_ids)
    group = sg.SE2_GROUP if ptag == "VERTEX_SE2" else sg.SE3_GROUP
    odometry = np.broadcast_to(group.identity, (n, *group.identity.shape)).copy()
    has_odo = np.zeros(n, bool)
    edges, lm = [], None
    for tag, block in slam.edges.items():
        etype, is_obs = ONLINE_EDGES[tag]
        ids = np.asarray(block.ids, np.int64).copy()
        meas = np.asarray(block.measurements, float)
        if tag == "EDGE_SE3:QUAT":
            meas = pose_from_qt(meas)
        if is_obs:
            ids[:, 1] += slam.point_id_offset
            step = np.searchsorted(pose_ids, ids[:, 0])
        else:
            step = np.searchsorted(pose_ids, ids.max(axis=1))
            fwd = (ids[:, 1] == ids[:, 0] + 1) & np.isin(ids[:, 1], pose_ids)
            back = (ids[:, 0] == ids[:, 1] + 1) & np.isin(ids[:, 0], pose_ids)
            for mask, inv in ((back, True), (fwd, False)):  # forward edges win
                rows = np.flatnonzero(mask)
                k = np.searchsorted(pose_ids, ids[rows].max(axis=1))
                ok = pose_ids[k - 1] == ids[rows].min(axis=1)
                rows, k = rows[ok], k[ok]
                _, first = np.unique(k, return_index=True)
                rows, k = rows[first], k[first]
                odometry[k] = group.inverse(meas[rows]) if inv else meas[rows]
                has_odo[k] = True
        srt = np.argsort(step, kind="stable")
        bounds = np.searchsorted(step[srt], np.arange(n + 1))
        edges.append(StepEdges(tag, etype, ids[srt], meas[srt],
                               np.asarray(block.information, float)[srt], bounds))
        if is_obs:
            lm = edges[-1]
    lm_type: type[BaseVertex] | None = None
    lm_ids = lm_first = np.zeros(0, np.int64)
    lm_bounds = np.zeros(n + 1, np.int64)
    if lm is not None:
        lm_type = VertexPointXY
        lm_ids, lm_first = np.unique(lm.ids[:, 1], return_index=True)
        srt = np.argsort(lm_first, kind="stable")
        lm_ids, lm_first = lm_ids[srt], lm_first[srt]
        step_of = np.searchsorted(lm.bounds, lm_first, side="right") - 1
        lm_bounds = np.searchsorted(step_of, np.arange(n + 1))
    return ReplaySchedule(pose_type, group, pose_ids, estimates, odometry, has_odo, edges,
                          lm_type, lm_ids, lm_first, lm_bounds)


def initial_pose(schedule: ReplaySchedule, k: int, previous: np.ndarray) -> np.ndarray:
    """The starting estimate of pose ``k`` (``(1, *pose_shape)``).

    Args:
        schedule: The schedule.
        k: The step (``k ≥ 1``).
        previous: ``(1, *pose_shape)`` the current estimate of pose ``k − 1``.
    """
    if schedule.has_odometry[k]:
        return schedule.group.compose(previous, schedule.odometry[k:k + 1])
    return schedule.estimates[k:k + 1].copy()


def initial_landmarks(schedule: ReplaySchedule, k: int, pose: np.ndarray) -> np.ndarray:
    """Starting estimates ``(l_k, 2)`` of the landmarks first observed at step ``k``, from
    their first observation by pose ``k`` (``pose``: ``(1, 3)``)."""
    a, b = schedule.landmark_bounds[k], schedule.landmark_bounds[k + 1]
    obs = next(e for e in schedule.edges if e.tag == "EDGE_SE2_XY")
    z = obs.measurements[schedule.landmark_first[a:b]]
    c, s = np.cos(pose[0, 2]), np.sin(pose[0, 2])
    return np.column_stack([pose[0, 0] + c * z[:, 0] - s * z[:, 1],
                            pose[0, 1] + s * z[:, 0] + c * z[:, 1]])



@dataclass
class Replay:
    """The outcome of :func:`replay`.

    Args:
        optimizer: The optimizer holding the replayed graph (estimates after the last step).
        incremental: The incremental optimizer that ran it.
        steps: ``(n,)`` seconds of every step (adding included; wall time).
        cpu_steps: ``(n,)`` the same in CPU time of the thread (what a loaded machine does not
            inflate).
        poses: ``(n, *pose_shape)`` final pose estimates in step order.
        landmarks: ``(l, 2)`` final landmark estimates in :attr:`ReplaySchedule.landmark_ids`
            order, or ``None``.
    """

    optimizer: SparseOptimizer
    incremental: IncrementalOptimizer
    steps: np.ndarray
    cpu_steps: np.ndarray
    poses: np.ndarray
    landmarks: np.ndarray | None


def replay(schedule: ReplaySchedule, config: IncrementalConfig | None = None,
           on_step: Callable[[int, UpdateReport, float, SparseOptimizer], None] | None = None,
           kernel: RobustKernel | None = None) -> Replay:
    """Replay the schedule with an :class:`~graphopt.online.IncrementalOptimizer`: per step,
    add the pose, the new landmarks and the edges to the optimizer, then one ``update``.

    Args:
        schedule: From :func:`replay_schedule`.
        config: The incremental optimizer's configuration.
        on_step: Called after every step with its index, report, seconds and the optimizer
            (outside the timing).
        kernel: A robust kernel for every edge, or ``None``.

    Returns:
        The :class:`Replay`.
    """
    opt = SparseOptimizer()
    inc = IncrementalOptimizer(opt, config)
    n = schedule.steps
    pid = schedule.pose_ids
    ptype, ltype = schedule.pose_type, schedule.landmark_type
    times = np.zeros(n)
    cpu = np.zeros(n)
    current = schedule.estimates[:1].copy()
    store = None
    for k in range(n):
        t0, c0 = time.perf_counter(), time.thread_time()
        if k:
            current = initial_pose(schedule, k, store.estimates[k - 1:k])
        opt.add_vertices(ptype, pid[k:k + 1], current, fixed=k == 0)
        if ltype is not None and schedule.landmark_bounds[k + 1] > schedule.landmark_bounds[k]:
            a, b = schedule.landmark_bounds[k], schedule.landmark_bounds[k + 1]
            opt.add_vertices(ltype, schedule.landmark_ids[a:b],
                             initial_landmarks(schedule, k, current))
        for e in schedule.edges:
            lo, hi = e.bounds[k], e.bounds[k + 1]
            if hi > lo:
                opt.add_edges(e.etype, e.ids[lo:hi], e.measurements[lo:hi],
                              e.information[lo:hi], robust_kernel=kernel)
        report = inc.update()
        times[k] = time.perf_counter() - t0
        cpu[k] = time.thread_time() - c0
        if store is None:
            store = opt.graph.stores[ptype]
        if on_step is not None:
            on_step(k, report, float(times[k]), opt)
    poses = opt.graph.stores[ptype].estimates.copy()  # added in step order
    lms = None
    if ltype is not None and len(schedule.landmark_ids):
        lms = opt.graph.stores[ltype].estimates.copy()  # added in first-observation order
    return Replay(opt, inc, times, cpu, poses, lms)
