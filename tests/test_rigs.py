"""Setting up rigs (Kalibr camchain files to COLMAP's rig configuration, `reconstruct
--rig_config`) and measuring how well a model keeps one (`evaluate`, rig consistency)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import yaml

from colmap_ext import cli, evaluate, mapper, reconstruct, rigs
from colmap_ext.compare import compare
from colmap_ext.errors import UserError
from colmap_ext.geometry import fit_similarity, rotation_angles_deg
from colmap_ext.ground_truth import GroundTruth
from colmap_ext.rig_consistency import model_rig_frames, rig_consistency
from colmap_ext.synthetic.pycolmap_generator import write_pycolmap_dataset
from colmap_ext.synthetic import driving_scene, rig_scene, side_by_side_rig, write_rig_config
from colmap_ext.synthetic.render import render_images
from colmap_ext.synthetic.scene import Scene, ring_scene

RADTAN = {"distortion_model": "radtan", "distortion_coeffs": [-0.28, 0.07, 1e-4, -2e-4]}
EQUIDISTANT = {"distortion_model": "equidistant",
               "distortion_coeffs": [-0.037, -0.009, 0.0089, -0.0038]}


def random_pose(rng: np.random.Generator, angle_deg: float = 40.0) -> pycolmap.Rigid3d:
    axis = rng.normal(size=3)
    rotation = pycolmap.Rotation3d(np.radians(angle_deg) * rng.uniform(0.2, 1) * axis
                                   / np.linalg.norm(axis))
    return pycolmap.Rigid3d(rotation, rng.uniform(-0.2, 0.2, 3))


def kalibr_matrix(pose: pycolmap.Rigid3d) -> list[list[float]]:
    return pose.matrix().tolist() + [[0.0, 0.0, 0.0, 1.0]]


def kalibr_camera(index: int, distortion: dict, **transforms: pycolmap.Rigid3d) -> dict:
    entry = {"camera_model": "pinhole", "intrinsics": [400.0 + index, 401.0, 320.5, 240.5],
             "resolution": [640, 480], "rostopic": f"/cam{index}/image_raw", **distortion}
    entry.update({key: kalibr_matrix(pose) for key, pose in transforms.items()})
    return entry


def write_yaml(path: Path, cameras: list[dict]) -> Path:
    path.write_text(yaml.safe_dump({f"cam{index}": camera for index, camera in enumerate(cameras)}))
    return path


def assert_same_pose(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d, tolerance: float = 1e-9) -> None:
    np.testing.assert_allclose(a.matrix(), b.matrix(), atol=tolerance)


def test_kalibr_camchains_linked_by_their_imu_round_trip_through_colmaps_rig_config(
        tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    cams_from_rig = [pycolmap.Rigid3d(), random_pose(rng), random_pose(rng)]
    rig_from_imu = random_pose(rng, 90.0)
    cams_from_imu = [cam_from_rig * rig_from_imu for cam_from_rig in cams_from_rig]
    stereo = write_yaml(tmp_path / "stereo-camchain-imucam.yaml", [
        kalibr_camera(0, RADTAN, T_cam_imu=cams_from_imu[0]),
        kalibr_camera(1, RADTAN, T_cam_imu=cams_from_imu[1],
                      T_cn_cnm1=cams_from_rig[1] * cams_from_rig[0].inverse())])
    side = write_yaml(tmp_path / "side-camchain-imucam.yaml",
                      [kalibr_camera(2, EQUIDISTANT, T_cam_imu=cams_from_imu[2])])

    output = tmp_path / "rig.json"
    rigs.main([str(stereo), str(side)], str(output), image_prefix=["left/", "right/", "side/"])
    (config,) = pycolmap.read_rig_config(str(output))

    assert [camera.image_prefix for camera in config.cameras] == ["left/", "right/", "side/"]
    assert [camera.ref_sensor for camera in config.cameras] == [True, False, False]
    for camera, truth in zip(config.cameras[1:], cams_from_rig[1:]):
        assert_same_pose(camera.cam_from_rig, truth)
    models = [camera.camera.model.name for camera in config.cameras]
    assert models == ["OPENCV", "OPENCV", "OPENCV_FISHEYE"]
    np.testing.assert_allclose(config.cameras[1].camera.params,
                               [401.0, 401.0, 320.5, 240.5, *RADTAN["distortion_coeffs"]])
    np.testing.assert_allclose(config.cameras[2].camera.params,
                               [402.0, 401.0, 320.5, 240.5, *EQUIDISTANT["distortion_coeffs"]])


def test_a_camchain_without_imu_is_chained_from_its_first_camera(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    cams_from_rig = [pycolmap.Rigid3d(), random_pose(rng), random_pose(rng)]
    path = write_yaml(tmp_path / "camchain.yaml", [kalibr_camera(0, EQUIDISTANT)] + [
        kalibr_camera(index, EQUIDISTANT,
                      T_cn_cnm1=cams_from_rig[index] * cams_from_rig[index - 1].inverse())
        for index in (1, 2)])

    cameras = rigs.read_kalibr_rig([path])

    for camera, truth in zip(cameras, cams_from_rig):
        assert_same_pose(camera.cam_from_rig, truth)


@pytest.mark.parametrize(("change", "message"), [
    ({"camera_model": "omni"}, "camera_model 'omni' is not supported"),
    ({"distortion_model": "fov"}, "distortion_model 'fov' is not supported"),
    ({"intrinsics": [400.0, 400.0, 320.0]},
     r"intrinsics \[fu, fv, pu, pv\] must be a list of 4 numbers"),
    ({"T_cam_imu": [[2.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]},
     "T_cam_imu does not hold a rotation"),
])
def test_a_camchain_it_cannot_read_is_a_one_line_error(tmp_path: Path, change: dict,
                                                        message: str) -> None:
    camera = {**kalibr_camera(0, RADTAN, T_cam_imu=pycolmap.Rigid3d()), **change}
    path = write_yaml(tmp_path / "camchain.yaml", [camera])
    with pytest.raises(UserError, match=message):
        rigs.main([str(path)], str(tmp_path / "rig.json"))
    assert not (tmp_path / "rig.json").exists()


def test_several_camchains_need_the_imu_to_link_them(tmp_path: Path) -> None:
    first = write_yaml(tmp_path / "a.yaml", [kalibr_camera(0, RADTAN)])
    second = write_yaml(tmp_path / "b.yaml", [kalibr_camera(1, RADTAN)])
    with pytest.raises(UserError, match="every camera needs T_cam_imu when several"):
        rigs.read_kalibr_rig([first, second])


def test_hilti_rigs_kalibr_files_agree_with_its_stereo_pairs_chain(real_data: Path) -> None:
    """hilti_rig: five cameras in four camchain-imucam files; cam1's place from the IMU
    equals its T_cn_cnm1 from cam0 (Kalibr's stereo calibration, 10.8 cm)."""
    calibration = real_data / "hilti_rig" / "calibration"
    files = sorted(calibration.glob("calib_3_cam*-camchain-imucam.yaml"))
    cameras = rigs.read_kalibr_rig(files)
    assert [camera.model for camera in cameras] == ["OPENCV_FISHEYE"] * 5
    stereo = yaml.safe_load(files[0].read_text())["cam1"]["T_cn_cnm1"]
    np.testing.assert_allclose(cameras[1].cam_from_rig.matrix(), np.array(stereo)[:3], atol=1e-6)


@pytest.fixture(scope="module")
def synthetic_rigs() -> pycolmap.Reconstruction:
    """COLMAP's generator: 2 rigs of 3 cameras, 3 frames each (the true model)."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 2, 3, 3
    options.num_points3D = 50
    pycolmap.set_random_seed(0)
    with pycolmap.Database.open(":memory:") as db:
        return pycolmap.synthesize_dataset(options, db)


def turned_sensor(model: pycolmap.Reconstruction, angle_deg: float,
                  ) -> tuple[pycolmap.Reconstruction, int]:
    """A copy of `model` with one non-reference camera of rig 1 turned by `angle_deg` on
    the rig; and that rig's id."""
    turned = pycolmap.Reconstruction(model)
    rig = turned.rigs[1]
    sensor_id = next(iter(rig.non_ref_sensors))
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.radians([angle_deg, 0.0, 0.0])), [0, 0, 0])
    rig.set_sensor_from_rig(sensor_id, turn * rig.sensor_from_rig(sensor_id))
    return turned, rig.rig_id


