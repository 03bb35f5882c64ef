"""The calibrated mapper: accuracy on synthetic databases and real data, the COLMAP
output layout, and the user's files left as they were."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext.database import read_database
from colmap_ext.evaluate import align_similarity, evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper import MapperOptions, run
from colmap_ext.mapper.pipeline import StageTimer, reconstruct
from colmap_ext.mapper.pruning import rotation_uncertainty
from colmap_ext.synthetic.database import scene_points, write_synthetic_database
from colmap_ext.synthetic.scene import ring_scene

def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A 12-view ring database (0.5 px noise, 20 % wrong matches) and its truth."""
    folder = tmp_path_factory.mktemp("synthetic")
    scene = ring_scene(num_images=12, seed=3)
    write_synthetic_database(folder / "database.db", scene, scene_points(scene, 1500, seed=3),
                             noise_px=0.5, outlier_ratio=0.2, seed=3)
    (folder / "images").mkdir()
    for name in scene.image_names:  # the mapper reads point colours from the images
        cv2.imwrite(str(folder / "images" / name), np.zeros((8, 8), np.uint8))
    return folder, scene


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "colmap_ext", *args], capture_output=True,
                          text=True, timeout=600)


def test_synthetic_ring_is_recovered_accurately(synthetic, tmp_path):
    folder, scene = synthetic
    database = folder / "database.db"
    before = sha256(database)
    reconstructions = run(database, folder / "images", tmp_path / "out",
                          MapperOptions(seed=0), progress=False)

    assert sha256(database) == before, "the user's database was modified"
    assert len(reconstructions) == 1
    model = reconstructions[0]
    assert model.num_reg_images() == scene.num_images
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    report = evaluate(model, truth)
    assert report["R_err_max_deg"] < 0.1
    # Centres after a similarity alignment, within 0.5 % of the scene's size.
    by_name = {image.name: image for image in model.images.values()}
    estimated = np.array([by_name[n].projection_center() for n in scene.image_names])
    true = np.array([pose.inverse().translation for pose in scene.cams_from_world])
    aligned = align_similarity(estimated, true)
    scene_size = np.ptp(true, axis=0).max()
    assert np.linalg.norm(aligned - true, axis=1).max() < 0.005 * scene_size
    for name in ("cameras", "images", "points3D", "rigs", "frames"):
        assert (tmp_path / "out" / "0" / f"{name}.bin").is_file()
    summary = json.loads((tmp_path / "out" / "mapper_summary.json").read_text())
    # Every registration after the initial pair is followed by at least one solve.
    assert summary["counts"]["bundle adjustment solves"] >= scene.num_images - 1
    assert summary["counts"]["bundle adjustment iterations"] >= \
        summary["counts"]["bundle adjustment solves"]


def test_bundle_adjustment_loss_reaches_ceres(synthetic):
    """The trivial loss converges in fewer Ceres iterations than the Cauchy loss, and
    both recover the ring (0.5 px noise, 20 % wrong matches); an unknown loss is refused."""
    folder, scene = synthetic
    db = read_database(folder / "database.db")
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    iterations = {}
    for loss in ("cauchy", "trivial"):
        timer = StageTimer()
        reconstructions = reconstruct(db, MapperOptions(ba_loss=loss, seed=0), timer=timer,
                                      progress=False)
        assert evaluate(reconstructions[0], truth)["R_err_max_deg"] < 0.1
        iterations[loss] = timer.counts["bundle adjustment iterations"]
    assert iterations["trivial"] < iterations["cauchy"]
    with pytest.raises(ValueError, match="ba_loss must be"):
        MapperOptions(ba_loss="huber")


