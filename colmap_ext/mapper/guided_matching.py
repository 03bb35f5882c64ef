"""Guided matching (paper, step 3c and 4c): features of two posed images that are
visually compatible (close descriptors) and geometrically compatible (on each
other's epipolar lines, with the poses the model already has)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions


def compatible_features(model: Model, image_id: int, other_id: int, kps: np.ndarray,
                        options: MapperOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For keypoints `kps` of `image_id`, the best compatible keypoint in `other_id`.

    Compatible: among the keypoint's `guided_num_neighbors` nearest descriptors, within
    `max_descriptor_distance`, and within the reprojection threshold of the epipolar
    line (Sampson distance). The closest such descriptor wins; each keypoint of the
    other image is used at most once. Returns (kps, other_kps, angles).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(kps) == 0 or len(model.keypoints[other_id]) == 0:
        return empty
    index, angles = model.nearest(image_id, other_id)
    index, angles = index[kps], angles[kps]
    E = pycolmap.essential_matrix_from_pose(model.poses[other_id] *
                                            model.poses[image_id].inverse())
    max_error = options.guided_matching.max_epipolar_error_px / model.focal(image_id)
    x1 = np.repeat(model.normalized[image_id][kps], index.shape[1], axis=0)
    errors = sampson_errors(E, x1, model.normalized[other_id][index.ravel()])
    compatible = (errors.reshape(index.shape) <= max_error) & \
        (angles <= options.guided_matching.max_descriptor_distance)
    first = np.argmax(compatible, axis=1)  # nearest compatible descriptor
    rows = np.flatnonzero(compatible.any(axis=1))
    kps, other, angles = kps[rows], index[rows, first[rows]], angles[rows, first[rows]]
    order = np.argsort(angles, kind="stable")
    _, unique = np.unique(other[order], return_index=True)
    keep = order[unique]
    return kps[keep], other[keep], angles[keep]


def sampson_errors(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance of corresponding normalized points to x2^T E x1 = 0."""
    h1 = np.hstack([x1, np.ones((len(x1), 1))])
    h2 = np.hstack([x2, np.ones((len(x2), 1))])
    lines2 = h1 @ E.T  # epipolar lines in image 2 of image 1's points
    lines1 = h2 @ E    # and in image 1 of image 2's points
    residual = np.einsum("ij,ij->i", lines2, h2)
    denominator = lines2[:, 0] ** 2 + lines2[:, 1] ** 2 + lines1[:, 0] ** 2 + lines1[:, 1] ** 2
    return np.abs(residual) / np.sqrt(np.maximum(denominator, 1e-300))
