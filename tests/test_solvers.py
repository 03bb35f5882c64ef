"""The solvers package on synthetic scenes: accuracy, agreement with pycolmap, conventions,
reproducibility, and bad or degenerate input (including a hypothesis fuzz)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pycolmap
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import solvers
from colmap_ext.geometry import sampson_angles

FOCAL = 1000.0  # pixels
SIZE = 1000  # image width and height in pixels
NOISE = 0.5 / FOCAL  # 0.5 px, in normalized image units (about radians near the axis)
MAX_ERROR = 2.0 / FOCAL  # radians: 2 px at the principal point, 4 sigma: nearly every true
#                          inlier passes
CAMERA = pycolmap.Camera(model="PINHOLE", width=SIZE, height=SIZE,
                         params=[FOCAL, FOCAL, SIZE / 2, SIZE / 2])
OUTLIER_RATIOS = [0.0, 0.2, 0.4, 0.6]
# Bounds of the accuracy tests, about 3x the worst error measured over 40 scenes per outlier
# ratio (seeds r*100 + 1000k, k < 40; RANSAC seeds 1 to 40), 0.5 px noise:
RELATIVE_MAX_ROTATION_DEG = 0.3  # worst 0.110 (300-500 points)
RELATIVE_MAX_TRANSLATION_DEG = 1.0  # worst 0.372
ABSOLUTE_MAX_ROTATION_DEG = 0.09  # worst 0.029 (300 points)
ABSOLUTE_MAX_TRANSLATION_DEG = 0.75  # worst 0.243 (t's direction is unstable when |t| is small)
ABSOLUTE_MAX_CENTRE_ERROR = 0.007  # worst 0.0022, scene 4.5 away
MIN_INLIER_AGREEMENT = 0.96  # worst 0.988 (1.2 % of the labels wrong)
# Rigs of three cameras 1 from the rig's centre (RIG), 0.5 px noise, about 3x the worst
# error measured over 12 scenes per outlier ratio 0, 0.2, 0.3, 0.4 (RANSAC seeds 1 to 12;
# relative pose: 6-point and 5+1-point, scenes 10 to 30 deg past a third of a turn):
RIG_ABSOLUTE_MAX_ROTATION_DEG = 0.025  # worst 0.0077
RIG_ABSOLUTE_MAX_CENTRE_ERROR = 0.0025  # worst 0.00077, scene 4.5 away
RIG_RELATIVE_MAX_ROTATION_DEG = 1.1  # worst 0.367
RIG_RELATIVE_MAX_TRANSLATION_ERROR = 0.2  # worst 0.061, rig moving about 0.5
RIG_OUTLIER_RATIOS = [0.0, 0.2, 0.4]
RIG_ANGULAR_NOISE = 3e-4  # radians, for rigs of 360-degree cameras


# ---------------------------------------------------------------- synthetic scenes

def rotation(rng: np.random.Generator, max_deg: float) -> pycolmap.Rotation3d:
    axis = rng.normal(size=3)
    return pycolmap.Rotation3d(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(0, max_deg)))


def transform(pose: pycolmap.Rigid3d, X: np.ndarray) -> np.ndarray:
    return X @ pose.rotation.matrix().T + pose.translation


def project(X_cam: np.ndarray) -> np.ndarray:
    return X_cam[:, :2] / X_cam[:, 2:]


def points_in_view(rng: np.random.Generator, n: int) -> np.ndarray:
    """Camera-frame points inside a 53 degree field of view, depths 3 to 6."""
    depth = rng.uniform(3, 6, n)
    return np.column_stack([rng.uniform(-0.45, 0.45, (n, 2)) * depth[:, None], depth])


@dataclass
class TwoView:
    pose: pycolmap.Rigid3d  # cam2_from_cam1, unit translation
    X: np.ndarray  # (N, 3) points in camera 1 (= world) coordinates
    x1: np.ndarray  # (N, 2) normalized image points, noisy
    x2: np.ndarray  # (N, 2), noisy, outliers replaced by random image points
    inliers: np.ndarray  # (N,) bool, true correspondences


def two_view(seed: int, n: int = 500, outlier_ratio: float = 0.0, noise: float = NOISE) -> TwoView:
    """Camera 2 one unit away from camera 1, mostly sideways, turned towards the scene."""
    rng = np.random.default_rng(seed)
    centre = rng.normal(size=3) * [1, 1, 0.3]
    centre /= np.linalg.norm(centre)
    z = np.array([0, 0, 4.5]) - centre
    z /= np.linalg.norm(z)
    x = np.cross([0, 1, 0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z]) @ rotation(rng, 3).matrix()
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre)
    X = points_in_view(rng, 3 * n)
    visible = np.all(np.abs(project(transform(pose, X))) < 0.5, axis=1)
    X = X[visible][:n]
    assert len(X) == n
    x1 = project(X) + rng.normal(0, noise, (n, 2))
    x2 = project(transform(pose, X)) + rng.normal(0, noise, (n, 2))
    inliers = np.ones(n, bool)
    inliers[rng.permutation(n)[:round(outlier_ratio * n)]] = False
    x2[~inliers] = rng.uniform(-0.5, 0.5, (np.count_nonzero(~inliers), 2))
    return TwoView(pose, X, x1, x2, inliers)


@dataclass
class OneView:
    pose: pycolmap.Rigid3d  # cam_from_world
    X: np.ndarray  # (N, 3) world points
    x: np.ndarray  # (N, 2) normalized image points, noisy, outliers random
    inliers: np.ndarray


def one_view(seed: int, n: int = 300, outlier_ratio: float = 0.0, noise: float = NOISE) -> OneView:
    rng = np.random.default_rng(seed)
    pose = pycolmap.Rigid3d(rotation(rng, 180), rng.normal(size=3) * 2)
    X_cam = points_in_view(rng, n)
    X = transform(pose.inverse(), X_cam)
    x = project(X_cam) + rng.normal(0, noise, (n, 2))
    inliers = np.ones(n, bool)
    inliers[rng.permutation(n)[:round(outlier_ratio * n)]] = False
    x[~inliers] = rng.uniform(-0.5, 0.5, (np.count_nonzero(~inliers), 2))
    return OneView(pose, X, x, inliers)


# ---------------------------------------------------------------- measures

def rotation_error_deg(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d) -> float:
    return float(np.rad2deg((a.rotation.inverse() * b.rotation).angle()))


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    return float(np.rad2deg(np.arctan2(np.linalg.norm(np.cross(u, v)), u @ v)))


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def essential(pose: pycolmap.Rigid3d) -> np.ndarray:
    """[t]x R for cam2_from_cam1, unit Frobenius norm."""
    E = skew(pose.translation) @ pose.rotation.matrix()
    return E / np.linalg.norm(E)


def same_up_to_sign(A: np.ndarray, B: np.ndarray) -> float:
    A, B = A / np.linalg.norm(A), B / np.linalg.norm(B)
    return min(np.abs(A - B).max(), np.abs(A + B).max())


def homogeneous(x: np.ndarray) -> np.ndarray:
    return np.hstack([x, np.ones((len(x), 1))])


def unit_rays(x: np.ndarray) -> np.ndarray:
    """The unit rays of normalized image points."""
    h = homogeneous(x)
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def pixels(x: np.ndarray) -> np.ndarray:
    return x * FOCAL + SIZE / 2


def assert_valid_pose(pose: pycolmap.Rigid3d, unit_translation: bool = False) -> None:
    R, t = pose.rotation.matrix(), pose.translation
    assert np.isfinite(R).all() and np.isfinite(t).all()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) > 0
    if unit_translation:
        assert np.linalg.norm(t) == pytest.approx(1.0, abs=1e-9)


def assert_valid_relative(result: solvers.RelativePoseResult, n: int) -> None:
    assert_valid_pose(result.cam2_from_cam1, unit_translation=True)
    assert result.inlier_mask.shape == (n,) and result.inlier_mask.dtype == bool
    assert result.num_inliers == np.count_nonzero(result.inlier_mask)
    assert np.isfinite(result.E).all()


def assert_valid_absolute(result: solvers.AbsolutePoseResult, n: int) -> None:
    assert_valid_pose(result.cam_from_world)
    assert result.inlier_mask.shape == (n,) and result.inlier_mask.dtype == bool
    assert result.num_inliers == np.count_nonzero(result.inlier_mask)


# ---------------------------------------------------------------- accuracy

@pytest.mark.parametrize("method", ["nister", "stewenius"])
@pytest.mark.parametrize("outlier_ratio", OUTLIER_RATIOS)
def test_relative_pose_recovers_truth(method, outlier_ratio):
    scene = two_view(seed=int(outlier_ratio * 100), outlier_ratio=outlier_ratio)
    result = solvers.relative_pose(scene.x1, scene.x2, max_error=MAX_ERROR, method=method, seed=1)
    assert_valid_relative(result, len(scene.x1))
    assert rotation_error_deg(result.cam2_from_cam1, scene.pose) < RELATIVE_MAX_ROTATION_DEG
    assert angle_deg(result.cam2_from_cam1.translation,
                     scene.pose.translation) < RELATIVE_MAX_TRANSLATION_DEG
    assert np.mean(result.inlier_mask == scene.inliers) > MIN_INLIER_AGREEMENT
    # E is [t]x R of the returned pose, and the inliers satisfy x2^T E x1 ~ 0.
    assert same_up_to_sign(result.E, essential(result.cam2_from_cam1)) < 1e-9
    assert sampson_angles(result.E, unit_rays(scene.x1), unit_rays(scene.x2))[result.inlier_mask].max() < MAX_ERROR
    algebraic = np.abs(np.sum(homogeneous(scene.x2) * (homogeneous(scene.x1) @ result.E.T), 1))
    assert algebraic[result.inlier_mask].max() < 5 * MAX_ERROR


@pytest.mark.parametrize("method", ["kneip", "gao"])
@pytest.mark.parametrize("outlier_ratio", OUTLIER_RATIOS)
def test_absolute_pose_recovers_truth(method, outlier_ratio):
    scene = one_view(seed=int(outlier_ratio * 100), outlier_ratio=outlier_ratio)
    result = solvers.absolute_pose(scene.x, scene.X, max_error=MAX_ERROR, method=method, seed=1)
    assert_valid_absolute(result, len(scene.x))
    assert rotation_error_deg(result.cam_from_world, scene.pose) < ABSOLUTE_MAX_ROTATION_DEG
    assert angle_deg(result.cam_from_world.translation,
                     scene.pose.translation) < ABSOLUTE_MAX_TRANSLATION_DEG
    centre_error = np.linalg.norm(result.cam_from_world.inverse().translation
                                  - scene.pose.inverse().translation)
    assert centre_error < ABSOLUTE_MAX_CENTRE_ERROR
    assert np.mean(result.inlier_mask == scene.inliers) > MIN_INLIER_AGREEMENT


@pytest.mark.parametrize("method", ["nister", "stewenius"])
def test_relative_pose_agrees_with_pycolmap(method):
    scene = two_view(seed=7, outlier_ratio=0.3)
    ours = solvers.relative_pose(scene.x1, scene.x2, max_error=MAX_ERROR, method=method, seed=2)
    options = pycolmap.RANSACOptions()
    options.max_error = MAX_ERROR * FOCAL
    options.random_seed = 2
    theirs = pycolmap.estimate_essential_matrix(pixels(scene.x1), pixels(scene.x2), CAMERA, CAMERA,
                                                options)
    assert rotation_error_deg(ours.cam2_from_cam1, theirs["cam2_from_cam1"]) < 0.2
    assert angle_deg(ours.cam2_from_cam1.translation, theirs["cam2_from_cam1"].translation) < 0.5
    assert same_up_to_sign(ours.E, theirs["E"]) < 0.01
    assert np.mean(ours.inlier_mask == theirs["inlier_mask"]) > 0.98


@pytest.mark.parametrize("method", ["kneip", "gao"])
def test_absolute_pose_agrees_with_pycolmap(method):
    scene = one_view(seed=7, outlier_ratio=0.3)
    ours = solvers.absolute_pose(scene.x, scene.X, max_error=MAX_ERROR, method=method, seed=2)
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = MAX_ERROR * FOCAL
    options.ransac.random_seed = 2
    theirs = pycolmap.estimate_absolute_pose(pixels(scene.x), scene.X, CAMERA, options)
    assert rotation_error_deg(ours.cam_from_world, theirs["cam_from_world"]) < 0.2
    assert np.linalg.norm(ours.cam_from_world.inverse().translation
                          - theirs["cam_from_world"].inverse().translation) < 0.02
    assert np.mean(ours.inlier_mask == theirs["inlier_mask"]) > 0.98


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_absolute_pose_is_the_least_squares_fit_of_its_own_inliers(seed):
    """The final refinement ends on a fixed point: the inliers are exactly the
    correspondences within the threshold of the pose, and the pose minimises their squared
    errors (a Gauss-Newton step from it, by numerical derivatives, moves nothing)."""
    scene = one_view(seed=seed, outlier_ratio=0.3)
    result = solvers.absolute_pose(scene.x, scene.X, max_error=MAX_ERROR, seed=3)
    f = unit_rays(scene.x)
    R, t = result.cam_from_world.rotation.matrix(), result.cam_from_world.translation

    def tangent_errors(delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Error vectors x / (f.x) - f (norm: the tangent of the angle) and depths f.x at
        the pose moved by delta (rotation vector, translation step)."""
        x = scene.X @ (pycolmap.Rotation3d(delta[:3]).matrix() @ R).T + t + delta[3:]
        depth = np.sum(f * x, axis=1)
        return x / depth[:, None] - f, depth

    errors, depth = tangent_errors(np.zeros(6))
    within = (np.linalg.norm(errors, axis=1) < MAX_ERROR) & (depth > 0)
    np.testing.assert_array_equal(result.inlier_mask, within)

    def residuals(delta: np.ndarray) -> np.ndarray:
        return tangent_errors(delta)[0][result.inlier_mask].ravel()

    h = 1e-6
    J = np.column_stack([(residuals(h * e) - residuals(-h * e)) / (2 * h) for e in np.eye(6)])
    step = np.linalg.lstsq(J, -residuals(np.zeros(6)), rcond=None)[0]
    assert np.rad2deg(np.linalg.norm(step[:3])) < 1e-6
    assert np.linalg.norm(step[3:]) < 1e-7 * np.linalg.norm(scene.X, axis=1).mean()


