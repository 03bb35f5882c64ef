"""glibc's allocator, told to hold less memory resident: the peak memory a user sees is
the process's resident set, and glibc keeps what it freed (BENCHMARKS.md). Elsewhere
(another C library) these do nothing."""

from __future__ import annotations

import ctypes
import os

# glibc's mallopt parameter for the most malloc arenas.
M_ARENA_MAX = -8


def limit_malloc_arenas(count: int = 2) -> None:
    """At most `count` malloc arenas, as MALLOC_ARENA_MAX would (unless the user set it).
    glibc gives threads that allocate arenas of their own, up to eight per core, and
    memory freed in one stays resident: with Ceres's and the descriptor search's
    threads that is tens of MiB of peak memory. Call it before any thread starts."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return
    try:
        ctypes.CDLL(None).mallopt(M_ARENA_MAX, count)
    except (OSError, AttributeError):
        pass


def return_freed_memory() -> None:
    """Give the memory freed so far back to the system (glibc's malloc_trim), after a
    step that freed much of it and before one that will need much."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass
