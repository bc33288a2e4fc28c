"""Optimisation algorithms: Gauss–Newton, Levenberg–Marquardt (g2o's rules) and Powell's Dogleg.

Each algorithm performs one iteration on a :class:`~graphopt.problem.Problem` — linearise, solve
damped systems, apply, evaluate, accept or restore — and reports what it did in an
:class:`~graphopt.result.IterationInfo`. It talks to the problem alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from graphopt.algorithm_configs import (
    SCHEDULES,
    AlgorithmConfig,
    DoglegConfig,
    GaussNewtonConfig,
    LevenbergConfig,
)
from graphopt.errors import NotPositiveDefiniteError, SingularSystemError
from graphopt.linear import Assembly
from graphopt.problem import Problem, Step
from graphopt.result import IterationInfo, StopReason
from graphopt.step_ops import axpy as _axpy
from graphopt.step_ops import dot as _dot
from graphopt.step_ops import predicted_decrease as _predicted_decrease
from graphopt.stopping import StoppingConfig

__all__ = ["SCHEDULES", "Algorithm", "AlgorithmConfig", "Dogleg", "DoglegConfig", "GaussNewton",
           "GaussNewtonConfig", "LevenbergConfig", "LevenbergMarquardt", "make_algorithm"]

#: Ceres' bounds on λ = 1 / trust-region radius (``max_/min_trust_region_radius``).
_CERES_LAMBDA = (1e-16, 1e32)


def _never() -> bool:
    return False


#: No stopping test (``iterate`` called without a config).
_NO_TESTS = StoppingConfig.iterations_only()


class _Tests:
    """The stopping tests of one iteration; the state norm is computed once, when needed.

    Args:
        p: The problem.
        stopping: The tests' tolerances.
    """

    def __init__(self, p: Problem, stopping: StoppingConfig) -> None:
        self.p, self.stopping = p, stopping
        self._state_norm: float | None = None

    def gradient(self, b: Step) -> bool:
        """The gradient at the linearisation point is negligible."""
        tol = self.stopping.gradient_tolerance
        return tol > 0 and self.stopping.gradient_converged(self.p.max_abs(b))

    def step(self, step: Step, norm: float | None = None) -> bool:
        """The step is negligible against the estimates (``norm``: ``‖step‖`` if known)."""
        if self.stopping.parameter_tolerance <= 0:
            return False
        if self._state_norm is None:
            self._state_norm = self.p.state_norm()
        if norm is None:
            norm = math.sqrt(_dot(step, step))
        return self.stopping.parameters_converged(norm, self._state_norm)

    def predicts_function(self, chi: float, decrease: float) -> bool:
        """The model's predicted decrease is under half the function tolerance: the trial will
        most likely end the run, so it need not linearise (if it does not end it, the next
        linearisation computes the Jacobians; the numbers are the same either way)."""
        return self.stopping.predicts_function(chi, decrease)

    def function(self, chi: float, new_chi: float) -> bool:
        """The trial changed chi2 by a negligible fraction."""
        return (self.stopping.function_tolerance > 0 and math.isfinite(new_chi)
                and self.stopping.function_converged(chi, new_chi))


class Algorithm:
    """Base of the algorithms.

    Every algorithm applies the stopping tests of :class:`~graphopt.stopping.StoppingConfig`
    where Ceres does: the gradient at the linearisation point (the iteration then makes no
    trial: ``trials == 0``), the size of every trial step before it is applied, the chi2 change
    of every trial. A test that fires sets :attr:`IterationInfo.stop`.

    Args:
        config: The algorithm's frozen configuration.
    """

    def __init__(self, config: AlgorithmConfig) -> None:
        self.config = config
        self.lam = 0.0
        # Whether the next trial lets linearize-on-trial edge types linearise: yes after an
        # accepted trial (the Jacobians are then reused), no after a rejected one (errors only,
        # as Ceres' unsuccessful step costs).
        self.trial_linearizes = True
        #: Set by the optimizer on the last iteration a run allows: no trial then linearises
        #: (nothing would read its Jacobians; the next run evaluates afresh).
        self.final_iteration = False
        #: Polled between the trials of an iteration; ``True`` ends the iteration with the
        #: estimate restored and the stop reason ``interrupted`` (the optimizer's ``stop()``).
        self.interrupted: Callable[[], bool] = _never

    def reset(self) -> None:
        """Forget state kept across iterations (λ, radius)."""
        self.trial_linearizes = True

    def iterate(self, p: Problem, iteration: int,
                stopping: StoppingConfig | None = None) -> IterationInfo:
        """Perform one iteration.

        Args:
            p: The problem.
            iteration: Iteration index.
            stopping: The stopping tests (``None``: none but a failed iteration).
        """
        raise NotImplementedError

    def _trial(self, p: Problem, step: Step, last: bool = False) -> float:
        """Apply a trial step (after :meth:`Problem.push`) and return the new robust chi2
        (``last``: the step is expected to end the run, its Jacobians would not be used)."""
        p.push()
        p.apply(step)
        return p.robust_chi2(self.trial_linearizes and not (self.final_iteration or last))

    def line_fields(self, info: IterationInfo) -> str:
        """The algorithm's fields of g2o's iteration line (after ``schur=``).

        Args:
            info: The iteration.
        """
        return ""


class GaussNewton(Algorithm):
    """Gauss–Newton. A step to a non-finite chi2 is undone and the iteration fails (the last
    finite estimate is kept, as in LM).

    Args:
        config: :class:`GaussNewtonConfig`.
    """

    def iterate(self, p: Problem, iteration: int,
                stopping: StoppingConfig | None = None) -> IterationInfo:
        """See :meth:`Algorithm.iterate`.

        Args:
            p: The problem.
            iteration: Iteration index.
            stopping: The stopping tests.
        """
        tests = _Tests(p, stopping if stopping is not None else _NO_TESTS)
        asm, chi = p.linearize()
        if tests.gradient(p.gradient(asm)):
            return IterationInfo(iteration, chi, trials=0, stop=StopReason.GRADIENT_TOLERANCE)
        try:
            step = p.solve(asm, 0.0)
        except NotPositiveDefiniteError as exc:  # never apply a step of a singular factor
            singular = isinstance(exc, SingularSystemError)
            return IterationInfo(iteration, chi, not_pd=1, singular=int(singular), failed=True,
                                 stop=StopReason.SINGULAR if singular else StopReason.FAILED)
        if tests.step(step):
            return IterationInfo(iteration, chi, failed=True,
                                 stop=StopReason.PARAMETER_TOLERANCE)
        new_chi = self._trial(p, step)
        if not math.isfinite(new_chi):  # keep the last finite estimate, as LM does
            p.pop()
            return IterationInfo(iteration, chi, failed=True, stop=StopReason.FAILED)
        stop = StopReason.FUNCTION_TOLERANCE if tests.function(chi, new_chi) else None
        return IterationInfo(iteration, new_chi, stop=stop)


class LevenbergMarquardt(Algorithm):
    """Levenberg–Marquardt with g2o's λ rules.

    Args:
        config: :class:`LevenbergConfig`.
    """

    config: LevenbergConfig

    def __init__(self, config: LevenbergConfig) -> None:
        super().__init__(config)
        self.reset()

    def reset(self) -> None:
        """Start again from the τ rule."""
        super().reset()
        self.lam = 0.0
        self.nu = 2.0
        self.schedule = self.config.schedule

    def _succeeded(self, rho: float) -> None:
        """Less damping after an accepted trial with gain ratio ``rho``."""
        schedule = self.schedule
        if schedule == "gtsam":
            self.lam /= self.config.factor
            return
        alpha = 1.0 - (2.0 * rho - 1.0) ** 3
        if schedule == "g2o":
            alpha = min(alpha, 2.0 / 3.0)
        self.lam *= max(1.0 / 3.0, alpha)
        if schedule == "ceres":
            self.lam = min(max(self.lam, _CERES_LAMBDA[0]), _CERES_LAMBDA[1])
        self.nu = 2.0

    def _failed(self) -> None:
        """More damping after a rejected or failed trial."""
        if self.schedule == "gtsam":
            self.lam *= self.config.factor
        else:
            self.lam *= self.nu
            self.nu *= 2.0
            if self.schedule == "ceres":
                self.lam = min(self.lam, _CERES_LAMBDA[1])

    def start_lambda(self, p: Problem, asm: Assembly) -> None:
        """λ₀ at a run's first linearisation: the configured one, GTSAM's 1e-5, Ceres' 1e-4
        (diagonal damping or the ``"ceres"`` schedule), else ``τ · max diag(H)`` (g2o).

        Args:
            p: The problem.
            asm: Its assembly at the first linearisation.
        """
        cfg = self.config
        if cfg.initial_lambda is not None:
            self.lam = cfg.initial_lambda
        elif self.schedule == "gtsam":
            self.lam = 1e-5
        elif cfg.diagonal_damping or self.schedule == "ceres":
            self.lam = 1e-4  # Ceres' initial trust-region radius, 1e4
        else:
            self.lam = cfg.tau * max(p.max_diagonal(asm), 1e-12)
        self.nu = 2.0

    def line_fields(self, info: IterationInfo) -> str:
        """g2o's ``lambda`` and ``levenbergIter`` fields.

        Args:
            info: The iteration.
        """
        return f"\t lambda= {info.lam:.6g}\t levenbergIter= {info.trials}"

    def iterate(self, p: Problem, iteration: int,
                stopping: StoppingConfig | None = None) -> IterationInfo:
        """See :meth:`Algorithm.iterate`.

        Args:
            p: The problem.
            iteration: Iteration index.
            stopping: The stopping tests.
        """
        tests = _Tests(p, stopping if stopping is not None else _NO_TESTS)
        asm, chi = p.linearize()
        cfg = self.config
        b = p.gradient(asm)
        if tests.gradient(b):
            return IterationInfo(iteration, chi, lam=self.lam, trials=0,
                                 stop=StopReason.GRADIENT_TOLERANCE)
        if self.lam <= 0.0:
            self.start_lambda(p, asm)
        damp = p.damping(asm, cfg.diagonal_damping)  # once per linearisation
        not_pd = singular = 0
        for trial in range(1, cfg.max_trials + 1):
            try:
                step = p.solve(asm, self.lam, damp)
            except NotPositiveDefiniteError as exc:
                not_pd += 1
                singular += isinstance(exc, SingularSystemError)
                self._failed()
                continue
            if tests.step(step):
                return IterationInfo(iteration, chi, lam=self.lam, trials=trial, not_pd=not_pd,
                                     singular=singular, failed=True,
                                     stop=StopReason.PARAMETER_TOLERANCE)
            # Predicted decrease of chi2 = Δ'(λDΔ + b) (g2o adds 1e-3 against a zero divisor).
            predicted = _predicted_decrease(step, damp, self.lam, b)
            new_chi = self._trial(p, step, tests.predicts_function(chi, predicted))
            rho = (chi - new_chi) / (predicted + 1e-3)
            stop = StopReason.FUNCTION_TOLERANCE if tests.function(chi, new_chi) else None
            if rho > 0 and math.isfinite(new_chi):
                lam_used = self.lam
                self._succeeded(rho)
                self.trial_linearizes = True
                return IterationInfo(iteration, new_chi, lam=lam_used, trials=trial,
                                     not_pd=not_pd, singular=singular, stop=stop)
            p.pop()
            self.trial_linearizes = False
            if stop is None and self.interrupted():  # between trials: the estimate is restored
                stop = StopReason.INTERRUPTED
            if stop is not None:  # a rejected step that changes nothing: converged
                return IterationInfo(iteration, chi, lam=self.lam, trials=trial, not_pd=not_pd,
                                     singular=singular, failed=True, stop=stop)
            self._failed()
        return IterationInfo(iteration, chi, lam=self.lam, trials=cfg.max_trials, not_pd=not_pd,
                             singular=singular, failed=True)


class Dogleg(Algorithm):
    """Powell's Dogleg trust-region method.

    Args:
        config: :class:`DoglegConfig`.
    """

    config: DoglegConfig

    def __init__(self, config: DoglegConfig) -> None:
        super().__init__(config)
        self.reset()

    def reset(self) -> None:
        """Start again from the initial radius and λ."""
        super().reset()
        self.radius = self.config.initial_radius
        self.lam = self.config.initial_lambda

    def line_fields(self, info: IterationInfo) -> str:
        """g2o's ``delta`` (trust radius) and ``lambda`` fields.

        Args:
            info: The iteration.
        """
        return f"\t delta= {info.radius:.6f}\t lambda= {info.lam:.6g}"

    def iterate(self, p: Problem, iteration: int,
                stopping: StoppingConfig | None = None) -> IterationInfo:
        """See :meth:`Algorithm.iterate`.

        Args:
            p: The problem.
            iteration: Iteration index.
            stopping: The stopping tests.
        """
        cfg = self.config
        tests = _Tests(p, stopping if stopping is not None else _NO_TESTS)
        asm, chi = p.linearize()
        b = p.gradient(asm)
        if tests.gradient(b):
            return IterationInfo(iteration, chi, lam=self.lam, trials=0, radius=self.radius,
                                 stop=StopReason.GRADIENT_TOLERANCE)
        bb = _dot(b, b)
        hb = p.hessian_product(asm, b)
        bhb = _dot(b, hb)
        alpha = bb / bhb if bhb > 0 else 0.0
        sd = _axpy(alpha, b, 0.0, b)
        sd_norm = math.sqrt(_dot(sd, sd))
        gn: Step | None = None
        not_pd = singular = 0
        trial = 0
        for trial in range(1, cfg.max_trials + 1):  # noqa: B007 - reported below
            if gn is None:
                try:
                    gn = p.solve(asm, self.lam)
                    self.lam = max(self.lam / cfg.lambda_factor, cfg.initial_lambda)
                except NotPositiveDefiniteError as exc:
                    not_pd += 1
                    singular += isinstance(exc, SingularSystemError)
                    self.lam *= cfg.lambda_factor
                    continue
            gn_norm = math.sqrt(_dot(gn, gn))
            if gn_norm <= self.radius:
                step = gn
            elif sd_norm >= self.radius:
                step = _axpy(self.radius / math.sqrt(bb), b, 0.0, b)
            else:
                # Point on the segment sd → gn at distance radius: ‖sd + β(gn − sd)‖ = radius.
                d = _axpy(1.0, gn, -1.0, sd)
                a2, a1 = _dot(d, d), 2.0 * _dot(sd, d)
                a0 = sd_norm**2 - self.radius**2
                beta = (-a1 + math.sqrt(max(a1 * a1 - 4 * a2 * a0, 0.0))) / (2 * a2)
                step = _axpy(1.0, sd, beta, d)
            step_norm = math.sqrt(_dot(step, step))
            if tests.step(step, step_norm):
                return IterationInfo(iteration, chi, lam=self.lam, trials=trial,
                                     radius=self.radius, not_pd=not_pd, singular=singular,
                                     failed=True, stop=StopReason.PARAMETER_TOLERANCE)
            hstep = p.hessian_product(asm, step)
            linear_gain = 2.0 * _dot(b, step) - _dot(step, hstep)  # in chi2 units
            new_chi = self._trial(p, step)
            rho = (chi - new_chi) / linear_gain if linear_gain > 0 else -1.0
            if rho > 0.75:
                self.radius = max(self.radius, 3.0 * step_norm)
            elif rho < 0.25:
                self.radius *= 0.5
            stop = StopReason.FUNCTION_TOLERANCE if tests.function(chi, new_chi) else None
            if rho > 0 and math.isfinite(new_chi):
                self.trial_linearizes = True
                return IterationInfo(iteration, new_chi, lam=self.lam, trials=trial,
                                     radius=self.radius, not_pd=not_pd, singular=singular,
                                     stop=stop)
            p.pop()
            self.trial_linearizes = False
            if stop is None and self.interrupted():  # between trials: the estimate is restored
                stop = StopReason.INTERRUPTED
            if stop is not None:  # a rejected step that changes nothing: converged
                return IterationInfo(iteration, chi, lam=self.lam, trials=trial,
                                     radius=self.radius, not_pd=not_pd, singular=singular,
                                     failed=True, stop=stop)
            if self.radius < 1e-30:
                break
        return IterationInfo(iteration, chi, lam=self.lam, trials=trial, radius=self.radius,
                             not_pd=not_pd, singular=singular, failed=True)


#: The algorithm class of every configuration type.
ALGORITHMS: dict[type, type[Algorithm]] = {
    GaussNewtonConfig: GaussNewton, LevenbergConfig: LevenbergMarquardt, DoglegConfig: Dogleg,
}
#: Names accepted by :func:`make_algorithm`.
NAMES: dict[str, type] = {
    "gn": GaussNewtonConfig, "gauss-newton": GaussNewtonConfig,
    "lm": LevenbergConfig, "levenberg": LevenbergConfig,
    "dogleg": DoglegConfig, "dl": DoglegConfig,
}
_DEFAULTS: dict[type, AlgorithmConfig] = {}  # the default configs made (frozen: shared)


def make_algorithm(spec: str | AlgorithmConfig) -> Algorithm:
    """Create an algorithm from a name (``gn``, ``lm``, ``dogleg``) or a config.

    Args:
        spec: Name or configuration dataclass.
    """
    if isinstance(spec, str):
        if spec.lower() not in NAMES:
            raise ValueError(f"unknown algorithm {spec!r}; choose gn, lm or dogleg")
        cls = NAMES[spec.lower()]
        spec = _DEFAULTS.get(cls) or _DEFAULTS.setdefault(cls, cls())
    for base in type(spec).__mro__:  # a subclass of a config runs its base's algorithm
        if base in ALGORITHMS:
            return ALGORITHMS[base](spec)  # type: ignore[arg-type]
    raise TypeError(f"not an algorithm configuration: {spec!r}")