@pytest.mark.parametrize("method, min_found", [("nister", 0.9), ("stewenius", 1.0)])
def test_five_point_finds_true_essential_matrix(method, min_found):
    """Every solution is an essential matrix fitting the five pairs, and the true one is
    among them; OpenGV's Nister solver misses it in a few percent of configurations."""
    found = []
    for seed in range(20):
        scene = two_view(seed, n=5, noise=0.0)
        solutions = solvers.five_point(scene.x1, scene.x2, method=method)
        assert len(solutions) <= 10
        for E in solutions:
            assert np.linalg.norm(E) == pytest.approx(1.0)
            assert sampson_angles(E, unit_rays(scene.x1), unit_rays(scene.x2)).max() < 1e-9
            EEt = E @ E.T  # the essential-matrix constraint 2 E E^T E = tr(E E^T) E
            assert np.abs(2 * EEt @ E - np.trace(EEt) * E).max() < 1e-3
        found.append(min([same_up_to_sign(E, essential(scene.pose)) for E in solutions],
                         default=np.inf) < 1e-6)
    assert np.mean(found) >= min_found


@pytest.mark.parametrize("method, min_found", [("kneip", 1.0), ("gao", 0.9)])
def test_p3p_finds_true_pose(method, min_found):
    """Every solution sees the three points along their rays, and the true pose is among
    them; OpenGV's Gao solver misses it in a few percent of configurations."""
    found = []
    for seed in range(20):
        scene = one_view(seed, n=3, noise=0.0)
        solutions = solvers.p3p(scene.x, scene.X, method=method)
        assert len(solutions) <= 4
        for pose in solutions:
            assert_valid_pose(pose)
            X_cam = transform(pose, scene.X)
            assert (X_cam[:, 2] > 0).all()
            np.testing.assert_allclose(project(X_cam), scene.x, atol=1e-3)
        found.append(any(rotation_error_deg(pose, scene.pose) < 1e-6
                         and np.abs(pose.translation - scene.pose.translation).max() < 1e-6
                         for pose in solutions))
    assert np.mean(found) >= min_found


