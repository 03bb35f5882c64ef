"""Synthetic data: projections follow the camera model, databases hold what was written, renders are stable."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from colmap_ext.synthetic.database import (
    add_outliers,
    observe,
    points_for_keypoints,
    scene_points,
    sequential_pairs,
    sift_like,
    true_tracks_reconstruction,
    write_rig_config,
    write_synthetic_database,
)
from colmap_ext.synthetic.render import pixel_grid, render_images, write_ground_truth, write_par_file
from colmap_ext.synthetic.scene import (
    GridIndex,
    cast_rays,
    default_camera,
    driving_scene,
    image_rays,
    rig_scene,
    ring_scene,
    side_by_side_rig,
    trajectory_scene,
)


def opencv_project(params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """OPENCV model written out independently of COLMAP (pixel (0,0)'s centre at (0.5, 0.5))."""
    fx, fy, cx, cy, k1, k2, p1, p2 = params
    x, y = points_cam[:, 0] / points_cam[:, 2], points_cam[:, 1] / points_cam[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def small_camera() -> pycolmap.Camera:
    """The default camera scaled down to 80x60, to keep rendering tests fast."""
    return pycolmap.Camera(
        camera_id=1, model="OPENCV", width=80, height=60, params=[75.0, 75.0, 39.75, 30.25, -0.1, 0.01, 0.0, 0.0]
    )


def to_cam(pose: pycolmap.Rigid3d, points: np.ndarray) -> np.ndarray:
    return points @ pose.rotation.matrix().T + pose.translation


@pytest.fixture(scope="module")
def ring() -> tuple:
    scene = ring_scene(num_images=8, seed=1)
    return scene, scene_points(scene, 3000, seed=2)


def test_ring_cameras_look_at_the_object(ring) -> None:
    scene, _ = ring
    for pose in scene.cams_from_world:
        centre = pose.inverse().translation
        assert np.linalg.norm(centre[:2]) == pytest.approx(3.0)
        origin_cam = to_cam(pose, np.array([[0.0, 0.0, 0.5]]))[0]
        assert origin_cam[2] > 2.5 and np.hypot(*origin_cam[:2]) / origin_cam[2] < 0.1


def test_observations_project_where_the_camera_model_says(ring) -> None:
    scene, points = ring
    params = np.asarray(scene.camera.params)
    for index, pose in enumerate(scene.cams_from_world):
        seen = observe(scene, index, points)
        assert len(seen.point_ids) > 300
        expected = opencv_project(params, to_cam(pose, points[seen.point_ids]))
        np.testing.assert_allclose(seen.pixels, expected, atol=1e-6)
        assert np.all((seen.pixels >= 0) & (seen.pixels < [640, 480]))


def test_hidden_box_faces_are_not_observed(ring) -> None:
    scene, _ = ring
    rng = np.random.default_rng(0)
    pedestal = scene.quads[5:11]  # after the room's floor and four walls
    a, b = rng.random((2, 200, 1))
    seen_on_facing = 0
    for pose_index, pose in enumerate(scene.cams_from_world):
        centre = pose.inverse().translation
        for quad in pedestal:
            points = quad.origin + a * quad.edge_u + b * quad.edge_v
            facing = float(quad.normal @ (centre - quad.origin)) > 0
            seen = observe(scene, pose_index, points)
            assert facing or len(seen.point_ids) == 0
            seen_on_facing += len(seen.point_ids)
    assert seen_on_facing > 1000


def test_rays_hit_the_points_they_were_cast_at(ring) -> None:
    scene, points = ring
    seen = observe(scene, 0, points)
    pose = scene.cams_from_world[0]
    rays = image_rays(scene.camera, seen.pixels)
    hits = cast_rays(scene, pose, rays[:, None, :])
    np.testing.assert_allclose(hits.depth[:, 0], to_cam(pose, points[seen.point_ids])[:, 2], rtol=1e-4)


def test_pixel_centres_follow_colmap_convention() -> None:
    camera = small_camera()
    grid = pixel_grid(camera, supersample=2)
    np.testing.assert_allclose(grid[0], [0.25, 0.25])
    np.testing.assert_allclose(pixel_grid(camera, supersample=1)[camera.width + 1], [1.5, 1.5])
    rays = image_rays(camera, grid)
    back = camera.img_from_cam(np.hstack([rays, np.ones((len(rays), 1))]))
    np.testing.assert_allclose(back, grid, atol=1e-6)


def test_database_round_trip(tmp_path: Path, ring) -> None:
    scene, points = ring
    path = tmp_path / "database.db"
    truth = write_synthetic_database(path, scene, points, noise_px=0.0, outlier_ratio=0.25, two_view_geometries=True)
    with pycolmap.Database.open(path) as db:
        assert db.num_images() == scene.num_images
        assert db.num_rigs() == 1 and db.num_frames() == scene.num_images
        assert db.read_camera(1).params.tolist() == scene.camera.params.tolist()
        for index, image_id in enumerate(truth.image_ids):
            assert db.read_image(image_id).name == scene.image_names[index]
            keypoints = db.read_keypoints(image_id)
            assert keypoints.shape == (len(truth.point_ids[index]), 6)
            np.testing.assert_allclose(keypoints[:, :2], truth.projections[index], atol=1e-3)
            descriptors = db.read_descriptors(image_id).data
            assert descriptors.shape == (len(keypoints), 128) and descriptors.dtype == np.uint8
        assert db.num_matched_image_pairs() == len(truth.matches)
        for pair, matches in truth.matches.items():
            np.testing.assert_array_equal(db.read_matches(*pair), matches)
        geometries = dict(zip(*db.read_two_view_geometries()))
    assert len(geometries) == sum(len(m) >= 15 for m in truth.inlier_matches.values())
    for pair, matches in truth.matches.items():
        i, j = truth.image_ids.index(pair[0]), truth.image_ids.index(pair[1])
        same_point = truth.point_ids[i][matches[:, 0]] == truth.point_ids[j][matches[:, 1]]
        inliers = truth.inlier_matches[pair]
        assert same_point.sum() == len(inliers)
        assert len(np.unique(matches[:, 0])) == len(matches) == len(np.unique(matches[:, 1]))
        if len(matches) >= 40:
            assert 1 - same_point.mean() == pytest.approx(0.25, abs=0.03)
    tri_pair = next(p for p, m in truth.inlier_matches.items() if len(m) >= 15)
    geometry = [g for p, g in geometries.items() if pycolmap.image_pair_to_pair_id(*tri_pair) == p][0]
    assert geometry.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    np.testing.assert_array_equal(geometry.inlier_matches, truth.inlier_matches[tri_pair])


def test_keypoint_noise_has_the_requested_size(tmp_path: Path, ring) -> None:
    scene, points = ring
    truth = write_synthetic_database(tmp_path / "noisy.db", scene, points, noise_px=0.5)
    with pycolmap.Database.open(tmp_path / "noisy.db") as db:
        residuals = np.concatenate(
            [db.read_keypoints(i)[:, :2] - p for i, p in zip(truth.image_ids, truth.projections)]
        )
    assert residuals.std() == pytest.approx(0.5, rel=0.1)


def test_true_tracks_hold_every_true_observation_at_the_truth(tmp_path: Path, ring) -> None:
    """The maximum-likelihood reference's start: every keypoint of a point seen twice or
    more is an observation of that point, at the database's (noisy) position, the images
    at their true poses; its reprojection errors are the noise's."""
    scene, points = ring
    truth = write_synthetic_database(tmp_path / "db.db", scene, points, noise_px=0.5)
    model = true_tracks_reconstruction(tmp_path / "db.db", scene, points, truth)
    seen = np.bincount(np.concatenate(truth.point_ids))
    assert model.num_points3D() == np.count_nonzero(seen >= 2)
    assert model.compute_num_observations() == seen[seen >= 2].sum()
    for view, image_id in enumerate(truth.image_ids):
        image = model.images[image_id]
        assert np.allclose(image.cam_from_world().matrix(), scene.cams_from_world[view].matrix())
        for kp in np.flatnonzero(seen[truth.point_ids[view]] >= 2)[:20]:
            point = model.points3D[image.points2D[kp].point3D_id]
            np.testing.assert_allclose(point.xyz, points[truth.point_ids[view][kp]])
    errors = [np.linalg.norm(model.cameras[image.camera_id].img_from_cam(
        to_cam(image.cam_from_world(), model.points3D[p.point3D_id].xyz[None]))[0] - p.xy)
        for image in model.images.values() for p in image.points2D if p.has_point3D()]
    assert np.sqrt(np.mean(np.square(errors))) == pytest.approx(0.5 * np.sqrt(2), rel=0.1)


def test_descriptors_match_their_own_point() -> None:
    rng = np.random.default_rng(3)
    base = rng.exponential(1.0, (500, 128))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    first, second = sift_like(base, rng).astype(float), sift_like(base, rng).astype(float)
    squared = (first**2).sum(1)[:, None] + (second**2).sum(1)[None] - 2 * first @ second.T
    distances = np.sqrt(np.maximum(squared, 0.0))
    nearest = np.sort(distances, axis=1)
    assert np.all(np.argmin(distances, axis=1) == np.arange(500))
    assert np.all(nearest[:, 0] < 0.8 * nearest[:, 1])


@settings(max_examples=40, deadline=None)
@given(
    num_true=st.integers(0, 120),
    extra=st.tuples(st.integers(0, 60), st.integers(0, 60)),
    ratio=st.floats(0.0, 0.6),
    seed=st.integers(0, 1000),
)
def test_outliers_are_one_to_one_and_wrong(num_true: int, extra: tuple[int, int], ratio: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    counts = (num_true + extra[0], num_true + extra[1])
    true_matches = np.stack([rng.permutation(counts[0])[:num_true], rng.permutation(counts[1])[:num_true]], axis=1)
    matches, inliers = add_outliers(true_matches, counts, ratio, rng)
    assert len(np.unique(matches[:, 0])) == len(matches) == len(np.unique(matches[:, 1]))
    true_set = {tuple(m) for m in true_matches.tolist()}
    assert [tuple(m) in true_set for m in matches.tolist()] == inliers.tolist()
    if len(matches) >= 20:
        assert abs((~inliers).mean() - ratio) <= 2 / len(matches) + 1e-9


def test_trajectory_views_overlap_only_locally() -> None:
    scene = trajectory_scene(num_images=30, seed=0)
    points = scene_points(scene, 6000, seed=0)
    seen = [set(observe(scene, i, points).point_ids.tolist()) for i in range(scene.num_images)]
    assert all(len(s) > 100 for s in seen)
    assert len(seen[0] & seen[1]) > 0.5 * len(seen[0])
    assert not seen[0] & seen[29]


def centres(scene) -> np.ndarray:
    return np.array([pose.inverse().translation for pose in scene.cams_from_world])


def view_directions(scene) -> np.ndarray:
    """The cameras' optical axes (camera z) in the world."""
    return np.array([pose.rotation.matrix()[2] for pose in scene.cams_from_world])


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cosines = np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.rad2deg(np.arccos(np.clip(cosines, -1.0, 1.0)))


@pytest.fixture(scope="module")
def drive():
    return driving_scene(400, seed=1, stop_every=150, stop_frames=10)


def test_driving_camera_looks_where_it_goes(drive) -> None:
    c = centres(drive)
    moving = np.flatnonzero(np.r_[True, np.linalg.norm(np.diff(c, axis=0), axis=1) > 0])
    travel = c[moving[2:]] - c[moving[:-2]]  # central differences over the places
    heading = np.rad2deg(np.arctan2(travel[:, 1], travel[:, 0]))
    off_axis = np.abs((heading + 45) % 90 - 45)  # the streets run along x and y
    straight = off_axis < 5.0
    straight[1:-1] &= straight[:-2] & straight[2:]  # not next to a corner, where the differences cut it
    assert straight.mean() > 0.75
    views = view_directions(drive)[moving[1:-1]]
    assert angles_deg(views[straight], travel[straight]).max() < 3.0


def test_driving_turns_are_sharp_corners(drive) -> None:
    c = centres(drive)
    places = c[np.r_[True, np.linalg.norm(np.diff(c, axis=0), axis=1) > 0]]
    steps = np.diff(places[:, :2], axis=0)
    turned = np.rad2deg(np.diff(np.unwrap(np.arctan2(steps[:, 1], steps[:, 0]))))
    turning = np.abs(turned) > 5.0
    runs = np.split(turned, np.flatnonzero(np.diff(turning.astype(int)))+ 1)
    corners = [run for run in runs if np.abs(run).min() > 5.0]
    assert len(corners) >= 4  # 400 m, a corner every 60 m or so
    for run in corners:
        assert len(run) <= 8 and abs(run.sum()) == pytest.approx(90.0, abs=6.0)
    assert [np.sign(run.sum()) for run in corners][:4] == [1, -1, 1, -1]  # left, right: no loop


def test_driving_stops_stand_still_and_the_rest_moves_a_step(drive) -> None:
    c = centres(drive)
    baselines = np.linalg.norm(np.diff(c, axis=0), axis=1)
    standing = np.flatnonzero(baselines == 0.0) + 1
    np.testing.assert_array_equal(standing, [*range(151, 160), *range(301, 310)])
    for first in (150, 300):  # one pose through the stop
        for frame in range(first + 1, first + 10):
            assert drive.cams_from_world[frame].rotation.angle_to(drive.cams_from_world[first].rotation) == 0.0
    moving = baselines[baselines > 0]  # a step; a little more or less round a corner's outside or inside
    assert np.median(moving) == pytest.approx(1.0, abs=0.01) and np.all((moving > 0.8) & (moving < 1.2))


def test_driving_loop_comes_back_to_its_start() -> None:
    scene = driving_scene(300, seed=2, loop=True)
    c = centres(scene)
    assert 0.5 < np.linalg.norm(c[-1] - c[0]) < 1.5
    assert angles_deg(view_directions(scene)[:1], view_directions(scene)[-1:])[0] < 5.0
    assert np.linalg.norm(c - c[0], axis=1).max() > 50.0  # it went somewhere
    points = points_for_keypoints(scene, 1000, seed=2, max_distance=40.0)
    first, last = (set(observe(scene, i, points, 40.0).point_ids.tolist()) for i in (0, scene.num_images - 1))
    assert len(first & last) > 0.5 * len(first)
    middle = set(observe(scene, scene.num_images // 2, points, 40.0).point_ids.tolist())
    assert not first & middle


def test_drive_database_has_the_keypoints_and_pairs_asked_for(tmp_path: Path) -> None:
    scene = driving_scene(120, seed=3, stop_every=50, stop_frames=5)
    points = points_for_keypoints(scene, 1000, seed=3, max_distance=40.0)
    truth = write_synthetic_database(tmp_path / "drive.db", scene, points, max_distance=40.0, seed=3,
                                     two_view_geometries=True, pairs=sequential_pairs(scene.num_images, 10))
    keypoints = np.array([len(ids) for ids in truth.point_ids])
    assert keypoints.mean() == pytest.approx(1000, rel=0.1) and keypoints.min() > 200
    depths = np.concatenate([observe(scene, i, points, 40.0).depths for i in range(0, 120, 10)])
    assert depths.max() <= 40.0 and np.percentile(depths, 5) > 4.0
    index = {image_id: k for k, image_id in enumerate(truth.image_ids)}
    gaps = [index[j] - index[i] for i, j in truth.matches]
    assert max(gaps) == 10 and len(truth.matches) > 0.9 * 10 * scene.num_images
    with pycolmap.Database.open(tmp_path / "drive.db") as db:
        standing = db.read_two_view_geometry(truth.image_ids[50], truth.image_ids[53])
        moving = db.read_two_view_geometry(truth.image_ids[40], truth.image_ids[43])
    assert standing.config == pycolmap.TwoViewGeometryConfiguration.PANORAMIC
    assert np.linalg.norm(standing.cam2_from_cam1.translation) == 0.0
    assert moving.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED


def test_sequential_pairs_wrap_round_a_loop() -> None:
    assert sequential_pairs(5, 2) == {(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4)}
    assert sequential_pairs(5, 2, closed=True) == sequential_pairs(5, 2) | {(0, 3), (0, 4), (1, 4)}


def test_sequential_pairs_of_a_rig_pair_every_image_of_the_next_frames_and_its_own() -> None:
    # Frames of two images: 0 = (0, 1), 1 = (2, 3), 2 = (4, 5).
    assert sequential_pairs(3, 1, images_per_frame=2) == {
        (0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3), (2, 4), (2, 5), (3, 4), (3, 5), (4, 5)}


def test_a_rig_scene_is_a_stereo_pair_at_every_pose_with_a_camera_per_folder(tmp_path: Path) -> None:
    """rig_scene's images, the rig's cameras at each pose of the drive; its database has a
    camera per image folder and, with its rig configuration applied, one frame a pose."""
    from colmap_ext.rigs import apply_rig_config, read_rig_config

    drive = driving_scene(30, seed=4)
    cams_from_rig = side_by_side_rig(2, 0.54)
    scene = rig_scene(drive, cams_from_rig, ["left/", "right/"])
    assert scene.image_names[:3] == ["left/drive00000.png", "right/drive00000.png", "left/drive00001.png"]
    for rig_from_world, left, right in zip(drive.cams_from_world, scene.cams_from_world[::2],
                                           scene.cams_from_world[1::2]):
        np.testing.assert_allclose(left.matrix(), rig_from_world.matrix(), atol=1e-12)
        right_of_left = left.rotation.matrix()[0]  # the camera's x axis in the world
        np.testing.assert_allclose(right.inverse().translation - left.inverse().translation,
                                   0.54 * right_of_left, atol=1e-12)
    write_synthetic_database(tmp_path / "rig.db", scene, points_for_keypoints(scene, 300, seed=4),
                             pairs=sequential_pairs(drive.num_images, 2, images_per_frame=2))
    write_rig_config(tmp_path / "rig.json", scene.camera, cams_from_rig, ["left/", "right/"])
    apply_rig_config(tmp_path / "rig.db", read_rig_config(tmp_path / "rig.json"))
    with pycolmap.Database.open(tmp_path / "rig.db") as db:
        cameras = {image.name.partition("/")[0]: image.camera_id for image in db.read_all_images()}
        (rig,) = db.read_all_rigs()
        frames = db.read_all_frames()
    assert len(set(cameras.values())) == 2
    assert rig.ref_sensor_id.id == cameras["left"] and len(frames) == drive.num_images
    right = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cameras["right"])
    np.testing.assert_allclose(rig.sensor_from_rig(right).matrix(), cams_from_rig[1].matrix())


def test_nearby_points_are_found_without_scanning() -> None:
    rng = np.random.default_rng(5)
    xy = rng.uniform(-300, 300, (20000, 2))
    grid = GridIndex(xy, 40.0)
    for center in rng.uniform(-350, 350, (20, 2)):
        found = grid.near(center, 55.0)
        within = np.flatnonzero(np.abs(xy - center).max(axis=1) <= 55.0)
        assert np.all(np.diff(found) > 0) and set(within) <= set(found)
        assert len(found) < 0.1 * len(xy)


def test_observing_near_the_camera_sees_what_observing_all_sees(drive) -> None:
    points = scene_points(drive, 60000, seed=6)
    grid = GridIndex(points[:, :2], 40.0)
    for image_index in (0, 57, 155, 399):
        everything = observe(drive, image_index, points, 40.0)
        nearby = observe(drive, image_index, points, 40.0, grid)
        assert len(everything.point_ids) > 100
        np.testing.assert_array_equal(nearby.point_ids, everything.point_ids)


def test_a_long_drive_database_takes_memory_in_proportion(tmp_path: Path) -> None:
    """300 frames of 1,000 keypoints: the generator's arrays (the ground truth it returns
    included) stay below 400 KiB a frame, about 2/3 of the database's size (matching every
    pair of views that share points, or scanning all points per view, would not; at 2,000
    frames, run alone under tracemalloc: 571 MiB, 292 KiB a frame)."""
    scene = driving_scene(300, seed=0)
    tracemalloc.start()
    try:
        points = points_for_keypoints(scene, 1000, seed=0, max_distance=40.0)
        write_synthetic_database(tmp_path / "drive.db", scene, points, max_distance=40.0,
                                 two_view_geometries=True, pairs=sequential_pairs(scene.num_images, 10))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 400 * 1024 * scene.num_images


def test_colmap_mapper_reconstructs_a_synthetic_database(tmp_path: Path) -> None:
    scene = ring_scene(num_images=10, seed=4)
    points = scene_points(scene, 2500, seed=4)
    write_synthetic_database(tmp_path / "db.db", scene, points, two_view_geometries=True, seed=4)
    options = pycolmap.IncrementalPipelineOptions()
    options.constant_cameras = {1}
    options.num_threads = 2
    (tmp_path / "images").mkdir()
    models = pycolmap.incremental_mapping(tmp_path / "db.db", tmp_path / "images", tmp_path / "sparse", options)
    model = max(models.values(), key=lambda m: m.num_reg_images())
    assert model.num_reg_images() == scene.num_images
    assert model.compute_mean_reprojection_error() < 1.0
    truth = dict(zip(scene.image_names, scene.cams_from_world))
    images = list(model.images.values())
    first_est, first_true = images[0].cam_from_world(), truth[images[0].name]
    for image in images[1:]:
        estimated = image.cam_from_world() * first_est.inverse()
        expected = truth[image.name] * first_true.inverse()
        assert estimated.rotation.angle_to(expected.rotation) < np.deg2rad(0.1)


def test_renders_have_the_camera_size_and_depend_only_on_the_seed(tmp_path: Path) -> None:
    scene = ring_scene(num_images=2, camera=small_camera())
    render_images(scene, tmp_path / "a", seed=5)
    render_images(scene, tmp_path / "b", seed=5)
    render_images(scene, tmp_path / "c", seed=6)
    for name in scene.image_names:
        image = cv2.imread(str(tmp_path / "a" / name), cv2.IMREAD_UNCHANGED)
        assert image.shape == (60, 80) and image.dtype == np.uint8
        assert image.std() > 20
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
        assert (tmp_path / "a" / name).read_bytes() != (tmp_path / "c" / name).read_bytes()


def test_ground_truth_files_hold_the_scene(tmp_path: Path) -> None:
    scene = ring_scene(num_images=4)
    write_par_file(scene, tmp_path / "ring_par.txt")
    write_ground_truth(scene, tmp_path / "gt")
    lines = (tmp_path / "ring_par.txt").read_text().splitlines()
    assert int(lines[0]) == 4
    model = pycolmap.Reconstruction(tmp_path / "gt")
    assert model.num_images() == 4 and model.cameras[1].params.tolist() == default_camera().params.tolist()
    for line, name, pose in zip(lines[1:], scene.image_names, scene.cams_from_world):
        fields = line.split()
        numbers = np.array(fields[1:], float)
        assert fields[0] == name and len(numbers) == 21
        np.testing.assert_allclose(numbers[:9].reshape(3, 3), default_camera().calibration_matrix())
        np.testing.assert_allclose(numbers[9:18].reshape(3, 3), pose.rotation.matrix(), atol=1e-12)
        np.testing.assert_allclose(numbers[18:], pose.translation, atol=1e-12)
        image = model.find_image_with_name(name)
        np.testing.assert_allclose(image.cam_from_world().matrix(), pose.matrix(), atol=1e-9)
