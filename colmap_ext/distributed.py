"""Ray: feature extraction, matching and cluster mapping as tasks on a cluster.

`--ray_address` names the cluster: `auto` (the one `ray start` runs on this machine or
RAY_ADDRESS names), `local` (one started inside this process) or `HOST:PORT` (its GCS).
Tasks are plain functions of their arguments; they return arrays and never touch the
user's files: the driver alone writes the database, in a staging file beside the
target that replaces it only when complete. A task whose worker dies is run again by
Ray (`MAX_RETRIES`), and its result is written once, when it arrives.

Images reach the workers by path when every node sees the driver's files (same size and
modification time: a shared file system), and as bytes, with their masks, otherwise.

Ray is an optional dependency (`pip install colmap-ext[ray]`), imported only here and
only when an address is given.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import math
import os
import signal
import socket
import sqlite3
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_ext import features as single_features
from colmap_ext import matching as single_matching
from colmap_ext.errors import UserError
from colmap_ext.features import FeatureSummary, quiet_colmap_logs
from colmap_ext.matching import MatchingSummary

# Ray runs a task again this many times when its worker process dies (Ray's default is 3).
MAX_RETRIES = 3
# Seconds to wait for the cluster's GCS port before calling it unreachable.
CONNECT_TIMEOUT_S = 5.0
# Work per task: images per extraction task and pairs per matching task, at most; fewer
# when that leaves some CPUs of the cluster idle.
MAX_IMAGES_PER_TASK = 16
MAX_PAIRS_PER_TASK = 500
# Tasks submitted ahead of the free CPUs: enough to keep them busy, few enough that
# images sent as bytes do not all sit in the object store at once.
TASKS_IN_FLIGHT_PER_CPU = 3
# Pairs are grouped by blocks of this many images (in name order) on both sides, so a
# task needs the features of at most two blocks.
PAIR_BLOCK_IMAGES = 32

Features = tuple[np.ndarray, np.ndarray]  # keypoints (n, 6) float32, descriptors (n, 128) uint8


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


class Cluster:
    """A connected Ray cluster: runs task functions over argument lists."""

    def __init__(self, ray: Any) -> None:
        self.ray = ray

    @property
    def num_cpus(self) -> int:
        return max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def node_ids(self) -> list[str]:
        return [node["NodeID"] for node in self.ray.nodes() if node["Alive"]]

    def run(self, function: Callable, arguments: Iterable[tuple], total: int, desc: str,
            progress: bool = True, num_cpus: float = 1) -> Iterator[Any]:
        """Run `function(*args)` as a Ray task per argument tuple, at most
        TASKS_IN_FLIGHT_PER_CPU per CPU at a time (the arguments are made as they are
        needed); yield results as they arrive. A UserError raised in a task is raised
        here as itself."""
        remote = self.ray.remote(num_cpus=num_cpus, max_retries=MAX_RETRIES)(function)
        arguments = iter(arguments)
        limit = TASKS_IN_FLIGHT_PER_CPU * self.num_cpus
        pending: list[Any] = []
        with tqdm(total=total, desc=desc, unit="task", disable=not progress) as bar:
            while True:
                for args in itertools.islice(arguments, limit - len(pending)):
                    pending.append(remote.remote(*args))
                if not pending:
                    return
                done, pending = self.ray.wait(pending, num_returns=1)
                yield self.get(done[0])
                bar.update(1)

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
        return self.ray.put(value)

    def on_every_node(self, function: Callable, *args: Any) -> list[Any]:
        """`function(*args)` once on each alive node."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        remote = self.ray.remote(num_cpus=0)(function)
        return self.get([remote.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
            node_id, soft=False)).remote(*args) for node_id in self.node_ids()])


@contextlib.contextmanager
def connect(address: str) -> Iterator[Cluster]:
    """Ray connected to `address` (auto, local or HOST:PORT) for the duration."""
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
        yield Cluster(ray)
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


def tasks_for(num_items: int, max_per_task: int, num_cpus: int) -> int:
    """Items per task: at most `max_per_task`, and few enough that every CPU gets two."""
    return max(1, min(max_per_task, math.ceil(num_items / (2 * num_cpus))))


def chunks(items: Sequence, size: int) -> list[Sequence]:
    return [items[start:start + size] for start in range(0, len(items), size)]