# ---------------------------------------------------------------- triangulation

def test_triangulate_recovers_points_and_flags_bad_ones():
    scene = two_view(seed=3, n=50, noise=0.0)
    cam1 = pycolmap.Rigid3d(rotation(np.random.default_rng(0), 30), [0.2, -0.1, 0.3])
    cam2 = scene.pose * cam1  # world -> cam1 -> cam2
    X_world = transform(cam1.inverse(), scene.X)
    rays1 = homogeneous(scene.x1)
    rays2 = transform(scene.pose, scene.X)  # (N, 3) rays, not normalized
    points, valid = solvers.triangulate(cam1, cam2, rays1, rays2)
    np.testing.assert_allclose(points, X_world, atol=1e-9)
    assert valid.all()

    # A ray pointing away from the point: the point is behind that camera.
    rays2[:5] *= -1
    points, valid = solvers.triangulate(cam1, cam2, rays1, rays2)
    np.testing.assert_allclose(points, X_world, atol=1e-9)
    assert not valid[:5].any() and valid[5:].all()

    # Far points: rays nearly parallel, below the minimum triangulation angle.
    far = scene.X * 100
    rays1, rays2 = far, transform(scene.pose, far)
    _, valid = solvers.triangulate(cam1, cam2, rays1, rays2, min_angle_deg=1.0)
    assert not valid.any()
    _, valid = solvers.triangulate(cam1, cam2, rays1, rays2, min_angle_deg=0.01)
    assert valid.all()


def test_triangulate_tracks_multi_view():
    rng = np.random.default_rng(4)
    cams = [pycolmap.Rigid3d(rotation(rng, 5), [-1.5 + v, 0.1 * v, 0]) for v in range(4)]
    X = points_in_view(rng, 40) + [0, 0, 2]
    views, point_ids, rays = [], [], []
    for p in range(len(X)):
        for v in range(p % 4 + 1):  # tracks of 1 to 4 observations
            views.append(v)
            point_ids.append(p)
            ray = transform(cams[v], X[p:p + 1])[0]
            rays.append(ray + rng.normal(0, 1e-4, 3) * np.linalg.norm(ray))
    points, valid = solvers.triangulate_tracks(cams, views, point_ids, np.array(rays))
    assert points.shape == (len(X), 3) and valid.shape == (len(X),)
    single = np.arange(len(X)) % 4 == 0
    assert not valid[single].any() and np.isnan(points[single]).all()
    assert valid[~single].all()
    assert np.abs(points[~single] - X[~single]).max() < 0.05


# ---------------------------------------------------------------- conventions

def test_conventions_round_trip():
    """One known pose through every function comes back unchanged."""
    scene = two_view(seed=11, n=100, noise=0.0)
    E_true = essential(scene.pose)
    # x2 = R x1 + t: pycolmap's Rigid3d maps camera 1 into camera 2.
    np.testing.assert_allclose(project(scene.pose * scene.X), scene.x2, atol=1e-12)

    rel = solvers.relative_pose(scene.x1, scene.x2, max_error=MAX_ERROR, seed=0)
    np.testing.assert_allclose(rel.cam2_from_cam1.matrix(), scene.pose.matrix(), atol=1e-8)
    assert same_up_to_sign(rel.E, E_true) < 1e-8
    assert rel.inlier_mask.all()

    E5 = solvers.five_point(scene.x1[:5], scene.x2[:5])
    assert min(same_up_to_sign(E, E_true) for E in E5) < 1e-8

    # The same pose as cam_from_world for points in world = camera 1 coordinates.
    ab = solvers.absolute_pose(scene.x2, scene.X, max_error=MAX_ERROR, seed=0)
    np.testing.assert_allclose(ab.cam_from_world.matrix(), scene.pose.matrix(), atol=1e-8)
    poses = solvers.p3p(scene.x2[:3], scene.X[:3])
    assert min(np.abs(p.matrix() - scene.pose.matrix()).max() for p in poses) < 1e-8

    points, valid = solvers.triangulate(pycolmap.Rigid3d(), scene.pose, scene.x1, scene.x2)
    np.testing.assert_allclose(points, scene.X, atol=1e-8)
    assert valid.all()


# ---------------------------------------------------------------- reproducibility and input forms

def test_seed_reproducibility():
    scene = two_view(seed=5, outlier_ratio=0.5)
    runs = [solvers.relative_pose(scene.x1, scene.x2, max_error=MAX_ERROR, seed=s)
            for s in (3, 3, 4)]
    np.testing.assert_array_equal(runs[0].inlier_mask, runs[1].inlier_mask)
    np.testing.assert_array_equal(runs[0].cam2_from_cam1.matrix(), runs[1].cam2_from_cam1.matrix())
    assert runs[0].num_iterations == runs[1].num_iterations
    for run in runs[1:]:  # another seed may differ, but finds the same pose
        assert rotation_error_deg(run.cam2_from_cam1, runs[0].cam2_from_cam1) < 0.2

    view = one_view(seed=5, outlier_ratio=0.5)
    runs = [solvers.absolute_pose(view.x, view.X, max_error=MAX_ERROR, seed=s) for s in (3, 3)]
    np.testing.assert_array_equal(runs[0].inlier_mask, runs[1].inlier_mask)
    np.testing.assert_array_equal(runs[0].cam_from_world.matrix(), runs[1].cam_from_world.matrix())
    unseeded = solvers.absolute_pose(view.x, view.X, max_error=MAX_ERROR)
    assert rotation_error_deg(unseeded.cam_from_world, view.pose) < 0.5


def test_normalized_points_and_rays_give_the_same_result():
    scene = two_view(seed=6, outlier_ratio=0.3)
    scale = np.random.default_rng(0).uniform(0.5, 3, (len(scene.x1), 1))
    a = solvers.relative_pose(scene.x1, scene.x2, max_error=MAX_ERROR, seed=9)
    b = solvers.relative_pose(homogeneous(scene.x1) * scale, homogeneous(scene.x2),
                              max_error=MAX_ERROR, seed=9)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    np.testing.assert_allclose(a.cam2_from_cam1.matrix(), b.cam2_from_cam1.matrix(), atol=1e-9)

    view = one_view(seed=6, outlier_ratio=0.3)
    a = solvers.absolute_pose(view.x, view.X, max_error=MAX_ERROR, seed=9)
    b = solvers.absolute_pose(homogeneous(view.x) * 2.5, view.X, max_error=MAX_ERROR, seed=9)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    np.testing.assert_allclose(a.cam_from_world.matrix(), b.cam_from_world.matrix(), atol=1e-9)

    points_a, valid_a = solvers.triangulate(pycolmap.Rigid3d(), scene.pose, scene.x1, scene.x2)
    points_b, valid_b = solvers.triangulate(pycolmap.Rigid3d(), scene.pose,
                                            homogeneous(scene.x1) * scale, homogeneous(scene.x2))
    np.testing.assert_allclose(points_a, points_b, atol=1e-9)
    np.testing.assert_array_equal(valid_a, valid_b)


