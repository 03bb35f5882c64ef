"""Where tasks run: threads or processes of this machine (LocalExecutor), or Ray tasks
on a cluster (distributed.Cluster).

Feature extraction, matching and the hierarchical mapper cut their work into tasks:
plain functions of picklable arguments that return their results and never touch the
user's files. The caller writes each result as it arrives, whichever executor ran the
task, so a database is the same row for row however its work was run.
"""

from __future__ import annotations

import abc
import contextlib
import ctypes
import itertools
import math
import multiprocessing
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait
from concurrent.futures import Executor as FuturesExecutor
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

from tqdm import tqdm

# Tasks submitted ahead of the free workers: enough to keep them busy, few enough that
# the inputs of the tasks (images sent as bytes, features) do not all wait at once.
TASKS_IN_FLIGHT_PER_WORKER = 3


class ImageSource(Protocol):
    """Where a task finds its images: `local()` gives (image folder, mask folder or None)
    readable where the task runs, for the duration."""

    def local(self) -> contextlib.AbstractContextManager[tuple[str, str | None]]: ...


@dataclass(frozen=True)
class ImageFolder:
    """Where a task reads its images and masks: folders it sees as they are."""

    image_path: str
    mask_path: str | None

    @contextlib.contextmanager
    def local(self) -> Iterator[tuple[str, str | None]]:
        """(image folder, mask folder) readable by the task."""
        yield self.image_path, self.mask_path


class Executor(abc.ABC):
    """Runs task functions over argument tuples, a bounded number ahead of its workers."""

    num_workers: int  # tasks that run at once
    threads_per_task: int = 1  # threads each task may use

    def map(self, function: Callable, arguments: Iterable[tuple], total: int, desc: str,
            progress: bool = True) -> Iterator[Any]:
        """`function(*args)` per argument tuple, results in the order they complete. The
        arguments are made as tasks are submitted, at most TASKS_IN_FLIGHT_PER_WORKER per
        worker ahead."""
        arguments = iter(arguments)
        limit = TASKS_IN_FLIGHT_PER_WORKER * self.num_workers
        with self._submitting(function) as submit, \
                tqdm(total=total, desc=desc, unit="task", disable=not progress) as bar:
            pending: list[Any] = []
            while True:
                pending += [submit(args) for args in
                            itertools.islice(arguments, limit - len(pending))]
                if not pending:
                    return
                result, pending = self._first_result(pending)
                yield result
                bar.update(1)

    @abc.abstractmethod
    def _submitting(self, function: Callable
                    ) -> contextlib.AbstractContextManager[Callable[[tuple], Any]]:
        """submit(args) -> a pending task running `function(*args)`, for the duration."""

    @abc.abstractmethod
    def _first_result(self, pending: list) -> tuple[Any, list]:
        """The result of the first pending task to complete, and the others."""

    def put(self, value: Any) -> Any:
        """A handle to `value` for the tasks: a task given it as an argument of its own
        (not inside a container) receives `value`. Here, the value itself."""
        return value

    def image_sources(self, image_path: str, mask_path: str | None,
                      groups: Sequence[Sequence[str]]) -> Iterator[ImageSource]:
        """Per group of image names, where a task finds those images and their masks,
        made as it is asked for."""
        for _ in groups:
            yield ImageFolder(image_path, mask_path)


class LocalExecutor(Executor):
    """Tasks in `num_workers` threads of this process, or in as many processes ("spawn":
    pycolmap and Ceres threads do not survive a fork), which end with this one; each
    task may use `threads_per_task` threads."""

    def __init__(self, num_workers: int | None = None, processes: bool = False,
                 threads_per_task: int = 1) -> None:
        self.num_workers = max(1, num_workers or os.cpu_count() or 1)
        self.processes = processes and self.num_workers > 1
        self.threads_per_task = max(1, threads_per_task)

    @contextlib.contextmanager
    def _submitting(self, function: Callable) -> Iterator[Callable[[tuple], Future]]:
        pool: FuturesExecutor
        if self.processes:
            pool = ProcessPoolExecutor(self.num_workers,
                                       mp_context=multiprocessing.get_context("spawn"),
                                       initializer=start_worker,
                                       initargs=(os.getpid(), tempfile.gettempdir()))
        else:
            pool = ThreadPoolExecutor(self.num_workers)
        try:
            yield lambda args: pool.submit(function, *args)
        except BaseException:  # an error or Ctrl-C/SIGTERM: end the workers, not wait for them
            if isinstance(pool, ProcessPoolExecutor):
                # A task's arguments larger than a pipe's buffer leave the pool's feeder
                # thread blocked writing them to a worker that is now gone, and shutting
                # down would wait for that thread for ever (CPython's ProcessPoolExecutor).
                pool._call_queue.cancel_join_thread()
                for worker in multiprocessing.active_children():
                    worker.kill()
            raise
        finally:  # the tasks not started are not started
            pool.shutdown(wait=True, cancel_futures=True)

    def _first_result(self, pending: list[Future]) -> tuple[Any, list[Future]]:
        done, _ = wait(pending, return_when=FIRST_COMPLETED)
        first = next(future for future in pending if future in done)
        return first.result(), [future for future in pending if future is not first]


def start_worker(parent_pid: int, temporary_folder: str) -> None:
    """In a local pool's worker process: ended with its parent (`end_with_parent`), its
    temporary folder the parent's, and tqdm's lock a thread lock.

    Python finds its temporary folder by writing a file with a random name there and
    removing it; a worker ended with its killed parent in between left that file in
    TMPDIR, so the folder is given, not probed. tqdm makes a multiprocessing lock by
    default, even for a disabled bar: a semaphore that a worker killed with its pool (on
    Ctrl-C) leaves to Python's resource tracker, which then warns of it after the
    command's last line."""
    tempfile.tempdir = temporary_folder
    tqdm.set_lock(threading.RLock())
    end_with_parent(parent_pid)


def end_with_parent(parent_pid: int) -> None:
    """In a local pool's worker process: be ended (SIGTERM) when the process that started
    it ends, however it ends; a killed command leaves no worker computing on (Linux's
    PR_SET_PDEATHSIG; elsewhere nothing is done)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent ended before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)


def items_per_task(num_items: int, max_per_task: int, num_workers: int) -> int:
    """Items per task: at most `max_per_task`, and, with several workers, few enough
    that every worker gets two."""
    if num_workers == 1:
        return max_per_task
    return max(1, min(max_per_task, math.ceil(num_items / (2 * num_workers))))


def chunks(items: Sequence, size: int) -> list[Sequence]:
    """`items` cut into consecutive slices of `size` (the last one shorter)."""
    return [items[start:start + size] for start in range(0, len(items), size)]
