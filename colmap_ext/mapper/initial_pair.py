"""The initial pair (paper, step 3): 5-point RANSAC for the relative pose, metric
triangulation of the consensus set, guided matching for more (see pipeline). Two
frames of a rig are related by the generalized relative pose of all their images'
matches (OpenGV), whose translation the rig makes metric. One frame of a rig whose
cameras have different centres is a stereo pair already: its images' matches
triangulate with the rig's own relative poses (a frame start)."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pycolmap

import solvers
from colmap_ext.errors import UserError
from colmap_ext.geometry import nearest_rotation, vector_angles_deg
from colmap_ext.mapper.guided_matching import epipolar_inliers, pair_pixel_angles
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import (InitializationOptions, TriangulationOptions,
                                       TwoViewOptions)
from colmap_ext.mapper.triangulation import (Tracks, shared_observation_groups,
                                              triangulate_points)
from colmap_ext.mapper.two_view import Pair, relative_pose

# Pairs reconstructed at each angle the mapper tries (best_pair); frames tried, those
# with most verified matches between their images.
MAX_CANDIDATE_PAIRS = 40
MAX_CANDIDATE_FRAMES = 40
# A pair is a candidate at an angle where its parallax (parallax_deg, the median over
# all its matches) reaches this share of it: the angle it must reach is the median over
# the points that triangulate well, which leave out the narrowest.
PARALLAX_SHARE = 0.75
# Matches per pair whose relative pose gives its parallax (parallax_deg).
PARALLAX_SAMPLE = 64


@dataclass
class TwoViewReconstruction:
    pair: Pair
    cam2_from_cam1: pycolmap.Rigid3d
    matches: np.ndarray  # (n, 2) matches that triangulate well
    xyz: np.ndarray  # (n, 3) their points, in camera 1's frame
    median_angle_deg: float
    # The frames' relative pose where one of them has several images (a rig's).
    rig2_from_rig1: pycolmap.Rigid3d | None = None


@dataclass
class FrameReconstruction:
    """One frame of a rig, its images' matches triangulated with the rig's relative poses."""

    image_id: int  # an image of the frame
    tracks: list[dict[int, int]]  # each point's observations: image id -> keypoint
    xyz: np.ndarray  # (n, 3) their points, in the rig's frame


def reconstruct_pair(model: Model, pair: Pair, matches: np.ndarray,
                     initialization: InitializationOptions, two_view: TwoViewOptions,
                     triangulation: TriangulationOptions,
                     seed: int | None) -> TwoViewReconstruction | None:
    """Relative pose and triangulated consensus set of a pair, or None if it is weak.
    `seed`: the RANSAC's (None: unseeded)."""
    id1, id2 = pair
    result = relative_pose(model, pair, matches, two_view.max_error_px,
                           initialization.min_num_inliers, seed)
    if result is None:
        return None
    inliers = matches[result.inlier_mask]
    identity = pycolmap.Rigid3d()
    xyz, valid = solvers.triangulate(identity, result.cam2_from_cam1, model.rays[id1][inliers[:, 0]],
                                     model.rays[id2][inliers[:, 1]],
                                     min_angle_deg=triangulation.min_tri_angle_deg)
    if valid.sum() < initialization.min_num_inliers:
        return None
    xyz, inliers = xyz[valid], inliers[valid]
    centre2 = result.cam2_from_cam1.inverse().translation
    ray1 = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    ray2 = (xyz - centre2) / np.linalg.norm(xyz - centre2, axis=1, keepdims=True)
    angles = np.degrees(np.arccos(np.clip(np.sum(ray1 * ray2, axis=1), -1, 1)))
    return TwoViewReconstruction(pair, result.cam2_from_cam1, inliers, xyz,
                                 float(np.median(angles)))


def reconstruct_frame(model: Model, image_id: int, matches: dict[Pair, np.ndarray],
                      two_view: TwoViewOptions,
                      triangulation: TriangulationOptions) -> FrameReconstruction:
    """The points of the frame of `image_id`, in its rig's frame: its tracks
    (_frame_tracks) triangulated with the rig's poses and kept by the triangulation's
    rule (triangulate_points)."""
    image_ids = model.frame_images(image_id)
    cams_from_rig = {i: model.cam_from_rig(i) for i in image_ids}
    tracks = _frame_tracks(model, cams_from_rig, matches, two_view)
    if not tracks:
        return FrameReconstruction(image_id, [], np.zeros((0, 3)))
    xyz, ok = triangulate_points(model, Tracks.of(tracks), triangulation, cams_from_rig)
    return FrameReconstruction(image_id, [track for track, keep in zip(tracks, ok) if keep],
                               xyz[ok])