# ------------------------------------------------------------------ images to workers


@dataclass(frozen=True)
class ImageSource:
    """Where a task finds its images: `root` on a shared file system, or `files` (image
    name -> bytes, mask files under "masks/") unpacked into a scratch folder."""

    root: str
    mask_root: str | None
    files: dict[str, bytes] | None = None

    @contextlib.contextmanager
    def local(self) -> Iterator[tuple[str, str | None]]:
        """(image folder, mask folder) readable on this node."""
        if self.files is None:
            yield self.root, self.mask_root
            return
        with tempfile.TemporaryDirectory(prefix="colmap-ext-images-") as scratch:
            for name, data in self.files.items():
                path = Path(scratch, name)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            yield str(Path(scratch, "images")), \
                None if self.mask_root is None else str(Path(scratch, "masks"))


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


def image_sources(image_path: str, mask_path: str | None, groups: Sequence[Sequence[str]],
                  by_path: bool) -> Iterator[ImageSource]:
    """An ImageSource per group of image names, made as it is asked for: paths, or the
    files' bytes."""
    root = str(Path(image_path).resolve())
    masks = None if mask_path is None else str(Path(mask_path).resolve())
    for names in groups:
        if by_path:
            yield ImageSource(root, masks)
            continue
        files = {f"images/{name}": Path(root, name).read_bytes() for name in names}
        if masks is not None:
            files.update({f"masks/{name}.png": Path(masks, f"{name}.png").read_bytes()
                          for name in names})
        yield ImageSource(root, masks, files)


# ------------------------------------------------------------------ extraction


@dataclass(frozen=True)
class ExtractedChunk:
    """What one extraction task found: per image name its final features, its keypoint
    count at the default threshold, and the peak threshold of the final features."""

    features: dict[str, Features]
    initial_keypoints: dict[str, int]
    peak_thresholds: dict[str, float]


def extract_chunk(source: ImageSource, names: list[str], camera_model: str, camera_params: str,
                  min_num_keypoints: int, domain_size_pooling: bool) -> ExtractedChunk:
    """The task: SIFT of `names` with the adaptive threshold rule (features.py), exactly
    as the single-machine extractor computes them, returned as arrays."""
    default = single_features.DEFAULT_PEAK_THRESHOLD
    with source.local() as (image_root, mask_root):
        reader = pycolmap.ImageReaderOptions(camera_model=camera_model,
                                             camera_params=camera_params)
        if mask_root is not None:
            reader.mask_path = Path(mask_root)
        found = single_features.extract_to_memory(image_root, names, reader, default,
                                                   domain_size_pooling)
        initial = {name: len(found[name][0]) for name in names}
        thresholds = dict.fromkeys(names, default)
        low = [name for name in names if initial[name] < min_num_keypoints]
        if low:
            found.update(single_features.reextract(image_root, low, reader, min_num_keypoints,
                                                   thresholds, progress=False,
                                                   domain_size_pooling=domain_size_pooling))
    features = {name: (np.asarray(keypoints, np.float32), np.asarray(descriptors.data, np.uint8))
                for name, (keypoints, descriptors) in found.items()}
    return ExtractedChunk(features, initial, thresholds)