def test_rig_consistency_finds_a_camera_turned_on_its_rig(synthetic_rigs) -> None:
    frames = model_rig_frames(synthetic_rigs)
    assert len(frames) == 6 and all(len(members) == 3 for members in frames.values())

    kept = rig_consistency(synthetic_rigs, frames)
    assert kept["rotation_max_deg"] < 1e-9 and kept["translation_max"] < 1e-5
    assert kept["scale"] == pytest.approx(1.0)

    turned, rig_id = turned_sensor(synthetic_rigs, 0.5)
    found = rig_consistency(turned, frames)
    assert found["rotation_max_deg"] == pytest.approx(0.5, abs=1e-9)
    for entry in found["per_frame"]:
        expected = 0.5 if synthetic_rigs.frames[int(entry["frame"])].rig_id == rig_id else 0.0
        assert entry["rotation_max_deg"] == pytest.approx(expected, abs=1e-9)


def rig_config_of(model: pycolmap.Reconstruction, rig_id: int) -> list[dict]:
    """The rig configuration of one rig of a synthesize_dataset model, whose images are
    named camera<camera id>_frame<n>.png."""
    rig = model.rigs[rig_id]
    cameras = []
    for sensor_id in rig.sensor_ids():
        entry: dict = {"image_prefix": f"camera{sensor_id.id:06d}_"}
        if sensor_id == rig.ref_sensor_id:
            entry["ref_sensor"] = True
        else:
            pose = rig.sensor_from_rig(sensor_id)
            x, y, z, w = pose.rotation.quat
            entry["cam_from_rig_rotation"] = [w, x, y, z]
            entry["cam_from_rig_translation"] = pose.translation.tolist()
        cameras.append(entry)
    return [{"cameras": sorted(cameras, key=lambda entry: "ref_sensor" not in entry)}]


