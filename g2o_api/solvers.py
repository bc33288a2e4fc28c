"""g2o's algorithm, block-solver and linear-solver classes, robust kernels and ``Flag``, mapped to
graphopt's configurations.

g2o composes ``OptimizationAlgorithmLevenberg(BlockSolverSE3(LinearSolverEigenSE3()))``; the
composition only selects graphopt's algorithm config and linear solver:

=====================================  =================================================
g2o                                    graphopt
=====================================  =================================================
``OptimizationAlgorithmLevenberg``     ``LevenbergConfig()`` (g2o's τ = 1e-5 and λ rule)
``OptimizationAlgorithmGaussNewton``   ``GaussNewtonConfig()``
``OptimizationAlgorithmDogleg``        ``DoglegConfig()``
``LinearSolverDense*``                 ``solver="dense"``
``LinearSolverEigen*`` / ``Cholmod*``  ``solver="auto"`` (dense Cholesky for small dense
/ ``CSparse*``                         reduced systems, CHOLMOD otherwise)
``LinearSolverPCG*``                   ``solver="pcg"``
``BlockSolverSE3/SE2/Sim3/X``          the Schur complement on marginalised vertices
=====================================  =================================================
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from graphopt.algorithms import DoglegConfig, GaussNewtonConfig, LevenbergConfig
from graphopt.robust_kernel import KERNELS, RobustKernel

__all__ = ["ALGORITHMS", "BLOCK_SOLVERS", "Flag", "IoFormat", "KERNEL_CLASSES", "LINEAR_SOLVERS",
           "OptimizationAlgorithm", "RobustKernelBase", "graphopt_kernel"]


class LinearSolver:
    """A g2o linear solver: only its name matters (``solver`` of graphopt)."""

    solver = "auto"

    def __init__(self, *args: Any) -> None:
        self._block_ordering = True

    def set_block_ordering(self, flag: bool) -> None:
        """Accepted for compatibility (graphopt orders the blocks itself).

        Args:
            flag: Ignored.
        """
        self._block_ordering = bool(flag)

    def set_write_debug(self, flag: bool) -> None:
        """Accepted for compatibility.

        Args:
            flag: Ignored.
        """

    def write_debug(self) -> bool:
        """Always ``False``."""
        return False


class BlockSolver:
    """A g2o block solver wrapping a linear solver.

    Args:
        linear_solver: A ``LinearSolver*`` object (default: the Eigen solver).
    """

    def __init__(self, linear_solver: LinearSolver | None = None) -> None:
        self.linear_solver = linear_solver if linear_solver is not None else LinearSolver()

    def set_write_debug(self, flag: bool) -> None:
        """Accepted for compatibility.

        Args:
            flag: Ignored.
        """

    def write_debug(self) -> bool:
        """Always ``False``."""
        return False


def _subclasses(base: type, names_solvers: dict[str, str], suffixes: tuple[str, ...]
                ) -> dict[str, type]:
    out: dict[str, type] = {}
    for family, solver in names_solvers.items():
        for suffix in suffixes:
            name = f"{base.__name__}{family}{suffix}"
            out[name] = type(name, (base,), {"solver": solver, "__module__": "graphopt.g2o",
                                             "__doc__": f"g2o's {name}: graphopt's "
                                                        f"solver={solver!r}."})
    return out


_SUFFIXES = ("SE2", "SE3", "Sim3", "X", "7_3", "6_3", "3_2")
#: ``LinearSolverDenseSE3`` … (both bindings' names; Cholmod and CSparse from the old ones).
LINEAR_SOLVERS = _subclasses(LinearSolver, {"Dense": "dense", "Eigen": "auto", "Cholmod": "auto",
                                            "CSparse": "auto", "PCG": "pcg"}, _SUFFIXES)
BLOCK_SOLVERS: dict[str, type] = {
    f"BlockSolver{s}": type(f"BlockSolver{s}", (BlockSolver,), {"__module__": "graphopt.g2o"})
    for s in _SUFFIXES}


class OptimizationAlgorithm:
    """A g2o optimisation algorithm over a block solver.

    Args:
        block_solver: A ``BlockSolver*`` object.
    """

    config: Any = LevenbergConfig()

    def __init__(self, block_solver: BlockSolver | None = None) -> None:
        self.block_solver = block_solver if block_solver is not None else BlockSolver()
        self.config = type(self).config

    @property
    def solver(self) -> str:
        """graphopt's linear solver name."""
        return self.block_solver.linear_solver.solver


