"""COLMAP's own mappers set up as `colmap-ext compare` and the benchmarks run them:
intrinsics and rigs held fixed, so they solve the problem ours solves. Imports pycolmap only,
so a process that runs COLMAP's mapper carries none of our modules."""

from __future__ import annotations

from pathlib import Path

import pycolmap


def fix_intrinsics_in_database(database_path: Path) -> tuple[set[int], int]:
    """Mark every camera's intrinsics as known; returns the camera ids and the image count."""
    with pycolmap.Database.open(database_path) as db:
        cameras = db.read_all_cameras()
        for camera in cameras:
            if not camera.has_prior_focal_length:
                camera.has_prior_focal_length = True
                db.update_camera(camera)
        return {camera.camera_id for camera in cameras}, db.num_images()


def colmap_incremental_options(camera_ids: set[int], seed: int,
                               num_threads: int = -1) -> pycolmap.IncrementalPipelineOptions:
    """COLMAP's incremental mapper with every camera's intrinsics and every rig held fixed."""
    options = pycolmap.IncrementalPipelineOptions()
    options.constant_cameras = set(camera_ids)
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.ba_refine_sensor_from_rig = False
    options.random_seed = seed
    options.num_threads = num_threads
    return options


def colmap_global_options(seed: int, num_images: int,
                          num_threads: int = -1) -> pycolmap.GlobalPipelineOptions:
    """COLMAP's global mapper (GLOMAP) with the intrinsics and rigs held fixed: its bundle
    adjustment is the only step of pycolmap 4.2.1's global pipeline that changes them. A track
    may span every image: the default cap of 100 views discards each track of a scene whose
    points more than 100 images see (COLMAP's generator at 150 images: no track, no model)."""
    options = pycolmap.GlobalPipelineOptions()
    options.mapper.track_max_num_views_per_track = max(
        options.mapper.track_max_num_views_per_track, num_images)
    bundle_adjustment = options.mapper.bundle_adjustment
    bundle_adjustment.refine_focal_length = False
    bundle_adjustment.refine_principal_point = False
    bundle_adjustment.refine_extra_params = False
    bundle_adjustment.refine_sensor_from_rig = False
    # pycolmap's wheel has no CUDA: asking for the GPU only adds a warning per stage.
    bundle_adjustment.ceres.use_gpu = False
    options.mapper.global_positioning.use_gpu = False
    options.random_seed = seed
    options.num_threads = num_threads
    return options
