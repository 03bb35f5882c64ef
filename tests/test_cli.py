"""The `colmap-ext` entry point's process settings."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

# A child with eight threads that allocate at once, then the number of malloc arenas
# glibc reports (malloc_info's <heap> elements).
COUNT_ARENAS = """
import ctypes, re, sys, threading
from colmap_ext.memory import limit_malloc_arenas
if sys.argv[1] == "limit":
    limit_malloc_arenas()
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.fopen.restype = ctypes.c_void_p
barrier = threading.Barrier(8)
def allocate():
    barrier.wait()
    for _ in range(200):
        libc.free(ctypes.c_void_p(libc.malloc(1 << 16)))
threads = [threading.Thread(target=allocate) for _ in range(8)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
report = libc.fopen(sys.argv[2].encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(report))
libc.fclose(ctypes.c_void_p(report))
print(len(re.findall("<heap nr=", open(sys.argv[2]).read())))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc arenas")
def test_entry_point_limits_malloc_arenas(tmp_path: Path) -> None:
    """Threads that allocate get malloc arenas of their own, whose freed memory stays
    resident; the command keeps them to two, unless MALLOC_ARENA_MAX says otherwise."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}

    def arenas(mode: str, **extra: str) -> int:
        result = subprocess.run([sys.executable, "-c", COUNT_ARENAS, mode,
                                 str(tmp_path / f"{mode}.xml")],
                                env={**env, **extra}, capture_output=True, text=True,
                                check=True)
        return int(result.stdout)

    assert arenas("limit") == 2
    assert arenas("unlimited") > 2
    assert arenas("limit", MALLOC_ARENA_MAX="4") > 2
