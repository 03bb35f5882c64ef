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


def sampson_errors(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distances (normalized units) of (..., 2) point pairs under x2^T E x1 = 0."""
    h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], axis=-1)
    h2 = np.concatenate([x2, np.ones(x2.shape[:-1] + (1,))], axis=-1)
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    c = np.sum(h2 * Ex1, axis=-1)
    d = Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2 + Etx2[..., 0] ** 2 + Etx2[..., 1] ** 2
    return np.abs(c) / np.sqrt(np.maximum(d, 1e-30))


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

    Among each keypoint's `guided_num_neighbors` nearest descriptors in the other image,
    keep those within `max_descriptor_distance` and within the reprojection threshold
    of the epipolar line, and take the closest descriptor. Each keypoint of the other
    image is used at most once. Returns (kps, other_kps, descriptor angles).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(kps) == 0 or len(model.keypoints[other_id]) == 0:
        return empty
    index, angles = nearest_descriptors(model.descriptors[image_id][kps],
                                        model.descriptors[other_id],
                                        options.guided_num_neighbors)
    E = essential_matrix(model.poses[other_id], model.poses[image_id])
    x1 = np.broadcast_to(model.normalized[image_id][kps][:, None, :], index.shape + (2,))
    x2 = model.normalized[other_id][index]
    max_error = options.max_reproj_error_px / model.focal(image_id)
    ok = (angles <= options.max_descriptor_distance) & (sampson_errors(E, x1, x2) <= max_error)
    angles = np.where(ok, angles, np.inf)
    best = np.argmin(angles, axis=1)
    best_angle = angles[np.arange(len(kps)), best]
    found = np.isfinite(best_angle)
    kps, other, best_angle = kps[found], index[found, best[found]], best_angle[found]
    order = np.argsort(best_angle, kind="stable")
    _, first = np.unique(other[order], return_index=True)
    keep = order[first]
    return kps[keep], other[keep], best_angle[keep]