def test_evaluate_measures_the_rig_of_a_configuration_or_else_the_models_own(
        synthetic_rigs, tmp_path: Path) -> None:
    turned, rig_id = turned_sensor(synthetic_rigs, 0.5)
    (tmp_path / "truth").mkdir()
    (tmp_path / "turned").mkdir()
    synthetic_rigs.write(str(tmp_path / "truth"))
    turned.write(str(tmp_path / "turned"))
    config = tmp_path / "rig.json"
    config.write_text(json.dumps(rig_config_of(synthetic_rigs, rig_id)))

    own = evaluate.main(tmp_path / "turned", tmp_path / "truth")
    against_config = evaluate.main(tmp_path / "turned", tmp_path / "truth", rig_config=config)

    assert own["rig_consistency"]["rotation_max_deg"] < 1e-9  # it keeps its own (turned) rig
    assert against_config["rig_consistency"]["rotation_max_deg"] == pytest.approx(0.5, abs=1e-9)
    assert against_config["rig_consistency"]["num_frames"] == 3  # the configured rig's frames
    assert own["R_err_max_deg"] == pytest.approx(0.5, abs=1e-6)


# A 320x240 pinhole camera for the rendered rig.
CAMERA = pycolmap.Camera(camera_id=1, model="PINHOLE", width=320, height=240,
                         params=[300.0, 300.0, 160.0, 120.0])


