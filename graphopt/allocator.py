"""glibc's malloc, held at the steady state its own heuristic reaches, once per process.

An iteration allocates and frees the same arrays every time (Jacobians, blocks, products:
0.1–30 MB). glibc serves a block from ``mmap`` when it is larger than its *mmap threshold* and
returns the free top of the heap to the system beyond its *trim threshold*; both start small
(128 KB, 256 KB) and grow only when an mmapped block is freed. Until they have grown, and
whenever a freed top is trimmed, the next iteration's arrays are fresh pages again, zeroed by
the kernel one page fault at a time: a 5,000-observation local BA took 170–240 faults an
iteration (0.2–0.5 ms of 2.2–2.8), the 25,000-observation one about 1,000.

:func:`tune` sets both thresholds to where glibc's dynamic rule ends for a process that has
freed a 32 MB block (``M_MMAP_THRESHOLD`` 32 MB, its maximum; ``M_TRIM_THRESHOLD`` twice that),
so the faults are gone from the first iteration on (measured: 0 an iteration on both local BA
sizes, 2.2–2.8 -> 2.1–2.2 ms and 9.9–10.3 -> 8.7–9.0 ms CPU). Arrays above 32 MB (large
problems) are mmapped and returned at once, as they were; at most 64 MB of freed heap stays
with the process. Only on glibc; ``GRAPHOPT_MALLOC_TUNE=0`` leaves the allocator alone.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: glibc's largest dynamic mmap threshold on 64-bit systems (``DEFAULT_MMAP_THRESHOLD_MAX``).
MMAP_THRESHOLD = 32 * 2**20
#: The trim threshold glibc sets with it (twice the mmap threshold).
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD

#: The outcome of the first call (``None``: not tried yet); later calls return it.
_done: bool | None = None


def tune() -> bool:
    """Set glibc's mmap and trim thresholds (see the module docstring), once per process.

    Returns:
        Whether the thresholds are set (``False`` off glibc, or when disabled by
        ``GRAPHOPT_MALLOC_TUNE=0``).
    """
    global _done
    if _done is not None:  # a failure is remembered too: a problem is built at every edit
        return _done
    _done = False
    if os.environ.get("GRAPHOPT_MALLOC_TUNE", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        # The process's own symbols (libc's among them): ctypes.util.find_library("c") would
        # run ldconfig in a subprocess, 3.5 ms in the first problem's set-up.
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # Order matters little: setting either one fixes both (glibc stops adjusting them).
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _done