def test_cli_writes_text_and_refuses_to_overwrite(synthetic, tmp_path):
    folder, scene = synthetic
    out = tmp_path / "out"
    args = ["mapper", "--database_path", str(folder / "database.db"), "--image_path",
            str(folder / "images"), "--output_path", str(out), "--seed", "1",
            "--output_type", "TXT"]
    first = run_cli(*args)
    assert first.returncode == 0, first.stderr
    assert f"Registered {scene.num_images} images in 1 model" in first.stdout
    written = sha256(out / "0" / "images.txt")

    refused = run_cli(*args)
    assert refused.returncode == 1
    assert "already holds a model; pass --overwrite" in refused.stderr
    assert "Traceback" not in refused.stderr
    assert sha256(out / "0" / "images.txt") == written

    replaced = run_cli(*args, "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert (out / "0" / "images.txt").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".colmap-ext-")]


def test_same_seed_gives_the_same_model(synthetic, tmp_path):
    folder, _ = synthetic
    paths = []
    for run_index in range(2):
        out = tmp_path / f"out{run_index}"
        run(folder / "database.db", folder / "images", out, MapperOptions(seed=7), progress=False)
        paths.append(out / "0")
    for name in ("images.bin", "points3D.bin"):
        assert sha256(paths[0] / name) == sha256(paths[1] / name)


@pytest.mark.parametrize("case", ["missing", "not_sqlite", "no_images_folder"])
def test_bad_input_is_one_clear_line(synthetic, tmp_path, case):
    folder, _ = synthetic
    database, images = folder / "database.db", folder / "images"
    if case == "missing":
        database = tmp_path / "nope.db"
        expected = "database not found"
    elif case == "not_sqlite":
        database = tmp_path / "text.db"
        database.write_text("hello")
        expected = "not an SQLite database"
    else:
        images = tmp_path / "no_such_folder"
        expected = "image path not found"
    result = run_cli("mapper", "--database_path", str(database), "--image_path", str(images),
                     "--output_path", str(tmp_path / "out"))
    assert result.returncode == 1
    assert expected in result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def _points_in_view(half_angle_deg: float, num_points: int) -> np.ndarray:
    """Points 9 to 11 units in front of the identity camera, spread over its field of view."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (num_points, 2)) * np.tan(np.radians(half_angle_deg))
    return np.hstack([xy, np.ones((num_points, 1))]) * rng.uniform(9, 11, (num_points, 1))


def test_rotation_uncertainty_grows_as_the_view_narrows_and_falls_with_inliers():
    identity = pycolmap.Rigid3d()
    wide = rotation_uncertainty(identity, _points_in_view(28, 20))
    narrow = rotation_uncertainty(identity, _points_in_view(5.5, 20))
    assert narrow > 2 * wide
    assert rotation_uncertainty(identity, _points_in_view(5.5, 80)) == pytest.approx(
        narrow / 2, rel=0.25)


@pytest.fixture(scope="module")
def real_databases(tmp_path_factory, real_data):
    """pycolmap default SIFT + exhaustive matching, intrinsics from the ground truth."""
    folder = tmp_path_factory.mktemp("real")
    databases = {}
    for name in ("templeSparseRing", "dinoSparseRing"):
        images = real_data / name
        truth = read_ground_truth(images)
        camera = next(iter(truth.cameras.values()))
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(str(p) for p in camera.params)
        database = folder / f"{name}.db"
        # Import first: the threaded extractor alone numbers images in the order its
        # threads finish, which changes from run to run (and so would the model).
        pycolmap.Database.open(database).close()
        pycolmap.import_images(database, images, camera_mode=pycolmap.CameraMode.SINGLE,
                               options=reader)
        pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        databases[name] = (database, images, truth)
    return databases


def test_temple_sparse_ring(real_databases, tmp_path):
    database, images, truth = real_databases["templeSparseRing"]
    reconstructions = run(database, images, tmp_path, MapperOptions(seed=0), progress=False)
    report = evaluate(reconstructions[0], truth)
    # COLMAP 4.2.1's incremental mapper registers 13 of 16 here, R_err max 0.82 deg. Ours
    # registers all 16; R_err max has measured 0.31 to 0.41 deg over seeds and orders.
    assert report["num_registered"] == 16
    assert report["R_err_max_deg"] < 0.5
    assert report["C_err_max"] < 0.02


def test_dino_sparse_ring(real_databases, tmp_path):
    database, images, truth = real_databases["dinoSparseRing"]
    reconstructions = run(database, images, tmp_path, MapperOptions(seed=0), progress=False)
    report = evaluate(reconstructions[0], truth)
    # COLMAP 4.2.1's incremental mapper registers 6 of 16 here, R_err max 0.65 deg. With
    # ~240 keypoints an image, no stored pair links images 1-5 and 14-16 to 7-13 (image 6
    # has none). Image 5 ends on 21 points that fix its rotation poorly (uncertainty 18.7)
    # and 2 deg off: it is deregistered. Two models of 6 remain; the one with more points,
    # 7-12, comes first, measured R_err max 0.33 to 0.34 deg over seeds.
    assert report["num_registered"] >= 6
    assert report["R_err_max_deg"] < 0.5
