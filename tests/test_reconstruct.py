"""`colmap-ext reconstruct`: its flags, its checks before any work, and a run end to end."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext.errors import UserError
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.database import read_database
from colmap_ext.mapper import MapperOptions, run
from colmap_ext.mapper.pipeline import reconstruct
from colmap_ext.reconstruct import add_arguments, main
from colmap_ext.synthetic.render import Renderer, render_images
from colmap_ext.synthetic.scene import cast_rays, ring_scene

# A 320x240 version of the synthetic scenes' distorted OPENCV camera.
CAMERA = pycolmap.Camera(camera_id=1, model="OPENCV", width=320, height=240,
                         params=[300.0, 300.0, 159.0, 121.0, -0.1, 0.01, 0.0, 0.0])
PARAMS = ",".join(f"{value:g}" for value in CAMERA.params)


@pytest.fixture
def images(tmp_path: Path) -> Path:
    """Two noise images: enough for every check that runs before extraction."""
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(folder / name), rng.integers(0, 256, (240, 320), dtype=np.uint8))
    return folder


def test_flags_are_mains_keywords_with_its_defaults() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = vars(parser.parse_args(["--image_path", "i", "--workspace_path", "w"]))
    parameters = inspect.signature(main).parameters
    assert set(args) == set(parameters)
    for name, parameter in parameters.items():
        if parameter.default is not inspect.Parameter.empty:
            assert args[name] == parameter.default, name


@pytest.mark.parametrize(("changes", "message"), [
    ({"camera_params": "300,300,159"}, "OPENCV takes 8 params"),
    ({"camera_params": "300,300,159,121,nan,0,0,0"}, "finite"),
    ({"camera_model": "OPENCVV"}, "unknown camera model"),
    ({"mask_path": "m", "segment": "threshold"}, "give --mask_path or --segment, not both"),
    ({"matcher": "vocab_tree"}, "unknown --matcher"),
    ({"output_type": "PLY"}, "--output_type must be BIN or TXT"),
    ({"image_path": "nowhere"}, "image folder not found"),
])
def test_bad_input_fails_before_any_work(images: Path, tmp_path: Path, changes: dict,
                                         message: str) -> None:
    arguments = {"image_path": images, "workspace_path": tmp_path / "ws",
                 "camera_model": "OPENCV", "camera_params": PARAMS, **changes}
    with pytest.raises(UserError, match=message.replace("(", r"\(")):
        main(**arguments)
    assert not (tmp_path / "ws" / "database.db").exists()


def test_an_earlier_database_needs_overwrite(images: Path, tmp_path: Path) -> None:
    workspace = tmp_path / "ws"
    workspace.mkdir()
    (workspace / "database.db").write_bytes(b"")
    with pytest.raises(UserError, match="already holds a workspace; pass --overwrite"):
        main(images, workspace, "OPENCV", PARAMS)


@pytest.fixture(scope="module")
def ring_run(tmp_path_factory):
    """Ten views of the synthetic ring scene through the distorted camera, reconstructed
    with seed 0: (scene, images folder, workspace, summary)."""
    folder = tmp_path_factory.mktemp("ring")
    scene = ring_scene(num_images=10, seed=0, camera=CAMERA)
    render_images(scene, folder / "images", supersample=1)
    summary = main(folder / "images", folder / "ws", "OPENCV", PARAMS, seed=0, output_type="txt")
    return scene, folder / "images", folder / "ws", summary


def test_ring_end_to_end(ring_run) -> None:
    """Ten views of the synthetic ring scene through a distorted camera: masks are not
    needed (the room is static), features, matching and the mapper run, and the
    workspace holds the database, the model and the summary."""
    scene, images, workspace, summary = ring_run

    assert (workspace / "database.db").is_file()
    assert (workspace / "sparse" / "0" / "images.txt").is_file()
    assert json.loads((workspace / "reconstruct_summary.json").read_text()) == \
        json.loads(json.dumps(summary))
    assert summary["inputs"]["seed"] == 0 and summary["features"]["num_images"] == 10
    assert summary["matching"]["matcher"] == "exhaustive"
    assert summary["models"][0]["num_registered"] >= 8
    # Every model's poses are the true ones. Wrong correspondences on the scene's repeated
    # texture agree on poses about 10 deg off; the registration's epipolar check turns
    # them down (measured: one model of 8 images at R_err max 0.35 deg; before the check,
    # 7 + 3 images, the 7 up to 44.7 deg off).
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    for entry in summary["models"]:
        report = evaluate(pycolmap.Reconstruction(entry["path"]), truth)
        assert report["R_err_max_deg"] < 2.5 and report["C_err_max"] < 0.12, entry["path"]
    assert set(summary["time_s"]) == {"features", "matching", "verification", "mapper", "total"}
    model = pycolmap.Reconstruction(workspace / "sparse" / "0")
    assert list(model.cameras[1].params) == pytest.approx(list(CAMERA.params))
    with pytest.raises(UserError, match="pass --overwrite"):
        main(images, workspace, "OPENCV", PARAMS)


@pytest.mark.xfail(strict=True, reason=(
    "product gap: the 10-view ring gives one model of 8 images (R_err max 0.35 deg); "
    "ring0002 and ring0003 stay out. Few of their correspondences are true (16 of 137 "
    "for ring0002), and P3P on them finds poses 10 deg off that the epipolar check turns "
    "down. Scene seed 2: models of 4, 3 and 3 images, each within 0.4 deg, not merged"))
def test_ring_end_to_end_matches_the_true_poses(ring_run) -> None:
    """The ten views make one model of all ten, its poses as accurate as the 16-view
    ring of the object alone at this resolution gives (R_err max 0.86 deg, C_err max
    0.039; test_segmented_object_ring_end_to_end)."""
    scene, _, _, summary = ring_run
    assert len(summary["models"]) == 1
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    report = evaluate(pycolmap.Reconstruction(summary["models"][0]["path"]), truth)
    assert report["num_registered"] == 10
    assert report["R_err_max_deg"] < 2.5
    assert report["C_err_max"] < 0.12


def test_mapper_maps_the_ring_database_with_any_seed(ring_run, tmp_path: Path) -> None:
    """The mapper finishes on the ring's database for seeds 0, 1 and 2."""
    _, images, workspace, _ = ring_run
    for seed in (0, 1, 2):
        assert run(workspace / "database.db", images, tmp_path / str(seed),
                   MapperOptions(seed=seed), progress=False)


