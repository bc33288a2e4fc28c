"""TEMPORARY shim until the graphopt/linear package lands (replaced at merge)."""

from dataclasses import dataclass

from graphopt.linear_system import Assembly, LinearSystem


@dataclass(frozen=True)
class SchurConfig:
    strategy: str = "auto"


__all__ = ["Assembly", "LinearSystem", "SchurConfig"]
