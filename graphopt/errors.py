"""The exceptions graphopt raises for bad input and for numerical failure."""

from __future__ import annotations

import numpy as np


class GraphError(ValueError):
    """Invalid graph input (ids, shapes, values); the message names the id and type."""


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """A block or the reduced system is not positive definite."""


class SingularSystemError(NotPositiveDefiniteError):
    """The system is positive semi-definite but rank deficient (a gauge freedom, an unobserved
    vertex): a pivot of the factorisation is negligible against the matrix's scale.

    A subclass of :class:`NotPositiveDefiniteError`, so LM and Dogleg retry it with more damping
    as any failed factorisation; Gauss–Newton stops with the stop reason ``singular``.
    """