@pytest.fixture(scope="module")
def rendered_rig(tmp_path_factory) -> tuple[Path, Path, pycolmap.Rigid3d]:
    """A two-camera rig (the second 0.4 to the side, turned 15 deg) at six places of the
    synthetic ring, rendered as left/frameN.png and right/frameN.png: (images, rig
    configuration, right_from_rig)."""
    folder = tmp_path_factory.mktemp("rendered_rig")
    ring = ring_scene(num_images=6, seed=0, camera=CAMERA)
    right_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.radians([0.0, -15.0, 0.0])),
                                      [-0.4, 0.0, 0.0])
    poses = [pose for rig_from_world in ring.cams_from_world
             for pose in (rig_from_world, right_from_rig * rig_from_world)]
    names = [f"{side}/frame{index}.png" for index in range(6) for side in ("left", "right")]
    render_images(Scene(CAMERA, poses, names, ring.quads), folder / "images", supersample=1)
    x, y, z, w = right_from_rig.rotation.quat
    pinhole = {"camera_model_name": "PINHOLE", "camera_params": list(CAMERA.params)}
    config = [{"cameras": [
        {"image_prefix": "left/", "ref_sensor": True, **pinhole},
        {"image_prefix": "right/", "cam_from_rig_rotation": [w, x, y, z],
         "cam_from_rig_translation": right_from_rig.translation.tolist(), **pinhole}]}]
    (folder / "rig.json").write_text(json.dumps(config))
    return folder / "images", folder / "rig.json", right_from_rig


def test_reconstruct_with_a_rig_config_writes_the_rig_and_its_frames(
        rendered_rig, tmp_path: Path) -> None:
    images, config, right_from_rig = rendered_rig
    summary = reconstruct.main(images, tmp_path / "ws", rig_config=str(config), seed=0)

    with pycolmap.Database.open(str(tmp_path / "ws" / "database.db")) as db:
        (rig,) = db.read_all_rigs()
        frames = db.read_all_frames()
        cameras = {image.name: image.camera_id for image in db.read_all_images()}
        (right_sensor,) = rig.non_ref_sensors
        assert_same_pose(rig.sensor_from_rig(right_sensor), right_from_rig)
        assert db.read_camera(right_sensor.id).model.name == "PINHOLE"
    assert len(frames) == 6 and all(frame.num_data_ids() == 2 for frame in frames)
    assert {cameras[name] for name in cameras if name.startswith("left/")} == {rig.ref_sensor_id.id}
    assert {cameras[name] for name in cameras if name.startswith("right/")} == {right_sensor.id}
    assert summary["models"][0]["num_registered"] >= 4


PINHOLE = {"camera_model_name": "PINHOLE", "camera_params": list(CAMERA.params)}


@pytest.mark.parametrize(("config", "message"), [
    ([{"cameras": [{"image_prefix": "left/", "ref_sensor": True, **PINHOLE}]}],
     "image right/frame0.png is under 0 of the rig configuration's image prefixes"),
    ([{"cameras": [{"image_prefix": "left/", "ref_sensor": True, **PINHOLE},
                   {"image_prefix": "right/", "cam_from_rig_rotation": [1, 0, 0, 0],
                    "cam_from_rig_translation": [1, 0, 0], **PINHOLE},
                   {"image_prefix": "top/", "cam_from_rig_rotation": [1, 0, 0, 0],
                    "cam_from_rig_translation": [0, 1, 0], **PINHOLE}]}],
     "no image under the rig configuration's image prefix 'top/'"),
    ([{"cameras": [{"image_prefix": "left/", **PINHOLE}]}],
     '"ref_sensor": false needs cam_from_rig_rotation'),
    ([{"cameras": [{"image_prefix": "left/", "ref_sensor": True, **PINHOLE},
                   {"image_prefix": "right/", "cam_from_rig_rotation": [1, 0, 0, 0],
                    "cam_from_rig_translation": [1, 0, 0], "camera_model_name": "PINHOLE",
                    "camera_params": [300.0, 300.0, 1e5, 120.0]}]}],
     r"principal point \(100000, 120\) is outside the 320x240 images"),
])
def test_reconstruct_checks_the_rig_config_before_any_work(
        rendered_rig, tmp_path: Path, config: list, message: str) -> None:
    images, _, _ = rendered_rig
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(config))
    with pytest.raises(UserError, match=message):
        reconstruct.main(images, tmp_path / "ws", rig_config=str(path))
    assert not (tmp_path / "ws" / "database.db").exists()