def test_rays_of_any_length_give_the_same_result():
    """Rays are normalised even where their squares leave the floating-point range."""
    view = one_view(seed=6, outlier_ratio=0.3)
    unit = solvers.absolute_pose(view.x, view.X, max_error=MAX_ERROR, seed=9)
    for length in (1e-200, 1e200):
        scaled = solvers.absolute_pose(homogeneous(view.x) * length, view.X,
                                       max_error=MAX_ERROR, seed=9)
        np.testing.assert_array_equal(unit.inlier_mask, scaled.inlier_mask)
        np.testing.assert_allclose(unit.cam_from_world.matrix(), scaled.cam_from_world.matrix(),
                                   atol=1e-9)


# ---------------------------------------------------------------- bad input

GOOD = two_view(seed=8, n=20)
GOOD_VIEW = one_view(seed=8, n=20)


@pytest.mark.parametrize("call, message", [
    (lambda: solvers.relative_pose(GOOD.x1[:, :1], GOOD.x2, max_error=1e-3), r"rays1 .*shape"),
    (lambda: solvers.relative_pose(GOOD.x1, np.zeros((20, 4)), max_error=1e-3), r"rays2 .*shape"),
    (lambda: solvers.relative_pose(GOOD.x1.ravel(), GOOD.x2, max_error=1e-3), r"rays1 .*2-D"),
    (lambda: solvers.relative_pose(GOOD.x1, GOOD.x2[:-1], max_error=1e-3), r"differ in length"),
    (lambda: solvers.relative_pose(GOOD.x1[:4], GOOD.x2[:4], max_error=1e-3), r"at least 5"),
    (lambda: solvers.relative_pose(np.where(np.eye(20, 2) > 0, np.nan, GOOD.x1), GOOD.x2,
                                   max_error=1e-3), r"rays1 .*NaN or inf"),
    (lambda: solvers.relative_pose(GOOD.x1, np.full((20, 2), np.inf), max_error=1e-3),
     r"rays2 .*NaN or inf"),
    (lambda: solvers.relative_pose(GOOD.x1, GOOD.x2, max_error=0.0), r"max_error"),
    (lambda: solvers.relative_pose(GOOD.x1, GOOD.x2, max_error=-1.0), r"max_error"),
    (lambda: solvers.relative_pose(GOOD.x1, GOOD.x2, max_error=float("nan")), r"max_error"),
    (lambda: solvers.relative_pose(GOOD.x1, GOOD.x2, max_error=1e-3, method="kneip"),
     r"unknown method 'kneip'"),
    (lambda: solvers.relative_pose(np.zeros((20, 3)), GOOD.x2, max_error=1e-3), r"zero-length"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x, GOOD_VIEW.X[:, :2], max_error=1e-3),
     r"points3D .*shape"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x[:2], GOOD_VIEW.X[:2], max_error=1e-3),
     r"at least 3"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x, GOOD_VIEW.X[:5], max_error=1e-3),
     r"differ in length"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x, GOOD_VIEW.X * np.inf, max_error=1e-3),
     r"points3D .*NaN or inf"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x, GOOD_VIEW.X, max_error=None), r"max_error"),
    (lambda: solvers.absolute_pose(GOOD_VIEW.x, GOOD_VIEW.X, max_error=1e-3, method="epnp"),
     r"unknown method 'epnp'"),
    (lambda: solvers.absolute_pose([["a", "b"]] * 5, GOOD_VIEW.X[:5], max_error=1e-3),
     r"rays .*numeric"),
    (lambda: solvers.five_point(GOOD.x1[:4], GOOD.x2[:4]), r"exactly 5"),
    (lambda: solvers.five_point(GOOD.x1[:5], GOOD.x2[:5], method="gao"), r"unknown method"),
    (lambda: solvers.p3p(GOOD_VIEW.x[:4], GOOD_VIEW.X[:4]), r"exactly 3"),
    (lambda: solvers.p3p(GOOD_VIEW.x[:3], GOOD_VIEW.X[:3], method="nister"), r"unknown method"),
    (lambda: solvers.triangulate(pycolmap.Rigid3d(), GOOD.pose, GOOD.x1, GOOD.x2[:3]),
     r"differ in length"),
    (lambda: solvers.triangulate(pycolmap.Rigid3d(), GOOD.pose, GOOD.x1, GOOD.x2,
                                 min_angle_deg=float("nan")), r"min_angle_deg"),
    (lambda: solvers.triangulate_tracks([pycolmap.Rigid3d()], [0, 1], [0, 0], GOOD.x1[:2]),
     r"view_index out of range"),
    (lambda: solvers.triangulate_tracks([pycolmap.Rigid3d()] * 2, [0, 1], [0, 0], GOOD.x1[:3]),
     r"differ in length"),
])
def test_bad_input_raises_value_error_naming_the_problem(call, message):
    with pytest.raises(ValueError, match=message):
        call()


# ---------------------------------------------------------------- degenerate data

def run_guarded(call, check):
    """Degenerate data: an EstimationError or a valid result, quickly."""
    start = time.perf_counter()
    try:
        check(call())
    except solvers.EstimationError:
        pass
    assert time.perf_counter() - start < 10


def assert_refused(call, what: str, n: int, need: int) -> None:
    """The documented failure: an EstimationError saying how few of the n agreed."""
    with pytest.raises(solvers.EstimationError,
                       match=rf"^no {what} pose: \d+ of {n} correspondences agree \(need {need}\)$"):
        call()


@pytest.mark.parametrize("method", ["nister", "stewenius"])
def test_relative_pose_degenerate_data(method):
    rng = np.random.default_rng(0)
    n = 100
    same = np.tile([[0.1, -0.2]], (n, 1))
    noise1, noise2 = rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(-0.5, 0.5, (n, 2))
    cases = [
        (same, same),  # all points identical
        (same, noise2),  # all points on the same ray in camera 1
        (noise1, noise1),  # no motion at all
        (noise1, noise1 + [0.01, 0]),  # pure image translation (rotation about y)
    ]
    for x1, x2 in cases:
        run_guarded(lambda: solvers.relative_pose(x1, x2, max_error=MAX_ERROR, method=method,
                                                  seed=0),
                    lambda r: assert_valid_relative(r, n))


@pytest.mark.parametrize("method", ["nister", "stewenius"])
def test_relative_pose_refuses_pure_noise(method):
    """Unrelated points give no pose: at most 12 of 100 agree by chance (measured over 20
    seeds), below the 15 that min_num_inliers asks for."""
    rng = np.random.default_rng(0)
    x1, x2 = rng.uniform(-0.5, 0.5, (100, 2)), rng.uniform(-0.5, 0.5, (100, 2))
    assert_refused(lambda: solvers.relative_pose(x1, x2, max_error=MAX_ERROR, method=method,
                                                 seed=0), "relative", 100, 15)


@pytest.mark.parametrize("method", ["kneip", "gao"])
def test_absolute_pose_degenerate_data(method):
    rng = np.random.default_rng(0)
    n = 100
    view = one_view(seed=0, n=n)
    on_one_ray = np.outer(rng.uniform(2, 5, n), [0.1, 0.2, 1.0])
    cases = [
        (np.tile(view.x[:1], (n, 1)), np.tile(view.X[:1], (n, 1))),  # one point, repeated
        (np.tile([[0.1, 0.2]], (n, 1)), on_one_ray),  # all points on one ray
        (view.x, np.tile(view.X.mean(0), (n, 1))),  # all rays to one point
        (view.x, view.X * [1, 1, 0]),  # coplanar points
    ]
    for x, X in cases:
        run_guarded(lambda: solvers.absolute_pose(x, X, max_error=MAX_ERROR, method=method, seed=0),
                    lambda r: assert_valid_absolute(r, n))


