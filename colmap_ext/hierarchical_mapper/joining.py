"""Joining cluster models: the similarity of two models from the images they share, a
maximum spanning tree of those links per group of models, and one reconstruction of each
group."""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.database import DatabaseContents
from colmap_ext.geometry import (fit_similarity, mean_rotation, rotation_angles_deg,
                                 vector_angles_deg)
from colmap_ext.hierarchical_mapper.clusters import ClusterModel
from colmap_ext.hierarchical_mapper.options import HierarchicalOptions
from colmap_ext.mapper.model import database_reconstruction
from colmap_ext.mapper.triangulation import shared_observation_groups


def similarity(target: ClusterModel, source: ClusterModel,
               options: HierarchicalOptions) -> tuple[pycolmap.Sim3d, int] | None:
    """target_from_source and the number of shared images that agree on it, or None.

    Each shared image's two rotations imply the similarity's rotation; the start is the
    mean of those that agree, within merge_max_angle_deg, with the image most others
    agree with. Under it, scale and translation come from the centres, robustly: the
    median ratio of the distances between two images in either model, and the median
    offset. An image agrees when, moved by the similarity, its rotation and its
    direction from the centre of the overlap are within merge_max_angle_deg of the
    target's, and its centre within max_centre_error of the overlap's extent. The
    agreeing images then give the similarity again (the mean of their rotations, the
    least-squares fit of their centres under it); the images that agree with that one
    are the answer's.

    The rotation comes from the cameras because the centres fix it poorly where they are
    nearly collinear, as on a walk or along a sequence (about the line they lie on): a
    start from the centres alone can disagree with every image's rotation there, and a
    wrong rotation at a junction is a bend that the final adjustment straightens only
    slowly."""
    shared, in_target, in_source = np.intersect1d(target.image_ids, source.image_ids,
                                                  return_indices=True)
    if len(shared) < options.min_shared_images:
        return None
    target_poses = target.cams_from_world[in_target]
    source_poses = source.cams_from_world[in_source]
    centres_target = target.centres()[in_target]
    centres_source = source.centres()[in_source]
    extent = np.sqrt(np.mean(np.sum((centres_target - centres_target.mean(0)) ** 2, axis=1)))
    if extent <= 0:
        return None
    # target_from_source's rotation as each shared image implies it: R_target^T @ R_source.
    implied = np.transpose(target_poses[:, :, :3], (0, 2, 1)) @ source_poses[:, :, :3]
    between = np.einsum("iba,jbc->ijac", implied, implied).reshape(-1, 3, 3)
    close = rotation_angles_deg(between).reshape(len(shared), -1) <= options.merge_max_angle_deg
    start = close[np.argmax(close.sum(axis=1))]
    target_from_source = robust_similarity(centres_source[start], centres_target[start],
                                           mean_rotation(implied[start]))
    if target_from_source is None:
        return None

    def agreeing(target_from_source: pycolmap.Sim3d) -> np.ndarray:
        moved = target_from_source * centres_source
        # cam_from_target of each shared image, through the source: R_source @ R^T.
        through_source = source_poses[:, :, :3] @ target_from_source.rotation.matrix().T
        rotation_error = rotation_angles_deg(
            np.transpose(target_poses[:, :, :3], (0, 2, 1)) @ through_source)
        middle = centres_target.mean(axis=0)
        direction_error = vector_angles_deg(centres_target - middle, moved - middle)
        centre_error = np.linalg.norm(moved - centres_target, axis=1) / extent
        return (rotation_error <= options.merge_max_angle_deg) & \
            (direction_error <= options.merge_max_angle_deg) & \
            (centre_error <= options.max_centre_error)

    for _ in range(2):
        agree = agreeing(target_from_source)
        if agree.sum() < options.min_shared_images:
            return None
        target_from_source = fit_similarity(centres_source[agree], centres_target[agree],
                                            mean_rotation(implied[agree]))
    return target_from_source, int(agree.sum())


def robust_similarity(source: np.ndarray, target: np.ndarray,
                      rotation: np.ndarray) -> pycolmap.Sim3d | None:
    """The similarity with `rotation` taking `source` points (n,3) onto `target`, its scale
    the median ratio of the distances between two points, its translation the median
    offset: neither moved by a minority of wrong points. None where no two source
    points are apart."""
    distances_source = np.linalg.norm(source[:, None] - source[None], axis=2)
    distances_target = np.linalg.norm(target[:, None] - target[None], axis=2)
    apart = np.triu(distances_source > 0, k=1)
    if not apart.any():
        return None
    scale = float(np.median(distances_target[apart] / distances_source[apart]))
    translation = np.median(target - scale * source @ rotation.T, axis=0)
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), translation)