class OptimizationAlgorithmLevenberg(OptimizationAlgorithm):
    """g2o's Levenberg–Marquardt (graphopt's ``LevenbergConfig``, g2o's λ rule and τ)."""

    config = LevenbergConfig()

    def set_user_lambda_init(self, lam: float) -> None:
        """Start from ``λ = lam`` instead of ``τ · max diag(H)``.

        Args:
            lam: The initial λ (positive).
        """
        self.config = replace(self.config, initial_lambda=float(lam))

    def user_lambda_init(self) -> float:
        """The user's initial λ, or 0 when the τ rule is used."""
        return self.config.initial_lambda or 0.0

    def set_max_trials_after_failure(self, n: int) -> None:
        """Damped solves per iteration.

        Args:
            n: At least 1.
        """
        self.config = replace(self.config, max_trials=int(n))


class OptimizationAlgorithmGaussNewton(OptimizationAlgorithm):
    """g2o's Gauss–Newton."""

    config = GaussNewtonConfig()


class OptimizationAlgorithmDogleg(OptimizationAlgorithm):
    """g2o's Powell's Dogleg."""

    config = DoglegConfig()


ALGORITHMS = {c.__name__: c for c in (OptimizationAlgorithmLevenberg,
                                      OptimizationAlgorithmGaussNewton,
                                      OptimizationAlgorithmDogleg)}


class IoFormat:
    """g2o's file formats for ``load``/``save`` (only ``G2O`` is read and written)."""

    G2O = 0
    BINARY = 1
    JSON = 2


class Flag:
    """The old bindings' ``g2o.Flag()``: a mutable boolean (ORB-SLAM passes one as the
    ``abortFlag``: ``optimizer.set_force_stop_flag(flag)``).

    Args:
        value: Initial value.
    """

    __slots__ = ("value",)

    def __init__(self, value: bool = False) -> None:
        self.value = bool(value)

    def __bool__(self) -> bool:
        return self.value


class RobustKernelBase:
    """A g2o robust kernel record (``delta()``/``set_delta``); edges with equal kernels (same
    class and δ) share one graphopt kernel.

    Args:
        delta: The kernel width (g2o's default 1).
    """

    __slots__ = ("_delta",)
    core: type[RobustKernel] = RobustKernel

    def __init__(self, delta: float = 1.0) -> None:
        self._delta = float(delta)

    def delta(self) -> float:
        """The kernel width."""
        return self._delta

    def set_delta(self, delta: float) -> None:
        """Set the kernel width.

        Args:
            delta: Positive.
        """
        self._delta = float(delta)

    def robustify(self, e2: float) -> list[float]:
        """``[ρ, ρ', ρ'']`` at a squared error (g2o's ``robustify``).

        Args:
            e2: ``eᵀΩe``.
        """
        import numpy as np

        return [float(r[0]) for r in self.core(self._delta).robustify(np.array([float(e2)]))]


def _kernel_class(name: str, core: type[RobustKernel]) -> type[RobustKernelBase]:
    return type(name, (RobustKernelBase,), {"__slots__": (), "core": core,
                                            "__module__": "graphopt.g2o",
                                            "__doc__": f"g2o's {name}."})


KERNEL_CLASSES: dict[str, type[RobustKernelBase]] = {
    c.__name__: _kernel_class(c.__name__, c) for c in KERNELS.values()}


def graphopt_kernel(kernel: Any) -> RobustKernel | None:
    """graphopt's kernel for a g2o kernel record (or a graphopt kernel, or ``None``).

    Args:
        kernel: The edge's kernel.
    """
    if kernel is None or isinstance(kernel, RobustKernel):
        return kernel
    if isinstance(kernel, RobustKernelBase):
        return kernel.core(kernel._delta)
    raise TypeError(f"set_robust_kernel: expected a robust kernel or None, got "
                    f"{type(kernel).__name__}")


def iteration_line(core: Any, info: Any, cum_time: float) -> str:
    """g2o's iteration line; LM's ``lambda`` is the value after the iteration's update, as g2o
    prints it.

    Args:
        core: graphopt's optimizer (after the iteration).
        info: The iteration's record.
        cum_time: Seconds of the ``optimize`` call so far.
    """
    p = core.problem
    schur = 1 if p is not None and p.system.schur else 0
    alg = core.algorithm
    fields = (f"\t lambda= {alg.lam:f}\t levenbergIter= {info.trials}"
              if isinstance(alg.config, LevenbergConfig) else alg.line_fields(info))
    return (f"iteration= {info.iteration}\t chi2= {info.chi2:f}\t time= {info.seconds:g}"
            f"\t cumTime= {cum_time:g}\t edges= {core.active_edge_count()}"
            f"\t schur= {schur}{fields}")
