"""The algorithms' frozen configurations: Gauss–Newton, Levenberg–Marquardt (g2o's rules and
the schedules beside them) and Powell's Dogleg."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GaussNewtonConfig:
    """Gauss–Newton: solve ``H Δ = b`` and accept unless the new chi2 is not finite.

    Args:
        name: Algorithm name used in messages.
    """

    name: str = "gn"


#: The LM damping schedules (:attr:`LevenbergConfig.schedule`).
SCHEDULES: tuple[str, ...] = ("g2o", "ceres", "gtsam")


@dataclass(frozen=True)
class LevenbergConfig:
    """Levenberg–Marquardt as in g2o's ``OptimizationAlgorithmLevenberg``.

    Args:
        tau: Initial ``λ = τ · max diag(H)`` (g2o: 1e-5), for identity damping.
        initial_lambda: Use this λ instead of the τ rule when given (with diagonal damping or
            the ``"ceres"`` schedule the default is 1e-4, Ceres' initial trust-region radius of
            1e4).
        max_trials: Damped solves per iteration before giving up (g2o: 10).
        diagonal_damping: Damp with ``λ·diag(H)`` (Marquardt, Ceres) instead of g2o's ``λ I``;
            invariant to the scaling of the parameters (focal lengths next to distortions).
        schedule: How λ changes after a trial with gain ratio ρ (measured per problem family
            by ``benchmarks/bench_schedules.py``: ``"g2o"`` is best on bundle adjustment — 21
            iterations on Ladybug-49 where ``"ceres"`` takes 32 and ``"gtsam"`` 29 — and
            ``"gtsam"`` on pose graphs — 9 iterations on ``w10000`` where ``"g2o"`` is not
            converged after 100 and ``"ceres"`` stops early after 41; the apps and
            :func:`~graphopt.types.build_graph` choose accordingly).
            ``"g2o"`` (default) (g2o's Nielsen rule): after a success
            ``λ ← λ·max(1/3, min(2/3, 1 − (2ρ − 1)³))`` (λ always falls), after a failure
            ``λ ← λν, ν ← 2ν``.
            ``"ceres"`` (Ceres' LM strategy, Nielsen's rule unclipped): after a success
            ``λ ← λ·max(1/3, 1 − (2ρ − 1)³)`` (λ grows up to ×2 when ρ < ½), after a failure
            ``λ ← λν, ν ← 2ν``; λ kept in [1e-16, 1e32] (Ceres' trust-region radius bounds).
            ``"gtsam"`` (GTSAM's fixed factor): ``λ ← λ/factor`` after a success,
            ``λ ← λ·factor`` after a failure, starting from ``initial_lambda`` or 1e-5.
        factor: The ``"gtsam"`` schedule's factor (GTSAM: 10).
        name: Algorithm name used in messages.
    """

    tau: float = 1e-5
    initial_lambda: float | None = None
    max_trials: int = 10
    diagonal_damping: bool = False
    schedule: str = "g2o"
    factor: float = 10.0
    name: str = "lm"

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise ValueError(f"unknown LM schedule {self.schedule!r}; choose "
                             f"{', '.join(SCHEDULES)}")
        if not self.factor > 1.0:
            raise ValueError(f"LM factor must be > 1, got {self.factor!r}")


@dataclass(frozen=True)
class DoglegConfig:
    """Powell's Dogleg as in g2o's ``OptimizationAlgorithmDogleg``.

    Args:
        initial_radius: Initial trust-region radius (g2o: 1e4).
        initial_lambda: Damping added to make ``H`` positive definite (g2o: 1e-7).
        lambda_factor: Factor on λ after a failed factorisation (g2o: 10).
        max_trials: Attempts per iteration (g2o: 100).
        name: Algorithm name used in messages.
    """

    initial_radius: float = 1e4
    initial_lambda: float = 1e-7
    lambda_factor: float = 10.0
    max_trials: int = 100
    name: str = "dogleg"


AlgorithmConfig = GaussNewtonConfig | LevenbergConfig | DoglegConfig