def spanning_trees(models: list[ClusterModel], options: HierarchicalOptions
                   ) -> list[dict[int, pycolmap.Sim3d]]:
    """Groups of models that join: per group, model index -> root_from_model, along a
    maximum spanning tree of the agreeing shared images; the largest model of each
    group is its root. Largest groups first."""
    links: dict[int, dict[int, tuple[pycolmap.Sim3d, int]]] = {i: {} for i in range(len(models))}
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            found = similarity(models[a], models[b], options)
            if found is not None:
                links[a][b] = found
                links[b][a] = (found[0].inverse(), found[1])
    unvisited = set(range(len(models)))
    groups = []
    while unvisited:
        root = max(unvisited, key=lambda i: (len(models[i].image_ids), -i))
        placed = {root: pycolmap.Sim3d()}
        unvisited.discard(root)
        while True:  # Prim: the strongest link from the tree to a model outside it
            candidates = [(support, -outside, inside, outside)
                          for inside in placed for outside, (_, support) in links[inside].items()
                          if outside in unvisited]
            if not candidates:
                break
            _, _, inside, outside = max(candidates)
            placed[outside] = placed[inside] * links[inside][outside][0]
            unvisited.discard(outside)
        groups.append(placed)
    return sorted(groups, key=lambda g: -len({i for m in g for i in models[m].image_ids}))


def join(db: DatabaseContents, models: list[ClusterModel],
         root_from_model: dict[int, pycolmap.Sim3d]) -> pycolmap.Reconstruction:
    """One reconstruction of a group: each frame posed by the model that observes most
    through one of its images; points that share an observation (image, keypoint) merged into one, at
    the mean of their positions, keeping one keypoint per image (the first model's)."""
    pose_of: dict[int, tuple[int, pycolmap.Rigid3d]] = {}
    for m, sim in root_from_model.items():
        counts = models[m].observations_per_image()
        for image_id, matrix in zip(models[m].image_ids.tolist(), models[m].cams_from_world):
            support = counts.get(image_id, 0)
            if image_id not in pose_of or support > pose_of[image_id][0]:
                pose_of[image_id] = (support, sim.transform_camera_world(pycolmap.Rigid3d(matrix)))
    reconstruction = database_reconstruction(db, pose_of)
    for image_id in sorted(pose_of, key=lambda i: -pose_of[i][0]):
        image = reconstruction.images[image_id]
        if not image.has_pose:
            reconstruction.frames[image.frame_id].set_cam_from_world(image.camera_id,
                                                                     pose_of[image_id][1])
            reconstruction.register_frame(image.frame_id)
    # Every model's points in the root's frame, numbered globally, and their observations.
    group = list(root_from_model)
    xyz = np.concatenate([np.zeros((0, 3))] + [root_from_model[m] * models[m].xyz
                                               for m in group if len(models[m].xyz)])
    offsets = np.cumsum([0] + [len(models[m].xyz) for m in group])
    point = np.concatenate([models[m].track_point + offset for m, offset in zip(group, offsets)])
    image = np.concatenate([models[m].track_image for m in group])
    keypoint = np.concatenate([models[m].track_keypoint for m in group])
    merged = shared_observation_groups(point, image, keypoint, len(xyz))
    # One keypoint per image and merged point: the first observation's.
    owner = merged[point]
    _, first = np.unique(owner * (image.max(initial=0) + 1) + image, return_index=True)
    first.sort()
    owner, image, keypoint = owner[first], image[first], keypoint[first]
    observed = np.zeros(len(xyz), bool)
    observed[point] = True
    sums = np.zeros_like(xyz)
    np.add.at(sums, merged[observed], xyz[observed])
    members = np.bincount(merged[observed], minlength=len(xyz))
    order = np.argsort(owner, kind="stable")
    owners, starts, lengths = np.unique(owner[order], return_index=True, return_counts=True)
    elements = [pycolmap.TrackElement(i, k) for i, k in zip(image[order].tolist(),
                                                           keypoint[order].tolist())]
    for owner_id, start, length in zip(owners.tolist(), starts.tolist(), lengths.tolist()):
        if length >= 2:
            reconstruction.add_point3D(sums[owner_id] / members[owner_id],
                                       pycolmap.Track(elements[start:start + length]))
    return reconstruction
