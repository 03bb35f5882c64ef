"""Guided matching (paper, step 3c and 4c): features of two posed images that are
visually compatible (close descriptors) and geometrically compatible (on each
other's epipolar lines, with the poses the model already has)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions


def essential_matrix(cam2_from_world: pycolmap.Rigid3d,
                     cam1_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """E with x2^T E x1 = 0 between two posed cameras (COLMAP's convention)."""
    cam2_from_cam1 = cam2_from_world * cam1_from_world.inverse()
    t = cam2_from_cam1.translation
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return skew @ cam2_from_cam1.rotation.matrix()


def nearest_descriptors(queries: np.ndarray, database: np.ndarray,
                        k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (q, k) of the k nearest unit descriptors and their angles (radians)."""
    k = min(k, len(database))
    similarity = queries @ database.T
    if k < len(database):
        index = np.argpartition(-similarity, k - 1, axis=1)[:, :k]
    else:
        index = np.broadcast_to(np.arange(len(database)), (len(queries), k))
    angles = np.arccos(np.clip(np.take_along_axis(similarity, index, axis=1), -1.0, 1.0))
    return index, angles


def compatible_features(model: Model, image_id: int, other_id: int, kps: np.ndarray,
                        options: MapperOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For keypoints `kps` of `image_id`, the best compatible keypoint in `other_id`.

    Compatible: among the keypoint's `guided_num_neighbors` nearest descriptors, within
    `max_descriptor_distance`, and within the reprojection threshold of the epipolar
    line. The closest such descriptor wins; each keypoint of the other image is used at
    most once. Instead of sorting every row for its k nearest, the best geometrically
    compatible candidate is found first and kept when fewer than k descriptors are
    closer: the same rule at a fraction of the cost. Returns (kps, other_kps, angles).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(kps) == 0 or len(model.keypoints[other_id]) == 0:
        return empty
    similarity = model.descriptors[image_id][kps] @ model.descriptors[other_id].T
    E = essential_matrix(model.poses[other_id], model.poses[image_id])
    max_error = options.max_reproj_error_px / model.focal(image_id)
    on_line = epipolar_mask(E, model.normalized[image_id][kps], model.normalized[other_id],
                            max_error)
    candidate = np.where(on_line, similarity, -np.inf)
    best = np.argmax(candidate, axis=1)
    rows = np.arange(len(kps))
    best_similarity = candidate[rows, best]
    rank = np.count_nonzero(similarity > best_similarity[:, None], axis=1)
    angles = np.arccos(np.clip(best_similarity, -1.0, 1.0))
    found = np.isfinite(best_similarity) & (rank < options.guided_num_neighbors) & \
        (angles <= options.max_descriptor_distance)
    kps, other, angles = kps[found], best[found], angles[found]
    order = np.argsort(angles, kind="stable")
    _, first = np.unique(other[order], return_index=True)
    keep = order[first]
    return kps[keep], other[keep], angles[keep]


def epipolar_mask(E: np.ndarray, x1: np.ndarray, x2: np.ndarray, max_error: float) -> np.ndarray:
    """(n1, n2) mask of point pairs within Sampson distance `max_error` of x2^T E x1 = 0."""
    h1 = np.hstack([x1, np.ones((len(x1), 1))]).astype(np.float32)
    h2 = np.hstack([x2, np.ones((len(x2), 1))]).astype(np.float32)
    lines2 = h1 @ E.T.astype(np.float32)  # epipolar lines in image 2 of image 1's points
    lines1 = h2 @ E.astype(np.float32)    # and in image 1 of image 2's points
    residual = lines2 @ h2.T
    denominator = (lines2[:, 0] ** 2 + lines2[:, 1] ** 2)[:, None] + \
        (lines1[:, 0] ** 2 + lines1[:, 1] ** 2)[None, :]
    return residual * residual <= np.float32(max_error ** 2) * denominator
