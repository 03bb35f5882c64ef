"""Feature matching by pycolmap (or exactly), geometric verification by our calibrated
5-point RANSAC.

Descriptors are matched as COLMAP matches SIFT (nearest neighbour, ratio test 0.8, which
is the paper's 1.25 inverted, and cross-check): by pycolmap's FAISS index, with its own
geometric verification switched off (`FeatureMatchingOptions.skip_geometric_verification`),
or with `exact` by brute force here (exact_matches). FAISS is approximate and, rarely,
not built the same twice (colmap/colmap#3874): a pair can then get a few matches more or
fewer, and a weak pair lose the ones it had. Every matched pair is then
verified with the known intrinsics: keypoints become undistorted rays through each
image's camera, `solvers.relative_pose` (OpenGV 5-point, LO-MSAC) finds E, the relative
pose and the inliers, and a CALIBRATED two-view geometry is written to the database,
where COLMAP's own mappers read it. A pair that fails is written as DEGENERATE with no
inliers, as COLMAP does.

Matchers: exhaustive (every pair), sequential (each image with the next `overlap` in
name order and, as COLMAP expands them, the other images of their frames; plus COLMAP's
quadratic overlap) and, for rings such as turntables, loop closure: the last frames
matched with the first ones. The quadratic and loop closure pairs join frames in the
sequence's order (sequence_frames), each pair of frames expanded to all pairs of their
images, so a rig's cameras, whose prefixed names sort one camera after another, are
paired as their frames.
Sequential matching also runs COLMAP's loop detection (every `loop_detection_period`-th
image with its most similar ones by visual words, where a sequence revisits a place),
on COLMAP's vocabulary tree file when one is given, otherwise on a vocabulary trained
here on the sequence's own descriptors: no download, offline too.
The pairs are matched and verified in blocks, each a task of an executor (threads
here, or Ray tasks), and written here as the blocks complete.
"""

from __future__ import annotations

import contextlib
import graphlib
import heapq
import os
import time
import zlib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pycolmap
from tqdm import tqdm

import solvers
from colmap_ext.cameras import pixel_angles, rays
from colmap_ext.errors import UserError
from colmap_ext.executors import Executor, LocalExecutor, chunks, items_per_task
from colmap_ext.features import quiet_colmap_logs
from colmap_ext.temporary import OwnedTemporaryDirectory

MATCHERS = ("auto", "exhaustive", "sequential")
# "auto": exhaustive up to this many images (n^2 / 2 pairs stay cheap), sequential beyond.
AUTO_EXHAUSTIVE_MAX_IMAGES = 100
# A pair needs this many inliers to be verified (COLMAP's TwoViewGeometryOptions default);
# COLMAP's matcher also stores no matches for a pair with fewer.
MIN_NUM_INLIERS = 15
# Exact matching takes the descriptor products of a pair in blocks of at most this many.
EXACT_BLOCK_PRODUCTS = 2**22
# COLMAP's SIFT matching: the bound on the angle (rad) between matched descriptors, and
# the length of a stored uint8 descriptor.
SIFT_MAX_DISTANCE = 0.7
SIFT_DESCRIPTOR_NORM = 512.0
# Pairs per matching task, at most (fewer when that leaves some workers idle).
MAX_PAIRS_PER_TASK = 500
# Pairs are grouped by blocks of this many images (in name order) on both sides, so a
# task needs the features of at most two blocks.
PAIR_BLOCK_IMAGES = 32
# Loop detection's own vocabulary: k-means (one round of this many iterations) of at most
# this many of the sequence's descriptors, drawn evenly from its images, into this many
# visual words (COLMAP's downloadable trees have 2^16 to 2^20, trained on millions of
# images; on one sequence 2^10 retrieve as well, in seconds: docs/experiments/loop-detection.md).
VOCABULARY_TRAINING_DESCRIPTORS = 2**16
VOCABULARY_WORDS = 2**10
VOCABULARY_ITERATIONS = 5
# Bits of each descriptor's Hamming embedding in the visual index (COLMAP's default).
VOCABULARY_EMBEDDING_BITS = 64

Config = pycolmap.TwoViewGeometryConfiguration
Features = tuple[np.ndarray, np.ndarray]  # keypoints (n, 6) float32, descriptors (n, 128) uint8


@dataclass(frozen=True)
class PairResult:
    """One matched pair: raw matches and the inliers of our verification (0 if it failed)."""

    name1: str
    name2: str
    num_matches: int
    num_inliers: int