def extract_features(cluster: Cluster, database_path: str | os.PathLike,
                     image_path: str | os.PathLike, *, camera_model: str,
                     camera_params: str | Sequence[float], camera_mode: str = "single",
                     mask_path: str | os.PathLike | None = None,
                     min_num_keypoints: int | None = None,
                     image_names: Sequence[str] | None = None, by_path: bool | None = None,
                     domain_size_pooling: bool = False, progress: bool = True) -> FeatureSummary:
    """features.extract_features on the cluster: the same database rows, the SIFT of
    each chunk of images computed by a task and written here. `by_path`: whether the
    tasks read the images by path (None: when every node sees them, shared_file_system)."""
    start = time.perf_counter()
    min_num_keypoints = single_features.DEFAULT_MIN_NUM_KEYPOINTS if min_num_keypoints is None \
        else min_num_keypoints
    params = single_features.check_camera(camera_model, camera_params)
    names = single_features.list_images(image_path, image_names)
    single_features.check_images(image_path, names, camera_mode, camera_model, params, mask_path)
    single_features.check_new_database(Path(database_path))
    params_text = ",".join(repr(p) for p in params)

    reader = pycolmap.ImageReaderOptions(camera_model=camera_model, camera_params=params_text)
    if mask_path is not None:
        reader.mask_path = Path(mask_path)
    with single_features.quiet_colmap_logs():
        pycolmap.Database.open(database_path).close()
        pycolmap.import_images(database_path, image_path,
                               camera_mode=single_features.CAMERA_MODES[camera_mode],
                               image_names=names, options=reader)
    groups = chunks(names, tasks_for(len(names), MAX_IMAGES_PER_TASK, cluster.num_cpus))
    if by_path is None:
        by_path = shared_file_system(cluster, str(Path(image_path).resolve()), names)
    sources = image_sources(str(image_path), None if mask_path is None else str(mask_path),
                            groups, by_path)
    initial: dict[str, int] = {}
    thresholds: dict[str, float] = {}
    final: dict[str, int] = {}
    db = pycolmap.Database.open(database_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        results = cluster.run(extract_chunk, (
            (source, list(group), camera_model, params_text, min_num_keypoints,
             domain_size_pooling)
            for source, group in zip(sources, groups)), len(groups),
            desc="extract (Ray)", progress=progress)
        for chunk in results:
            with pycolmap.DatabaseTransaction(db):
                for name, (keypoints, descriptors) in chunk.features.items():
                    db.write_keypoints(ids[name], keypoints)
                    db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(
                        pycolmap.FeatureExtractorType.SIFT, descriptors))
                    final[name] = len(keypoints)
            initial.update(chunk.initial_keypoints)
            thresholds.update(chunk.peak_thresholds)
    finally:
        db.close()
    order = {name: index for index, name in enumerate(names)}
    in_name_order = [dict(sorted(counts.items(), key=lambda item: order[item[0]]))
                     for counts in (initial, final, thresholds)]
    return FeatureSummary(*in_name_order, time.perf_counter() - start)


# ------------------------------------------------------------------ matching


def pair_blocks(pairs: list[tuple[int, int]], order: dict[int, int],
                pairs_per_task: int) -> list[list[tuple[int, int]]]:
    """The pairs grouped by the blocks of PAIR_BLOCK_IMAGES images their two images fall
    in, then cut into tasks of at most `pairs_per_task`."""
    def block(pair: tuple[int, int]) -> tuple[int, int]:
        a, b = sorted(order[i] // PAIR_BLOCK_IMAGES for i in pair)
        return a, b

    grouped: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for pair in pairs:
        grouped.setdefault(block(pair), []).append(pair)
    return [list(task) for key in sorted(grouped)
            for task in chunks(grouped[key], pairs_per_task)]


@dataclass(frozen=True)
class MatchedPair:
    """One pair as the database stores it (id1 < id2): raw matches and verified geometry."""

    id1: int
    id2: int
    matches: np.ndarray
    geometry: pycolmap.TwoViewGeometry | None  # None: no matches, nothing to verify


def match_and_verify(pairs: Sequence[tuple[int, int]], features: dict[int, Features],
                     cameras: dict[int, pycolmap.Camera], names: dict[int, str],
                     max_ratio: float, max_error_px: float, seed: int | None,
                     exact: bool) -> tuple[list[MatchedPair], float, float]:
    """Match the pairs as matching.match_features does (exact_matches, or pycolmap's
    matching pipeline on a scratch database of the pairs' images under their own ids),
    then verify each with matching.two_view_geometry. Returns the pairs and the seconds
    spent in each step."""
    start = time.perf_counter()
    if exact:
        found = {(id1, id2): single_matching.exact_matches(features[id1][1], features[id2][1],
                                                           max_ratio)
                 for id1, id2 in (sorted(pair) for pair in pairs)}
    else:
        found = faiss_matches(pairs, features, cameras, names, max_ratio)
    matched = time.perf_counter()
    results = []
    for id1, id2 in sorted((min(pair), max(pair)) for pair in pairs):
        matches = found.get((id1, id2))
        if matches is None or not len(matches):  # an empty row and, as verify_matches, no geometry
            results.append(MatchedPair(id1, id2, np.zeros((0, 2), np.uint32), None))
            continue
        geometry = single_matching.two_view_geometry(
            cameras[id1], cameras[id2], features[id1][0][:, :2].astype(np.float64),
            features[id2][0][:, :2].astype(np.float64), matches, max_error_px,
            single_matching.pair_seed(seed, names[id1], names[id2]))
        results.append(MatchedPair(id1, id2, matches, geometry))
    return results, matched - start, time.perf_counter() - matched


def faiss_matches(pairs: Sequence[tuple[int, int]], features: dict[int, Features],
                  cameras: dict[int, pycolmap.Camera], names: dict[int, str],
                  max_ratio: float) -> dict[tuple[int, int], np.ndarray]:
    """(id1, id2) with id1 < id2 -> the matches pycolmap's matcher stores for the pair."""
    needed = {image_id for pair in pairs for image_id in pair}
    with tempfile.TemporaryDirectory(prefix="colmap-ext-match-") as scratch:
        database_path = Path(scratch) / "database.db"
        with pycolmap.Database.open(database_path) as db, pycolmap.DatabaseTransaction(db):
            for camera in {cameras[i].camera_id: cameras[i] for i in needed}.values():
                db.write_camera(camera, use_camera_id=True)
            for image_id in sorted(needed):
                keypoints, descriptors = features[image_id]
                db.write_image(pycolmap.Image(name=names[image_id], image_id=image_id,
                                              camera_id=cameras[image_id].camera_id),
                               use_image_id=True)
                db.write_keypoints(image_id, keypoints)
                db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                    pycolmap.FeatureExtractorType.SIFT, descriptors))
        options = single_matching.matching_options(max_ratio)
        options.num_threads = 1
        with quiet_colmap_logs():
            single_matching.match_pairs(database_path, [(names[a], names[b]) for a, b in pairs],
                                        options)
        with pycolmap.Database.open(database_path) as db:
            pair_ids, all_matches = db.read_all_matches()
    return {tuple(pycolmap.pair_id_to_image_pair(pair_id)): matches
            for pair_id, matches in zip(pair_ids, all_matches)}