@pytest.mark.parametrize(("flags", "message"), [
    ({}, "give --camera_model and --camera_params, or a --rig_config with camera_model_name"),
    ({"camera_model": "PINHOLE", "camera_params": "300,300,160,120"}, "not both"),
])
def test_reconstruct_needs_intrinsics_from_the_flags_or_else_the_rig_config(
        rendered_rig, tmp_path: Path, flags: dict, message: str) -> None:
    images, config, _ = rendered_rig
    entries = json.loads(config.read_text())
    if not flags:
        del entries[0]["cameras"][1]["camera_model_name"], entries[0]["cameras"][1]["camera_params"]
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(entries))
    with pytest.raises(UserError, match=message):
        reconstruct.main(images, tmp_path / "ws", rig_config=str(path), **flags)


def test_reconstruct_maps_a_rig_whose_cameras_have_two_image_sizes(tmp_path: Path) -> None:
    """Issue 45, defect 14: "images sharing one camera must have one size" refused a rig
    whose second camera is 240x180; each prefix's images now get a camera of their size."""
    small = pycolmap.Camera(camera_id=1, model="PINHOLE", width=240, height=180,
                            params=[225.0, 225.0, 120.0, 90.0])
    ring = ring_scene(num_images=6, seed=0, camera=CAMERA)
    right_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.radians([0.0, -15.0, 0.0])),
                                      [-0.4, 0.0, 0.0])
    for camera, side, cam_from_rig in ((CAMERA, "left", pycolmap.Rigid3d()),
                                       (small, "right", right_from_rig)):
        render_images(Scene(camera, [cam_from_rig * pose for pose in ring.cams_from_world],
                            [f"{side}/frame{index}.png" for index in range(6)], ring.quads),
                      tmp_path / "images", supersample=1)
    x, y, z, w = right_from_rig.rotation.quat
    config = [{"cameras": [
        {"image_prefix": "left/", "ref_sensor": True, **PINHOLE},
        {"image_prefix": "right/", "cam_from_rig_rotation": [w, x, y, z],
         "cam_from_rig_translation": right_from_rig.translation.tolist(),
         "camera_model_name": "PINHOLE", "camera_params": list(small.params)}]}]
    (tmp_path / "rig.json").write_text(json.dumps(config))

    summary = reconstruct.main(tmp_path / "images", tmp_path / "ws",
                               rig_config=str(tmp_path / "rig.json"), seed=0)

    model = pycolmap.Reconstruction(tmp_path / "ws" / "sparse" / "0")
    sizes = {image.name.split("/")[0]: (image.camera.width, image.camera.height,
                                        list(image.camera.params))
             for image in model.images.values() if image.has_pose}
    assert sizes == {"left": (320, 240, list(CAMERA.params)),
                     "right": (240, 180, list(small.params))}
    assert summary["models"][0]["num_registered"] >= 4
    assert summary["inputs"]["rig_cameras"]["right/"]["camera_params"] == list(small.params)
    assert "camera_model" not in summary["inputs"]


def test_reconstruct_maps_a_rig_of_one_camera_under_the_empty_prefix(
        rendered_rig, tmp_path: Path) -> None:
    """Issue 45, defect 6: a one-camera rig with image_prefix "" ended in a traceback;
    every image is then a frame of its own."""
    images, _, _ = rendered_rig
    (tmp_path / "rig.json").write_text(json.dumps(
        [{"cameras": [{"image_prefix": "", "ref_sensor": True, **PINHOLE}]}]))

    summary = reconstruct.main(images, tmp_path / "ws", rig_config=str(tmp_path / "rig.json"),
                               seed=0)

    assert summary["models"][0]["num_registered"] >= 4
    with pycolmap.Database.open(str(tmp_path / "ws" / "database.db")) as db:
        assert len(db.read_all_cameras()) == 1 and len(db.read_all_frames()) == 12


# A rendered stereo drive (0.54 m baseline, 1 m a frame) matched sequentially: with 20
# frames, sequential matching's overlap of 10 also proposes its quadratic (16 frames
# apart) and loop closure pairs. Measured: R_err max 0.128 deg, centres within 0.012 m
# of the truth after a rigid alignment; about 3x and 4x that.
DRIVE_FRAMES = 20
DRIVE_R_ERR_MAX_DEG = 0.4
DRIVE_CENTRE_MAX_M = 0.05


