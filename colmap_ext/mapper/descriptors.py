"""Nearest SIFT descriptors between two images: exact, by blocks of cosines, so
memory stays bounded whatever the keypoint counts; and a per-pair store of them for
guided matching, which asks for the same pairs again. Where an exact search would
compare too many keypoint pairs, the database's matches stand in for it."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from threadpoolctl import ThreadpoolController

import solvers

# Cosines computed at once: 4 MiB of float32, which stays in cache while the
# nearest are taken (smaller and larger blocks measured slower).
QUERY_BLOCK_ENTRIES = 2**20
# A search for at most this share of an image's keypoints (a grown model's few free
# ones) covers those rows alone and is not kept; a larger one, the whole pair, kept.
FEW_ROWS_SHARE = 0.25
# The BLAS libraries loaded, found once at import: the search runs Python inside a
# ctypes callback, where a Ctrl-C would be printed and lost instead of raised.
BLAS = ThreadpoolController()


def unit_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """SIFT descriptors as float32 unit vectors (their dot products are cosines)."""
    d = descriptors.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _similarity_blocks(unit_queries: np.ndarray,
                       unit_database: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(first row, cosines of a block of queries against the whole database), from unit
    descriptors: blocks of about QUERY_BLOCK_ENTRIES, so memory stays bounded whatever
    the keypoint counts."""
    block = max(1, QUERY_BLOCK_ENTRIES // max(len(unit_database), 1))
    for start in range(0, len(unit_queries), block):
        yield start, unit_queries[start:start + block] @ unit_database.T


def _angles(cosines: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(cosines, -1.0, 1.0))


def nearest_descriptors(queries: np.ndarray, database: np.ndarray, k: int,
                        subset: np.ndarray | None = None, k_subset: int = 0,
                        ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Indices (q, k) of the k nearest descriptors (uint8 SIFT), nearest first, and
    their angles (radians); from the same cosines, the k_subset nearest among the
    database rows `subset` (indices into it, angles)."""
    return nearest_unit_descriptors(unit_descriptors(queries), unit_descriptors(database), k,
                                    subset, k_subset)


def nearest_unit_descriptors(unit_queries: np.ndarray, unit_database: np.ndarray, k: int,
                             subset: np.ndarray | None = None, k_subset: int = 0,
                             ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """nearest_descriptors from the descriptors' unit_descriptors."""
    index, angles, found, _ = search_both_ways(unit_queries, unit_database, k, subset, k_subset,
                                               reverse=False)
    return index, angles, found


def search_both_ways(unit_queries: np.ndarray, unit_database: np.ndarray, k: int,
                     subset: np.ndarray | None, k_subset: int, reverse: bool
                     ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray],
                                tuple[np.ndarray, np.ndarray] | None]:
    """nearest_unit_descriptors, and with `reverse` from the same cosines the search the
    other way (the k nearest queries of each database descriptor: index, angles), which
    is that search's exact answer: a cosine is the same dot product either way."""
    k_reverse = min(k, len(unit_queries)) if reverse else 0
    k = min(k, len(unit_database))
    k_subset = min(k_subset, 0 if subset is None else len(subset))
    index = np.empty((len(unit_queries), k), np.int32)
    best = np.empty((len(unit_queries), k), np.float32)
    sub_index = np.empty((len(unit_queries), k_subset), np.int64)
    sub_best = np.empty((len(unit_queries), k_subset), np.float32)
    reverse_index = np.zeros((len(unit_database), k_reverse), np.int64)
    reverse_best = np.full((len(unit_database), k_reverse), -np.inf, np.float32)
    for start, similarity in _similarity_blocks(unit_queries, unit_database):
        rows = slice(start, start + len(similarity))
        index[rows], best[rows], sub_index[rows], sub_best[rows] = solvers.largest_per_row(
            similarity, k, subset=subset, k_subset=k_subset)
        if reverse:
            solvers.largest_per_column(similarity, k_reverse, start, reverse_index, reverse_best)
    found = (reverse_index.astype(np.int32), _angles(reverse_best)) if reverse else None
    return index, _angles(best), (sub_index, _angles(sub_best)), found


class LeastRecentlyUsed:
    """Arrays by key within `max_bytes`, the least recently used given up first (the
    newest always kept)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.items: OrderedDict[Hashable, tuple[np.ndarray, ...]] = OrderedDict()
        self.bytes = 0

    def __contains__(self, key: Hashable) -> bool:
        return key in self.items

    def get(self, key: Hashable) -> tuple[np.ndarray, ...]:
        """The arrays kept under `key`, now the most recently used."""
        self.items.move_to_end(key)
        return self.items[key]

    def clear(self) -> None:
        self.items.clear()
        self.bytes = 0

    def keep(self, key: Hashable, arrays: tuple[np.ndarray, ...]) -> None:
        if key in self.items:
            self.bytes -= sum(array.nbytes for array in self.items.pop(key))
        self.items[key] = arrays
        self.bytes += sum(array.nbytes for array in arrays)
        while self.bytes > self.max_bytes and len(self.items) > 1:
            _, old = self.items.popitem(last=False)
            self.bytes -= sum(array.nbytes for array in old)


class NearestDescriptors:
    """For every keypoint of an image, its k nearest descriptors in another image: the
    guided matching's candidates (paper, step 4c). Descriptors never change, so each
    ordered pair of images is searched once and kept, the least recently used pairs
    given up first beyond `max_bytes`, and the search of (image, other) also gives
    (other, image) where that is not kept yet: the same cosines, read down the columns
    (search_both_ways). So are the images' unit descriptors kept, which the
    searches of an image's pairs share (another `max_bytes` at most). A registration's
    search against a neighbour's observed keypoints comes from the same cosines
    (`search_subsets`). Every search runs with single-threaded BLAS, searches against
    several images in parallel, one per thread of a pool kept until `close`: on a
    loaded machine that is about twice as fast as BLAS's own threads.

    A pair whose exact search would compare more than `max_search_pairs` keypoint pairs
    (the cost grows with the product of the keypoint counts) takes its candidates from
    `matches`, the database's matches (image pair -> keypoint index pairs, as
    DatabaseContents.raw_matches): each matched keypoint's one candidate is the keypoint
    it was matched to, which the matcher found nearest and distinct (ratio test). Those
    are quick to take again and are not kept: the store holds exact searches alone."""

    def __init__(self, descriptors: Mapping[int, np.ndarray], num_keypoints: Mapping[int, int],
                 k: int, max_bytes: int, num_threads: int,
                 matches: dict[tuple[int, int], np.ndarray] | None = None,
                 max_search_pairs: int | None = None) -> None:
        self.descriptors = descriptors  # read when a search needs them (DescriptorReader)
        self.num_keypoints = num_keypoints
        self.k = k
        self.num_threads = max(1, num_threads)
        self.matches = matches or {}
        self.max_search_pairs = max_search_pairs
        self.pairs = LeastRecentlyUsed(max_bytes)  # (image, other image) -> (index, angles)
        self.units = LeastRecentlyUsed(max_bytes)  # image -> (its unit descriptors,)
        self._pool: ThreadPoolExecutor | None = None

    def close(self) -> None:
        """Stop the search threads (a later search starts them again)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def release(self) -> None:
        """Give up the searches, unit descriptors and descriptors kept: a model's last
        adjustments ask for none, and they are its peak of memory. A later search (a
        retriangulation's) reads and searches again."""
        self.pairs.clear()
        self.units.clear()
        if hasattr(self.descriptors, "release"):  # a DescriptorReader, not a dict
            self.descriptors.release()

    def __call__(self, image_id: int, other_id: int, kps: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(index, angles), each (keypoints of image_id, k), nearest first, or for its
        keypoints `kps` alone; one column for a pair whose candidates are the database's
        matches. A few keypoints (FEW_ROWS_SHARE) of a pair not kept are searched alone."""
        if self._uses_matches(image_id, other_id):
            index, angles, _ = self._matched(image_id, other_id, np.zeros(0, np.int64), 0)
        elif kps is not None and (image_id, other_id) not in self.pairs and \
                self._few(image_id, kps):
            units = self._unit(image_id)[kps], self._unit(other_id)
            with BLAS.limit(limits=1, user_api="blas"):
                index, angles, _ = nearest_unit_descriptors(*units, self.k)
            return index, angles
        else:
            self.prefetch(image_id, [other_id])
            index, angles = self.pairs.get((image_id, other_id))
        return (index, angles) if kps is None else (index[kps], angles[kps])

    def prefetch(self, image_id: int, other_ids: list[int], kps: np.ndarray | None = None) -> None:
        """Search the pairs (image_id, other) not kept yet, in parallel; none where only
        a few keypoints `kps` will be asked for (they are searched alone)."""
        if kps is not None and self._few(image_id, kps):
            return
        missing = [(other_id, np.zeros(0, np.int64)) for other_id in other_ids
                   if (image_id, other_id) not in self.pairs
                   and not self._uses_matches(image_id, other_id)]
        self.search_subsets(image_id, missing, 0)

    def search_subsets(self, image_id: int, subsets: list[tuple[int, np.ndarray]],
                       k: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """For each (other image, keypoints of it), the k nearest among those keypoints
        (indices into them, angles), keeping each search over all of them."""
        def search(other_id: int, subset: np.ndarray):
            if self._uses_matches(image_id, other_id):
                return *self._matched(image_id, other_id, subset, k), None
            return search_both_ways(units[image_id], units[other_id], self.k, subset, k,
                                    reverse=(other_id, image_id) not in self.pairs)

        if not subsets:
            return []
        # Unit descriptors read and kept here: the threads only search.
        searched = [other_id for other_id, _ in subsets
                    if not self._uses_matches(image_id, other_id)]
        units = {i: self._unit(i) for i in ([image_id] + searched if searched else [])}
        with BLAS.limit(limits=1, user_api="blas"):
            if len(subsets) > 1 and self.num_threads > 1:
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(self.num_threads)
                results = list(self._pool.map(search, *zip(*subsets)))
            else:
                results = [search(other_id, subset) for other_id, subset in subsets]
        for (other_id, _), (index, angles, _, reverse) in zip(subsets, results):
            if not self._uses_matches(image_id, other_id):
                self.pairs.keep((image_id, other_id), (index, angles))
            if reverse is not None:
                self.pairs.keep((other_id, image_id), reverse)
        return [found for _, _, found, _ in results]

    def pair_angles(self, image_id: int, kps: np.ndarray, other_id: int,
                    other_kps: np.ndarray) -> np.ndarray:
        """The descriptor angles (radians) of keypoint pairs (kps[i], other_kps[i]), from
        those keypoints' descriptors alone (a pair of large images is never searched:
        their unit descriptors are not worth keeping)."""
        return _angles(np.einsum("ij,ij->i", unit_descriptors(self.descriptors[image_id][kps]),
                                 unit_descriptors(self.descriptors[other_id][other_kps])))

    def _unit(self, image_id: int) -> np.ndarray:
        """The image's unit_descriptors, kept for its other pairs."""
        if image_id not in self.units:
            self.units.keep(image_id, (unit_descriptors(self.descriptors[image_id]),))
        return self.units.get(image_id)[0]

    def _few(self, image_id: int, kps: np.ndarray) -> bool:
        return len(kps) <= FEW_ROWS_SHARE * self.num_keypoints[image_id]

    def _uses_matches(self, image_id: int, other_id: int) -> bool:
        """Whether the pair's exact search would compare more than max_search_pairs."""
        return self.max_search_pairs is not None and self.num_keypoints[image_id] * \
            self.num_keypoints[other_id] > self.max_search_pairs

    def _matched(self, image_id: int, other_id: int, subset: np.ndarray, k: int):
        """As a search, from the database's matches of the pair: each matched keypoint's
        nearest matched candidate, in a single column (index 0 at an infinite angle for the
        others); within `subset`, its matched candidates there in k columns."""
        if (image_id, other_id) in self.matches:
            pairs = self.matches[(image_id, other_id)]
        else:
            pairs = self.matches.get((other_id, image_id), np.zeros((0, 2), np.int64))[:, ::-1]
        kps, other_kps = pairs[:, 0], pairs[:, 1].astype(np.int64)
        pair_angles = self.pair_angles(image_id, kps, other_id, other_kps)
        num_queries = self.num_keypoints[image_id]
        index, angles = nearest_candidates_each(num_queries, 1, kps, other_kps, pair_angles)
        position = np.full(self.num_keypoints[other_id], -1, np.int64)
        position[subset] = np.arange(len(subset))
        in_subset = position[other_kps] >= 0
        sub_index, sub_angles = nearest_candidates_each(
            num_queries, min(k, len(subset)), kps[in_subset], position[other_kps[in_subset]],
            pair_angles[in_subset])
        return index, angles, (sub_index, sub_angles)


def nearest_candidates_each(num_rows: int, columns: int, rows: np.ndarray, targets: np.ndarray,
                            angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Search results (index, angles), `columns` wide, that give each of `rows` (a row
    may come several times) its candidates `targets` at `angles`, nearest first, at most
    `columns` of them; every other place holds index 0 at an infinite angle, which no
    descriptor test passes."""
    index = np.zeros((num_rows, columns), np.int32)
    all_angles = np.full((num_rows, columns), np.inf, np.float32)
    if columns and len(rows):
        order = np.lexsort((angles, rows))
        rows, targets, angles = rows[order], targets[order], angles[order]
        rank = np.arange(len(rows)) - np.searchsorted(rows, rows)  # place within its row
        kept = rank < columns
        index[rows[kept], rank[kept]] = targets[kept]
        all_angles[rows[kept], rank[kept]] = angles[kept]
    return index, all_angles