def match_block(pairs: list[tuple[int, int]], feature_refs: dict[int, Any],
                cameras: dict[int, pycolmap.Camera], names: dict[int, str], max_ratio: float,
                max_error_px: float, seed: int | None,
                exact: bool) -> tuple[list[MatchedPair], float, float]:
    """The task: fetch the features of the block's images from the object store, then
    match_and_verify."""
    import ray

    ids = list(feature_refs)
    features = dict(zip(ids, ray.get([feature_refs[i] for i in ids])))
    return match_and_verify(pairs, features, cameras, names, max_ratio, max_error_px, seed,
                            exact)


def match_features(cluster: Cluster, database_path: str | os.PathLike, *,
                   matcher: str = "auto", overlap: int = 10, loop_closure: bool = True,
                   max_ratio: float = 0.8, max_error_px: float = 4.0, seed: int | None = 0,
                   exact: bool = False, progress: bool = True) -> MatchingSummary:
    """matching.match_features on the cluster: the same pairs, matches and two-view
    geometries, each block of pairs matched and verified by a task, written here."""
    single_matching.check_options(matcher, overlap, max_ratio, max_error_px, seed)
    database_path = Path(database_path)
    all_names = single_matching.image_names(database_path)
    if matcher == "auto":
        matcher = "exhaustive" if len(all_names) <= single_matching.AUTO_EXHAUSTIVE_MAX_IMAGES \
            else "sequential"
    start = time.perf_counter()
    pairs = single_matching.pairs_to_match(database_path, matcher, overlap, loop_closure)
    db = pycolmap.Database.open(database_path)
    try:
        camera_of = {camera.camera_id: camera for camera in db.read_all_cameras()}
        images = {image.image_id: image for image in db.read_all_images()}
        names = {image_id: image.name for image_id, image in images.items()}
        refs = {image_id: cluster.put((db.read_keypoints(image_id),
                                       db.read_descriptors(image_id).data))
                for image_id in images}
        order = {image_id: index for index, image_id in
                 enumerate(sorted(images, key=lambda i: names[i]))}
        tasks = pair_blocks(pairs, order, tasks_for(len(pairs), MAX_PAIRS_PER_TASK,
                                                    cluster.num_cpus))
        arguments = []
        for task in tasks:
            needed = sorted({i for pair in task for i in pair})
            arguments.append((task, {i: refs[i] for i in needed},
                              {i: camera_of[images[i].camera_id] for i in needed},
                              {i: names[i] for i in needed}, max_ratio, max_error_px, seed,
                              exact))
        results: list[Any] = []
        worker_seconds = np.zeros(2)
        for matched, match_s, verify_s in cluster.run(match_block, arguments, len(arguments),
                                                      desc="match and verify (Ray)",
                                                      progress=progress):
            with pycolmap.DatabaseTransaction(db):
                for pair in matched:
                    db.write_matches(pair.id1, pair.id2, pair.matches)
                    if pair.geometry is not None:
                        db.write_two_view_geometry(pair.id1, pair.id2, pair.geometry)
            results += [pair for pair in matched if pair.geometry is not None]
            worker_seconds += (match_s, verify_s)
    finally:
        db.close()
    results.sort(key=lambda pair: pycolmap.image_pair_to_pair_id(pair.id1, pair.id2))
    elapsed = time.perf_counter() - start
    # Matching and verification share the tasks: the wall time is split as the workers'.
    share = worker_seconds[0] / worker_seconds.sum() if worker_seconds.sum() > 0 else 1.0
    pair_results = [single_matching.PairResult(names[p.id1], names[p.id2], len(p.matches),
                                               len(p.geometry.inlier_matches)) for p in results]
    return MatchingSummary(matcher, pair_results, elapsed * share, elapsed * (1 - share))


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
                      times: dict[str, float], *, camera_model: str,
                      camera_params: Sequence[float], camera_mode: str,
                      mask_path: str | os.PathLike | None, min_num_keypoints: int,
                      image_names: Sequence[str], matcher: str, seed: int | None,
                      exact_matching: bool, domain_size_pooling: bool = False
                      ) -> tuple[FeatureSummary, MatchingSummary, dict]:
    """Features and matching on the cluster into a staging database that replaces
    `database_path` once both are done; records the stages' seconds in `times` and
    returns both summaries and what the cluster was (nodes, CPUs, how images went)."""
    by_path = shared_file_system(cluster, str(Path(image_path).resolve()), image_names)
    with staged_database(database_path) as staging:
        start = time.perf_counter()
        features = extract_features(cluster, staging, image_path, camera_model=camera_model,
                                    camera_params=camera_params, camera_mode=camera_mode,
                                    mask_path=mask_path, min_num_keypoints=min_num_keypoints,
                                    image_names=image_names, by_path=by_path,
                                    domain_size_pooling=domain_size_pooling)
        times["features"] = time.perf_counter() - start
        matching = match_features(cluster, staging, matcher=matcher, seed=seed,
                                  exact=exact_matching)
    return features, matching, {"num_nodes": len(cluster.node_ids()),
                                "num_cpus": cluster.num_cpus,
                                "images": "by path" if by_path else "as bytes"}


