"""Guided matching (paper, step 3c and 4c): features of two posed images that are
visually compatible (close descriptors) and geometrically compatible (on each
other's epipolar lines, with the poses the model already has)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.geometry import sampson_angles
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions


def compatible_features(model: Model, image_id: int, other_id: int, kps: np.ndarray,
                        guided: GuidedMatchingOptions
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For keypoints `kps` of `image_id`, the best compatible keypoint in `other_id`.

    Compatible: among the keypoint's `num_neighbors` nearest descriptors, within
    `max_descriptor_distance`, and within the reprojection threshold of the epipolar
    line (angular Sampson error, against the threshold in pixels times the mean angle a
    pixel spans at the two keypoints). The closest such descriptor wins; each keypoint of the
    other image is used at most once. Returns (kps, other_kps, angles).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(kps) == 0 or len(model.keypoints[other_id]) == 0:
        return empty
    index, angles = model.nearest(image_id, other_id)
    index, angles = index[kps], angles[kps]
    E = pycolmap.essential_matrix_from_pose(model.pose(other_id) * model.pose(image_id).inverse())
    repeated = np.repeat(kps, index.shape[1])
    max_errors = guided.max_epipolar_error_px * pair_pixel_angles(
        model, image_id, repeated, other_id, index.ravel())
    errors = sampson_angles(E, model.rays[image_id][repeated], model.rays[other_id][index.ravel()])
    compatible = (errors <= max_errors).reshape(index.shape) & \
        (angles <= guided.max_descriptor_distance)
    first = np.argmax(compatible, axis=1)  # nearest compatible descriptor
    rows = np.flatnonzero(compatible.any(axis=1))
    kps, other, angles = kps[rows], index[rows, first[rows]], angles[rows, first[rows]]
    order = np.argsort(angles, kind="stable")
    _, unique = np.unique(other[order], return_index=True)
    keep = order[unique]
    return kps[keep], other[keep], angles[keep]


def pair_pixel_angles(model: Model, id1: int, kps1: np.ndarray, id2: int,
                      kps2: np.ndarray) -> np.ndarray:
    """The mean angle (radians) a pixel spans at two corresponding keypoints: what a
    pixel threshold on a pair's epipolar error is multiplied by."""
    return 0.5 * (model.pixel_angles[id1][kps1] + model.pixel_angles[id2][kps2])
