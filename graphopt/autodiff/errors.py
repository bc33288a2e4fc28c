"""The error of an operation that jets cannot differentiate."""

from __future__ import annotations

from graphopt.errors import GraphError

__all__ = ["JetError"]


class JetError(GraphError):
    """A NumPy operation that graphopt's jets cannot differentiate (named in the message)."""

    def __init__(self, function: str, why: str = "") -> None:
        self.function = function
        super().__init__(f"automatic differentiation does not support {function}"
                         + (f": {why}" if why else ""))
