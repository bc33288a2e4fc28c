"""The normal equations in three tiers: the block *structure* (built once per graph
structure), the *assembly* (once per linearisation) and the *Schur reduction* (once per λ),
behind the :class:`LinearSystem` facade. See ``docs/architecture.md``."""

from graphopt.linear.assembly import Assembly
from graphopt.linear.schur_config import SchurConfig, SchurCostModel
from graphopt.linear.system import LinearSystem

__all__ = ["Assembly", "LinearSystem", "SchurConfig", "SchurCostModel"]
