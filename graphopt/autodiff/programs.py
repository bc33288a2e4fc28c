"""Which traced block programs (:mod:`graphopt.autodiff.replay`) a linearisation may replay.

A program is kept per *signature*: the edge type, the block's length, and everything the
traced operations were decided on — each input's shape, dtype and strides, the per-vertex
jets' column supports and group structures (their generators are constants of the program),
the shared parameters (``ctx.params``, by value), which derived values exist. A linearisation
with the same signature replays the program; any difference (another block length, a layout,
a structure that no longer fits) traces a new one.

Life of a program: traced on one block of the second linearisation with its signature (a
signature seen once is not worth a trace; that block's results are the trace's own, computed
through the tape as usual); checked once, on another block, against the tape bit for bit
(both run; a copy of block data that the trace could not see would make them differ, and the
traced block is then computed again by the tape); then replayed. A trace that is
:class:`~graphopt.autodiff.replay.Poisoned` (a data-dependent branch, a plain view of block
data, an unsupported call) or a failed check marks the signature as not replayable: its
blocks go through the tape, at no further cost.
"""

from __future__ import annotations

import pickle
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

import graphopt.autodiff.tape as tape
from graphopt.autodiff.replay import Poisoned, Program, Traced, Tracer, tracing

__all__ = ["ENABLED", "TRACE_AFTER", "Plan", "clear", "plan"]

#: Replay traced block programs (``False``: every block through the tape, e.g. to compare).
ENABLED = True

#: The linearisation with a signature that traces it (the second: see :func:`plan`).
TRACE_AFTER = 2

#: Signatures seen: a checked or unchecked program, or ``None`` (not replayable).
_PLANS: dict[tuple[Any, ...], Plan] = {}
_LIMIT = 32


class Plan:
    """The program of one signature and its state.

    Args:
        key: The signature.
        length: The block length it applies to.
    """

    def __init__(self, key: tuple[Any, ...], length: int) -> None:
        self.key, self.length = key, length
        self.program: Program | None = None
        self.checked = False
        self.dead = False  # not replayable (poisoned, or the check failed)
        self.has_active = False
        self.seen = 0  # linearisations with this signature
        # One thread traces or checks at a time (the others take the tape meanwhile); a
        # checked program runs in any number of threads (its constants are only read).
        self.lock = threading.Lock()

    def trace(self, inputs: list[Any], evaluate: Callable[[list[Any]], Any]) -> Any:
        """Run ``evaluate`` on traced views of ``inputs`` and keep its program.

        ``evaluate`` returns ``(error value, active or None, J or None)``, which is returned
        with the arrays as plain views (``None`` if the trace was poisoned: the caller
        evaluates the block again, untraced).
        """
        tr = Tracer()
        try:
            with tracing(tr):
                traced = [tr.input(a) for a in inputs]
                ev, active, J = evaluate(traced)
                if type(ev) is not Traced or J is None or not (
                        active is None or type(active) is Traced):
                    raise Poisoned("the block's error or Jacobian is not traced")
                outs = [tr.slot(ev)] + ([] if active is None else [tr.slot(active)])
        except Exception:  # noqa: BLE001 - poisoned, or code that behaves otherwise on a
            self.dead = True  # traced array (a `type(x) is np.ndarray` test): the tape's way
            return None
        self.program = Program(tr, outs)
        self.has_active = active is not None
        plain = np.ndarray.view
        return (plain(ev, np.ndarray), None if active is None else plain(active, np.ndarray),
                plain(J, np.ndarray))

    def run(self, inputs: list[Any]) -> tuple[np.ndarray, np.ndarray | None]:
        """``(error, active or None)`` of a block (its Jacobian rows land in the last input)."""
        assert self.program is not None
        out = self.program.run(inputs)
        return out[0], (out[1] if self.has_active else None)

    def check(self, inputs: list[Any], e: np.ndarray, active: np.ndarray | None,
              J: np.ndarray) -> None:
        """Compare the program on ``inputs`` (a fresh Jacobian buffer last) with the tape's
        ``e``, ``active`` and ``J`` of the same block; keep or drop it."""
        try:
            pe, pa = self.run(inputs)
            same = (np.array_equal(pe, e, equal_nan=True)
                    and np.array_equal(inputs[-1].reshape(J.shape), J, equal_nan=True)
                    and (active is None) == (pa is None)
                    and (active is None or np.array_equal(pa, active)))
        except Exception:  # noqa: BLE001 - a program that cannot run on other data is dead
            same = False
        self.checked, self.dead = same, not same
        if not same:
            self.program = None


def clear() -> None:
    """Forget every program (tests; a changed error function)."""
    _PLANS.clear()


def _array(a: Any) -> Any:
    if a is None:
        return None
    if not isinstance(a, np.ndarray):
        return False  # (a slice: not an input)
    return (a.shape, a.dtype.str, a.strides)


def _struct(s: Any) -> Any:
    if s is None:
        return None
    return (s.G.tobytes(), s.G.shape, s.lo, s.left, s.zero.tobytes(), s.one.tobytes())


def _bits(a: Any) -> Any:
    return None if a is None else (a.shape, a.tobytes())


def _jet(j: Any) -> Any:
    if j is None or not hasattr(j, "columns"):
        return type(j).__name__
    cols = None if j.columns is None else tuple(tuple(c) for c in j.columns)
    return (j.lo, j.n, cols, j.seed)


def plan(edge_type: type, positions: list[Any], arrays: list[list[Any]],
         measurement: np.ndarray, ctx: Any, want: bool, length: int,
         blocks: int) -> Plan | None:
    """The plan of a linearisation whose first block reads ``arrays`` (per position, from
    :meth:`~graphopt.autodiff.jacobians._Position.arrays`), or ``None`` when programs do not
    apply (off, one block only, per-edge context data).

    Args:
        edge_type: The edge class.
        positions: The vertex positions (``_Position``).
        arrays: The first block's arrays per position.
        measurement: The first block's measurements.
        ctx: The caller's :class:`~graphopt.edge.EdgeContext` (or ``None``).
        want: Derived values are recomputed on jets.
        length: Edges per block.
        blocks: Number of blocks of that length.
    """
    if not ENABLED or not tape.ENABLED or blocks < 2:  # (forward jets: not what is traced)
        return None
    params: Any = None
    if ctx is not None:
        if ctx.data or ctx.measured is not None or (ctx.derived is not None and not want):
            return None  # per-edge context arrays: inputs this module does not name
        try:
            params = pickle.dumps(ctx.params, protocol=5)
        except Exception:  # noqa: BLE001 - unpicklable parameters: no signature
            return None
    key = (edge_type, length, want, params, _array(measurement),
           tuple((p.vtype, p.vector, p.lo, p.n, _struct(p.struct), _struct(p.dstruct),
                  _jet(p.jet), _jet(p.derived), _bits(p.support), _bits(p.dsupport),
                  tuple(_array(a) for a in arr))
                 for p, arr in zip(positions, arrays, strict=True)))
    found = _PLANS.get(key)
    if found is None:
        if len(_PLANS) >= _LIMIT:
            _PLANS.pop(next(iter(_PLANS)), None)
        found = _PLANS[key] = Plan(key, length)
    found.seen += 1
    # Traced the second time a signature is seen: a trace costs ~5 blocks of the tape, which
    # a signature seen once (edges added at every step of an online problem) never repays.
    return None if found.dead or found.seen < TRACE_AFTER else found
