"""A unary group's evaluations kept by the estimate of its one vertex.

ORB-SLAM's ``PoseOptimization`` restarts every round of a frame from the same predicted pose,
and a round whose outliers did not change retraces the last one: the edge type's call — a pure
function of the estimates, the measurements and the data, which are fixed while the structure
stands — need not be repeated. :class:`~graphopt.single_vertex.SingleVertexProblem` keeps one
memo per unary group for as long as its structure (the problem) lives, and consults it for the
evaluations at a run's start and for queries, not for trial steps: a trial's state is new (none
of the procedure's trials ever hit it, and keeping their outputs cost about 5 % of the stereo
100-match procedure).
"""

from __future__ import annotations

from graphopt.edge import Linearization
from graphopt.numeric import frozen_copy

#: Evaluations kept per group at most (the oldest goes first).
MEMO_STATES = 16

#: Bytes kept per group at most: a 100-match group's evaluation is 11 KB, a 30,000-edge one's
#: 3.4 MB (four of them kept).
MEMO_BYTES = 16 << 20


class EvaluationMemo:
    """The last :data:`MEMO_STATES` outputs (:data:`MEMO_BYTES` at most) of one group's
    ``evaluate`` or ``linearize``, by the estimate's bytes; the errors of a linearisation serve
    an ``evaluate`` too."""

    def __init__(self) -> None:
        self._kept: dict[tuple[str, bytes], Linearization] = {}
        self._sizes: dict[tuple[str, bytes], int] = {}
        self._bytes = 0
        # The group's latest output that was not kept (a trial's), until the type is called
        # again (its buffers may then be reused): see settle.
        self._held: tuple[str, bytes, Linearization] | None = None

    def get(self, method: str, at: bytes) -> Linearization | None:
        """The kept output of ``method`` (or of ``linearize``) at the estimate ``at``.

        Args:
            method: ``"evaluate"`` or ``"linearize"``.
            at: The estimate's bytes.
        """
        out = self._kept.get(("linearize", at))
        if out is None and method != "linearize":
            out = self._kept.get((method, at))
        return out

    def put(self, method: str, at: bytes, out: Linearization) -> None:
        """Keep a read-only copy of ``out`` (a type may return its own buffers, ``out=``,
        which its next call overwrites).

        Args:
            method: ``"evaluate"`` or ``"linearize"``.
            at: The estimate's bytes.
            out: The type's (checked) output.
        """
        e, jacs = out.error, out.jacobians
        size = e.nbytes + sum([j.nbytes for j in jacs])
        if size > MEMO_BYTES:
            return
        kept, sizes = self._kept, self._sizes
        red, act = out.reduced_error, out.active
        new = Linearization(frozen_copy(e), tuple([frozen_copy(j) for j in jacs]),
                            None if red is None else frozen_copy(red),
                            None if act is None else frozen_copy(act))
        key = (method, at)
        self._bytes += size - sizes.get(key, 0)
        kept[key], sizes[key] = new, size
        while len(kept) > MEMO_STATES or self._bytes > MEMO_BYTES:
            old = next(iter(kept))
            del kept[old]
            self._bytes -= sizes.pop(old)

    def hold(self, method: str, at: bytes, out: Linearization) -> None:
        """Remember the group's latest output without keeping it (a trial's).

        Args:
            method: ``"evaluate"`` or ``"linearize"``.
            at: The estimate's bytes.
            out: The type's (checked) output.
        """
        self._held = (method, at, out)

    def release(self) -> None:
        """Forget the held output: the type is called again, and may reuse its buffers."""
        self._held = None

    def settle(self) -> None:
        """Keep the held output (a finished run's last trial's: a replay of the run evaluates
        its end state again)."""
        if self._held is not None:
            self.put(*self._held)
            self._held = None
