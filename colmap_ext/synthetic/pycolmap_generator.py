"""Databases from COLMAP's own generator (`pycolmap.synthesize_dataset`), for any camera
model: a second generator, independent of ours, that COLMAP's mapper tests use."""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.colmap_mappers import fix_intrinsics_in_database

# Intrinsics per model for 1024 x 768 images (EQUIRECTANGULAR: 1024 x 512): a focal length
# of 500 px (a field of view of about 90 degrees across) and mild distortion.
CAMERA_PARAMS = {
    "SIMPLE_PINHOLE": [500, 512, 384],
    "PINHOLE": [500, 500, 512, 384],
    "SIMPLE_RADIAL": [500, 512, 384, 0.05],
    "OPENCV": [500, 500, 512, 384, 0.05, -0.01, 0.001, 0.001],
    "EQUIRECTANGULAR": [1024, 512],
    "SIMPLE_RADIAL_FISHEYE": [500, 512, 384, 0.05],
    "RADIAL_FISHEYE": [500, 512, 384, 0.05, -0.01],
    "OPENCV_FISHEYE": [500, 500, 512, 384, 0.05, -0.01, 0.002, -0.001],
    "FOV": [500, 500, 512, 384, 0.9],
    "EUCM": [500, 500, 512, 384, 0.6, 1.1],
    "SIMPLE_DIVISION": [500, 512, 384, -0.1],
    "DIVISION": [500, 500, 512, 384, -0.1],
}


def write_pycolmap_dataset(database_path: str | Path, camera_model: str | None, seed: int,
                           num_images: int = 30, noise_px: float = 0.5,
                           num_points: int = 100, num_cameras: int = 1,
                           params: list[float] | None = None,
                           num_rigs: int = 1,
                           rig_baseline: float | None = None) -> pycolmap.Reconstruction:
    """Write a new database of `num_images` images (frames of `num_rigs` rigs of
    `num_cameras` cameras of `camera_model`; None: the generator's own camera) with
    keypoint noise, and return its ground truth. `rig_baseline`: the standard deviation
    of the cameras' offsets on their rig (None: the generator's, 0.05)."""
    pycolmap.set_random_seed(seed)
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = num_rigs
    if rig_baseline is not None:
        options.sensor_from_rig_translation_stddev = rig_baseline
    options.num_cameras_per_rig = num_cameras
    options.num_frames_per_rig = num_images // (num_rigs * num_cameras)
    options.num_points3D = num_points
    if camera_model is not None:
        options.camera_model_id = getattr(pycolmap.CameraModelId, camera_model)
        options.camera_params = params or CAMERA_PARAMS[camera_model]
    if camera_model == "EQUIRECTANGULAR":
        options.camera_width, options.camera_height = map(int, options.camera_params)
    database = pycolmap.Database.open(str(database_path))
    try:
        truth = pycolmap.synthesize_dataset(options, database)
        if noise_px:
            noise = pycolmap.SyntheticNoiseOptions()
            noise.point2D_stddev = noise_px
            pycolmap.synthesize_noise(noise, truth, database)
    finally:
        database.close()
    return truth


def verify_with_colmap(database_path: Path,
                       pairs: Iterable[tuple[str, str]] | None = None) -> None:
    """Replace the generator's two-view geometries, which hold its true matches alone (and,
    ours, the true relative poses), by COLMAP's geometric verification of the raw matches
    of `pairs` of image names (None: every pair), focal lengths marked known: the essential
    matrix, as a calibrated user's database is made: the wrong matches that agree with a
    pair's geometry get through, as on real images."""
    fix_intrinsics_in_database(database_path)
    with pycolmap.Database.open(database_path) as database:
        database.clear_two_view_geometries()
        names = sorted(image.name for image in database.read_all_images())
    pairs_path = database_path.with_name(database_path.stem + "_pairs.txt")
    pairs_path.write_text("".join(f"{first} {second}\n" for first, second in
                                  (itertools.combinations(names, 2) if pairs is None else pairs)))
    try:
        pycolmap.verify_matches(database_path, pairs_path)
    finally:
        pairs_path.unlink()


def wrong_observations(model: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> int:
    """How many of the model's observations see another true point than most of their
    track does (the generator's keypoints: the same images and indices as the truth's)."""
    true_points = {image_id: np.array([p.point3D_id if p.has_point3D() else -1
                                       for p in image.points2D])
                   for image_id, image in truth.images.items()}
    wrong = 0
    for point in model.points3D.values():
        seen = [true_points[e.image_id][e.point2D_idx] for e in point.track.elements]
        wrong += len(seen) - np.unique(seen, return_counts=True)[1].max()
    return wrong


# A 360-degree equidistant fisheye: r = f * angle from the axis fills a frame of this size.
WIDE_FISHEYE_FOCAL_PX = 200.0
WIDE_FISHEYE_SIZE = 1280


def wide_fisheye_from_panoramas(database_path: str | Path, truth: pycolmap.Reconstruction,
                                turn_deg: float = 90.0) -> None:
    """Turn a database of EQUIRECTANGULAR images and its ground truth
    (write_pycolmap_dataset) into those of an equidistant fisheye lens that sees every
    direction (r = f * angle from its axis, up to 180 degrees), its axis turned by
    `turn_deg` about each panorama's y axis: with 90, the scene (ahead of the panoramas)
    straddles the edge of the front half. The camera is described by the closest COLMAP
    model, OPENCV_FISHEYE without distortion, which holds the directions within 90
    degrees of the axis alone; the keypoints beyond stay in the database, as a real lens
    wider than 180 degrees gives them."""
    turn = pycolmap.Rotation3d(np.array([0.0, np.radians(turn_deg), 0.0]))
    focal_px, size = WIDE_FISHEYE_FOCAL_PX, WIDE_FISHEYE_SIZE
    database = pycolmap.Database.open(str(database_path))
    try:
        panoramas = {camera.camera_id: camera for camera in database.read_all_cameras()}
        for image in database.read_all_images():
            keypoints = database.read_keypoints(image.image_id)
            directions = panoramas[image.camera_id].cam_ray_from_img(keypoints[:, :2]) @ \
                turn.matrix().T
            angle = np.arctan2(np.linalg.norm(directions[:, :2], axis=1), directions[:, 2])
            azimuth = np.arctan2(directions[:, 1], directions[:, 0])
            keypoints[:, 0] = size / 2 + focal_px * angle * np.cos(azimuth)
            keypoints[:, 1] = size / 2 + focal_px * angle * np.sin(azimuth)
            database.update_keypoints(image.image_id, keypoints.astype(np.float32))
        for camera in panoramas.values():
            fisheye = pycolmap.Camera(model="OPENCV_FISHEYE", width=size, height=size,
                                      params=[focal_px, focal_px, size / 2, size / 2, 0, 0, 0, 0],
                                      camera_id=camera.camera_id)
            database.update_camera(fisheye)
            truth.cameras[camera.camera_id] = fisheye
    finally:
        database.close()
    for frame in truth.frames.values():
        frame.rig_from_world = pycolmap.Rigid3d(turn, np.zeros(3)) * frame.rig_from_world
