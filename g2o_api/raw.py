"""Float vectors as the records keep them: ``set_measurement`` and a vector vertex's
``set_estimate`` store a float64 array's bytes (``tobytes``: a third of a copy's cost, and not an
object the cyclic collector tracks); filing joins a batch's bytes into one array in one step."""

from __future__ import annotations

from math import prod
from typing import Any

import numpy as np

__all__ = ["joined", "unbytes"]


def joined(raws: list[Any], shape: tuple[int, ...]) -> np.ndarray | None:
    """``(n, *shape)`` float vectors from their bytes (what ``set_estimate`` and
    ``set_measurement`` keep of a float array) in one join, or ``None`` unless every raw value
    is bytes of the right length.

    Args:
        raws: The records' raw values.
        shape: One value's shape.
    """
    if not raws or type(raws[0]) is not bytes:
        return None
    try:  # C loops; len() of None or join of a list raise TypeError
        if set(map(len, raws)) != {8 * prod(shape)}:  # (math.prod: np.prod costs 3 µs)
            return None
        buf = b"".join(raws)
    except TypeError:
        return None
    return np.frombuffer(buf).reshape(len(raws), *shape).copy()


def unbytes(raws: list[Any]) -> list[Any]:
    """The raw values with bytes (see :func:`joined`) back as float arrays.

    Args:
        raws: The records' raw values.
    """
    return [np.frombuffer(r) if type(r) is bytes else r for r in raws]