def test_reconstruct_maps_a_rendered_stereo_drive_frame_by_frame_with_sequential_matching(
        tmp_path: Path) -> None:
    """`reconstruct --rig_config --matcher sequential` on a stereo sequence: one model of
    every frame with both its images, at the rig's metric scale (no scale fitted)."""
    cams_from_rig = side_by_side_rig(2, 0.54)
    scene = rig_scene(driving_scene(DRIVE_FRAMES, seed=1, camera=CAMERA, stop_every=0),
                      cams_from_rig, ["left/", "right/"])
    render_images(scene, tmp_path / "images", supersample=1)
    write_rig_config(tmp_path / "rig.json", CAMERA, cams_from_rig, ["left/", "right/"])

    summary = reconstruct.main(tmp_path / "images", tmp_path / "ws",
                               rig_config=str(tmp_path / "rig.json"), matcher="sequential",
                               seed=0)

    assert summary["matching"]["matcher"] == "sequential" and len(summary["models"]) == 1
    model = pycolmap.Reconstruction(tmp_path / "ws" / "sparse" / "0")
    assert model.num_reg_frames() == DRIVE_FRAMES and model.num_reg_images() == 2 * DRIVE_FRAMES
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    assert evaluate.evaluate(model, truth)["R_err_max_deg"] < DRIVE_R_ERR_MAX_DEG
    cameras, _ = evaluate.aligned_to_ground_truth(model, truth, with_scale=False)
    assert max(np.linalg.norm(pose.inverse().translation - truth.poses[name].inverse().translation)
               for name, pose in cameras.items()) < DRIVE_CENTRE_MAX_M


def generated_rigs(database_path: Path, num_rigs: int, num_cameras: int, num_frames: int,
                   num_points: int, seed: int, noise_px: float = 0.0) -> pycolmap.Reconstruction:
    """COLMAP's generator with its own camera: `num_rigs` rigs of `num_cameras` cameras,
    `num_frames` frames each; returns the truth."""
    return write_pycolmap_dataset(database_path, None, seed, num_rigs * num_cameras * num_frames,
                                  noise_px, num_points, num_cameras, num_rigs=num_rigs)


def test_compare_measures_each_mappers_model_against_the_databases_rig(tmp_path: Path) -> None:
    """COLMAP's generator: one rig of 3 cameras, 5 frames, no noise; black images (our
    mapper reads point colours)."""
    truth = generated_rigs(tmp_path / "database.db", 1, 3, 5, num_points=200, seed=0)
    (tmp_path / "images").mkdir()
    for image in truth.images.values():
        cv2.imwrite(str(tmp_path / "images" / image.name), np.zeros((8, 8), np.uint8))

    report = compare(tmp_path / "database.db", tmp_path / "images", tmp_path / "CMP",
                     mappers="ours,colmap_incremental", seed=0, progress=False)

    assert set(report["mappers"]) == {"ours", "colmap_incremental"}
    for name, entry in report["mappers"].items():  # noise-free: each keeps the rig closely
        consistency = entry["rig_consistency"]
        assert consistency["num_frames"] == 5, name
        assert consistency["rotation_max_deg"] < 1e-3, name
        assert consistency["translation_max"] < 1e-3, name


@pytest.mark.parametrize(("num_rigs", "num_cameras"), [(1, 2), (2, 3)])
def test_mapper_registers_whole_frames_and_keeps_the_rig(tmp_path: Path, num_rigs: int,
                                                         num_cameras: int) -> None:
    """COLMAP's generator, rigs of calibrated cameras with 0.5 px noise: every image
    registered, each frame in one piece with the rig's relative poses exactly (held
    constant), poses near the truth, and the rigs and frames in the model written."""
    truth = generated_rigs(tmp_path / "database.db", num_rigs, num_cameras, 12 // num_rigs,
                           num_points=300, seed=0, noise_px=0.5)
    (tmp_path / "images").mkdir()

    mapper.run(tmp_path / "database.db", tmp_path / "images", tmp_path / "out",
               mapper.MapperOptions(seed=0), progress=False)

    model = pycolmap.Reconstruction(tmp_path / "out" / "0")
    assert model.num_reg_images() == truth.num_images()
    assert model.num_frames() == truth.num_frames() and model.num_rigs() == num_rigs
    kept = rig_consistency(model, model_rig_frames(truth))
    assert kept["num_frames"] == truth.num_frames()
    assert kept["rotation_max_deg"] < 1e-6 and kept["translation_max"] < 1e-6
    report = evaluate.evaluate(model, GroundTruth(
        {image.name: image.cam_from_world() for image in truth.images.values()}, {}))
    assert report["R_err_max_deg"] < 0.1  # measured 0.026 (1x2) and 0.023 deg (2x3)


