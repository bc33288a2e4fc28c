"""Arrays filled by chunks (one per ``add_edges`` call or flush): joined lazily, and one
value for a whole chunk (a kernel slot, a level) kept as a broadcast — no bytes per edge —
until it is set per edge."""

from __future__ import annotations

import numpy as np

__all__ = ["const_ints", "join_chunks", "join_values", "per_edge"]


def join_chunks(chunks: list[np.ndarray]) -> np.ndarray:
    """The chunks as one array: the only chunk itself, or their concatenation.

    Args:
        chunks: Arrays with the same trailing shape.
    """
    return chunks[0] if len(chunks) == 1 else np.concatenate(chunks)


def const_ints(value: int, n: int) -> np.ndarray:
    """``(n,)`` int64 read-only, every entry ``value``: one number's bytes (stride 0), what
    ``np.broadcast_to`` gives at half its cost.

    Args:
        value: The value.
        n: The length.
    """
    out = np.ndarray((n,), np.int64, np.full(1, value, np.int64), 0, (0,))
    out.flags.writeable = False
    return out


def per_edge(value: int | np.ndarray, n: int) -> np.ndarray:
    """``(n,)`` int64 values: a broadcast of one value (no bytes per edge), or a copy.

    Args:
        value: One value, or ``(n,)`` values.
        n: The number of edges.
    """
    if type(value) is int:
        return const_ints(value, n)
    arr = np.asarray(value, dtype=np.int64)
    return const_ints(int(arr), n) if arr.ndim == 0 else arr.copy()


def join_values(chunks: list[np.ndarray], n: int) -> np.ndarray:
    """Per-edge value chunks as one array: a broadcast while all are the same broadcast.

    Args:
        chunks: ``(n_i,)`` int64 values per chunk.
        n: Their total length.
    """
    if len(chunks) == 1:  # (a broadcast stays one)
        return chunks[0]
    live = [c for c in chunks if len(c)]
    if live and all(c.strides == (0,) for c in live) and len({int(c[0]) for c in live}) == 1:
        return const_ints(int(live[0][0]), n)
    return join_chunks(chunks) if chunks else np.zeros(0, dtype=np.int64)
