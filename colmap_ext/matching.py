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
name order, plus COLMAP's quadratic overlap) and, for rings such as turntables, loop
closure: the last images matched with the first ones, through an imported pair list.
"""

from __future__ import annotations

import functools
import os
import tempfile
import time
import zlib
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

import solvers
from colmap_ext.cameras import pixel_angles, rays
from colmap_ext.errors import UserError
from colmap_ext.features import quiet_colmap_logs

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
# Images whose descriptors exact matching keeps at once (pairs come in image order).
EXACT_CACHED_IMAGES = 64

Config = pycolmap.TwoViewGeometryConfiguration


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
            "pairs": [[p.name1, p.name2, p.num_matches, p.num_inliers] for p in self.pairs],
        }


def match_features(database_path: str | os.PathLike, *, matcher: str = "auto",
                   overlap: int = 10, loop_closure: bool = True, max_ratio: float = 0.8,
                   max_error_px: float = 4.0, seed: int | None = 0, exact: bool = False,
                   progress: bool = True) -> MatchingSummary:
    """Match the database's features and verify every new pair with known intrinsics.

    `max_error_px` is the Sampson error threshold of the verification, in pixels
    (COLMAP's default, 4); `seed` makes the RANSAC of every pair reproducible; `exact`
    matches by brute force instead of FAISS: the same matches on every run and machine.
    """
    check_options(matcher, overlap, max_ratio, max_error_px, seed)
    database_path = Path(database_path)
    names = image_names(database_path)
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= AUTO_EXHAUSTIVE_MAX_IMAGES else "sequential"
    start = time.perf_counter()
    pairs = pairs_to_match(database_path, matcher, overlap, loop_closure)
    if exact:
        match_exactly(database_path, pairs, max_ratio, progress)
    else:
        with pycolmap.Database.open(database_path) as db:
            name_of = {image.image_id: image.name for image in db.read_all_images()}
        with quiet_colmap_logs():
            match_pairs(database_path, [(name_of[a], name_of[b]) for a, b in pairs],
                        matching_options(max_ratio))
    matched = time.perf_counter()
    verified = verify_matches(database_path, max_error_px=max_error_px, seed=seed,
                              progress=progress)
    return MatchingSummary(matcher, verified, matched - start, time.perf_counter() - matched)


def pairs_to_match(database_path: Path, matcher: str, overlap: int,
                   loop_closure: bool) -> list[tuple[int, int]]:
    """The image-id pairs to match, in COLMAP's orientation: pycolmap's exhaustive or
    sequential pair generator, then the quadratic and loop closure pairs not among them."""
    with pycolmap.Database.open(database_path) as db:
        if matcher == "exhaustive":
            generator = pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
        else:
            # pycolmap's quadratic overlap replaces the linear pairs rather than adding
            # to them: linear pairs from pycolmap, the quadratic ones from us.
            generator = pycolmap.SequentialPairGenerator(
                pycolmap.SequentialPairingOptions(overlap=overlap, quadratic_overlap=False), db)
        pairs = [tuple(pair) for pair in generator.all_pairs()]
        if matcher != "exhaustive":
            ids = {image.name: image.image_id for image in db.read_all_images()}
            names = sorted(ids)
            more = quadratic_pairs(names, overlap)
            if loop_closure:
                more += loop_closure_pairs(names, overlap)
            pairs += [(ids[a], ids[b]) for a, b in more]
    seen: set[int] = set()
    unique = []
    for id1, id2 in pairs:
        pair_id = pycolmap.image_pair_to_pair_id(id1, id2)
        if id1 != id2 and pair_id not in seen:
            seen.add(pair_id)
            unique.append((id1, id2))
    return unique


def match_exactly(database_path: Path, pairs: list[tuple[int, int]], max_ratio: float,
                  progress: bool) -> None:
    """Write exact_matches for the pairs that have no matches yet."""
    with pycolmap.Database.open(database_path) as db:
        todo = [pair for pair in pairs if not db.exists_matches(*pair)]
        descriptors = functools.lru_cache(EXACT_CACHED_IMAGES)(
            lambda image_id: db.read_descriptors(image_id).data)
        with pycolmap.DatabaseTransaction(db):
            for pair in tqdm(todo, desc="match pairs (exact)", unit="pair",
                             disable=not progress or not todo):
                id1, id2 = sorted(pair)
                db.write_matches(id1, id2, exact_matches(descriptors(id1), descriptors(id2),
                                                         max_ratio))


def check_options(matcher: str, overlap: int, max_ratio: float, max_error_px: float,
                  seed: int | None) -> None:
    """One-line errors for options pycolmap or the solvers would reject less clearly."""
    if matcher not in MATCHERS:
        raise UserError(f"unknown matcher {matcher!r}; choose one of {', '.join(MATCHERS)}")
    if isinstance(overlap, bool) or not isinstance(overlap, int) or overlap < 1:
        raise UserError(f"overlap must be a positive integer, got {overlap!r}")
    if not 0 < max_ratio <= 1:
        raise UserError(f"max_ratio must be in (0, 1], got {max_ratio!r}")
    if not (np.isfinite(max_error_px) and max_error_px > 0):
        raise UserError(f"max_error_px must be a positive number, got {max_error_px!r}")
    if seed is not None and not 0 <= seed < 2**63:
        raise UserError(f"seed must be a non-negative integer, got {seed!r}")


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


def matching_options(max_ratio: float) -> pycolmap.FeatureMatchingOptions:
    """pycolmap's SIFT matching (FAISS), with ratio test and cross-check, leaving
    verification to us."""
    options = pycolmap.FeatureMatchingOptions()
    options.skip_geometric_verification = True
    options.num_threads = os.cpu_count() or 1
    options.sift.max_ratio = max_ratio
    options.sift.max_distance = SIFT_MAX_DISTANCE
    options.sift.cross_check = True
    return options


def quadratic_pairs(names: list[str], overlap: int) -> list[tuple[str, str]]:
    """COLMAP's quadratic overlap beyond the linear one: each image with the images
    2^k after it (k < overlap) that lie more than `overlap` ahead."""
    return [(names[i], names[i + 2**k]) for i in range(len(names)) for k in range(overlap)
            if overlap < 2**k and i + 2**k < len(names)]


def loop_closure_pairs(names: list[str], overlap: int) -> list[tuple[str, str]]:
    """The pairs sequential matching would add if the sequence were a closed ring: each
    of the last `overlap` images with the next ones counted from the start, except pairs
    that are within `overlap` of each other anyway (short sequences)."""
    n = len(names)
    return [(names[i], names[i + step - n])
            for i in range(n) for step in range(1, overlap + 1)
            if i + step >= n and n - step > overlap]


def match_pairs(database_path: Path, pairs: Iterable[tuple[str, str]],
                options: pycolmap.FeatureMatchingOptions) -> None:
    """Match the listed pairs of image names (pairs matched before are skipped by COLMAP)."""
    pairs = list(pairs)
    if not pairs:
        return
    with tempfile.TemporaryDirectory(prefix="colmap-ext-pairs-") as scratch:
        pairs_path = Path(scratch) / "pairs.txt"
        pairs_path.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        pycolmap.match_image_pairs(
            database_path, matching_options=options,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_path),
            device=pycolmap.Device.cpu)


def verify_matches(database_path: str | os.PathLike, *, max_error_px: float = 4.0,
                   seed: int | None = 0, progress: bool = True) -> list[PairResult]:
    """Write a calibrated two-view geometry for every matched pair that has none yet."""
    db = pycolmap.Database.open(database_path)
    try:
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        images = {image.image_id: image for image in db.read_all_images()}
        pair_ids, all_matches = db.read_all_matches()
        todo = [(pair_id, matches) for pair_id, matches in zip(pair_ids, all_matches)
                if not db.exists_two_view_geometry(*pycolmap.pair_id_to_image_pair(pair_id))]
        keypoints = {image_id: db.read_keypoints(image_id)[:, :2].astype(np.float64)
                     for image_id in images}

        def verify(item: tuple[int, np.ndarray]) -> pycolmap.TwoViewGeometry:
            pair_id, matches = item
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            return two_view_geometry(
                cameras[images[id1].camera_id], cameras[images[id2].camera_id],
                keypoints[id1], keypoints[id2], matches, max_error_px,
                pair_seed(seed, images[id1].name, images[id2].name))

        results = []
        with ThreadPoolExecutor(os.cpu_count() or 1) as pool, pycolmap.DatabaseTransaction(db):
            geometries = pool.map(verify, todo)
            for (pair_id, matches), geometry in tqdm(zip(todo, geometries), total=len(todo),
                                                     desc="verify pairs", unit="pair",
                                                     disable=not progress):
                id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
                db.write_two_view_geometry(id1, id2, geometry)
                results.append(PairResult(images[id1].name, images[id2].name, len(matches),
                                          len(geometry.inlier_matches)))
        return results
    finally:
        db.close()


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
    backward = np.zeros(len(b.T), np.int64)
    backward_first = np.full(len(b.T), -np.inf, np.float32)
    backward_second = np.full(len(b.T), -np.inf, np.float32)
    block = max(2, EXACT_BLOCK_PRODUCTS // len(b.T))
    for start in range(0, len(a), block):
        dot = a[start:start + block] @ b
        index, largest, _, _ = solvers.largest_per_row(dot.T, 2)  # the columns' two largest
        best, first, second = index[:, 0], largest[:, 0], largest[:, 1]
        backward_second = np.maximum(np.maximum(backward_second, second),
                                     np.minimum(backward_first, first))
        backward = np.where(first > backward_first, best + start, backward)
        backward_first = np.maximum(backward_first, first)
        index, largest, _, _ = solvers.largest_per_row(dot, 2)
        forward[start:start + len(dot)] = index[:, 0]
        forward_ok[start:start + len(dot)] = _passes_ratio_test(largest[:, 0], largest[:, 1],
                                                                max_ratio, max_distance)
    backward_ok = _passes_ratio_test(backward_first, backward_second, max_ratio, max_distance)
    matched = np.flatnonzero(forward_ok)
    matched = matched[backward_ok[forward[matched]] & (backward[forward[matched]] == matched)]
    if len(matched) < MIN_NUM_INLIERS:
        return none
    return np.stack([matched, forward[matched]], axis=1).astype(np.uint32)