@pytest.mark.parametrize("method", ["kneip", "gao"])
def test_absolute_pose_refuses_pure_noise(method):
    """Rays unrelated to the points give no pose: 4 of 100 agree (every one of 20 seeds
    measured), below the 6 that min_num_inliers asks for."""
    rng = np.random.default_rng(0)
    x, X = rng.uniform(-0.5, 0.5, (100, 2)), rng.normal(size=(100, 3)) * 5
    assert_refused(lambda: solvers.absolute_pose(x, X, max_error=MAX_ERROR, method=method, seed=0),
                   "absolute", 100, 6)


def test_triangulate_degenerate_data():
    scene = two_view(seed=9, n=30, noise=0.0)
    # Both cameras in the same place: no parallax, no valid point, no crash.
    points, valid = solvers.triangulate(scene.pose, scene.pose, scene.x2, scene.x2)
    assert points.shape == (30, 3) and not valid.any()
    # The same ray from both cameras: a point at infinity, or one behind a camera.
    points, valid = solvers.triangulate(pycolmap.Rigid3d(), scene.pose, scene.x1,
                                        np.tile([[0.0, 0.0]], (30, 1)))
    assert points.shape == (30, 3)
    assert (~valid | np.isfinite(points).all(axis=1)).all()


# ---------------------------------------------------------------- fuzz

SPECIAL = [np.nan, np.inf, -np.inf, 0.0, 1e300, -1e300, 1e-300, 1e30]
# Intact scenes (no corruption drawn) must give the true pose. Fewest true correspondences
# for that (min_num_inliers 15 and 6, plus a margin), and bounds about 3x the worst measured
# over 300 scenes of 20-60 true correspondences (half with as many outliers), 500 iterations:
FUZZ_MIN_RELATIVE_INLIERS = 20
FUZZ_MIN_ABSOLUTE_INLIERS = 10
FUZZ_RELATIVE_MAX_ROTATION_DEG = 2.0  # worst 0.70
FUZZ_ABSOLUTE_MAX_ROTATION_DEG = 0.6  # worst 0.20
FUZZ_ABSOLUTE_MAX_CENTRE_ERROR = 0.05  # worst 0.016
FUZZ_TRIANGULATION_MAX_ERROR = 1.0  # worst 0.32 (points 3 to 6 away, baseline 1)
FUZZ_TRIANGULATION_MIN_VALID = 0.7  # worst 0.905 of true correspondences (1 deg minimum angle)


def sometimes(draw, one_in: int) -> bool:
    # sampled_from rather than integers or booleans: hypothesis favours 0 and False.
    return draw(st.sampled_from([False] * (one_in - 1) + [True]))


@st.composite
def corrupted(draw, base_a: np.ndarray, base_b: np.ndarray):
    """Two arrays from (mostly valid) base arrays with some of: awkward values, duplicated
    rows, zero rows, another length, another number of columns, another dtype."""
    arrays = [base_a.copy(), base_b.copy()]
    for k in range(2):
        array = arrays[k]
        if len(array) and sometimes(draw, 3):  # awkward values at a few places
            for _ in range(draw(st.integers(1, 3))):
                index = (draw(st.integers(0, len(array) - 1)),
                         draw(st.integers(0, array.shape[1] - 1)))
                array[index] = draw(st.sampled_from(SPECIAL))
        if len(array) > 1 and sometimes(draw, 6):  # all rows the same
            array[1:] = array[0]
        if len(array) and sometimes(draw, 8):  # a zero row
            array[draw(st.integers(0, len(array) - 1))] = 0
        if sometimes(draw, 8):  # another length
            array = array[:draw(st.integers(0, len(array)))]
        if sometimes(draw, 8):  # another number of columns, 1 to 4
            columns = draw(st.integers(1, 4))
            array = np.hstack([array, np.ones((len(array), 4))])[:, :columns]
        dtype = draw(st.sampled_from(["float64"] * 5 + ["float32", "int64", "object"]))
        if dtype == "object":
            array = np.full(array.shape, draw(st.sampled_from(["x", None, "1.5"])), dtype=object)
        elif dtype != "float64":
            with np.errstate(all="ignore"):
                array = np.nan_to_num(array).astype(dtype)
        arrays[k] = array
    return arrays


def unharmed(array: np.ndarray, base: np.ndarray) -> bool:
    """The same numbers as `base`, give or take float32 rounding."""
    return (array.dtype != object and array.shape == base.shape
            and np.allclose(array, base, rtol=0, atol=1e-6))


def intact_scene(scene, base: tuple, drawn: list, min_inliers: int):
    """`scene` if the drawn arrays are its correspondences unharmed, enough of them true."""
    if scene is None or not all(unharmed(a, b) for a, b in zip(drawn, base)):
        return None
    return scene if np.count_nonzero(scene.inliers[:len(base[0])]) >= min_inliers else None


@st.composite
def relative_inputs(draw):
    """(rays1, rays2, the TwoView they come from intact, else None)."""
    n = draw(st.integers(0, 300))
    scene = None
    if not sometimes(draw, 3):
        scene = two_view(draw(st.integers(0, 1000)), n=max(n, 1),
                         outlier_ratio=draw(st.sampled_from([0.0, 0.5, 1.0])))
        base = scene.x1[:n], scene.x2[:n]
    else:
        rng = np.random.default_rng(draw(st.integers(0, 1000)))
        base = rng.uniform(-1, 1, (n, 2)), rng.uniform(-1, 1, (n, 3))
    drawn = draw(corrupted(*base))
    return (*drawn, intact_scene(scene, base, drawn, FUZZ_MIN_RELATIVE_INLIERS))


@st.composite
def absolute_inputs(draw):
    """(rays, points3D, the OneView they come from intact, else None)."""
    n = draw(st.integers(0, 300))
    view = None
    if not sometimes(draw, 3):
        view = one_view(draw(st.integers(0, 1000)), n=max(n, 1),
                        outlier_ratio=draw(st.sampled_from([0.0, 0.5, 1.0])))
        base = view.x[:n], view.X[:n]
    else:
        rng = np.random.default_rng(draw(st.integers(0, 1000)))
        base = rng.uniform(-1, 1, (n, 2)), rng.normal(size=(n, 3)) * 5
    drawn = draw(corrupted(*base))
    return (*drawn, intact_scene(view, base, drawn, FUZZ_MIN_ABSOLUTE_INLIERS))


def check_or_expected_error(call, check):
    try:
        result = call()
    except (ValueError, solvers.EstimationError):
        return
    check(result)


FUZZ = settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))
# Intact inputs that every fuzz run tries, besides what hypothesis draws.
INTACT_TWO_VIEW = two_view(seed=12, n=40, outlier_ratio=0.5)
INTACT_ONE_VIEW = one_view(seed=12, n=20, outlier_ratio=0.5)


@FUZZ
@given(inputs=relative_inputs(), seed=st.integers(0, 2**64 - 1))
@example(inputs=(INTACT_TWO_VIEW.x1, INTACT_TWO_VIEW.x2, INTACT_TWO_VIEW), seed=0)
def test_fuzz_relative_pose(inputs, seed):
    """Any input gives a valid pose or a named error; an intact scene gives its true pose."""
    a, b, scene = inputs

    def call():
        return solvers.relative_pose(a, b, max_error=MAX_ERROR, max_iterations=500, seed=seed)

    if scene is None:
        check_or_expected_error(call, lambda r: assert_valid_relative(r, len(a)))
        return
    result = call()
    assert_valid_relative(result, len(a))
    assert rotation_error_deg(result.cam2_from_cam1, scene.pose) < FUZZ_RELATIVE_MAX_ROTATION_DEG


