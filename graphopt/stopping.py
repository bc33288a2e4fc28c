"""When a run has converged: Ceres' stopping tests beside g2o's gain threshold and the cap.

The tests compare quantities of one iteration, in chi2 units (``chi2 = 2 × Ceres' cost``, so the
relative tests read the same as Ceres'):

* *function tolerance*: ``|chi2 − chi2_trial| ≤ tol · chi2`` for a trial step, accepted or not
  (Ceres' ``function_tolerance``: the step changed the cost by a negligible fraction);
* *gradient tolerance*: ``max |b| ≤ tol`` for the gradient ``b = −Jᵀρ'Ωe`` of ``½ chi2`` at the
  linearisation point, in the tangent space of every free vertex (Ceres' ``gradient_tolerance``);
* *parameter tolerance*: ``‖Δ‖ ≤ tol · (‖x‖ + tol)`` for a trial step ``Δ`` and the estimates
  ``x`` of the free vertices (Ceres' ``parameter_tolerance``);
* *gain*: g2o's ``-gain``: the relative chi2 decrease of an accepted iteration
  ``(chi2_before − chi2_after) / chi2_after`` below the threshold;
* the iteration cap.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The relative chi2 change that :meth:`StoppingConfig.g2o` reads as none (g2o's ``rho == 0``):
#: above the rounding of a converged chi2 (1e-16 to 3e-15 on ORB-SLAM's problems), far below
#: any change that moves an estimate within its uncertainty.
ROUNDING_CHANGE = 1e-12


@dataclass(frozen=True)
class StoppingConfig:
    """The stopping tests of :meth:`~graphopt.optimizer.SparseOptimizer.optimize`.

    The defaults are Ceres' (``Solver::Options``): a run stops when it has converged rather than
    after a fixed number of iterations. ``0`` disables a test; :meth:`iterations_only` disables
    all but the cap (g2o's behaviour: run the iterations asked for unless no step is found).

    Args:
        max_iterations: Iterations when ``optimize`` is called without a count (Ceres: 50).
        function_tolerance: Relative chi2 change of a trial step below which the run has
            converged (Ceres: 1e-6).
        gradient_tolerance: Max-norm of the gradient below which the run has converged
            (Ceres: 1e-10).
        parameter_tolerance: Relative step size below which the run has converged
            (Ceres: 1e-8).
        gain_threshold: g2o's ``-gain``: relative chi2 decrease of an accepted iteration below
            which the run stops (0: off, as in g2o).
    """

    max_iterations: int = 50
    function_tolerance: float = 1e-6
    gradient_tolerance: float = 1e-10
    parameter_tolerance: float = 1e-8
    gain_threshold: float = 0.0

    def __post_init__(self) -> None:
        if int(self.max_iterations) != self.max_iterations or self.max_iterations < 0:
            raise ValueError(f"max_iterations must be a non-negative integer, got "
                             f"{self.max_iterations!r}")
        for name in ("function_tolerance", "gradient_tolerance", "parameter_tolerance",
                     "gain_threshold"):
            value = getattr(self, name)
            if not value >= 0.0:  # also rejects NaN
                raise ValueError(f"{name} must be >= 0, got {value!r}")

    @classmethod
    def iterations_only(cls, max_iterations: int = 50) -> StoppingConfig:
        """Only the cap (and an iteration that finds no step): g2o's ``optimize(n)``.

        Args:
            max_iterations: The cap.
        """
        return cls(max_iterations, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def g2o(cls, max_iterations: int = 50, change: float = ROUNDING_CHANGE) -> StoppingConfig:
        """g2o's ``optimize(n)`` as its users see it: the cap, an iteration that finds no step,
        and g2o's end when a trial leaves chi2 unchanged (its LM's ``rho == 0``), read as a
        change of at most :data:`ROUNDING_CHANGE` of chi2.

        Why not exactly 0: once converged, chi2 changes only in its last digits, which depend
        on the order of the sums. g2o spends its remaining iterations there — ORB-SLAM's
        ``PoseOptimization`` at 2,000 matches makes 86 trials of which 70 change chi2 by less
        than 3e-15 — and so would any copy of it, on other digits. The estimate those trials
        move is the same to well within its uncertainty. :meth:`iterations_only` keeps the
        exact count (for timing iterations or comparing them one by one).

        Args:
            max_iterations: The cap.
            change: The relative chi2 change read as none (0: :meth:`iterations_only`).
        """
        return cls(max_iterations, change, 0.0, 0.0, 0.0)

    def function_converged(self, chi2: float, trial_chi2: float) -> bool:
        """Whether a trial's chi2 change is negligible (function tolerance).

        Args:
            chi2: Chi2 at the linearisation point.
            trial_chi2: Chi2 after the trial step (finite).
        """
        return abs(chi2 - trial_chi2) <= self.function_tolerance * chi2

    def predicts_function(self, chi2: float, decrease: float) -> bool:
        """Whether the model's predicted decrease is under half the function tolerance: the
        trial will most likely end the run (LM then does not linearise it).

        Args:
            chi2: Chi2 at the linearisation point.
            decrease: The damped model's predicted decrease of chi2.
        """
        tol = self.function_tolerance
        return tol > 0 and 0.0 <= decrease < 0.5 * tol * chi2

    def gradient_converged(self, max_gradient: float) -> bool:
        """Whether the gradient is negligible (gradient tolerance).

        Args:
            max_gradient: ``max |b|`` over the free unknowns.
        """
        return max_gradient <= self.gradient_tolerance

    def parameters_converged(self, step_norm: float, state_norm: float) -> bool:
        """Whether a step is negligible against the estimates (parameter tolerance).

        Args:
            step_norm: ``‖Δ‖``.
            state_norm: ``‖x‖`` over the free vertices' estimates.
        """
        tol = self.parameter_tolerance
        return step_norm <= tol * (state_norm + tol)

    def gain_reached(self, chi2_before: float, chi2_after: float) -> bool:
        """Whether an accepted iteration gained too little (g2o's ``-gain``).

        Args:
            chi2_before: Chi2 before the iteration.
            chi2_after: Chi2 after it (positive).
        """
        if self.gain_threshold <= 0.0 or chi2_after <= 0.0:
            return False
        gain = (chi2_before - chi2_after) / chi2_after
        return 0.0 <= gain < self.gain_threshold
