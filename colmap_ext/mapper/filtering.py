"""Filtering (paper, step 4e, "pruning"): observations no longer geometrically
compatible with their point go, then points without enough support or triangulation
angle (`filter_points`); at the end, images whose points leave their rotation poorly
determined (`filter_images`)."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import FilteringOptions

# An observation whose reprojection error exceeds this many times the model's median
# counts as an outlier in `errors_look_gaussian`.
OUTLIER_ERROR_RATIO = 3.0


def filter_points(model: Model, image_ids: list[int], filtering: FilteringOptions,
                  final: bool = False, max_error_ratio: float = 0.0) -> tuple[int, int]:
    """Filter the observations in `image_ids` and the points they see. Before the end
    (`final` False), points younger than the grace period may keep two-view tracks.

    An observation goes beyond `error_limit`: max_reproj_error_px or more where the
    keypoint noise reaches it, and with `max_error_ratio` no more than that many times
    the median error of these observations. Where keypoints are good to a few tenths of
    a pixel, an observation two pixels off is a near-miss match that still pulls on the
    poses under the robust loss; which of them a model holds depends on its run's RANSAC
    draws, and its poses did too.
    Returns (observations removed, points removed)."""
    observed = [(image_id, *_observation_errors(model, image_id)) for image_id in image_ids]
    all_errors = np.concatenate([errors for *_, errors in observed]) if observed else []
    limit = error_limit(filtering.max_reproj_error_px,
                        float(np.median(all_errors)) if len(all_errors) else np.inf,
                        filtering.noise_max_error_ratio, max_error_ratio)
    removed_observations = 0
    touched: set[int] = set()
    for image_id, kps, point_ids, errors in observed:
        # Read afresh where a deletion took a point of this image (of a two-image track).
        if (model.point_of[image_id][kps] != point_ids).any():
            kps, point_ids, errors = _observation_errors(model, image_id)
        touched.update(point_ids.tolist())
        for kp in kps[errors > limit].tolist():
            model.delete_observation(image_id, kp)
            removed_observations += 1
    candidates = [p for p in touched if model.has_point(p)]
    lengths, images = model.track_images(candidates)
    wide = has_triangulation_angle(model, candidates, lengths, images, filtering.min_tri_angle_deg)
    point_ids = np.array(candidates, np.int64)
    unsupported = ~_supported(model, point_ids, lengths, wide, filtering, final)
    for point_id in point_ids[unsupported].tolist():
        model.delete_point(point_id)
    return removed_observations, int(np.count_nonzero(unsupported))


def error_limit(max_error_px: float, median_error_px: float, noise_max_error_ratio: float,
                max_error_ratio: float = 0.0) -> float:
    """The reprojection error (px) beyond which an observation does not belong to its
    point: `max_error_px`, raised to `noise_max_error_ratio` x the median error where the
    keypoint noise reaches it (a threshold in pixels that the noise crosses drops true
    observations and splits tracks), lowered to `max_error_ratio` x the median where
    that is given and smaller."""
    limit = max(max_error_px, noise_max_error_ratio * median_error_px)
    if max_error_ratio > 0:
        limit = min(limit, max_error_ratio * median_error_px)
    return limit


def errors_look_gaussian(errors: np.ndarray, filtering: FilteringOptions) -> bool:
    """Whether reprojection errors look like Gaussian keypoint noise alone: at most
    FilteringOptions.gaussian_max_outlier_share of them beyond OUTLIER_ERROR_RATIO x their
    median (Gaussian noise puts 0.2 % there: the errors follow a Rayleigh distribution),
    where wrong or poorly localised matches put more; False if there are none."""
    if not len(errors):
        return False
    share = np.mean(errors > OUTLIER_ERROR_RATIO * np.median(errors))
    return bool(share <= filtering.gaussian_max_outlier_share)


def reprojection_errors(model: Model, image_ids: list[int]) -> np.ndarray:
    """The reprojection errors (px) of every observation in `image_ids`."""
    errors = [_observation_errors(model, image_id)[2] for image_id in image_ids]
    return np.concatenate(errors) if errors else np.zeros(0)


def _observation_errors(model: Model, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keypoints, point ids, reprojection errors in px) of an image's observations."""
    kps, point_ids = model.observations(image_id)
    return kps, point_ids, model.reprojection_errors(image_id, kps, model.xyz[point_ids])


def _supported(model: Model, point_ids: np.ndarray, track_lengths: np.ndarray,
               wide: np.ndarray, filtering: FilteringOptions, final: bool) -> np.ndarray:
    """Which points keep their place: two observations or more, min_track_length or more
    unless younger than the grace period (before the end), and a wide enough angle."""
    long_enough = track_lengths >= filtering.min_track_length
    if not final:  # young points keep shorter tracks
        long_enough |= model.num_registered - model.born[point_ids] < \
            filtering.track_grace_registrations
    return (track_lengths >= 2) & long_enough & wide