def end_with_parent(parent_pid: int) -> None:
    """In a local pool's worker: be ended (SIGTERM) when the process that started it
    ends, however it ends; a killed command leaves no worker computing on (Linux's
    PR_SET_PDEATHSIG; elsewhere nothing is done)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent ended before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)


def run_local_or_on_cluster(cluster: Cluster | None, function: Callable,
                            arguments: Sequence[tuple], num_workers: int, desc: str,
                            progress: bool, num_cpus: float = 1) -> Iterable[Any]:
    """Results of `function(*args)` per argument tuple, as they complete: Ray tasks on
    `cluster`, else a pool of `num_workers` local processes (in this process if 1)."""
    if cluster is not None:
        yield from cluster.run(function, arguments, len(arguments), desc, progress,
                               num_cpus=num_cpus)
        return
    with tqdm(total=len(arguments), desc=desc, unit="task", disable=not progress) as bar:
        if num_workers <= 1:
            for args in arguments:
                yield function(*args)
                bar.update(1)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # "spawn": pycolmap and Ceres threads do not survive a fork.
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(num_workers, mp_context=context, initializer=end_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            futures = [pool.submit(function, *args) for args in arguments]
            try:
                for future in as_completed(futures):
                    yield future.result()
                    bar.update(1)
            except BaseException:  # an error or Ctrl-C/SIGTERM: end the workers, not wait for them
                for worker in multiprocessing.active_children():
                    worker.terminate()
                raise