def test_domain_size_pooling_reaches_the_extractor(ring_run, tmp_path: Path) -> None:
    """--SiftExtraction.domain_size_pooling 1: COLMAP's DSP-SIFT (its covariant
    extractor: other keypoints and descriptors on every image), recorded in the summary."""
    _, images, workspace, _ = ring_run
    summary = main(images, tmp_path / "ws", "OPENCV", PARAMS, seed=0, domain_size_pooling=True)
    assert summary["inputs"]["domain_size_pooling"] is True
    features = {}
    for name, folder in (("plain", workspace), ("pooled", tmp_path / "ws")):
        database = pycolmap.Database.open(folder / "database.db")
        try:
            features[name] = {image.name: (database.read_keypoints(image.image_id),
                                           database.read_descriptors(image.image_id).data)
                              for image in database.read_all_images()}
        finally:
            database.close()
    assert features["plain"].keys() == features["pooled"].keys()
    for name, (keypoints, descriptors) in features["plain"].items():
        pooled_keypoints, pooled_descriptors = features["pooled"][name]
        assert len(pooled_keypoints) == len(pooled_descriptors) > 0, name
        assert not (np.array_equal(keypoints, pooled_keypoints)
                    or np.array_equal(descriptors, pooled_descriptors)), name


@pytest.fixture(scope="module")
def object_ring(tmp_path_factory):
    """The ring scene's objects alone (no room: a uniform grey background, like a
    turntable's), 16 views: the scene and its images folder."""
    scene = ring_scene(num_images=16, seed=0, camera=CAMERA)
    # ring_scene's first five quads are the room's floor and walls.
    scene = dataclasses.replace(scene, quads=scene.quads[5:])
    folder = tmp_path_factory.mktemp("object_ring")
    render_images(scene, folder / "images", supersample=1)
    return scene, folder / "images"