def test_refining_the_rig_moves_its_cameras_only_where_asked(tmp_path: Path) -> None:
    """--Mapper.ba_refine_sensor_from_rig 1 on a rig whose calibration is off by a turn of
    the second camera: the adjustment moves that camera back towards the truth; with the
    rig in --Mapper.constant_rig_list_path, the calibration stays as given."""
    generated_rigs(tmp_path / "database.db", 1, 2, 6, num_points=300, seed=1)
    with pycolmap.Database.open(str(tmp_path / "database.db")) as db:
        (rig,) = db.read_all_rigs()
        (sensor,) = rig.non_ref_sensors
        true_pose = rig.sensor_from_rig(sensor)
        rig.set_sensor_from_rig(sensor, pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.radians([0.3, 0.0, 0.0])), np.zeros(3)) * true_pose)
        db.update_rig(rig)
    (tmp_path / "images").mkdir()
    (tmp_path / "rigs.txt").write_text(f"{rig.rig_id}\n")

    def turned_by(output: Path, *flags: str) -> float:
        args = ["mapper", "--database_path", tmp_path / "database.db", "--image_path",
                tmp_path / "images", "--output_path", output, "--seed", "0", *flags]
        assert cli.main([str(arg) for arg in args]) == 0
        model = pycolmap.Reconstruction(output / "0")
        pose = model.rigs[rig.rig_id].sensor_from_rig(sensor)
        return rotation_angles_deg((pose.rotation.matrix().T @ true_pose.rotation.matrix())[None])[0]

    assert turned_by(tmp_path / "constant") == pytest.approx(0.3, abs=1e-9)
    assert turned_by(tmp_path / "listed", "--Mapper.ba_refine_sensor_from_rig", "1",
                     "--Mapper.constant_rig_list_path", tmp_path / "rigs.txt") == \
        pytest.approx(0.3, abs=1e-9)
    assert turned_by(tmp_path / "refined", "--Mapper.ba_refine_sensor_from_rig", "1") < 0.1


def wide_rig(database_path: Path, seed: int) -> pycolmap.Reconstruction:
    """COLMAP's generator: one rig of 3 cameras about 0.5 apart (the scene about 5 away),
    4 frames, 0.5 px noise; returns the truth."""
    return write_pycolmap_dataset(database_path, None, seed, 12, 0.5, 200, 3,
                                  rig_baseline=0.5)


def assert_metric_and_near_the_truth(model: pycolmap.Reconstruction,
                                     truth: pycolmap.Reconstruction) -> None:
    """Every image registered, the rig kept, and the poses within 0.1 deg of the truth's
    after a similarity whose scale is the truth's to 1 %: the rig's baseline made the
    model metric."""
    assert model.num_reg_images() == truth.num_images()
    assert rig_consistency(model, model_rig_frames(truth))["rotation_max_deg"] < 1e-6
    names = sorted(image.name for image in truth.images.values())
    centres = [np.array([reconstruction.find_image_with_name(name).projection_center()
                         for name in names]) for reconstruction in (model, truth)]
    assert fit_similarity(*centres).scale == pytest.approx(1.0, abs=0.01)
    report = evaluate.evaluate(model, GroundTruth(
        {image.name: image.cam_from_world() for image in truth.images.values()}, {}))
    assert report["R_err_max_deg"] < 0.1


