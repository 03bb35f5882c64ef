"""The calibrated bundle adjuster (solvers.bundle_adjust): on COLMAP's generator, from
perturbed poses and points, it reaches the optimum of pycolmap's Ceres adjuster on the
same problem, for several camera models and a rig; its residual is the reprojection error
in pixels to first order (cameras.pixels_from_tangent)."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

import solvers
from colmap_ext.cameras import pixels_from_tangent, rays
from colmap_ext.mapper.options import BundleAdjustmentOptions
from colmap_ext.synthetic.pycolmap_generator import write_pycolmap_dataset


def _rotation_deg(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d) -> float:
    cosine = (np.trace(a.rotation.matrix().T @ b.rotation.matrix()) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))


def _perturbed(truth: pycolmap.Reconstruction, seed: int) -> pycolmap.Reconstruction:
    """The truth with each frame turned by about 0.3 degrees and moved, and the points moved."""
    rng = np.random.default_rng(seed)
    start = pycolmap.Reconstruction(truth)
    for frame in start.frames.values():
        turn = pycolmap.Rotation3d(rng.normal(scale=0.003, size=3))
        pose = frame.rig_from_world
        frame.rig_from_world = pycolmap.Rigid3d(turn * pose.rotation,
                                                pose.translation + rng.normal(scale=0.01, size=3))
    for point in start.points3D.values():
        point.xyz = point.xyz + rng.normal(scale=0.01, size=3)
    return start


def _ceres(start: pycolmap.Reconstruction, loss: str) -> tuple[pycolmap.Reconstruction, float]:
    """pycolmap's adjuster to convergence (intrinsics and rigs constant, COLMAP's gauge):
    the adjusted model and its cost."""
    model = pycolmap.Reconstruction(start)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in model.reg_image_ids():
        config.add_image(image_id)
    for camera_id in model.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    for rig in model.rigs.values():
        for sensor_id in rig.non_ref_sensors:
            config.set_constant_sensor_from_rig_pose(sensor_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False,
                                               refine_extra_params=False, print_summary=False)
    options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss.upper())
    options.ceres.solver_options.gradient_tolerance = 1e-12
    options.ceres.solver_options.max_num_iterations = 200
    summary = pycolmap.create_default_bundle_adjuster(options, config, model).solve()
    return model, summary.ceres_summary.final_cost


def _ours(start: pycolmap.Reconstruction, loss: str,
          num_threads: int = 1) -> solvers.BundleAdjustmentResult:
    """solvers.bundle_adjust on the same problem and gauge as _ceres: the first image's
    frame constant, and the next frame's translation held along its largest baseline."""
    image_ids = sorted(start.reg_image_ids())
    frame_ids = sorted({start.images[i].frame_id for i in image_ids})
    frames = [start.frames[f].rig_from_world for f in frame_ids]
    point_ids = sorted(start.points3D)
    point_index = {p: k for k, p in enumerate(point_ids)}
    observation_image, observation_point, image_rays, jacobians, sensors = [], [], [], [], []
    for k, image_id in enumerate(image_ids):
        image = start.images[image_id]
        camera = start.cameras[image.camera_id]
        observed = [p for p in image.points2D if p.has_point3D()]
        directions = camera.cam_ray_from_img(np.array([p.xy for p in observed]))
        image_rays.append(directions)
        jacobians.append(pixels_from_tangent(camera, directions))
        observation_image += [k] * len(observed)
        observation_point += [point_index[p.point3D_id] for p in observed]
        rig_from_world = start.frames[image.frame_id].rig_from_world
        sensors.append(image.cam_from_world() * rig_from_world.inverse())
    image_frame = [frame_ids.index(start.images[i].frame_id) for i in image_ids]
    free = np.ones((len(frames), 6), bool)
    first, second = image_frame[0], next(f for f in image_frame if f != image_frame[0])
    free[first] = False
    baseline = (frames[first] * frames[second].inverse()).translation
    free[second, 3 + int(np.argmax(np.abs(baseline)))] = False
    return solvers.bundle_adjust(
        frames, free, sensors, image_frame, np.array([start.points3D[p].xyz for p in point_ids]),
        np.ones(len(point_ids), bool), observation_image, observation_point,
        np.concatenate(image_rays), np.concatenate(jacobians), loss=loss, max_iterations=200,
        gradient_tolerance=1e-12, num_threads=num_threads)