@dataclass(frozen=True)
class MatchingSummary:
    matcher: str  # the one that ran ("auto" resolved)
    pairs: list[PairResult]  # pairs verified by this call, in pair-id order
    matching_seconds: float
    verification_seconds: float
    # Loop detection's vocabulary training, indexing and retrieval (sequential matching).
    loop_detection_seconds: float = 0.0

    @property
    def num_verified(self) -> int:
        return sum(pair.num_inliers > 0 for pair in self.pairs)

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "matcher": self.matcher,
            "num_matched_pairs": len(self.pairs),
            "num_verified_pairs": self.num_verified,
            "num_inlier_matches": sum(pair.num_inliers for pair in self.pairs),
            "matching_seconds": round(self.matching_seconds, 3),
            "verification_seconds": round(self.verification_seconds, 3),
            "loop_detection_seconds": round(self.loop_detection_seconds, 3),
            "pairs": [[p.name1, p.name2, p.num_matches, p.num_inliers] for p in self.pairs],
        }


@dataclass
class MatchingOptions:
    """Feature matching and its verification with known intrinsics (match_features)."""

    # One of MATCHERS: "auto" is exhaustive up to AUTO_EXHAUSTIVE_MAX_IMAGES, sequential beyond.
    matcher: str = "auto"
    # Sequential matching: each image with the next `overlap` in name order.
    overlap: int = 10
    # Sequential matching: the last images with the first ones too (rings, turntables).
    loop_closure: bool = True
    # Sequential matching: COLMAP's loop detection, every `loop_detection_period`-th image
    # with its `loop_detection_num_images` most similar images by visual words (COLMAP's
    # defaults, off as in COLMAP's sequential matcher: up to period x num_images more pairs,
    # twice the sequential ones at 201 frames, for sequences that never come back).
    loop_detection: bool = False
    loop_detection_period: int = 10
    loop_detection_num_images: int = 50
    # COLMAP's vocabulary tree file for loop detection, used as it is; None: a vocabulary
    # trained on the database's own descriptors.
    vocab_tree_path: str | os.PathLike | None = None
    # SIFT ratio test (the paper's 1.25, inverted).
    max_ratio: float = 0.8
    # Sampson error threshold (px) of the verification (COLMAP's default).
    max_error_px: float = 4.0
    # Seed of every pair's RANSAC (pair_seed); None: random.
    seed: int | None = 0
    # Match descriptors by brute force, not by pycolmap's FAISS index: the same matches
    # on every run and machine.
    exact: bool = False

    def check(self) -> None:
        """One-line errors for options pycolmap or the solvers would reject less clearly."""
        if self.matcher not in MATCHERS:
            raise UserError(f"unknown matcher {self.matcher!r}; choose one of "
                            f"{', '.join(MATCHERS)}")
        if isinstance(self.overlap, bool) or not isinstance(self.overlap, int) \
                or self.overlap < 1:
            raise UserError(f"overlap must be a positive integer, got {self.overlap!r}")
        for name in ("loop_detection_period", "loop_detection_num_images"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UserError(f"{name} must be a positive integer, got {value!r}")
        if self.vocab_tree_path is not None and not Path(self.vocab_tree_path).is_file():
            raise UserError(f"vocabulary tree not found: {self.vocab_tree_path}")
        if not 0 < self.max_ratio <= 1:
            raise UserError(f"max_ratio must be in (0, 1], got {self.max_ratio!r}")
        if not (np.isfinite(self.max_error_px) and self.max_error_px > 0):
            raise UserError(f"max_error_px must be a positive number, got {self.max_error_px!r}")
        if self.seed is not None and not 0 <= self.seed < 2**63:
            raise UserError(f"seed must be a non-negative integer, got {self.seed!r}")


def match_features(database_path: str | os.PathLike, options: MatchingOptions | None = None,
                   *, executor: Executor | None = None, progress: bool = True
                   ) -> MatchingSummary:
    """Match the database's features and verify every pair not matched before with the
    known intrinsics. Blocks of pairs are tasks of `executor` (default: this machine's
    threads), each matched and verified there and written here as it completes."""
    options = options or MatchingOptions()
    options.check()
    database_path = Path(database_path)
    names = image_names(database_path)
    matcher = options.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= AUTO_EXHAUSTIVE_MAX_IMAGES else "sequential"
    start = time.perf_counter()
    pairs, loop_detection_seconds = pairs_to_match(database_path, matcher, options, progress)
    # Here, one task at a time on every core: pycolmap's matcher builds the FAISS index of
    # each image again in every task, and holds it in memory while the task runs.
    executor = executor or LocalExecutor(1, threads_per_task=os.cpu_count() or 1)
    results: list[MatchedPair] = []
    worker_seconds = np.zeros(2)
    with pycolmap.Database.open(database_path) as db:
        pairs = [pair for pair in pairs if not db.exists_matches(*pair)]  # as COLMAP does
        tasks = pair_blocks(pairs, names, db, items_per_task(len(pairs), MAX_PAIRS_PER_TASK,
                                                             executor.num_workers))
        for matched, match_s, verify_s in executor.map(
                match_block, block_arguments(tasks, db, options, executor), len(tasks),
                desc="match and verify", progress=progress):
            with pycolmap.DatabaseTransaction(db):
                for pair in matched:
                    db.write_matches(pair.id1, pair.id2, pair.matches)
                    if pair.geometry is not None:
                        db.write_two_view_geometry(pair.id1, pair.id2, pair.geometry)
            results += [pair for pair in matched if pair.geometry is not None]
            worker_seconds += (match_s, verify_s)
        name_of = {image.image_id: image.name for image in db.read_all_images()}
    results.sort(key=lambda pair: pycolmap.image_pair_to_pair_id(pair.id1, pair.id2))
    elapsed = time.perf_counter() - start - loop_detection_seconds
    # Matching and verification share the tasks: the wall time is split as the workers'.
    share = worker_seconds[0] / worker_seconds.sum() if worker_seconds.sum() > 0 else 1.0
    pair_results = [PairResult(name_of[p.id1], name_of[p.id2], len(p.matches),
                               len(p.geometry.inlier_matches)) for p in results]
    return MatchingSummary(matcher, pair_results, elapsed * share, elapsed * (1 - share),
                           loop_detection_seconds)


def pair_blocks(pairs: list[tuple[int, int]], names: list[str], db: pycolmap.Database,
                pairs_per_task: int) -> list[list[tuple[int, int]]]:
    """The pairs grouped by the blocks of PAIR_BLOCK_IMAGES images (in name order) their
    two images fall in, then cut into tasks of at most `pairs_per_task`: a task needs
    the features of at most two blocks."""
    order = {name: index for index, name in enumerate(names)}
    block_of = {image.image_id: order[image.name] // PAIR_BLOCK_IMAGES
                for image in db.read_all_images()}
    grouped: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for pair in pairs:
        grouped.setdefault(tuple(sorted(block_of[i] for i in pair)), []).append(pair)
    return [list(task) for key in sorted(grouped)
            for task in chunks(grouped[key], pairs_per_task)]


def block_arguments(tasks: list[list[tuple[int, int]]], db: pycolmap.Database,
                    options: MatchingOptions, executor: Executor) -> Iterator[tuple]:
    """match_block's arguments per task, made as the executor asks for them: each
    image's features put once and let go after the last task that needs them."""
    cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
    images = {image.image_id: image for image in db.read_all_images()}
    last_task = {image_id: index for index, task in enumerate(tasks)
                 for pair in task for image_id in pair}
    handles: dict[int, Any] = {}
    for index, task in enumerate(tasks):
        needed = sorted({image_id for pair in task for image_id in pair})
        for image_id in needed:
            if image_id not in handles:
                handles[image_id] = executor.put((db.read_keypoints(image_id),
                                                  db.read_descriptors(image_id).data))
        yield (task, {i: cameras[images[i].camera_id] for i in needed},
               {i: images[i].name for i in needed}, options, executor.threads_per_task,
               *(handles[i] for i in needed))
        for image_id in needed:
            if last_task[image_id] == index:
                del handles[image_id]


@dataclass(frozen=True)
class MatchedPair:
    """One pair as the database stores it (id1 < id2): raw matches and verified geometry."""

    id1: int
    id2: int
    matches: np.ndarray
    geometry: pycolmap.TwoViewGeometry | None  # None: no matches, nothing to verify


def match_block(pairs: list[tuple[int, int]], cameras: dict[int, pycolmap.Camera],
                names: dict[int, str], options: MatchingOptions, num_threads: int,
                *features: Features) -> tuple[list[MatchedPair], float, float]:
    """The task: match the pairs (exact_matches, or pycolmap's matcher on a scratch
    database of the pairs' images under their own ids), then verify each with
    two_view_geometry, in `num_threads` threads. `features`: keypoints and descriptors
    of the images of `cameras`, in image id order. Returns the pairs and the seconds
    spent in each step."""
    features_of = dict(zip(sorted(cameras), features))
    start = time.perf_counter()
    if options.exact:
        found = {(id1, id2): exact_matches(features_of[id1][1], features_of[id2][1],
                                           options.max_ratio)
                 for id1, id2 in (sorted(pair) for pair in pairs)}
    else:
        found = faiss_matches(pairs, features_of, cameras, names, options.max_ratio,
                              num_threads)
    matched = time.perf_counter()

    def verify(pair: tuple[int, int]) -> MatchedPair:
        id1, id2 = pair
        matches = found.get(pair)
        if matches is None or not len(matches):  # an empty row, and no geometry
            return MatchedPair(id1, id2, np.zeros((0, 2), np.uint32), None)
        return MatchedPair(id1, id2, matches, two_view_geometry(
            cameras[id1], cameras[id2], features_of[id1][0][:, :2].astype(np.float64),
            features_of[id2][0][:, :2].astype(np.float64), matches, options.max_error_px,
            pair_seed(options.seed, names[id1], names[id2])))

    with ThreadPoolExecutor(num_threads) as pool:
        results = list(pool.map(verify, sorted((min(pair), max(pair)) for pair in pairs)))
    return results, matched - start, time.perf_counter() - matched


def faiss_matches(pairs: list[tuple[int, int]], features: dict[int, Features],
                  cameras: dict[int, pycolmap.Camera], names: dict[int, str],
                  max_ratio: float, num_threads: int) -> dict[tuple[int, int], np.ndarray]:
    """(id1, id2) with id1 < id2 -> the matches pycolmap's matcher stores for the pair."""
    with OwnedTemporaryDirectory("colmap-ext-match-") as scratch:
        database_path = Path(scratch) / "database.db"
        with pycolmap.Database.open(database_path) as db, pycolmap.DatabaseTransaction(db):
            for camera in {camera.camera_id: camera for camera in cameras.values()}.values():
                db.write_camera(camera, use_camera_id=True)
            for image_id, (keypoints, descriptors) in features.items():
                db.write_image(pycolmap.Image(name=names[image_id], image_id=image_id,
                                              camera_id=cameras[image_id].camera_id),
                               use_image_id=True)
                db.write_keypoints(image_id, keypoints)
                db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                    pycolmap.FeatureExtractorType.SIFT, descriptors))
        pairs_path = Path(scratch) / "pairs.txt"
        pairs_path.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
        with quiet_colmap_logs():
            pycolmap.match_image_pairs(
                database_path, matching_options=matching_options(max_ratio, num_threads),
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
                device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database_path) as db:
            pair_ids, all_matches = db.read_all_matches()
    return {tuple(pycolmap.pair_id_to_image_pair(pair_id)): matches
            for pair_id, matches in zip(pair_ids, all_matches)}