@pytest.mark.parametrize("method", ["threshold", "grabcut"])
def test_segmented_object_ring_end_to_end(object_ring, tmp_path: Path, method: str) -> None:
    """`reconstruct --segment`: a mask per image that matches the objects' true
    silhouette, every keypoint inside it, and one accurate model of all 16 views."""
    scene, images = object_ring
    workspace = tmp_path / "ws"
    summary = main(images, workspace, "OPENCV", PARAMS, segment=method, seed=0)
    assert summary["masks"]["path"] == str(workspace / "masks")
    assert sorted(summary["masks"]["coverage"]) == scene.image_names
    rays = Renderer(scene, supersample=1).rays
    database = pycolmap.Database.open(workspace / "database.db")
    try:
        keypoints = {image.name: database.read_keypoints(image.image_id)[:, :2]
                     for image in database.read_all_images()}
    finally:
        database.close()
    for name, pose in zip(scene.image_names, scene.cams_from_world):
        mask = cv2.imread(str(workspace / "masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 0
        silhouette = cast_rays(scene, pose, rays).quad_index >= 0
        # Intersection over union: measured at least 0.75 (threshold), 0.77 (grabcut).
        assert (mask & silhouette).sum() / (mask | silhouette).sum() > 0.5, name
        columns, rows = keypoints[name].astype(int).T
        assert mask[rows, columns].all(), name
    assert [model["num_registered"] for model in summary["models"]] == [16]
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    report = evaluate(pycolmap.Reconstruction(summary["models"][0]["path"]), truth)
    # Measured over both methods and seeds 0-2: R_err max 0.64-0.86 deg, C_err max
    # 0.026-0.039 (320x240 views of small objects).
    assert report["R_err_max_deg"] < 2.6
    assert report["C_err_max"] < 0.12


def reconstruct_real_set(images: Path, truth: GroundTruth, workspace: Path,
                         exact_matching: bool = False) -> tuple[dict, dict]:
    """`reconstruct` on a real set with its ground-truth intrinsics (seed 0): the run's
    summary and the evaluation of its first model."""
    camera = next(iter(truth.cameras.values()))
    params = ",".join(repr(float(p)) for p in camera.params)
    summary = main(images, workspace, camera.model.name, params, exact_matching=exact_matching,
                   seed=0)
    report = evaluate(pycolmap.Reconstruction(summary["models"][0]["path"]), truth)
    return summary, report


def test_temple_sparse_ring_end_to_end(tmp_path: Path, real_data: Path) -> None:
    """Issue 4's real-data target: templeSparseRing from its images and the calibrated
    intrinsics; issue 15's bound, R_err max at most 0.35 deg on every seed. Measured
    R_err max 0.213 deg (seed 0; 0.200-0.232 over seeds 0-9), C_err max 0.0092."""
    folder = real_data / "templeSparseRing"
    _, report = reconstruct_real_set(folder, read_ground_truth(folder), tmp_path / "ws")
    assert report["num_registered"] == 16
    assert report["R_err_max_deg"] < 0.35
    assert report["C_err_max"] < 0.02


def test_strecha_entry_end_to_end(tmp_path: Path, real_data: Path) -> None:
    """Issue 15's textured photographs: strecha_entry-P10 (ten 3072x2048 photographs, LIDAR
    ground truth) from its images, within the paper's figures for Strecha's sets (R_err at
    most 0.1 deg, C_err below 0.015). Measured (seed 0): R_err max 0.054 / median 0.025 deg,
    C_err max 0.0105; COLMAP's mappers on their own features 0.054 / 0.024-0.025.
    dtu_scan24 (49 photographs) takes five minutes end to end here and stays in
    benchmarks/accuracy.py."""
    folder = real_data / "strecha_entry-P10"
    truth = read_ground_truth(folder / "gt_cameras")
    summary, report = reconstruct_real_set(folder / "images", truth, tmp_path / "ws")
    assert len(summary["models"]) == 1
    assert report["num_registered"] == 10
    assert report["R_err_max_deg"] < 0.07
    assert report["R_err_median_deg"] < 0.035
    assert report["C_err_max"] < 0.015


def test_dino_sparse_ring_end_to_end(tmp_path: Path, real_data: Path) -> None:
    """dinoSparseRing falls apart into two arcs of 8 images (neighbours across the gaps
    share 18-27 matches and hardly any points); the arcs are joined by the similarity
    that images 6 and 13, posed among the other arc's points, agree on. Issue 15's bound:
    one model of 16 and R_err max at most 0.45 deg on every seed 0-9, here the mapper's
    seeds 0-9 on the database of reconstruct's seed 0, matched exactly. Measured: R_err max
    0.350 deg for seed 0 (C_err max 0.0123), 0.351-0.385 for seeds 1-9; on a database from
    pycolmap's FAISS index 0.257-0.331 (0.274 for seed 0)."""
    folder = real_data / "dinoSparseRing"
    truth = read_ground_truth(folder)
    # Exact matching: the same database on every run. With pycolmap's FAISS index, one run
    # in this session's five got 3431 raw matches instead of 3460 (matching.py) and two
    # models of 9 and 7 images; a weak link across a gap is that easily lost.
    summary, report = reconstruct_real_set(folder, truth, tmp_path / "ws", exact_matching=True)
    assert len(summary["models"]) == 1
    assert report["num_registered"] == 16
    assert report["R_err_max_deg"] < 0.45
    assert report["C_err_max"] < 0.025
    database = read_database(tmp_path / "ws" / "database.db")
    for seed in range(1, 10):
        models = reconstruct(database, MapperOptions(seed=seed), progress=False)
        assert [model.num_reg_images() for model in models] == [16], seed
        assert evaluate(models[0], truth)["R_err_max_deg"] < 0.45, seed
