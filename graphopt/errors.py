"""The exceptions graphopt raises for bad input and for numerical failure."""

from __future__ import annotations

import numpy as np


class GraphError(ValueError):
    """Invalid graph input (ids, shapes, values); the message names the id and type."""


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """A block or the reduced system is not positive definite."""