def pairs_to_match(database_path: Path, matcher: str, options: MatchingOptions,
                   progress: bool = True) -> tuple[list[tuple[int, int]], float]:
    """The image-id pairs to match, in COLMAP's orientation: pycolmap's exhaustive or
    sequential pair generator (with loop detection), then the quadratic and loop closure
    pairs of frames, each expanded to all pairs of their images, not among them; and the
    seconds loop detection took."""
    loop_detection_seconds = 0.0
    with pycolmap.Database.open(database_path) as db:
        if matcher == "exhaustive":
            generator = pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
            pairs = [tuple(pair) for pair in generator.all_pairs()]
        elif not options.loop_detection:
            pairs = sequential_pairs(db, options, None, progress)
        else:
            start = time.perf_counter()
            with loop_detection_vocabulary(db, options.vocab_tree_path, progress) as vocabulary:
                pairs = sequential_pairs(db, options, vocabulary, progress)
            loop_detection_seconds = time.perf_counter() - start
        if matcher != "exhaustive":
            frames = sequence_frames(db)
            more = quadratic_pairs(frames, options.overlap)
            if options.loop_closure:
                more += loop_closure_pairs(frames, options.overlap)
            pairs += [(id1, id2) for frame1, frame2 in more for id1 in frame1 for id2 in frame2]
    seen: set[int] = set()
    unique = []
    for id1, id2 in pairs:
        pair_id = pycolmap.image_pair_to_pair_id(id1, id2)
        if id1 != id2 and pair_id not in seen:
            seen.add(pair_id)
            unique.append((id1, id2))
    return unique, loop_detection_seconds


