"""Databases from COLMAP's own generator (`pycolmap.synthesize_dataset`), for any camera
model: a second generator, independent of ours, that COLMAP's mapper tests use."""

from __future__ import annotations

from pathlib import Path

import pycolmap

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


def write_pycolmap_dataset(database_path: str | Path, camera_model: str, seed: int,
                           num_images: int = 30, noise_px: float = 0.5,
                           num_points: int = 100, num_cameras: int = 1,
                           params: list[float] | None = None) -> pycolmap.Reconstruction:
    """Write a new database of `num_images` images (frames of one rig of `num_cameras`
    cameras of `camera_model`) with keypoint noise, and return its ground truth."""
    pycolmap.set_random_seed(seed)
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_cameras_per_rig = num_cameras
    options.num_frames_per_rig = num_images // num_cameras
    options.num_points3D = num_points
    options.camera_model_id = getattr(pycolmap.CameraModelId, camera_model)
    options.camera_params = params or CAMERA_PARAMS[camera_model]
    if camera_model == "EQUIRECTANGULAR":
        options.camera_width, options.camera_height = map(int, options.camera_params)
    database = pycolmap.Database.open(str(database_path))
    try:
        truth = pycolmap.synthesize_dataset(options, database)
        noise = pycolmap.SyntheticNoiseOptions()
        noise.point2D_stddev = noise_px
        pycolmap.synthesize_noise(noise, truth, database)
    finally:
        database.close()
    return truth