@pytest.mark.parametrize("camera_model, num_cameras, loss", [
    ("PINHOLE", 1, "trivial"),
    ("SIMPLE_RADIAL", 1, "cauchy"),
    ("OPENCV_FISHEYE", 1, "trivial"),
    ("EQUIRECTANGULAR", 1, "cauchy"),
    ("PINHOLE", 3, "trivial"),  # a rig of three cameras, sensor_from_rig constant
])
def test_bundle_adjust_reaches_the_optimum_of_pycolmaps_adjuster(tmp_path, camera_model,
                                                                  num_cameras, loss):
    truth = write_pycolmap_dataset(tmp_path / "database.db", camera_model, seed=1,
                                   num_images=12 if num_cameras == 1 else 15, noise_px=1.0,
                                   num_points=200, num_cameras=num_cameras)
    start = _perturbed(truth, seed=2)
    ceres, ceres_cost = _ceres(start, loss)
    result = _ours(start, loss)

    frame_ids = sorted({start.images[i].frame_id for i in start.reg_image_ids()})
    moved = max(_rotation_deg(start.frames[f].rig_from_world, ceres.frames[f].rig_from_world)
                for f in frame_ids)
    apart = max(_rotation_deg(pose, ceres.frames[f].rig_from_world)
                for f, pose in zip(frame_ids, result.rigs_from_world))
    assert moved > 0.1  # the start is far from the optimum ...
    assert apart < 2e-3  # ... which both reach, to first order in the residuals
    assert result.final_cost == pytest.approx(ceres_cost, rel=1e-4)  # first order, too


@pytest.mark.parametrize("num_threads", [2, 3])
def test_bundle_adjust_on_threads_takes_the_steps_of_one_thread(tmp_path, num_threads):
    """The residuals and the Schur complement shared among threads: the optimum of one
    thread (the sums are taken in another order: equal to rounding, so near the optimum
    the two may stop an iteration apart)."""
    truth = write_pycolmap_dataset(tmp_path / "database.db", "SIMPLE_RADIAL", seed=3,
                                   num_images=10, noise_px=1.0, num_points=150)
    start = _perturbed(truth, seed=4)
    one, several = _ours(start, "cauchy"), _ours(start, "cauchy", num_threads)
    assert min(several.iterations, one.iterations) > 3
    assert several.final_cost == pytest.approx(one.final_cost, rel=1e-9)
    assert several.final_cost < 0.5 * several.initial_cost
    np.testing.assert_allclose(several.points3D, one.points3D, atol=1e-8)
    for a, b in zip(one.rigs_from_world, several.rigs_from_world):
        assert _rotation_deg(a, b) < 1e-5  # arccos resolves no finer


def _exact_problem(rng: np.random.Generator, num_frames: int, tracks: list[np.ndarray]):
    """Frames on a circle looking at its centre, points near the centre, each track the
    frames seeing one point, every observation exact (a PINHOLE camera): (true frames,
    true points, and the bundle_adjust arguments from perturbed frames and points, the
    first frame and the second's largest translation held, as _ours does)."""
    camera = pycolmap.Camera(model="PINHOLE", width=1000, height=1000,
                             params=[800, 800, 500, 500])
    frames = []
    for angle in np.linspace(0, 2 * np.pi, num_frames, endpoint=False):
        centre = np.array([10 * np.cos(angle), 10 * np.sin(angle), 0.0])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 0.0, 1.0], z)
        rotation = np.stack([x, np.cross(z, x), z])
        frames.append(pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre))
    points = rng.uniform(-2, 2, size=(len(tracks), 3))
    observation_point = np.concatenate([np.full(len(t), p) for p, t in enumerate(tracks)])
    observation_image = np.concatenate(tracks)
    directions = np.array([frames[f] * points[p] for f, p in zip(observation_image,
                                                                 observation_point)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    start = [pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(scale=0.003, size=3)) * f.rotation,
                              f.translation + rng.normal(scale=0.01, size=3)) for f in frames]
    free = np.ones((num_frames, 6), bool)
    start[0] = frames[0]
    free[0] = False
    start[1] = pycolmap.Rigid3d(start[1].rotation, np.where(
        np.arange(3) == np.argmax(np.abs(frames[1].translation)), frames[1].translation,
        start[1].translation))
    free[1, 3 + int(np.argmax(np.abs(frames[1].translation)))] = False
    arguments = (start, free, [pycolmap.Rigid3d()] * num_frames, list(range(num_frames)),
                 points + rng.normal(scale=0.01, size=points.shape), np.ones(len(tracks), bool),
                 observation_image, observation_point, directions,
                 pixels_from_tangent(camera, directions))
    return frames, points, arguments