def sequential_pairs(db: pycolmap.Database, options: MatchingOptions,
                     vocabulary: Path | None, progress: bool) -> list[tuple[int, int]]:
    """pycolmap's sequential pairs, with COLMAP's loop detection on `vocabulary` (None:
    without). pycolmap's quadratic overlap replaces the linear pairs rather than adding
    to them: linear pairs here, the quadratic ones from quadratic_pairs."""
    pairing = pycolmap.SequentialPairingOptions(overlap=options.overlap, quadratic_overlap=False)
    if vocabulary is not None:
        pairing.loop_detection = True
        pairing.loop_detection_period = options.loop_detection_period
        pairing.loop_detection_num_images = options.loop_detection_num_images
        pairing.vocab_tree_path = vocabulary
    with quiet_colmap_logs():
        try:  # the generator indexes every image on the vocabulary
            generator = pycolmap.SequentialPairGenerator(pairing, db)
        except (RuntimeError, ValueError) as error:
            raise UserError(f"cannot use the vocabulary tree {vocabulary}: "
                            f"{str(error).strip().splitlines()[-1]}") from None
        if vocabulary is None:
            return [tuple(pair) for pair in generator.all_pairs()]
        # One step per image, then one per loop detection query.
        num_images = db.num_images()
        num_steps = num_images + -(-num_images // options.loop_detection_period)
        pairs = []
        with tqdm(total=num_steps, desc="loop detection", unit="image",
                  disable=not progress) as bar:
            while not generator.has_finished():
                pairs += [tuple(pair) for pair in generator.next()]
                bar.update()
    return pairs


@contextlib.contextmanager
def loop_detection_vocabulary(db: pycolmap.Database, vocab_tree_path: str | os.PathLike | None,
                              progress: bool) -> Iterator[Path]:
    """The vocabulary tree file for loop detection: `vocab_tree_path` as it is, or one
    trained on the database's own descriptors in a temporary folder, removed on exit."""
    if vocab_tree_path is not None:
        yield Path(vocab_tree_path)
        return
    with OwnedTemporaryDirectory("colmap-ext-vocabulary-") as scratch:
        path = Path(scratch) / "vocabulary.bin"
        with tqdm(total=1, desc="loop detection vocabulary", unit="vocabulary",
                  disable=not progress) as bar:
            trained_vocabulary(db).write(path)
            bar.update()
        yield path


def trained_vocabulary(db: pycolmap.Database) -> pycolmap.VisualIndex:
    """A visual index whose words are the k-means clusters of at most
    VOCABULARY_TRAINING_DESCRIPTORS of the database's descriptors, the same number
    drawn at random (seeded: the same vocabulary on every run) from each image."""
    image_ids = sorted(image.image_id for image in db.read_all_images())
    per_image = max(1, VOCABULARY_TRAINING_DESCRIPTORS // len(image_ids))
    rng = np.random.default_rng(0)
    samples = []
    for image_id in image_ids:
        descriptors = db.read_descriptors(image_id).data
        samples.append(descriptors[rng.choice(len(descriptors), min(per_image, len(descriptors)),
                                              replace=False)])
    training = np.concatenate(samples)
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words = min(VOCABULARY_WORDS, len(training))
    build.num_iterations = VOCABULARY_ITERATIONS
    build.num_rounds = 1
    vocabulary = pycolmap.VisualIndex.create(training.shape[1], VOCABULARY_EMBEDDING_BITS)
    vocabulary.build(build, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                        training).to_float())
    return vocabulary


def image_names(database_path: Path) -> list[str]:
    """Names of the database's images, sorted (the order of sequential matching)."""
    if not database_path.is_file():
        raise UserError(f"database not found: {database_path}")
    db = pycolmap.Database.open(database_path)
    try:
        names = sorted(image.name for image in db.read_all_images())
        if not names or db.num_keypoints() == 0:
            raise UserError(f"no features in {database_path}: extract features first")
        return names
    finally:
        db.close()


def matching_options(max_ratio: float, num_threads: int) -> pycolmap.FeatureMatchingOptions:
    """pycolmap's SIFT matching (FAISS) in `num_threads` threads, with ratio test and
    cross-check, leaving verification to us."""
    options = pycolmap.FeatureMatchingOptions()
    options.skip_geometric_verification = True
    options.num_threads = num_threads
    options.sift.max_ratio = max_ratio
    options.sift.max_distance = SIFT_MAX_DISTANCE
    options.sift.cross_check = True
    return options


def sequence_frames(db: pycolmap.Database) -> list[list[int]]:
    """The database's frames, each the ids of its images in name order, in the sequence's
    order: every camera's images in name order (a rig's are named alike under each
    camera's prefix, as COLMAP's rig configuration has them, so that is their frames'
    order too), and where that leaves a choice, the frame whose first name sorts first.
    With one image a frame that is the images' name order. An image in no frame is a
    frame of its own; frames that no order satisfies follow their first names."""
    images = sorted(db.read_all_images(), key=lambda image: image.name)
    name_of = {image.image_id: image.name for image in images}
    frames = [sorted((data.id for data in frame.image_ids), key=name_of.__getitem__)
              for frame in db.read_all_frames() if frame.image_ids]
    framed = {image_id for frame in frames for image_id in frame}
    frames += [[image.image_id] for image in images if image.image_id not in framed]
    frame_of = {image_id: index for index, frame in enumerate(frames) for image_id in frame}
    sorter = graphlib.TopologicalSorter({index: () for index in range(len(frames))})
    last_of_camera: dict[int, int] = {}
    for image in images:  # each frame after the frame of its camera's previous image
        index = frame_of[image.image_id]
        if last_of_camera.get(image.camera_id, index) != index:
            sorter.add(index, last_of_camera[image.camera_id])
        last_of_camera[image.camera_id] = index
    try:
        sorter.prepare()
    except graphlib.CycleError:
        return sorted(frames, key=lambda frame: name_of[frame[0]])
    order: list[list[int]] = []
    ready: list[tuple[str, int]] = []
    while sorter.is_active():
        for index in sorter.get_ready():
            heapq.heappush(ready, (name_of[frames[index][0]], index))
        _, index = heapq.heappop(ready)
        order.append(frames[index])
        sorter.done(index)
    return order


Item = TypeVar("Item")


def quadratic_pairs(sequence: list[Item], overlap: int) -> list[tuple[Item, Item]]:
    """COLMAP's quadratic overlap beyond the linear one: each item (image or frame) with
    the items 2^k after it (k < overlap) that lie more than `overlap` ahead."""
    return [(sequence[i], sequence[i + 2**k]) for i in range(len(sequence))
            for k in range(overlap) if overlap < 2**k and i + 2**k < len(sequence)]


def loop_closure_pairs(sequence: list[Item], overlap: int) -> list[tuple[Item, Item]]:
    """The pairs sequential matching would add if the sequence were a closed ring: each
    of the last `overlap` items (images or frames) with the next ones counted from the
    start, except pairs that are within `overlap` of each other anyway (short sequences)."""
    n = len(sequence)
    return [(sequence[i], sequence[i + step - n])
            for i in range(n) for step in range(1, overlap + 1)
            if i + step >= n and n - step > overlap]


def pair_seed(seed: int | None, name1: str, name2: str) -> int | None:
    """A RANSAC seed per pair from the run's seed and the image names: independent of
    thread scheduling and of image ids, which COLMAP's threaded extractor assigns in
    varying order."""
    if seed is None:
        return None
    key = zlib.crc32("\0".join(sorted((name1, name2))).encode())
    return int(np.random.SeedSequence([seed, key]).generate_state(1, np.uint64)[0])


def two_view_geometry(camera1: pycolmap.Camera, camera2: pycolmap.Camera,
                      keypoints1: np.ndarray, keypoints2: np.ndarray, matches: np.ndarray,
                      max_error_px: float, seed: int | None) -> pycolmap.TwoViewGeometry:
    """CALIBRATED geometry (E, F, cam2_from_cam1, inliers) of one pair, or DEGENERATE."""
    if len(matches) < MIN_NUM_INLIERS:
        return pycolmap.TwoViewGeometry(config=Config.DEGENERATE)
    points1, points2 = keypoints1[matches[:, 0], :2], keypoints2[matches[:, 1], :2]
    rays1, rays2 = rays(camera1, points1), rays(camera2, points2)
    max_errors = max_error_px * 0.5 * (pixel_angles(camera1, points1) +
                                       pixel_angles(camera2, points2))
    # Keypoints outside a camera model's valid domain (far fisheye corners) give no ray.
    valid = np.isfinite(rays1).all(axis=1) & np.isfinite(rays2).all(axis=1) & \
        np.isfinite(max_errors)
    if valid.sum() < MIN_NUM_INLIERS:
        return pycolmap.TwoViewGeometry(config=Config.DEGENERATE)
    try:
        result = solvers.relative_pose(rays1[valid], rays2[valid], max_error=max_errors[valid],
                                       min_num_inliers=MIN_NUM_INLIERS, seed=seed)
    except solvers.EstimationError:
        return pycolmap.TwoViewGeometry(config=Config.DEGENERATE)
    geometry = pycolmap.TwoViewGeometry(
        config=Config.CALIBRATED, E=result.E, cam2_from_cam1=result.cam2_from_cam1,
        inlier_matches=np.ascontiguousarray(matches[valid][result.inlier_mask], dtype=np.uint32))
    if camera1.is_perspective() and camera2.is_perspective():  # F needs a K (COLMAP's check)
        K1_inv = np.linalg.inv(camera1.calibration_matrix())
        K2_inv = np.linalg.inv(camera2.calibration_matrix())
        F = K2_inv.T @ result.E @ K1_inv
        geometry.F = F / np.linalg.norm(F)
    return geometry


# ------------------------------------------------------------------ exact matching


def _passes_ratio_test(first: np.ndarray, second: np.ndarray, max_ratio: float,
                       max_distance: float) -> np.ndarray:
    """COLMAP's test, in its float32 arithmetic, on the angles between descriptors
    (stored at unit length x 512): within `max_distance`, and below `max_ratio` times
    the second nearest."""
    scale = np.float32(1 / SIFT_DESCRIPTOR_NORM**2)
    best = np.arccos(np.minimum(first * scale, np.float32(1)))
    next_best = np.arccos(np.minimum(second * scale, np.float32(1)))
    return (best <= np.float32(max_distance)) & (best < np.float32(max_ratio) * next_best)


def exact_matches(descriptors1: np.ndarray, descriptors2: np.ndarray, max_ratio: float,
                  max_distance: float = SIFT_MAX_DISTANCE) -> np.ndarray:
    """SIFT matches by brute force, as COLMAP defines them: nearest neighbour by the
    angle between descriptors, ratio test, distance bound and cross-check; (n, 2) uint32
    keypoint indices, none when fewer than MIN_NUM_INLIERS (COLMAP keeps none then).
    The matches of pycolmap's `cpu_brute_force_matcher`, several times faster.

    Float32 dot products of uint8 descriptors are sums of integers below 2^24, hence
    exact: the matches do not depend on the BLAS, its threads or the machine."""
    none = np.zeros((0, 2), np.uint32)
    if len(descriptors1) < 2 or len(descriptors2) < 2:
        return none
    a, b = descriptors1.astype(np.float32), descriptors2.astype(np.float32).T.copy()
    forward = np.zeros(len(a), np.int64)
    forward_ok = np.zeros(len(a), bool)
    # Each column's two largest over the blocks so far: the backward search.
    backward = np.zeros((len(b.T), 2), np.int64)
    backward_largest = np.full((len(b.T), 2), -np.inf, np.float32)
    block = max(2, EXACT_BLOCK_PRODUCTS // len(b.T))
    for start in range(0, len(a), block):
        dot = a[start:start + block] @ b
        solvers.largest_per_column(dot, 2, start, backward, backward_largest)
        index, largest, _, _ = solvers.largest_per_row(dot, 2)
        forward[start:start + len(dot)] = index[:, 0]
        forward_ok[start:start + len(dot)] = _passes_ratio_test(largest[:, 0], largest[:, 1],
                                                                max_ratio, max_distance)
    backward_ok = _passes_ratio_test(backward_largest[:, 0], backward_largest[:, 1], max_ratio,
                                     max_distance)
    matched = np.flatnonzero(forward_ok)
    matched = matched[backward_ok[forward[matched]] & (backward[forward[matched], 0] == matched)]
    if len(matched) < MIN_NUM_INLIERS:
        return none
    return np.stack([matched, forward[matched]], axis=1).astype(np.uint32)