def _frame_tracks(model: Model, cams_from_rig: dict[int, pycolmap.Rigid3d],
                  matches: dict[Pair, np.ndarray],
                  two_view: TwoViewOptions) -> list[dict[int, int]]:
    """The tracks of one frame's images (image id -> its pose in the rig): the verified
    matches between two of them at different centres that lie within
    two_view.max_error_px of their epipolar lines under the rig's relative pose (the
    5-point RANSAC's inlier test), joined where they share a keypoint; a track holding
    two keypoints of one image is left out."""
    images, keypoints = [], []  # of each consistent match's two observations, in turn
    for id1, id2 in itertools.combinations(sorted(cams_from_rig), 2):
        pair_matches = matches.get((id1, id2))
        cam1_from_rig, cam2_from_rig = cams_from_rig[id1], cams_from_rig[id2]
        if pair_matches is None or np.array_equal(cam1_from_rig.inverse().translation,
                                                  cam2_from_rig.inverse().translation):
            continue
        consistent = pair_matches[epipolar_inliers(
            model, (id1, id2), pair_matches, cam2_from_rig * cam1_from_rig.inverse(),
            two_view.max_error_px)]
        images.append(np.tile([id1, id2], len(consistent)))
        keypoints.append(consistent.ravel())
    if not images:
        return []
    images, keypoints = np.concatenate(images), np.concatenate(keypoints)
    match_index = np.arange(len(images)) // 2
    group = shared_observation_groups(match_index, images, keypoints, len(images) // 2)
    tracks: dict[int, dict[int, int]] = {}
    conflicting = set()
    for label, image, keypoint in zip(group[match_index].tolist(), images.tolist(),
                                      keypoints.tolist()):
        if tracks.setdefault(label, {}).setdefault(image, keypoint) != keypoint:
            conflicting.add(label)
    return [track for label, track in tracks.items() if label not in conflicting]


def choose_initial_pair(model: Model, matches: dict[Pair, np.ndarray],
                        initialization: InitializationOptions, two_view: TwoViewOptions,
                        triangulation: TriangulationOptions, excluded: set[Pair],
                        seed: int | None
                        ) -> TwoViewReconstruction | FrameReconstruction | None:
    """The requested pair, or the mapper's choice: the best pair (best_pair), unless the
    frame of a rig whose images' matches triangulate into most points (reconstruct_frame)
    gives more, and at least initialization.min_num_inliers. A pair that fails joins
    `excluded`. `seed`: the RANSAC's (None: unseeded)."""
    if initialization.image_id1 >= 0 or initialization.image_id2 >= 0:
        return _requested_pair(model, matches, initialization, two_view, triangulation, seed)
    pair = best_pair(model, matches, initialization, two_view, triangulation, excluded, seed)
    frames = [reconstruct_frame(model, image_ids[0], matches, two_view, triangulation)
              for image_ids in _candidate_frames(model, matches)]
    frame = max(frames, key=lambda frame: len(frame.tracks), default=None)
    if frame is None or len(frame.tracks) < initialization.min_num_inliers:
        return pair
    return frame if pair is None or len(frame.tracks) > len(pair.matches) else pair


def _candidate_frames(model: Model, matches: dict[Pair, np.ndarray]) -> list[list[int]]:
    """The images of the model's frames with most verified matches between their images
    (at most MAX_CANDIDATE_FRAMES frames, each with some)."""
    frame_of = {image_id: model.frame_id(image_id) for image_id in model.image_ids}
    within: dict[int, int] = {}  # frame id -> verified matches between its images
    for (id1, id2), pair_matches in matches.items():
        if frame_of[id1] == frame_of[id2]:
            within[frame_of[id1]] = within.get(frame_of[id1], 0) + len(pair_matches)
    best = sorted(within, key=lambda frame_id: -within[frame_id])[:MAX_CANDIDATE_FRAMES]
    return [[image_id for image_id in model.image_ids if frame_of[image_id] == frame_id]
            for frame_id in best]


def best_pair(model: Model, matches: dict[Pair, np.ndarray],
              initialization: InitializationOptions, two_view: TwoViewOptions,
              triangulation: TriangulationOptions, excluded: set[Pair],
              seed: int | None) -> TwoViewReconstruction | None:
    """The best-conditioned pair of images of two frames: most well-triangulated points
    among the pairs whose median triangulation angle reaches
    initialization.min_tri_angle_deg. Every verified pair is a candidate, ranked before
    it is reconstructed: at each angle, the MAX_CANDIDATE_PAIRS pairs with most matches
    among those whose parallax (parallax_deg) reaches PARALLAX_SHARE of it are
    reconstructed. On a sequence the pairs with most matches are neighbours without
    parallax; on an object most are wide, and these are the pairs with most matches
    (as before the parallax was asked). As COLMAP relaxes
    its initialization, the angle halves while no pair reaches it, down to
    triangulation.min_tri_angle_deg. A pair that fails joins `excluded`. `seed`: the
    RANSAC's (None: unseeded)."""
    ranked = sorted((pair for pair, m in matches.items()
                     if len(m) >= initialization.min_num_inliers and pair not in excluded
                     and model.frame_id(pair[0]) != model.frame_id(pair[1])),
                    key=lambda pair: -len(matches[pair]))
    parallax: dict[Pair, float] = {}  # of the pairs ranked[:len(parallax)]
    reconstructed: dict[Pair, TwoViewReconstruction] = {}
    min_angle = initialization.min_tri_angle_deg
    while True:
        # The pairs with most matches among the wide enough, their parallax found in
        # rank order as far as it takes: on an object, a few more than
        # MAX_CANDIDATE_PAIRS; on a sequence, every pair.
        candidates = [pair for pair in parallax if pair not in excluded
                      and parallax[pair] >= PARALLAX_SHARE * min_angle]
        for pair in ranked[len(parallax):]:
            if len(candidates) >= MAX_CANDIDATE_PAIRS:
                break
            parallax[pair] = parallax_deg(model, pair, matches[pair], two_view, seed)
            if parallax[pair] >= PARALLAX_SHARE * min_angle:
                candidates.append(pair)
        candidates = candidates[:MAX_CANDIDATE_PAIRS]
        for pair in candidates:
            if pair in reconstructed:
                continue
            candidate = reconstruct_pair(model, pair, matches[pair], initialization, two_view,
                                         triangulation, seed)
            if candidate is None:
                excluded.add(pair)
            else:
                reconstructed[pair] = candidate
        wide = [candidate for candidate in reconstructed.values()
                if candidate.median_angle_deg >= min_angle]
        # Most points first; a rig's frames must also give their relative pose
        # (with_frames), asked of one candidate at a time: it is the costly step.
        for candidate in sorted(wide, key=lambda candidate: -len(candidate.matches)):
            framed = with_frames(model, candidate, matches, initialization, two_view, seed)
            if framed is not None:
                return framed
            excluded.add(candidate.pair)
            del reconstructed[candidate.pair]
        if min_angle / 2 < triangulation.min_tri_angle_deg:
            return None
        min_angle /= 2


def parallax_deg(model: Model, pair: Pair, matches: np.ndarray, two_view: TwoViewOptions,
                 seed: int | None) -> float:
    """The median triangulation angle of a pair's matches, over at most PARALLAX_SAMPLE of
    them: a match's angle is that between its two rays in one frame, which the relative
    rotation alone gives (that of a 5-point RANSAC on the sample). Where one rotation
    aligns the rays within two_view.max_error_px (orthogonal Procrustes; a standstill or
    a camera turning on the spot), the relative pose is undetermined and the parallax is
    what that rotation leaves. Cheap enough to rank every verified pair before any is
    reconstructed."""
    sample = matches[np.linspace(0, len(matches) - 1, min(len(matches), PARALLAX_SAMPLE))
                     .astype(np.int64)]
    rays1 = model.rays[pair[0]][sample[:, 0]]
    rays2 = model.rays[pair[1]][sample[:, 1]]
    rotation_only = np.median(vector_angles_deg(rays1, rays2 @ nearest_rotation(rays2.T @ rays1)))
    noise = np.degrees(two_view.max_error_px * np.median(
        pair_pixel_angles(model, pair[0], sample[:, 0], pair[1], sample[:, 1])))
    if rotation_only <= noise:
        return float(rotation_only)
    result = relative_pose(model, pair, sample, two_view.max_error_px, min_num_inliers=5,
                           seed=seed)
    if result is None:
        return 0.0
    inliers = result.inlier_mask
    return float(np.median(vector_angles_deg(
        rays1[inliers], rays2[inliers] @ result.cam2_from_cam1.rotation.matrix())))


def check_requested_pair(image_ids: Iterable[int], initialization: InitializationOptions) -> None:
    """A UserError unless each requested initial image is one of `image_ids`."""
    for image_id in (initialization.image_id1, initialization.image_id2):
        if image_id >= 0 and image_id not in image_ids:
            raise UserError(f"--Mapper.init_image_id1/2: no image with id {image_id} in the database")


def _requested_pair(model: Model, matches: dict[Pair, np.ndarray],
                    initialization: InitializationOptions, two_view: TwoViewOptions,
                    triangulation: TriangulationOptions, seed: int | None
                    ) -> TwoViewReconstruction | FrameReconstruction:
    """The requested pair; two images of one frame of a rig request a frame start."""
    id1, id2 = initialization.image_id1, initialization.image_id2
    check_requested_pair(model.db.images, initialization)
    key = (min(id1, id2), max(id1, id2))
    if key not in matches:
        raise UserError(f"initial images {id1} and {id2} have no verified matches")
    if model.frame_id(id1) == model.frame_id(id2):
        frame = reconstruct_frame(model, id1, matches, two_view, triangulation)
        if len(frame.tracks) < initialization.min_num_inliers:
            raise UserError(f"initial images {id1} and {id2} are of one frame of a rig, whose "
                            f"cameras' matches give {len(frame.tracks)} well-triangulated "
                            f"points with the rig's baseline (fewer than "
                            f"--Mapper.init_min_num_inliers {initialization.min_num_inliers})")
        return frame
    requested = _reconstruct_frames(model, key, matches, initialization, two_view,
                                    triangulation, seed)
    if requested is None:
        raise UserError(f"initial images {id1} and {id2} do not give a relative pose "
                        f"with enough well-triangulated points")
    return requested


def _reconstruct_frames(model: Model, pair: Pair, matches: dict[Pair, np.ndarray],
                        initialization: InitializationOptions, two_view: TwoViewOptions,
                        triangulation: TriangulationOptions,
                        seed: int | None) -> TwoViewReconstruction | None:
    """The pair reconstructed (reconstruct_pair), with its frames' relative pose where
    they are a rig's (with_frames); None where either fails."""
    reconstructed = reconstruct_pair(model, pair, matches[pair], initialization, two_view,
                                     triangulation, seed)
    if reconstructed is None:
        return None
    return with_frames(model, reconstructed, matches, initialization, two_view, seed)


def with_frames(model: Model, reconstructed: TwoViewReconstruction,
                matches: dict[Pair, np.ndarray], initialization: InitializationOptions,
                two_view: TwoViewOptions, seed: int | None) -> TwoViewReconstruction | None:
    """The pair as it is where each image is alone in its frame; else with its frames'
    generalized relative pose from the verified matches between all their images, or
    None where that fails."""
    id1, id2 = reconstructed.pair
    images1, images2 = model.frame_images(id1), model.frame_images(id2)
    if len(images1) == 1 and len(images2) == 1:
        return reconstructed
    rays1, rays2, index1, index2, max_errors = [], [], [], [], []
    for k1, a in enumerate(images1):
        for k2, b in enumerate(images2):
            pair_matches = matches.get((a, b)) if a < b else matches.get((b, a))
            if pair_matches is None:
                continue
            kps_a, kps_b = (pair_matches[:, 0], pair_matches[:, 1]) if a < b else \
                (pair_matches[:, 1], pair_matches[:, 0])
            rays1.append(model.rays[a][kps_a])
            rays2.append(model.rays[b][kps_b])
            index1.append(np.full(len(kps_a), k1))
            index2.append(np.full(len(kps_b), len(images1) + k2))
            max_errors.append(two_view.max_error_px *
                              pair_pixel_angles(model, a, kps_a, b, kps_b))
    cams_from_rig = [model.cam_from_rig(i) for i in images1 + images2]
    try:
        result = solvers.generalized_relative_pose(
            np.concatenate(rays1), np.concatenate(index1), np.concatenate(rays2),
            np.concatenate(index2), cams_from_rig, max_error=np.concatenate(max_errors),
            min_num_inliers=initialization.min_num_inliers, seed=seed)
    except (solvers.EstimationError, ValueError):
        return None
    return dataclasses.replace(reconstructed, rig2_from_rig1=result.rig2_from_rig1)


def initialize(model: Model, start: TwoViewReconstruction | FrameReconstruction) -> list[int]:
    """Register the pair (camera 1 at the origin, unit baseline) and add its points; a
    rig's frames (frame 1 at the origin, the rig's metric baseline) without points; a
    frame start (the frame at the origin) with its points. Returns the images the
    pipeline triangulates next against every registered one."""
    if isinstance(start, FrameReconstruction):
        model.register_frame(start.image_id, pycolmap.Rigid3d())
        _add_points(model, start.tracks, start.xyz)
        return model.frame_images(start.image_id)
    id1, id2 = start.pair
    if start.rig2_from_rig1 is not None:
        model.register_frame(id1, pycolmap.Rigid3d())
        model.register_frame(id2, start.rig2_from_rig1)
    else:
        model.register(id1, pycolmap.Rigid3d())
        model.register(id2, start.cam2_from_cam1)
        _add_points(model, [{id1: kp1, id2: kp2} for kp1, kp2 in start.matches.tolist()],
                    start.xyz)
    return model.frame_images(id2)


def _add_points(model: Model, tracks: list[dict[int, int]], xyz: np.ndarray) -> None:
    """Add the points whose keypoints observe none yet (a keypoint joins one point)."""
    for track, point in zip(tracks, xyz):
        if all(model.point_of[image_id][kp] < 0 for image_id, kp in track.items()):
            model.add_point(point, track)
