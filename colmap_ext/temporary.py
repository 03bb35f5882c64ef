"""Temporary folders that a later run can tell from live ones once their run is killed.

A run removes its temporary folders however it ends, except when it is killed outright
(`kill -9`, a power cut): then they stay. Each folder made here holds a lock file locked
for as long as its run lives (the kernel releases the lock when the process ends, however
it ends), and each new folder first removes the leftovers of its kind beside it, those
whose lock is free: never a folder in use, whichever process or machine uses it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import tempfile
from pathlib import Path

# The lock file in each folder, and its name while it is made (never taken for a leftover).
OWNER_LOCK = ".owner.lock"
_PENDING_LOCK = ".owner.lock.pending"


class OwnedTemporaryDirectory(tempfile.TemporaryDirectory):
    """tempfile.TemporaryDirectory(prefix, dir) that holds its lock file until `cleanup()`
    (or the end of its process), after removing the unlocked leftovers named `prefix*` in
    `dir` (default: TMPDIR)."""

    def __init__(self, prefix: str, dir: str | os.PathLike | None = None) -> None:
        remove_leftovers(Path(dir or tempfile.gettempdir()), prefix)
        super().__init__(prefix=prefix, dir=dir, ignore_cleanup_errors=True)
        self._lock = lock_folder(Path(self.name))

    def cleanup(self) -> None:
        super().cleanup()
        with contextlib.suppress(OSError):
            os.close(self._lock)


def lock_folder(folder: Path) -> int:
    """Make and lock `folder`'s owner lock; returns its file descriptor, which holds the
    lock until it is closed. The file is locked before it gets the name a sweep looks
    for, so no sweep finds it unlocked."""
    fd = os.open(folder / _PENDING_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.rename(folder / _PENDING_LOCK, folder / OWNER_LOCK)
    return fd


def remove_leftovers(folder: Path, prefix: str) -> None:
    """Remove the folders named `prefix*` in `folder` whose owner lock is free: left by a
    run that was killed. Folders without an owner lock are left alone."""
    try:
        candidates = [entry for entry in folder.iterdir() if entry.name.startswith(prefix)]
    except OSError:
        return
    for candidate in candidates:
        try:
            fd = os.open(candidate / OWNER_LOCK, os.O_RDONLY)
        except OSError:  # not a folder of ours, or one still being made
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # its run is alive
            os.close(fd)
            continue
        try:
            shutil.rmtree(candidate, ignore_errors=True)
        finally:
            os.close(fd)
