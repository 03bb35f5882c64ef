"""Mapping one cluster: the task a worker runs, and the arrays it returns."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pycolmap

from colmap_ext.database import DatabaseContents
from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.pipeline import reconstruct


@dataclass
class ClusterModel:
    """One model of one cluster, as arrays (what a task returns: pycolmap 4.2.1's
    Reconstruction cannot be pickled), read-only: poses, and points with their tracks as
    flat observation lists; joining.join makes the group's Reconstruction of them."""

    image_ids: np.ndarray  # (k,)
    cams_from_world: np.ndarray  # (k, 3, 4)
    xyz: np.ndarray  # (p, 3)
    track_point: np.ndarray  # (m,) index into xyz of each observation
    track_image: np.ndarray  # (m,) image id
    track_keypoint: np.ndarray  # (m,) keypoint index

    @classmethod
    def from_reconstruction(cls, reconstruction: pycolmap.Reconstruction) -> ClusterModel:
        image_ids = np.array(sorted(reconstruction.reg_image_ids()), np.int64)
        poses = np.array([reconstruction.images[i].cam_from_world().matrix() for i in image_ids])
        point_ids = sorted(reconstruction.point3D_ids())
        xyz = np.array([reconstruction.points3D[p].xyz for p in point_ids]).reshape(-1, 3)
        observations = [(index, element.image_id, element.point2D_idx)
                        for index, point_id in enumerate(point_ids)
                        for element in reconstruction.points3D[point_id].track.elements]
        columns = np.array(observations, np.int64).reshape(-1, 3).T
        return cls(image_ids, poses.reshape(-1, 3, 4), xyz, *columns)

    def centres(self) -> np.ndarray:
        rotations, translations = self.cams_from_world[:, :, :3], self.cams_from_world[:, :, 3]
        return -np.einsum("kji,kj->ki", rotations, translations)

    def observations_per_image(self) -> dict[int, int]:
        images, counts = np.unique(self.track_image, return_counts=True)
        return dict(zip(images.tolist(), counts.tolist()))


def database_subset(db: DatabaseContents, image_ids: list[int]) -> DatabaseContents:
    """The images and matches of `image_ids` alone, with every camera, rig and frame:
    what a task needs."""
    keep = set(image_ids)
    return DatabaseContents(
        db.cameras, {i: db.images[i] for i in image_ids},
        {i: db.descriptors[i] for i in image_ids},
        {p: m for p, m in db.verified_matches.items() if p[0] in keep and p[1] in keep},
        {p: m for p, m in db.raw_matches.items() if p[0] in keep and p[1] in keep},
        db.rigs, db.frames)


def map_cluster(index: int, db: DatabaseContents, options: MapperOptions,
                threads: int) -> tuple[int, list[ClusterModel], float]:
    """The task: the calibrated mapper on one cluster, on `threads` threads (its options'
    for Ceres, and as many for BLAS, so that workers sharing a machine do not
    oversubscribe it); (index, models, seconds). Without the models' closing global
    adjustments and retriangulation: the joined model's end (pipeline.py) replaces them."""
    from threadpoolctl import threadpool_limits

    start = time.perf_counter()
    with threadpool_limits(threads):
        reconstructions = reconstruct(db, options, progress=False, final_adjustment=False)
    return index, [ClusterModel.from_reconstruction(r) for r in reconstructions], \
        time.perf_counter() - start