@pytest.mark.parametrize("long_tracks", [False, True])
def test_bundle_adjust_above_200_frames_reaches_the_truth(long_tracks: bool) -> None:
    """Beyond 200 free frames the reduced camera system is sparse where few frame pairs
    share points (short tracks around a ring) and dense where most do (every point seen
    by every frame, as on a turntable); both solve exact observations to the truth."""
    rng = np.random.default_rng(5)
    num_frames = 210
    tracks = [np.arange(num_frames)] * 40 if long_tracks else \
        [(start + np.arange(4)) % num_frames for start in range(num_frames) for _ in range(5)]
    frames, points, arguments = _exact_problem(rng, num_frames, tracks)
    result = solvers.bundle_adjust(*arguments, max_iterations=100, gradient_tolerance=1e-10,
                                   num_threads=2)
    assert result.initial_cost > 1e3 and result.final_cost < 1e-12
    assert max(_rotation_deg(a, b) for a, b in zip(result.rigs_from_world, frames)) < 1e-4
    np.testing.assert_allclose(result.points3D, points, atol=1e-6)


def test_bundle_adjust_from_an_undamped_first_step_reaches_the_same_optimum_sooner() -> None:
    """A chain of frames, each point seen by four neighbours (a sequence's banded
    problem): the initial trust region radius of a global adjustment in least squares
    (BundleAdjustmentOptions.trust_region_radius) starts with nearly a Gauss-Newton step
    and solves it to the truth in fewer iterations than Ceres's default damping."""
    num_frames = 210
    tracks = [(start + np.arange(4)) % num_frames for start in range(num_frames) for _ in range(5)]
    frames, points, arguments = _exact_problem(np.random.default_rng(6), num_frames, tracks)
    options = BundleAdjustmentOptions()
    radii = (options.initial_trust_region_radius,
             options.trust_region_radius("trivial", local=False))
    damped, undamped = (solvers.bundle_adjust(*arguments, max_iterations=100,
                                              gradient_tolerance=1e-10,
                                              initial_trust_region_radius=radius)
                        for radius in radii)
    for result in (damped, undamped):
        assert result.final_cost < 1e-12
        assert max(_rotation_deg(a, b) for a, b in zip(result.rigs_from_world, frames)) < 1e-4
    assert undamped.iterations < damped.iterations


def test_pixels_from_tangent_give_reprojection_errors_to_first_order():
    """A point 1-3 px off its keypoint's ray, on every kind of camera model: the matrix
    times the point's offset on the tangent plane is its pixel error within 3 % (a
    panorama's keypoints within 45 degrees of its equator: nearer the poles, where a
    pixel across spans ever less, the second order grows with the latitude's tangent)."""
    rng = np.random.default_rng(0)
    for model, params in [("PINHOLE", [500, 500, 512, 384]),
                          ("OPENCV_FISHEYE", [300, 300, 512, 384, 0.05, -0.01, 0.002, -0.001]),
                          ("EQUIRECTANGULAR", [1024, 512])]:
        camera = pycolmap.Camera(model=model, width=1024, height=768 if model != "EQUIRECTANGULAR"
                                 else 512, params=params)
        pixels = rng.uniform([50, 128], [974, 384], size=(100, 2))
        offsets = pixels + rng.normal(scale=2.0, size=pixels.shape)
        # Keypoints the model gives a ray (a fisheye's corners lie beyond it).
        valid = np.isfinite(rays(camera, pixels)).all(1) & np.isfinite(rays(camera, offsets)).all(1)
        assert valid.sum() > 50
        pixels, offsets = pixels[valid], offsets[valid]
        directions = camera.cam_ray_from_img(pixels)
        moved = camera.cam_ray_from_img(offsets)
        tangent = moved / np.einsum("ij,ij->i", moved, directions)[:, None] - directions
        predicted = np.einsum("nij,nj->ni", pixels_from_tangent(camera, directions), tangent)
        np.testing.assert_allclose(predicted, offsets - pixels, atol=0.03 * 3, rtol=0.03,
                                   err_msg=model)


def test_bundle_adjust_refuses_inconsistent_arrays():
    pose = pycolmap.Rigid3d()
    with pytest.raises(ValueError, match="inconsistent array lengths"):
        solvers.bundle_adjust([pose], np.ones((2, 6), bool), [pose], [0], np.zeros((1, 3)),
                              [True], [0], [0], [[0, 0, 1.0]], np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match="unknown loss"):
        solvers.bundle_adjust([pose], np.ones((1, 6), bool), [pose], [0], np.zeros((1, 3)),
                              [True], [0], [0], [[0, 0, 1.0]], np.zeros((1, 2, 3)), loss="l2")