@FUZZ
@given(inputs=absolute_inputs(), seed=st.integers(0, 2**64 - 1))
@example(inputs=(INTACT_ONE_VIEW.x, INTACT_ONE_VIEW.X, INTACT_ONE_VIEW), seed=0)
def test_fuzz_absolute_pose(inputs, seed):
    """Any input gives a valid pose or a named error; an intact scene gives its true pose."""
    a, X, view = inputs

    def call():
        return solvers.absolute_pose(a, X, max_error=MAX_ERROR, max_iterations=500, seed=seed)

    if view is None:
        check_or_expected_error(call, lambda r: assert_valid_absolute(r, len(a)))
        return
    result = call()
    assert_valid_absolute(result, len(a))
    assert rotation_error_deg(result.cam_from_world, view.pose) < FUZZ_ABSOLUTE_MAX_ROTATION_DEG
    centre_error = np.linalg.norm(result.cam_from_world.inverse().translation
                                  - view.pose.inverse().translation)
    assert centre_error < FUZZ_ABSOLUTE_MAX_CENTRE_ERROR


@FUZZ
@given(inputs=relative_inputs())
@example(inputs=(INTACT_TWO_VIEW.x1, INTACT_TWO_VIEW.x2, INTACT_TWO_VIEW))
def test_fuzz_triangulate(inputs):
    """Any input gives finite valid points or a named error; an intact scene, triangulated
    with its true pose, gives its points back."""
    a, b, scene = inputs

    def check(result):
        points, valid = result
        assert points.shape == (len(a), 3) and valid.shape == (len(a),)
        assert np.isfinite(points[valid]).all()

    if scene is None:
        pose = two_view(0, n=1).pose
        check_or_expected_error(lambda: solvers.triangulate(pycolmap.Rigid3d(), pose, a, b), check)
        return
    result = solvers.triangulate(pycolmap.Rigid3d(), scene.pose, a, b)
    check(result)
    points, valid = result
    true = scene.inliers[:len(a)]
    assert np.mean(valid[true]) >= FUZZ_TRIANGULATION_MIN_VALID
    assert np.abs(points[valid & true] - scene.X[:len(a)][valid & true]).max() \
        < FUZZ_TRIANGULATION_MAX_ERROR


# ---------------------------------------------------------------- camera rigs (generalized solvers)

def ring_rig(num_cameras: int = 3, radius: float = 0.3) -> list[pycolmap.Rigid3d]:
    """cams_from_rig of cameras on a horizontal ring, each looking outwards."""
    cams = []
    for k in range(num_cameras):
        yaw = 2 * np.pi * k / num_cameras
        R = pycolmap.Rotation3d(np.array([0, -yaw, 0])).matrix()  # looks along rig's (sin, 0, cos)
        centre = radius * np.array([np.sin(yaw), 0, np.cos(yaw)])
        cams.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre))
    return cams


RIG = ring_rig(radius=1.0)


@dataclass
class RigOneView:
    pose: pycolmap.Rigid3d  # rig_from_world
    camera_index: np.ndarray  # (N,) camera of each observation
    X: np.ndarray  # (N, 3) world points
    x: np.ndarray  # (N, 2) normalized image points in their cameras, noisy, outliers random
    inliers: np.ndarray


def rig_one_view(seed: int, n: int = 300, outlier_ratio: float = 0.0,
                 noise: float = NOISE) -> RigOneView:
    rng = np.random.default_rng(seed)
    pose = pycolmap.Rigid3d(rotation(rng, 180), rng.normal(size=3) * 2)
    camera_index = rng.integers(0, len(RIG), n)
    X_cam = points_in_view(rng, n)
    X = np.empty_like(X_cam)
    for c, cam_from_rig in enumerate(RIG):
        seen = camera_index == c
        X[seen] = transform((cam_from_rig * pose).inverse(), X_cam[seen])
    x = project(X_cam) + rng.normal(0, noise, (n, 2))
    inliers = np.ones(n, bool)
    inliers[rng.permutation(n)[:round(outlier_ratio * n)]] = False
    x[~inliers] = rng.uniform(-0.5, 0.5, (np.count_nonzero(~inliers), 2))
    return RigOneView(pose, camera_index, X, x, inliers)


@dataclass
class RigTwoView:
    pose: pycolmap.Rigid3d  # rig2_from_rig1, metric
    camera_index1: np.ndarray
    x1: np.ndarray  # (N, 2) normalized, noisy
    camera_index2: np.ndarray
    x2: np.ndarray  # (N, 2) normalized, noisy, outliers random
    inliers: np.ndarray


def rig_two_view(seed: int, n: int = 300, outlier_ratio: float = 0.0,
                 noise: float = NOISE) -> RigTwoView:
    """The rig turns by a third of a turn and 10 to 30 deg more about another axis, and
    moves about 0.5: most points are seen by one camera in frame 1 and by the next in
    frame 2. (Exactly a third would carry each camera onto the next one's place: those
    pairs' translations would all be the rig's, which leaves its scale to the noise.)"""
    rng = np.random.default_rng(seed)
    third = pycolmap.Rotation3d(np.array([0, 2 * np.pi / len(RIG), 0]))
    axis = rng.normal(size=3)
    turn = pycolmap.Rotation3d(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(10, 30)))
    pose = pycolmap.Rigid3d(turn * third, rng.normal(size=3) * 0.3)
    candidates = 10 * n
    camera_index1 = rng.integers(0, len(RIG), candidates)
    X_cam1 = points_in_view(rng, candidates)
    X_rig2 = np.empty_like(X_cam1)
    for c, cam_from_rig in enumerate(RIG):
        seen = camera_index1 == c
        X_rig2[seen] = transform(pose * cam_from_rig.inverse(), X_cam1[seen])
    camera_index2 = np.full(candidates, -1)
    x2 = np.zeros((candidates, 2))
    for c, cam_from_rig in enumerate(RIG):  # the camera nearest the point's direction
        X_cam2 = transform(cam_from_rig, X_rig2)
        x = project(X_cam2)
        seen = (X_cam2[:, 2] > 1) & (np.abs(x).max(axis=1) < 0.5) & (camera_index2 < 0)
        camera_index2[seen], x2[seen] = c, x[seen]
    keep = np.flatnonzero(camera_index2 >= 0)[:n]
    assert len(keep) == n
    x1 = project(X_cam1[keep]) + rng.normal(0, noise, (n, 2))
    x2 = x2[keep] + rng.normal(0, noise, (n, 2))
    inliers = np.ones(n, bool)
    inliers[rng.permutation(n)[:round(outlier_ratio * n)]] = False
    x2[~inliers] = rng.uniform(-0.5, 0.5, (np.count_nonzero(~inliers), 2))
    return RigTwoView(pose, camera_index1[keep], x1, camera_index2[keep], x2, inliers)


def centre_distance(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d) -> float:
    return float(np.linalg.norm(a.inverse().translation - b.inverse().translation))


def generalized_absolute(scene: RigOneView, **kwargs) -> solvers.GeneralizedAbsolutePoseResult:
    return solvers.generalized_absolute_pose(scene.x, scene.camera_index, scene.X, RIG,
                                             max_error=MAX_ERROR, **kwargs)


def generalized_relative(scene: RigTwoView, **kwargs) -> solvers.GeneralizedRelativePoseResult:
    return solvers.generalized_relative_pose(scene.x1, scene.camera_index1, scene.x2,
                                             scene.camera_index2, RIG, max_error=MAX_ERROR,
                                             **kwargs)


