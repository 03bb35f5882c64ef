"""Ray: the executor of feature extraction, matching and cluster mapping on a cluster.

`--ray_address` names the cluster: `auto` (the one `ray start` runs on this machine or
RAY_ADDRESS names), `local` (one started inside this process) or `HOST:PORT` (its GCS).
Tasks (features.extract_chunk, matching.match_block, ...) are plain functions of their
arguments; they return arrays and never touch the user's files: the driver alone writes
the database, in a staging file beside the target that replaces it only when complete.
A task whose worker dies is run again by Ray (`MAX_RETRIES`), and its result is written
once, when it arrives.

Images reach the workers by path when every node sees the driver's files (same size and
modification time: a shared file system), and as bytes, with their masks, otherwise.

Ray is an optional dependency (`pip install colmap-ext[ray]`), imported only here and
only when an address is given.
"""

from __future__ import annotations

import contextlib
import os
import socket
import sqlite3
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from colmap_ext.errors import UserError
from colmap_ext.executors import Executor, ImageFolder, ImageSource
from colmap_ext.features import FeatureOptions, FeatureSummary, extract_features
from colmap_ext.matching import MatchingOptions, MatchingSummary, match_features
from colmap_ext.temporary import OwnedTemporaryDirectory
from colmap_ext.timing import StageTimer

# Ray runs a task again this many times when its worker process dies (Ray's default is 3).
MAX_RETRIES = 3
# Seconds to wait for the cluster's GCS port before calling it unreachable.
CONNECT_TIMEOUT_S = 5.0


def ray_installed() -> bool:
    """Whether Ray can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("ray") is not None


def check_address(address: str) -> None:
    """A one-line error for an address that cannot work, before Ray is started: a
    malformed HOST:PORT, or a port nothing listens on."""
    if address in ("auto", "local"):
        return
    host, _, port = address.rpartition(":")
    if address.startswith("ray://"):
        raise UserError(f"--ray_address {address}: Ray Client addresses (ray://) are not "
                        "supported; give the cluster's HOST:PORT, auto or local")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"--ray_address must be auto, local or HOST:PORT, got {address!r}")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc) or type(exc).__name__
        raise UserError(f"cannot reach the Ray cluster at {address}: {reason}") from None


class Cluster(Executor):
    """A connected Ray cluster as an executor: a task per argument tuple holding one CPU,
    values in the object store, and the images sent to nodes that do not see them."""

    def __init__(self, ray: Any, images_by_path: bool | None = None) -> None:
        self.ray = ray
        # Whether tasks read the images by path; None: decided at the first images
        # (shared_file_system).
        self.images_by_path = images_by_path

    @property
    def num_cpus(self) -> int:
        return max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    @property
    def num_workers(self) -> int:
        return self.num_cpus

    def node_ids(self) -> list[str]:
        return [node["NodeID"] for node in self.ray.nodes() if node["Alive"]]

    @contextlib.contextmanager
    def _submitting(self, function: Callable) -> Iterator[Callable[[tuple], Any]]:
        remote = self.ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(function)
        yield lambda args: remote.remote(*args)

    def _first_result(self, pending: list) -> tuple[Any, list]:
        done, rest = self.ray.wait(pending, num_returns=1)
        return self.get(done[0]), rest

    def get(self, reference: Any) -> Any:
        """ray.get, with a task's UserError raised as itself, and a task lost to the
        cluster (its worker or node died more than MAX_RETRIES times) as one line."""
        exceptions = self.ray.exceptions
        try:
            return self.ray.get(reference)
        except exceptions.RayTaskError as exc:
            if isinstance(exc.cause, UserError):
                raise UserError(str(exc.cause)) from None
            raise
        except (exceptions.WorkerCrashedError, exceptions.NodeDiedError,
                exceptions.ObjectLostError) as exc:
            first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise UserError(f"the Ray cluster lost a task after {MAX_RETRIES} retries: "
                            f"{type(exc).__name__}: {first_line}") from None

    def put(self, value: Any) -> Any:
        """An object reference (Ray gives a task the value of a reference it takes as an
        argument of its own)."""
        return self.ray.put(value)

    def on_every_node(self, function: Callable, *args: Any) -> list[Any]:
        """`function(*args)` once on each alive node."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        remote = self.ray.remote(num_cpus=0)(function)
        return self.get([remote.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
            node_id, soft=False)).remote(*args) for node_id in self.node_ids()])

    def image_sources(self, image_path: str, mask_path: str | None,
                      groups: Sequence[Sequence[str]]) -> Iterator[ImageSource]:
        """Per group of image names: the folders, or the files' bytes, made as they are
        asked for."""
        root = str(Path(image_path).resolve())
        masks = None if mask_path is None else str(Path(mask_path).resolve())
        if self.images_by_path is None:
            self.images_by_path = shared_file_system(self, root,
                                                     [name for names in groups for name in names])
        for names in groups:
            if self.images_by_path:
                yield ImageFolder(root, masks)
                continue
            files = {f"images/{name}": Path(root, name).read_bytes() for name in names}
            if masks is not None:
                files.update({f"masks/{name}.png": Path(masks, f"{name}.png").read_bytes()
                              for name in names})
            yield ImageBytes(files, masks is not None)

    def describe(self) -> dict:
        """What the cluster was: nodes, CPUs, and how the images went."""
        return {"num_nodes": len(self.node_ids()), "num_cpus": self.num_cpus,
                "images": "by path" if self.images_by_path else "as bytes"}


