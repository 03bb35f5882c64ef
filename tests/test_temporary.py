"""Temporary folders: a new one removes the leftovers of killed runs of its kind, never a
live run's, nor a folder that is not ours (issue 45, defect 17; the end-to-end cases, a run
killed and run again, are in test_bad_input.py)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from colmap_ext.executors import LocalExecutor
from colmap_ext.temporary import OWNER_LOCK, OwnedTemporaryDirectory

# Another process holding a temporary folder until its stdin closes.
HOLDER = """
import sys
from colmap_ext.temporary import OwnedTemporaryDirectory
folder = OwnedTemporaryDirectory("colmap-ext-x-", sys.argv[1])
print(folder.name, flush=True)
sys.stdin.read()
"""


def test_only_the_leftovers_of_ended_runs_are_removed(tmp_path: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        live = Path(holder.stdout.readline().strip())
        ended = Path(tempfile.mkdtemp(prefix="colmap-ext-x-", dir=tmp_path))
        (ended / OWNER_LOCK).touch()  # its run is gone: no one holds the lock
        (ended / "sift.db").write_bytes(b"half written")
        not_ours = tmp_path / "colmap-ext-x-notes"  # no owner lock
        not_ours.mkdir()
        other_kind = Path(tempfile.mkdtemp(prefix="colmap-ext-y-", dir=tmp_path))
        (other_kind / OWNER_LOCK).touch()

        with OwnedTemporaryDirectory("colmap-ext-x-", tmp_path) as new:
            assert {path.name for path in tmp_path.iterdir()} == \
                {live.name, not_ours.name, other_kind.name, Path(new).name}
        assert live.is_dir() and not Path(new).exists()
    finally:
        holder.communicate("")
    assert not live.exists(), "the holder did not clean up after itself"


def test_worker_processes_take_the_parents_temporary_folder(tmp_path: Path, monkeypatch) -> None:
    """A worker process is given its parent's temporary folder rather than probing TMPDIR
    (Python writes a randomly named file there to probe it, which a worker ended with its
    killed parent left behind)."""
    given = tmp_path / "given"
    given.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(given))
    workers = LocalExecutor(2, processes=True)
    found = list(workers.map(tempfile.gettempdir, [()] * 4, total=4, desc="", progress=False))
    assert found == [str(given)] * 4