def test_generalized_absolute_pose_exact_without_noise():
    scene = rig_one_view(seed=3, n=50, noise=0.0)
    result = generalized_absolute(scene, seed=1)
    assert_valid_pose(result.rig_from_world)
    assert rotation_error_deg(result.rig_from_world, scene.pose) < 1e-7
    assert centre_distance(result.rig_from_world, scene.pose) < 1e-9
    assert result.inlier_mask.all()


@pytest.mark.parametrize("outlier_ratio", RIG_OUTLIER_RATIOS)
def test_generalized_absolute_pose_recovers_truth(outlier_ratio):
    scene = rig_one_view(seed=int(outlier_ratio * 100), outlier_ratio=outlier_ratio)
    result = generalized_absolute(scene, seed=1)
    assert_valid_pose(result.rig_from_world)
    assert result.inlier_mask.shape == scene.inliers.shape
    assert result.num_inliers == np.count_nonzero(result.inlier_mask)
    assert rotation_error_deg(result.rig_from_world, scene.pose) < RIG_ABSOLUTE_MAX_ROTATION_DEG
    assert centre_distance(result.rig_from_world, scene.pose) < RIG_ABSOLUTE_MAX_CENTRE_ERROR
    assert np.mean(result.inlier_mask == scene.inliers) > MIN_INLIER_AGREEMENT


def test_generalized_absolute_pose_of_one_camera_is_absolute_pose():
    """A rig of one camera at the rig's origin is a single camera: the same pose as P3P's."""
    scene = one_view(seed=5, outlier_ratio=0.2)
    single = solvers.absolute_pose(scene.x, scene.X, max_error=MAX_ERROR, seed=1)
    rig = solvers.generalized_absolute_pose(scene.x, np.zeros(len(scene.x), int), scene.X,
                                            [pycolmap.Rigid3d()], max_error=MAX_ERROR, seed=1)
    assert rotation_error_deg(rig.rig_from_world, single.cam_from_world) < 1e-6
    assert centre_distance(rig.rig_from_world, single.cam_from_world) < 1e-6
    assert (rig.inlier_mask == single.inlier_mask).all()


@pytest.mark.parametrize("method", ["fivept_plus_one", "sixpt", "seventeenpt"])
def test_generalized_relative_pose_exact_without_noise(method):
    scene = rig_two_view(seed=3, n=60, noise=0.0)
    result = generalized_relative(scene, method=method, seed=1)
    assert_valid_pose(result.rig2_from_rig1)
    assert rotation_error_deg(result.rig2_from_rig1, scene.pose) < 1e-6
    assert np.linalg.norm(result.rig2_from_rig1.translation - scene.pose.translation) < 1e-7
    assert result.inlier_mask.all()


@pytest.mark.parametrize("method, outlier_ratio", [
    *(("fivept_plus_one", ratio) for ratio in RIG_OUTLIER_RATIOS),
    ("sixpt", 0.0), ("sixpt", 0.2), ("sixpt", 0.4), ("seventeenpt", 0.0), ("seventeenpt", 0.1)])
def test_generalized_relative_pose_recovers_truth(method, outlier_ratio):
    scene = rig_two_view(seed=int(outlier_ratio * 100), outlier_ratio=outlier_ratio)
    result = generalized_relative(scene, method=method, seed=1)
    assert_valid_pose(result.rig2_from_rig1)
    assert result.num_inliers == np.count_nonzero(result.inlier_mask)
    assert rotation_error_deg(result.rig2_from_rig1, scene.pose) < RIG_RELATIVE_MAX_ROTATION_DEG
    assert np.linalg.norm(result.rig2_from_rig1.translation - scene.pose.translation) \
        < RIG_RELATIVE_MAX_TRANSLATION_ERROR
    assert np.mean(result.inlier_mask == scene.inliers) > MIN_INLIER_AGREEMENT


def rig_pixels(camera_index: np.ndarray) -> list[int]:
    return [int(c) for c in camera_index]


def test_generalized_absolute_pose_agrees_with_pycolmap():
    scene = rig_one_view(seed=7, outlier_ratio=0.3)
    ours = generalized_absolute(scene, seed=2)
    options = pycolmap.RANSACOptions()
    options.max_error = MAX_ERROR * FOCAL
    options.random_seed = 2
    theirs = pycolmap.estimate_generalized_absolute_pose(
        pixels(scene.x), scene.X, rig_pixels(scene.camera_index), RIG, [CAMERA] * len(RIG),
        options)
    assert rotation_error_deg(ours.rig_from_world, theirs["rig_from_world"]) < 0.05
    assert centre_distance(ours.rig_from_world, theirs["rig_from_world"]) < 0.01
    assert np.mean(ours.inlier_mask == theirs["inlier_mask"]) > 0.98
    # At least as close to the truth (ours refines on all inliers; a little slack for noise).
    assert rotation_error_deg(ours.rig_from_world, scene.pose) \
        <= rotation_error_deg(theirs["rig_from_world"], scene.pose) + 0.002


def test_generalized_relative_pose_agrees_with_pycolmap():
    """The same inliers as pycolmap's, and a pose at least as close to the truth: the
    rig's baseline fixes the translation's scale only weakly (points 3 to 6 away from
    cameras 1 apart), and the two differ mostly there."""
    scene = rig_two_view(seed=7, outlier_ratio=0.2)
    ours = generalized_relative(scene, seed=2)
    options = pycolmap.RANSACOptions()
    options.max_error = MAX_ERROR * FOCAL
    options.random_seed = 2
    theirs = pycolmap.estimate_generalized_relative_pose(
        pixels(scene.x1), pixels(scene.x2), rig_pixels(scene.camera_index1),
        rig_pixels(scene.camera_index2), RIG, [CAMERA] * len(RIG), options)
    assert np.mean(ours.inlier_mask == theirs["inlier_mask"]) > 0.97
    assert rotation_error_deg(ours.rig2_from_rig1, scene.pose) \
        <= rotation_error_deg(theirs["rig2_from_rig1"], scene.pose) + 0.01
    assert np.linalg.norm(ours.rig2_from_rig1.translation - scene.pose.translation) \
        <= np.linalg.norm(theirs["rig2_from_rig1"].translation - scene.pose.translation) + 0.02


@pytest.mark.parametrize("method", ["fivept_plus_one", "sixpt"])
def test_generalized_relative_pose_refuses_a_single_camera_pair(method):
    """Correspondences of one camera pair leave the scale open: no pose, not a wrong one."""
    scene = rig_two_view(seed=5, n=300)
    one_pair = (scene.camera_index1 == 0) & (scene.camera_index2 == 1)
    n = int(one_pair.sum())
    assert n >= 50
    assert_refused(lambda: solvers.generalized_relative_pose(
        scene.x1[one_pair], scene.camera_index1[one_pair], scene.x2[one_pair],
        scene.camera_index2[one_pair], RIG, max_error=MAX_ERROR, method=method, seed=0),
        "generalized relative", n, 15)


RIG_VIEW = rig_one_view(seed=8, n=20)
RIG_PAIR = rig_two_view(seed=8, n=20)


