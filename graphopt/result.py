"""What an optimisation did: one record per iteration, and the result derived from them."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum


class StopReason(StrEnum):
    """Why :meth:`~graphopt.optimizer.SparseOptimizer.optimize` stopped.

    A ``StrEnum``: each member equals its value (``StopReason.GAIN == "gain"``), so it prints
    and serialises as the plain word.
    """

    #: The iteration count was reached.
    ITERATIONS = "iterations"
    #: A trial step changed chi2 by less than the function tolerance (relative).
    FUNCTION_TOLERANCE = "function_tolerance"
    #: The gradient's max-norm fell below the gradient tolerance.
    GRADIENT_TOLERANCE = "gradient_tolerance"
    #: A step was negligible against the estimates (parameter tolerance).
    PARAMETER_TOLERANCE = "parameter_tolerance"
    #: The relative chi2 decrease of an iteration fell below the gain threshold.
    GAIN = "gain"
    #: :meth:`~graphopt.optimizer.SparseOptimizer.force_stop` was called (g2o's flag).
    STOPPED = "stopped"
    #: :meth:`~graphopt.optimizer.SparseOptimizer.stop` was called (Ctrl-C, another thread).
    INTERRUPTED = "interrupted"
    #: Zero chi2, or no trial step reduced chi2 although the solves worked.
    CONVERGED = "converged"
    #: Every solve of the last iteration met a system that is not positive definite, or the
    #: step led to a non-finite chi2 (Gauss–Newton).
    FAILED = "failed"
    #: Gauss–Newton met a rank-deficient (singular) system; no step was applied.
    SINGULAR = "singular"

    @property
    def converged(self) -> bool:
        """Whether the run stopped at a minimum: a tolerance, zero chi2 or no better step."""
        return self in (StopReason.FUNCTION_TOLERANCE, StopReason.GRADIENT_TOLERANCE,
                        StopReason.PARAMETER_TOLERANCE, StopReason.CONVERGED, StopReason.GAIN)


@dataclass
class IterationInfo:
    """What one iteration did.

    Args:
        iteration: Index, from 0.
        chi2: Robust chi2 after the iteration (before it, when it failed).
        lam: λ used for the accepted step (LM/Dogleg), 0 for GN.
        trials: Damped solves tried (g2o's ``levenbergIter``).
        radius: Trust-region radius (Dogleg), else 0.
        not_pd: How many solves met a non-positive-definite system.
        singular: How many of those found it rank deficient (singular).
        failed: True when no acceptable step was found (the optimisation stops).
        stop: The stopping test this iteration met, if any (set by the algorithm:
            tolerances, a singular or failed solve).
        linearize_seconds: Time for errors, Jacobians and assembly.
        schur_seconds: Time for damping and the Schur complement.
        solve_seconds: Time in the linear solver.
        seconds: Wall time of the whole iteration.
    """

    iteration: int
    chi2: float
    lam: float = 0.0
    trials: int = 1
    radius: float = 0.0
    not_pd: int = 0
    singular: int = 0
    failed: bool = False
    stop: StopReason | None = None
    linearize_seconds: float = 0.0
    schur_seconds: float = 0.0
    solve_seconds: float = 0.0
    seconds: float = 0.0


@dataclass
class OptimizationResult:
    """What :meth:`~graphopt.optimizer.SparseOptimizer.optimize` did.

    One definition of an *iteration* everywhere (iteration lines, these records, the apps'
    JSON, the recordings' ``iteration`` timeline): one linearisation followed by at least one
    trial step — accepted, or rejected as the last iteration that found no acceptable step
    (its chi2 is the unchanged one). A run that stops because the gradient at the start of an
    iteration is negligible does not count that linearisation as an iteration; its time is in
    :attr:`seconds` (as the set-up).

    Args:
        initial_chi2: Robust chi2 before the first iteration.
        final_chi2: Robust chi2 at the end.
        seconds: Wall time of the whole call.
        stop_reason: Why the run stopped.
        info: The :class:`IterationInfo` of every iteration.
        replayed: The run had the inputs of an earlier one on the same structure, whose end
            state and records it took instead of iterating (:mod:`~graphopt.run_memo`; the
            records' times are that run's).
    """

    initial_chi2: float
    final_chi2: float = float("nan")
    seconds: float = 0.0
    stop_reason: StopReason = StopReason.ITERATIONS
    info: list[IterationInfo] = field(default_factory=list)
    replayed: bool = False

    @property
    def iterations(self) -> int:
        """Iterations performed (a last one that found no acceptable step included)."""
        return len(self.info)

    @property
    def accepted_iterations(self) -> int:
        """Iterations whose step was accepted (the state changed)."""
        return sum(1 for r in self.info if not r.failed)

    @property
    def chi2_history(self) -> list[float]:
        """Robust chi2 after each iteration."""
        return [r.chi2 for r in self.info]

    @property
    def lambda_history(self) -> list[float]:
        """λ of each iteration (LM/Dogleg)."""
        return [r.lam for r in self.info]

    @property
    def iteration_seconds(self) -> list[float]:
        """Wall time of each iteration."""
        return [r.seconds for r in self.info]

    @property
    def linearize_seconds(self) -> list[float]:
        """Per iteration: errors, Jacobians, assembly."""
        return [r.linearize_seconds for r in self.info]

    @property
    def schur_seconds(self) -> list[float]:
        """Per iteration: damping and Schur complement (all trials)."""
        return [r.schur_seconds for r in self.info]

    @property
    def solve_seconds(self) -> list[float]:
        """Per iteration: linear solver (all trials)."""
        return [r.solve_seconds for r in self.info]

    @property
    def trials(self) -> list[int]:
        """Per iteration: damped solves (g2o's ``levenbergIter``)."""
        return [r.trials for r in self.info]

    @property
    def not_positive_definite(self) -> int:
        """Solves that met a non-positive-definite system, over all iterations."""
        return sum(r.not_pd for r in self.info)

    @property
    def seconds_per_iteration(self) -> float:
        """Mean wall time of one iteration (:attr:`seconds` over :attr:`iterations`)."""
        return self.seconds / self.iterations if self.iterations else 0.0
