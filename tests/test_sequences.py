"""The mapper on driving sequences (forward motion, corners, stretches standing still):
the pairs with most matches are neighbours without parallax, and the mapper must still
start, with its default flags, and keep every frame in one model near the truth. A
synthetic drive, a real one (KITTI odometry), and a synthetic stereo rig's, mapped frame by
frame at the rig's metric scale."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext import rigs
from colmap_ext.evaluate import aligned_to_ground_truth, evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.synthetic import (driving_scene, points_for_keypoints, rig_scene,
                                  sequential_pairs, side_by_side_rig, write_ground_truth,
                                  write_placeholder_images, write_rig_config,
                                  write_synthetic_database)

KITTI = "kitti03_600-800"
# The sequence's last 51 frames: the car slows down and stands still from frame 782. The
# 40 pairs with most matches are all 1 to 4 frames apart, and before a8e9a0d's initial
# pair none of them started a model ("no model could be reconstructed").
FRAMES = range(750, 801)
# Measured: R_err max 0.277-0.295 deg, ATE median 0.070-0.071 m (the ground truth is
# GPS/INS); about 2x and 3x that.
R_ERR_MAX_DEG = 0.6
ATE_MEDIAN_M = 0.2
# SIFT features an image, a quarter of pycolmap's default: extraction and matching stay short.
MAX_NUM_FEATURES = 2048

# A synthetic drive of 120 frames (1 m a frame, a corner every 40 m or so, 8 frames standing
# still every 50), 500 keypoints an image, 0.5 px noise, 20 % wrong matches, each frame
# matched with the next 10 as COLMAP's sequential matching. Measured: R_err max 0.113 deg,
# ATE median 0.018 m (COLMAP incremental on the same database: 11.4 deg, 1.03 m); bounds
# about 3x ours.
DRIVE_FRAMES = 120
DRIVE_R_ERR_MAX_DEG = 0.3
DRIVE_ATE_MEDIAN_M = 0.05

# A KITTI-like stereo drive: 100 frames, a corner (about 60 m in), stops of 9 frames from
# frames 41 and 81; each image matched with the next 10 frames' and its frame's other one.
STEREO_FRAMES = 100
STEREO_PREFIXES = ["left/", "right/"]
STEREO_BASELINE = 0.54
# Measured (seed 1): R_err max 0.029 deg; centres after a rigid alignment within 0.009 m
# (the similarity's scale 1.0001); about 3x and 5x that. A model 1 % off the metric scale
# would be some 0.4 m off at the drive's ends.
STEREO_R_ERR_MAX_DEG = 0.1
STEREO_CENTRE_MAX_M = 0.05


def run_mapper(database: Path, images: Path, out: Path) -> pycolmap.Reconstruction:
    """`colmap-ext mapper` with its default flags (seed 0); its one model."""
    done = subprocess.run([sys.executable, "-m", "colmap_ext", "mapper", "--database_path",
                           str(database), "--image_path", str(images), "--output_path", str(out),
                           "--seed", "0"], capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "mapper_summary.json").read_text())
    assert summary["num_models"] == 1
    return pycolmap.Reconstruction(out / "0")


def errors_from_truth(model: pycolmap.Reconstruction, truth) -> tuple[float, float]:
    """R_err max (deg, evaluate's) and the median distance (m) of the camera centres from
    the truth's after the similarity that best aligns them."""
    report = evaluate(model, truth)
    cameras, _ = aligned_to_ground_truth(model, truth)
    ate = [np.linalg.norm(pose.inverse().translation - truth.poses[name].inverse().translation)
           for name, pose in cameras.items()]
    return report["R_err_max_deg"], float(np.median(ate))


def test_mapper_maps_a_synthetic_drive_in_one_model(write_drive, tmp_path):
    """Forward motion, corners and stops (frames without baseline): every frame in one
    model, with the default flags."""
    scene = write_drive(tmp_path, DRIVE_FRAMES)
    write_ground_truth(scene, tmp_path / "truth")
    model = run_mapper(tmp_path / "database.db", tmp_path / "images", tmp_path / "out")
    assert model.num_reg_images() == DRIVE_FRAMES
    r_err_max, ate_median = errors_from_truth(model, read_ground_truth(tmp_path / "truth"))
    assert r_err_max < DRIVE_R_ERR_MAX_DEG
    assert ate_median < DRIVE_ATE_MEDIAN_M


@pytest.fixture(scope="module")
def kitti_database(tmp_path_factory, real_data):
    """pycolmap's SIFT, at most MAX_NUM_FEATURES an image, and sequential matching (overlap
    10), the known intrinsics; images imported first and a seeded verification (see
    test_mapper.real_databases). pycolmap's approximate matcher: its exact one took 377 s
    here against 12 s, and the bounds leave room for the few matches a run gains or loses."""
    images = real_data / KITTI / "images"
    truth = read_ground_truth(real_data / KITTI / "kitti03_par.txt")
    names = [f"{frame:06d}.jpg" for frame in FRAMES]
    camera = next(iter(truth.cameras.values()))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(p) for p in camera.params)
    database = tmp_path_factory.mktemp("kitti") / "database.db"
    pycolmap.Database.open(database).close()
    pycolmap.import_images(database, images, camera_mode=pycolmap.CameraMode.SINGLE,
                           image_names=names, options=reader)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = MAX_NUM_FEATURES
    pycolmap.extract_features(database, images, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0
    pycolmap.match_sequential(database, pairing_options=pycolmap.SequentialPairingOptions(overlap=10),
                              verification_options=verification,
                              device=pycolmap.Device.cpu)
    return database, images, truth, names


def test_mapper_starts_on_forward_motion(kitti_database, tmp_path):
    """`colmap-ext mapper` with its default flags: one model of every frame, within the
    ground truth's GPS/INS accuracy."""
    database, images, truth, names = kitti_database
    model = run_mapper(database, images, tmp_path / "out")
    assert model.num_reg_images() == len(names)
    subset = type(truth)({name: truth.poses[name] for name in names}, truth.cameras)
    r_err_max, ate_median = errors_from_truth(model, subset)
    assert r_err_max < R_ERR_MAX_DEG
    assert ate_median < ATE_MEDIAN_M


@pytest.fixture(scope="module")
def stereo_drive(tmp_path_factory):
    """The stereo drive's database, set up as a COLMAP user sets up a rig: one camera per
    image folder, then the rig configuration JSON applied (rigs.apply_rig_config, as
    `reconstruct --rig_config`); blank images. (folder, its scene, the rig's cams_from_rig)."""
    folder = tmp_path_factory.mktemp("stereo_drive")
    drive = driving_scene(STEREO_FRAMES, seed=1, stop_every=40, stop_frames=10)
    cams_from_rig = side_by_side_rig(len(STEREO_PREFIXES), STEREO_BASELINE)
    scene = rig_scene(drive, cams_from_rig, STEREO_PREFIXES)
    points = points_for_keypoints(scene, 1000, seed=1, max_distance=40.0)
    write_synthetic_database(folder / "database.db", scene, points, max_distance=40.0, seed=1,
                             two_view_geometries=True,
                             pairs=sequential_pairs(STEREO_FRAMES, 10, images_per_frame=2))
    write_rig_config(folder / "rig.json", scene.camera, cams_from_rig, STEREO_PREFIXES)
    rigs.apply_rig_config(folder / "database.db", rigs.read_rig_config(folder / "rig.json"))
    write_placeholder_images(folder / "images", scene.image_names)
    return folder, scene, cams_from_rig


def test_a_stereo_drive_maps_frame_by_frame_at_the_rigs_scale(stereo_drive, tmp_path):
    """Forward motion, a corner and two stops, seen by a stereo rig: with the default flags,
    one model of every frame, each frame's two images registered together with the right
    camera where the rig puts it, and the centres in metres (no scale fitted)."""
    folder, scene, cams_from_rig = stereo_drive
    centres = np.array([pose.inverse().translation for pose in scene.cams_from_world[::2]])
    headings = np.diff(centres[:, :2], axis=0)
    turned = np.degrees(np.arccos(headings[0] @ headings[-1] / np.prod(
        np.linalg.norm(headings[[0, -1]], axis=1))))
    assert turned > 80 and np.sum(np.all(headings == 0, axis=1)) >= 16  # a corner, two stops

    model = run_mapper(folder / "database.db", folder / "images", tmp_path / "out")
    assert model.num_reg_frames() == STEREO_FRAMES
    assert model.num_reg_images() == 2 * STEREO_FRAMES
    (rig,) = model.rigs.values()
    assert rig.num_sensors() == 2  # the configured rig: no image a frame of its own
    for frame in model.frames.values():
        assert frame.has_pose()
        left, right = sorted((model.images[data.id] for data in frame.image_ids),
                             key=lambda image: image.name)
        assert (left.name, right.name) == tuple(prefix + left.name.removeprefix("left/")
                                                for prefix in STEREO_PREFIXES)
        right_from_left = right.cam_from_world() * left.cam_from_world().inverse()
        np.testing.assert_allclose(right_from_left.matrix(), cams_from_rig[1].matrix(), atol=1e-9)

    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    assert evaluate(model, truth)["R_err_max_deg"] < STEREO_R_ERR_MAX_DEG
    cameras, _ = aligned_to_ground_truth(model, truth, with_scale=False)
    errors = [np.linalg.norm(pose.inverse().translation - truth.poses[name].inverse().translation)
              for name, pose in cameras.items()]
    assert max(errors) < STEREO_CENTRE_MAX_M
