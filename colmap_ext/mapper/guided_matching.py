"""Guided matching (paper, step 3c and 4c): features of two posed images that are
visually compatible (close descriptors) and geometrically compatible (on each
other's epipolar lines, with the poses the model already has)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.geometry import sampson_errors
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