@contextlib.contextmanager
def connect(address: str, images_by_path: bool | None = None) -> Iterator[Cluster]:
    """Ray connected to `address` (auto, local or HOST:PORT) for the duration;
    `images_by_path`: as Cluster's."""
    if not ray_installed():
        raise UserError("--ray_address needs Ray: pip install 'colmap-ext[ray]'")
    check_address(address)
    import logging

    import ray

    try:
        ray.init(address=None if address == "local" else address, logging_level=logging.WARNING,
                 log_to_driver=False, include_dashboard=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UserError(f"cannot connect to the Ray cluster at {address}: {first_line}") from None
    try:
        yield Cluster(ray, images_by_path)
    finally:
        ray.shutdown()


@contextlib.contextmanager
def optional_cluster(address: str | None) -> Iterator[Cluster | None]:
    """connect(address), or None (work stays in this process) when no address is given."""
    if address is None:
        yield None
        return
    with connect(address) as cluster:
        yield cluster


# ------------------------------------------------------------------ images to workers


@dataclass(frozen=True)
class ImageBytes:
    """A task's images (and masks) as files: path -> bytes, images under "images/" and
    masks under "masks/", unpacked into a scratch folder on the task's node."""

    files: dict[str, bytes]
    has_masks: bool

    @contextlib.contextmanager
    def local(self) -> Iterator[tuple[str, str | None]]:
        """(image folder, mask folder) readable on this node."""
        with OwnedTemporaryDirectory("colmap-ext-images-") as scratch:
            for name, data in self.files.items():
                path = Path(scratch, name)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            yield str(Path(scratch, "images")), \
                str(Path(scratch, "masks")) if self.has_masks else None


def fingerprints(root: str, names: Sequence[str]) -> list[tuple[int, int] | None]:
    """(size, modification time in ns) of each file under `root`; None if missing."""
    result = []
    for name in names:
        try:
            stat = os.stat(Path(root, name))
            result.append((stat.st_size, stat.st_mtime_ns))
        except OSError:
            result.append(None)
    return result


def shared_file_system(cluster: Cluster, root: str, names: Sequence[str]) -> bool:
    """Whether every node sees the driver's files under `root` (a sample of them)."""
    sample = list(names[:: max(1, len(names) // 8)])
    expected = fingerprints(root, sample)
    return all(seen == expected for seen in cluster.on_every_node(fingerprints, root, sample))


# ------------------------------------------------------------------ the database


@contextlib.contextmanager
def staged_database(database_path: Path) -> Iterator[Path]:
    """A new database file beside `database_path` to write into; it replaces
    `database_path` when the block completes, and is removed if it fails."""
    staging = database_path.with_name(f".colmap-ext-{os.getpid()}-{database_path.name}")
    for suffix in ("", "-wal", "-shm", "-journal"):
        Path(f"{staging}{suffix}").unlink(missing_ok=True)
    try:
        yield staging
        with contextlib.closing(sqlite3.connect(staging)) as connection:
            connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        os.replace(staging, database_path)
    finally:
        for suffix in ("", "-wal", "-shm", "-journal"):
            Path(f"{staging}{suffix}").unlink(missing_ok=True)


def extract_and_match(cluster: Cluster, database_path: Path, image_path: str | os.PathLike,
                      image_names: Sequence[str], features: FeatureOptions,
                      matching: MatchingOptions, timer: StageTimer
                      ) -> tuple[FeatureSummary, MatchingSummary, dict]:
    """Features and matching on the cluster into a staging database that replaces
    `database_path` once both are done; times the features in `timer` and returns both
    summaries and what the cluster was (Cluster.describe)."""
    with staged_database(database_path) as staging:
        with timer("features"):
            feature_summary = extract_features(staging, image_path, features,
                                               image_names=image_names, executor=cluster)
        matching_summary = match_features(staging, matching, executor=cluster)
    return feature_summary, matching_summary, cluster.describe()
