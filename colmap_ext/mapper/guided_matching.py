"""Guided matching (paper, step 3c and 4c): features of two posed images that are
visually compatible (close descriptors) and geometrically compatible (on each
other's epipolar lines, with the poses the model already has)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.geometry import sampson_angles
from colmap_ext.mapper.descriptors import nearest_candidates_each
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import GuidedMatchingOptions


Partners = tuple[np.ndarray, np.ndarray]  # (rows into a keypoint array, other image's keypoints)


def compatible_features(model: Model, image_id: int, other_id: int, kps: np.ndarray,
                        guided: GuidedMatchingOptions, partners: Partners | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For keypoints `kps` of `image_id`, the best compatible keypoint in `other_id`.

    Compatible: among the keypoint's `num_neighbors` nearest descriptors, within
    `max_descriptor_distance`, and within the reprojection threshold of the epipolar
    line (angular Sampson error, against the threshold in pixels times the mean angle a
    pixel spans at the two keypoints). The closest such descriptor wins; each keypoint of the
    other image is used at most once. `partners` (verified_partners): a keypoint's verified
    matches are its candidates, and only the keypoints without one are searched.
    Returns (kps, other_kps, angles).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(kps) == 0 or len(model.keypoints[other_id]) == 0:
        return empty
    index, angles = _candidates(model, image_id, other_id, kps, partners)
    candidates = np.column_stack([np.repeat(kps, index.shape[1]), index.ravel()])
    on_epipolar_lines = epipolar_inliers(
        model, (image_id, other_id), candidates,
        model.pose(other_id) * model.pose(image_id).inverse(), guided.max_epipolar_error_px)
    compatible = on_epipolar_lines.reshape(index.shape) & \
        (angles <= guided.max_descriptor_distance)
    first = np.argmax(compatible, axis=1)  # nearest compatible descriptor
    rows = np.flatnonzero(compatible.any(axis=1))
    kps, other, angles = kps[rows], index[rows, first[rows]], angles[rows, first[rows]]
    order = np.argsort(angles, kind="stable")
    _, unique = np.unique(other[order], return_index=True)
    keep = order[unique]
    return kps[keep], other[keep], angles[keep]


def verified_partners(model: Model, image_id: int, kps: np.ndarray, matches: np.ndarray,
                      guided: GuidedMatchingOptions) -> Partners | None:
    """The pair's verified `matches` (keypoint of image_id, of the other image) from the
    distinct keypoints `kps`: (rows into kps, the other image's keypoints), every match of
    a keypoint matched more than once (a wrong match can pass verification beside the true
    one); None (search them all) unless guided.skip_search_verified_share of kps have one."""
    row_of = np.full(len(model.keypoints[image_id]), -1, np.int64)
    row_of[kps] = np.arange(len(kps))
    rows = row_of[matches[:, 0]]
    from_kps = rows >= 0
    rows, others = rows[from_kps], matches[from_kps, 1].astype(np.int64)
    if np.count_nonzero(np.bincount(rows, minlength=len(kps))) < \
            guided.skip_search_verified_share * len(kps):
        return None
    return rows, others


def _candidates(model: Model, image_id: int, other_id: int, kps: np.ndarray,
                partners: Partners | None) -> tuple[np.ndarray, np.ndarray]:
    """(index, angles) of the keypoints' candidates in the other image, nearest first:
    their nearest descriptors, or their verified partners (the other places at an
    infinite angle) with the nearest descriptors of those without one."""
    if partners is None:
        return model.nearest(image_id, other_id, kps)
    rows, others = partners
    index, angles = nearest_candidates_each(
        len(kps), model.nearest.k, rows, others,
        model.nearest.pair_angles(image_id, kps[rows], other_id, others))
    matched = np.zeros(len(kps), bool)
    matched[rows] = True
    if not matched.all():
        searched_index, searched_angles = model.nearest(image_id, other_id, kps[~matched])
        columns = searched_index.shape[1]
        index[~matched, :columns], angles[~matched, :columns] = searched_index, searched_angles
    return index, angles


def pair_pixel_angles(model: Model, id1: int, kps1: np.ndarray, id2: int,
                      kps2: np.ndarray) -> np.ndarray:
    """The mean angle (radians) a pixel spans at two corresponding keypoints: what a
    pixel threshold on a pair's epipolar error is multiplied by."""
    return 0.5 * (model.pixel_angles[id1][kps1] + model.pixel_angles[id2][kps2])


def epipolar_inliers(model: Model, pair: tuple[int, int], matches: np.ndarray,
                     cam2_from_cam1: pycolmap.Rigid3d, max_error_px: float) -> np.ndarray:
    """Whether each match (keypoint of pair[0], keypoint of pair[1]) lies within
    `max_error_px` of its epipolar lines under the relative pose `cam2_from_cam1`: its
    angular Sampson error against the threshold times the pair's pixel angle there
    (pair_pixel_angles). The one epipolar test of guided matching, the 5-point RANSAC's
    inliers, registration's epipolar check and a rig frame's matches."""
    id1, id2 = pair
    errors = sampson_angles(pycolmap.essential_matrix_from_pose(cam2_from_cam1),
                            model.rays[id1][matches[:, 0]], model.rays[id2][matches[:, 1]])
    return errors <= max_error_px * pair_pixel_angles(model, id1, matches[:, 0], id2,
                                                      matches[:, 1])