def test_a_model_starts_from_one_frame_where_no_two_frames_share_verified_matches(
        tmp_path: Path) -> None:
    """Verified matches only within frames: no pair of two frames can start a model, one
    frame's rig baseline can (the next frames registered through raw matches)."""
    truth = wide_rig(tmp_path / "database.db", seed=0)
    with pycolmap.Database.open(str(tmp_path / "database.db")) as db:
        frame_of = {image.image_id: image.frame_id for image in db.read_all_images()}
        pair_ids, _ = db.read_two_view_geometries()
        for pair_id in pair_ids:
            id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
            if frame_of[id1] != frame_of[id2]:
                db.delete_two_view_geometry(id1, id2)
    (tmp_path / "images").mkdir()

    mapper.run(tmp_path / "database.db", tmp_path / "images", tmp_path / "out",
               mapper.MapperOptions(seed=0), progress=False)

    assert_metric_and_near_the_truth(pycolmap.Reconstruction(tmp_path / "out" / "0"), truth)


def test_initial_images_of_one_frame_start_the_model_from_that_frame(tmp_path: Path) -> None:
    """--Mapper.init_image_id1/2 of one frame: the model starts from that frame, which
    holds the gauge at the origin; a frame whose matches triangulate into fewer points
    than --Mapper.init_min_num_inliers is a one-line error."""
    truth = wide_rig(tmp_path / "database.db", seed=1)
    frame = truth.frames[2]
    id1, id2 = sorted(data_id.id for data_id in frame.image_ids)[:2]
    (tmp_path / "images").mkdir()

    def run(output: Path, min_num_inliers: int) -> None:
        options = mapper.MapperOptions(seed=0)
        options.initialization = dataclasses.replace(
            options.initialization, image_id1=id1, image_id2=id2,
            min_num_inliers=min_num_inliers)
        mapper.run(tmp_path / "database.db", tmp_path / "images", output, options,
                   progress=False)

    run(tmp_path / "out", min_num_inliers=30)
    model = pycolmap.Reconstruction(tmp_path / "out" / "0")
    assert_metric_and_near_the_truth(model, truth)
    np.testing.assert_allclose(model.frames[frame.frame_id].rig_from_world.matrix(),
                               np.eye(4)[:3], atol=1e-12)
    with pytest.raises(UserError, match=f"initial images {id1} and {id2} are of one frame"):
        run(tmp_path / "few", min_num_inliers=10_000)


def test_the_frames_relative_pose_is_asked_of_the_chosen_pair_alone(tmp_path: Path,
                                                                     monkeypatch) -> None:
    """The initial pair of a rig's frames: the generalized relative pose (the costly
    step) is computed for the pair with most points, not for every candidate; a
    candidate whose frames give none makes way for the next best, as where all were asked."""
    from colmap_ext.database import read_database
    from colmap_ext.mapper import initial_pair
    from colmap_ext.mapper.descriptors import NearestDescriptors
    from colmap_ext.mapper.model import Model
    from colmap_ext.mapper.two_view import verified_matches

    generated_rigs(tmp_path / "database.db", 1, 4, 6, num_points=300, seed=0, noise_px=0.5)
    db = read_database(tmp_path / "database.db")
    options = mapper.MapperOptions(seed=0)
    model = Model(db, NearestDescriptors(db.descriptors, {i: len(db.images[i].keypoints)
                                                          for i in db.images}, 3, 2**26, 1))
    matches = verified_matches(model, options.two_view, 0, progress=False)
    asked = []
    with_frames = initial_pair.with_frames

    def choose(refuse: set):
        def counted(model, reconstructed, *args):
            asked.append(reconstructed.pair)
            return None if reconstructed.pair in refuse else with_frames(model, reconstructed,
                                                                         *args)
        monkeypatch.setattr(initial_pair, "with_frames", counted)
        asked.clear()
        return initial_pair.best_pair(model, matches, options.initialization, options.two_view,
                                      options.triangulation, set(), 0)

    chosen = choose(set())
    assert asked == [chosen.pair] and chosen.rig2_from_rig1 is not None
    after = choose({chosen.pair})
    assert asked == [chosen.pair, after.pair] and after.rig2_from_rig1 is not None
    assert len(after.matches) <= len(chosen.matches)