@pytest.mark.parametrize("call, message", [
    (lambda: solvers.generalized_absolute_pose(RIG_VIEW.x, RIG_VIEW.camera_index + 3, RIG_VIEW.X,
                                               RIG, max_error=1e-3), r"camera_index out of range"),
    (lambda: solvers.generalized_absolute_pose(RIG_VIEW.x, RIG_VIEW.camera_index * 1.0, RIG_VIEW.X,
                                               RIG, max_error=1e-3), r"camera_index .*integers"),
    (lambda: solvers.generalized_absolute_pose(RIG_VIEW.x, RIG_VIEW.camera_index[:5], RIG_VIEW.X,
                                               RIG, max_error=1e-3), r"differ in length"),
    (lambda: solvers.generalized_absolute_pose(RIG_VIEW.x, RIG_VIEW.camera_index, RIG_VIEW.X,
                                               [np.eye(4)], max_error=1e-3),
     r"cams_from_rig .*pycolmap.Rigid3d"),
    (lambda: solvers.generalized_relative_pose(  # a single camera: no baseline, no scale
        RIG_PAIR.x1, RIG_PAIR.camera_index1 * 0, RIG_PAIR.x2, RIG_PAIR.camera_index2 * 0,
        [pycolmap.Rigid3d()], max_error=1e-3), r"cams_from_rig: .*share one centre"),
    (lambda: solvers.generalized_relative_pose(  # two cameras turned about one centre
        RIG_PAIR.x1, RIG_PAIR.camera_index1 % 2, RIG_PAIR.x2, RIG_PAIR.camera_index2 % 2,
        [pycolmap.Rigid3d(), pycolmap.Rigid3d(pycolmap.Rotation3d([0, 1, 0]), [0, 0, 0])],
        max_error=1e-3), r"share one centre"),
    (lambda: solvers.generalized_relative_pose(RIG_PAIR.x1, RIG_PAIR.camera_index1, RIG_PAIR.x2,
                                               -RIG_PAIR.camera_index2 - 1, RIG, max_error=1e-3),
     r"camera_index2 out of range"),
    (lambda: solvers.generalized_relative_pose(RIG_PAIR.x1[:5], RIG_PAIR.camera_index1[:5],
                                               RIG_PAIR.x2[:5], RIG_PAIR.camera_index2[:5], RIG,
                                               max_error=1e-3), r"at least 6"),
    (lambda: solvers.generalized_relative_pose(RIG_PAIR.x1[:16], RIG_PAIR.camera_index1[:16],
                                               RIG_PAIR.x2[:16], RIG_PAIR.camera_index2[:16], RIG,
                                               max_error=1e-3, method="seventeenpt"),
     r"at least 17"),
    (lambda: solvers.generalized_relative_pose(RIG_PAIR.x1, RIG_PAIR.camera_index1, RIG_PAIR.x2,
                                               RIG_PAIR.camera_index2, RIG, max_error=1e-3,
                                               method="ge"), r"unknown method 'ge'"),
])
def test_generalized_bad_input_raises_value_error_naming_the_problem(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@dataclass
class RigAllAround:
    pose: pycolmap.Rigid3d  # rig2_from_rig1 = rig_from_world of frame 2 (world: rig 1)
    X: np.ndarray  # (N, 3) world points all around the rig
    camera_index1: np.ndarray
    rays1: np.ndarray  # (N, 3) unit rays with angular noise, in any direction
    camera_index2: np.ndarray
    rays2: np.ndarray


def rig_all_around(seed: int, n: int = 300, noise_by_camera=(RIG_ANGULAR_NOISE,) * len(RIG)
                   ) -> RigAllAround:
    """RIG as three 360-degree cameras, moving by about 0.5 among points 4 to 8 from it in
    every direction: each point seen by a random camera in each frame, along a unit ray
    (about half behind the camera's image plane) with the camera's angular noise."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    X = directions / np.linalg.norm(directions, axis=1, keepdims=True) * rng.uniform(4, 8, (n, 1))
    pose = pycolmap.Rigid3d(rotation(rng, 30), rng.normal(size=3) * 0.3)

    def observed(rig_from_world: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
        camera_index = rng.integers(0, len(RIG), n)
        rays = np.empty_like(X)
        for c, cam_from_rig in enumerate(RIG):
            seen = camera_index == c
            x_cam = transform(cam_from_rig * rig_from_world, X[seen])
            rays[seen] = x_cam / np.linalg.norm(x_cam, axis=1, keepdims=True) + \
                rng.normal(0, noise_by_camera[c], x_cam.shape)
        return camera_index, rays / np.linalg.norm(rays, axis=1, keepdims=True)

    return RigAllAround(pose, X, *observed(pycolmap.Rigid3d()), *observed(pose))


def test_generalized_solvers_take_rays_in_every_direction():
    """GP3P and the 5+1-point and 6-point relative poses from rays all around each camera
    (half behind its image plane), angular thresholds: every correspondence an inlier, the
    poses within the accuracy tests' bounds."""
    scene = rig_all_around(seed=4)
    assert (scene.rays2[:, 2] < 0).mean() > 0.3
    max_error = 4 * RIG_ANGULAR_NOISE
    absolute = solvers.generalized_absolute_pose(scene.rays2, scene.camera_index2, scene.X, RIG,
                                                 max_error=max_error, seed=0)
    assert absolute.inlier_mask.mean() > 0.95
    assert rotation_error_deg(absolute.rig_from_world, scene.pose) < RIG_ABSOLUTE_MAX_ROTATION_DEG
    assert centre_distance(absolute.rig_from_world, scene.pose) < RIG_ABSOLUTE_MAX_CENTRE_ERROR
    for method in ("fivept_plus_one", "sixpt"):
        relative = solvers.generalized_relative_pose(
            scene.rays1, scene.camera_index1, scene.rays2, scene.camera_index2, RIG,
            max_error=max_error, method=method, seed=0)
        assert relative.inlier_mask.mean() > 0.95
        assert rotation_error_deg(relative.rig2_from_rig1, scene.pose) \
            < RIG_RELATIVE_MAX_ROTATION_DEG
        assert np.linalg.norm(relative.rig2_from_rig1.translation - scene.pose.translation) \
            < RIG_RELATIVE_MAX_TRANSLATION_ERROR


def test_generalized_solvers_take_one_threshold_per_correspondence():
    """Camera 0 eight times as noisy as the others: with thresholds per correspondence
    (4 sigma of its camera, or of the noisier camera of a pair) its correspondences stay
    inliers; one threshold for all, the others' 3 sigma, loses most of them."""
    noise = RIG_ANGULAR_NOISE * np.array([8.0, 1.0, 1.0])
    scene = rig_all_around(seed=6, noise_by_camera=noise)
    one_threshold = 3 * RIG_ANGULAR_NOISE
    noisy = scene.camera_index2 == 0
    for max_error, noisy_inliers in ((4 * noise[scene.camera_index2], (0.9, 1.0)),
                                     (one_threshold, (0.0, 0.6))):
        absolute = solvers.generalized_absolute_pose(scene.rays2, scene.camera_index2, scene.X,
                                                     RIG, max_error=max_error, seed=0)
        assert noisy_inliers[0] < absolute.inlier_mask[noisy].mean() <= noisy_inliers[1]
        assert absolute.inlier_mask[~noisy].mean() > 0.9
        assert rotation_error_deg(absolute.rig_from_world, scene.pose) \
            < RIG_ABSOLUTE_MAX_ROTATION_DEG
    noisy = (scene.camera_index1 == 0) | (scene.camera_index2 == 0)
    pair_errors = 4 * np.maximum(noise[scene.camera_index1], noise[scene.camera_index2])
    for max_error, noisy_inliers in ((pair_errors, (0.9, 1.0)), (one_threshold, (0.0, 0.6))):
        relative = solvers.generalized_relative_pose(
            scene.rays1, scene.camera_index1, scene.rays2, scene.camera_index2, RIG,
            max_error=max_error, seed=0)
        assert noisy_inliers[0] < relative.inlier_mask[noisy].mean() <= noisy_inliers[1]
        assert relative.inlier_mask[~noisy].mean() > 0.9
        assert rotation_error_deg(relative.rig2_from_rig1, scene.pose) \
            < RIG_RELATIVE_MAX_ROTATION_DEG
    with pytest.raises(ValueError, match="one per correspondence"):
        solvers.generalized_relative_pose(scene.rays1, scene.camera_index1, scene.rays2,
                                          scene.camera_index2, RIG, max_error=pair_errors[1:])