def has_triangulation_angle(model: Model, point_ids: list[int], lengths: np.ndarray,
                            images: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """Whether some two rays of each point's track meet at `min_angle_deg` or more; the
    tracks' lengths and images as Model.track_images gives them.

    Linear in the number of observations: with a_k the angle between ray k and a
    pivot ray, the widest pair is at least max(a_k) and at most 2 max(a_k) (triangle
    inequality). The first ray, then the ray farthest from it, serve as pivots; only
    the points both bounds leave undecided are compared pair by pair."""
    if not point_ids:
        return np.zeros(0, bool)
    observing = np.unique(images)  # the tracks' images alone: a sequence has thousands
    centres = np.zeros((int(observing[-1]) + 1, 3))
    centres[observing] = [model.centre(image_id) for image_id in observing.tolist()]
    rays = np.repeat(model.xyz[point_ids], lengths, axis=0) - centres[images]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    starts = np.cumsum(lengths) - lengths
    owner = np.repeat(np.arange(len(point_ids)), lengths)
    min_cos = np.cos(np.radians(min_angle_deg))
    wide = np.zeros(len(point_ids), bool)
    undecided = np.ones(len(point_ids), bool)
    pivot = starts
    for _ in range(2):
        cosines = np.einsum("ij,ij->i", rays, rays[pivot[owner]])
        farthest = np.minimum.reduceat(cosines, starts)  # cos of the widest angle to the pivot
        wide |= farthest <= min_cos
        undecided &= ~wide & (2 * np.arccos(np.clip(farthest, -1.0, 1.0))
                              >= np.radians(min_angle_deg))
        if not undecided.any():
            return wide
        order = np.lexsort((cosines, owner))  # within each point, the farthest ray first
        pivot = order[starts]
    for p in np.flatnonzero(undecided):
        track_rays = rays[starts[p]:starts[p] + lengths[p]]
        wide[p] = (track_rays @ track_rays.T).min() <= min_cos
    return wide


def filter_images(model: Model, filtering: FilteringOptions) -> list[int]:
    """Deregister the images whose observed points fix their rotation worse than
    `max_rotation_uncertainty` (see `rotation_uncertainty`); returns their ids.

    Run on a finished model: a weak image at the edge of a model (few points through a
    narrow field of view) can sit degrees off with every observation within a pixel,
    and nothing registered after it corrects it. Judged at the end, not at
    registration, an image that later images and joined models support is kept."""
    weak = []
    for image_id in model.registered:
        if model.frame_id(image_id) in model.fixed_frame_ids or \
                len(model.frame_images(image_id)) > 1:
            continue  # a rig's frame is posed by all its images together
        _, point_ids = model.observations(image_id)
        if rotation_uncertainty(model.pose(image_id), model.xyz[point_ids]) > \
                filtering.max_rotation_uncertainty:
            model.deregister(image_id)
            weak.append(image_id)
    return weak


def rotation_uncertainty(cam_from_world: pycolmap.Rigid3d, xyz: np.ndarray) -> float:
    """How poorly the points `xyz` fix the pose's rotation: the standard deviation of
    the rotation (radians, about its least determined axis, marginal over the
    translation) per radian of keypoint noise, the points taken as exact.

    Gauss-Newton on the angular reprojection errors (radians; each point's offset on
    the plane tangent to the unit sphere at its direction, as absolute_pose's
    refinement), for points in any direction: covariance (J^T J)^-1. Few inliers in a
    narrow field of view, or on a shallow scene, let a rotation trade off against a
    translation (bas-relief): the uncertainty grows, and so does any bias of the points."""
    pose = cam_from_world.matrix()
    rotated = xyz @ pose[:, :3].T
    x = rotated + pose[:, 3]
    distance = np.linalg.norm(x, axis=1)
    direction = x / distance[:, None]
    # d(tangent-plane offset)/dx at the point's own direction: B^T / |x|, with B an
    # orthonormal basis of the plane orthogonal to the direction.
    helper = np.where(np.abs(direction[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    tangent1 = np.cross(direction, helper)
    tangent1 /= np.linalg.norm(tangent1, axis=1, keepdims=True)
    tangent2 = np.cross(direction, tangent1)
    dproject = np.stack([tangent1, tangent2], axis=1) / distance[:, None, None]
    skew = np.zeros((len(x), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -rotated[:, 2], rotated[:, 1], -rotated[:, 0]
    skew -= skew.transpose(0, 2, 1)
    jacobian = np.concatenate([-dproject @ skew, dproject], axis=2)  # d(residual)/d(w, u)
    normal = np.einsum("nki,nkj->ij", jacobian, jacobian)
    try:
        covariance = np.linalg.inv(normal)[:3, :3]
    except np.linalg.LinAlgError:
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(covariance)[-1], 0.0)))
