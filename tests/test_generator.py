"""The mapper on databases from COLMAP's own generator (`pycolmap.synthesize_dataset` with
`synthesize_noise`), the neutral ground of benchmarks/neutral.py: poses against the
truth, tracks against the true tracks, and a least-squares last adjustment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext.geometry import rotation_angles_deg
from colmap_ext.database import read_database
from colmap_ext.evaluate import aligned_to_ground_truth
from colmap_ext.ground_truth import GroundTruth
from colmap_ext.mapper import MapperOptions
from colmap_ext.mapper.pipeline import reconstruct
from colmap_ext.synthetic.pycolmap_generator import verify_with_colmap, wrong_observations
from colmap_ext.timing import StageTimer

CAMERA_PARAMS = {"PINHOLE": [1280.0, 1280.0, 512.0, 384.0],
                 "SIMPLE_RADIAL": [1280.0, 512.0, 384.0, 0.05]}


def generate(folder: Path, camera_model: str, noise_px: float, inlier_ratio: float,
             seed: int) -> pycolmap.Reconstruction:
    """A 12-image, 300-point database in folder/database.db; returns the truth."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 1, 1, 12
    options.num_points3D = 300
    options.camera_model_id = getattr(pycolmap.CameraModelId, camera_model)
    options.camera_params = CAMERA_PARAMS[camera_model]
    options.inlier_match_ratio = inlier_ratio
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev = noise_px
    with pycolmap.Database.open(folder / "database.db") as db:
        pycolmap.set_random_seed(seed)
        truth = pycolmap.synthesize_dataset(options, db)
        pycolmap.set_random_seed(seed)
        pycolmap.synthesize_noise(noise, truth, db)
    return truth


def aligned_rotations(model: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> np.ndarray:
    """The rotations (n,3,3) of the model's images in the truth's order, after the
    similarity alignment of their centres onto the truth's."""
    cameras, _ = aligned_to_ground_truth(model, GroundTruth(true_poses(truth), {}))
    return np.array([pose.rotation.matrix() for pose in cameras.values()])


def true_poses(truth: pycolmap.Reconstruction) -> dict[str, pycolmap.Rigid3d]:
    return {image.name: image.cam_from_world()
            for image in sorted(truth.images.values(), key=lambda image: image.name)}


def angles_between(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    return rotation_angles_deg(np.swapaxes(R1, 1, 2) @ R2)


def rotation_errors(model: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> np.ndarray:
    """Per image, the rotation error (deg) after a similarity alignment on the centres."""
    true = np.array([pose.rotation.matrix() for pose in true_poses(truth).values()])
    return angles_between(true, aligned_rotations(model, truth))


def least_squares_optimum(truth: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
    """The truth's own tracks (every true observation, with its noise) adjusted in least
    squares to convergence from the true poses: the maximum-likelihood answer of a perfect
    association (benchmarks/neutral.py's reference row)."""
    from colmap_ext.mapper.bundle_adjustment import adjust_reconstruction
    from colmap_ext.mapper.options import BundleAdjustmentOptions
    optimum = pycolmap.Reconstruction(truth)
    adjust_reconstruction(optimum, BundleAdjustmentOptions(
        loss="trivial", global_max_iterations=200, global_gradient_tolerance=1e-10), num_threads=1)
    return optimum


def ours(folder: Path, options: MapperOptions | None = None) -> pycolmap.Reconstruction:
    models = reconstruct(read_database(folder / "database.db"), options or MapperOptions(seed=0),
                         progress=False)
    assert len(models) == 1
    return models[0]


@pytest.mark.parametrize("camera_model, noise_px, inlier_ratio, max_error_deg, min_observations", [
    ("PINHOLE", 0.5, 1.0, 0.1, 1.0),
    ("SIMPLE_RADIAL", 0.5, 0.7, 0.1, 1.0),
    ("PINHOLE", 1.5, 0.7, 0.3, 0.99),
])
def test_poses_and_tracks_of_generated_databases(tmp_path, camera_model, noise_px, inlier_ratio,
                                                 max_error_deg, min_observations):
    """Every image registered, rotations within about 2.5x the worst measured, and the
    true tracks kept whole: one point per true track and every true observation, nearly
    every one where the noise crosses the pixel thresholds. Measured over seeds 0-2
    (2026-11-26): R_err max 0.043 deg at 0.5 px, 0.131 at 1.5 px; observations 1.000 of the
    truth's at 0.5 px, 0.996-0.999 at 1.5 px in 1.00-1.01 points per true track (the day
    before, the retriangulation's cap and a noise limit at 3x the median: 0.997-1.000 and
    0.966-0.974 in 1.02-1.04; thresholds fixed at 3 px, at 30 images: 0.83 in 1.39)."""
    truth = generate(tmp_path, camera_model, noise_px, inlier_ratio, seed=1)
    model = ours(tmp_path)
    assert model.num_reg_images() == truth.num_images()
    assert rotation_errors(model, truth).max() < max_error_deg
    assert model.num_points3D() <= 1.02 * truth.num_points3D()
    assert model.compute_num_observations() >= min_observations * truth.compute_num_observations()


def test_wrong_matches_through_colmaps_verification_stay_out_of_the_model(tmp_path):
    """Half the raw matches wrong, verified by COLMAP's own geometric verification (some
    wrong ones agree with a pair's geometry and get through), 1.5 px noise: every image
    registered, no wrong observation in the model, and nearly every true one. Measured
    (2026-11-26, seeds 0-5, 12 images): 205-240 wrong of about 19 900 verified matches;
    no wrong observation in any model, 0.997-0.999 of the true observations, R_err max
    0.071-0.131 deg (1.0 px: 0.047-0.086, every true observation)."""
    truth = generate(tmp_path, "PINHOLE", 1.5, 0.5, seed=1)
    verify_with_colmap(tmp_path / "database.db")
    true_points = {image_id: [p.point3D_id for p in image.points2D]
                   for image_id, image in truth.images.items()}
    with pycolmap.Database.open(tmp_path / "database.db") as database:
        wrong_verified = sum(
            true_points[first][i] != true_points[second][j]
            for pair_id, geometry in zip(*database.read_two_view_geometries())
            for first, second in [pycolmap.pair_id_to_image_pair(pair_id)]
            for i, j in geometry.inlier_matches)
    assert wrong_verified > 100
    model = ours(tmp_path)
    assert model.num_reg_images() == truth.num_images()
    assert wrong_observations(model, truth) == 0
    assert model.compute_num_observations() >= 0.99 * truth.compute_num_observations()
    assert rotation_errors(model, truth).max() < 0.3


def test_colmaps_verification_of_the_pairs_given_alone(tmp_path):
    """verify_with_colmap with pairs (a sequence's, as benchmarks/sequences.py's
    --verification colmap passes them): two-view geometries for those pairs alone, every
    one of the generator's replaced."""
    generate(tmp_path, "PINHOLE", 0.5, 1.0, seed=0)
    with pycolmap.Database.open(tmp_path / "database.db") as database:
        names = sorted(image.name for image in database.read_all_images())
    pairs = [(names[i], names[i + 1]) for i in range(len(names) - 1)]
    verify_with_colmap(tmp_path / "database.db", pairs)
    with pycolmap.Database.open(tmp_path / "database.db") as database:
        name_of = {image.image_id: image.name for image in database.read_all_images()}
        verified = {tuple(sorted(name_of[i] for i in pycolmap.pair_id_to_image_pair(pair_id)))
                    for pair_id, geometry in zip(*database.read_two_view_geometries())
                    if len(geometry.inlier_matches)}
    assert verified == set(pairs)


@pytest.mark.parametrize("seed", [0, 4])
def test_poses_are_the_least_squares_optimum_of_the_true_tracks(tmp_path, seed):
    """At 0.5 px, every match true: the model is the maximum-likelihood answer of a perfect
    association, the truth's own tracks (every true observation, with its noise) adjusted in
    least squares to convergence from the true poses (benchmarks/neutral.py's reference
    row); measured within 7e-6 deg of it, the optimum 0.024-0.031 deg from the truth. On
    seed 4, completing tracks during growth (triangulation.complete_tracks) adds 29
    observations that the first images left out."""
    truth = generate(tmp_path, "PINHOLE", 0.5, 1.0, seed)
    optimum = least_squares_optimum(truth)
    model = ours(tmp_path)
    assert model.compute_num_observations() == truth.compute_num_observations()
    assert angles_between(aligned_rotations(model, truth),
                          aligned_rotations(optimum, truth)).max() < 1e-4
    assert rotation_errors(optimum, truth).max() > 0.01  # the noise moved the optimum


@pytest.mark.parametrize("max_outlier_share, least_squares", [(0.01, True), (0.0, False)])
def test_gaussian_errors_end_on_a_least_squares_adjustment(tmp_path, max_outlier_share,
                                                            least_squares):
    """Where the reprojection errors look like Gaussian noise (at most
    FilteringOptions.gaussian_max_outlier_share of them beyond 3x their median;
    this database: 0.1 %), the model ends on a least-squares adjustment of the observations
    its last filter kept, run to COLMAP's gradient tolerance: the maximum-likelihood poses,
    which a further least-squares adjustment to convergence moves by 7e-6 deg. Where the
    test says otherwise (a share of 0 here), the robust loss stays and down-weights good
    observations, and the poses move by 0.0066 deg."""
    generate(tmp_path, "PINHOLE", 0.5, 1.0, seed=0)
    options = MapperOptions(seed=0)
    options.filtering.gaussian_max_outlier_share = max_outlier_share
    model = ours(tmp_path, options)
    image_ids = sorted(model.reg_image_ids())
    before = np.array([model.images[i].cam_from_world().rotation.matrix() for i in image_ids])
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in image_ids:
        config.add_image(image_id)
    for camera_id in model.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False,
                                               refine_principal_point=False,
                                               refine_extra_params=False, print_summary=False)
    options.ceres.solver_options.max_num_iterations = 100
    assert options.ceres.loss_function_type == pycolmap.LossFunctionType.TRIVIAL
    pycolmap.create_default_bundle_adjuster(options, config, model).solve()
    after = np.array([model.images[i].cam_from_world().rotation.matrix() for i in image_ids])
    assert (angles_between(before, after).max() < 0.001) == least_squares


def test_verified_matches_stand_in_for_a_descriptor_search_with_nothing_left_to_find(
        tmp_path, monkeypatch):
    """Here verified matches give 99 % of each image's keypoints a correspondence (the
    real sets: at most 39 %): registration and triangulation then search no image pair's
    descriptors (GuidedMatchingOptions.skip_search_verified_share), and the model is the
    one the searches give."""
    from colmap_ext.mapper.descriptors import NearestDescriptors
    truth = generate(tmp_path, "PINHOLE", 0.5, 1.0, seed=2)
    searched = []
    search = NearestDescriptors.search_subsets
    monkeypatch.setattr(NearestDescriptors, "search_subsets",
                        lambda self, image_id, subsets, k: searched.extend(subsets) or
                        search(self, image_id, subsets, k))
    model = ours(tmp_path)
    assert not searched
    options = MapperOptions(seed=0)
    options.guided_matching.skip_search_verified_share = 1.0
    with_search = ours(tmp_path, options)
    assert len(searched) > truth.num_images()
    assert angles_between(aligned_rotations(model, truth),
                          aligned_rotations(with_search, truth)).max() < 1e-6
    assert model.compute_num_observations() == with_search.compute_num_observations()


@pytest.mark.parametrize("noise_px, seed, left_out", [(0.5, 0, True), (0.8, 1, False),
                                                     (1.5, 0, False)])
def test_retriangulation_only_where_matches_disagree_with_tracks(tmp_path, monkeypatch,
                                                                 noise_px, seed, left_out):
    """Errors that look Gaussian: the finished model's points are triangulated again only
    where verified matches disagree with its tracks (refinement.points_off_matches). At
    0.5 px, none on seed 0 (retriangulation left out: the tracks were completed after
    each adjustment); at 0.8 px, 4 of 300 on seed 1; at 1.5 px the noise split many
    tracks (131 points). Each time the model is as near the least-squares optimum of the
    true tracks as a retriangulation of every point leaves it, and holds as many of the
    true observations, give or take one in a thousand. Measured on 12 images: 0.5 px
    1e-6 deg from the optimum either way; 0.8 px seed 1 2e-5 deg against 6e-3 (every point
    left an observation out); 1.5 px seeds 0-2 0.0097-0.0109 deg against 0.0093-0.0112,
    against R_err max of 0.07-0.13 deg."""
    import colmap_ext.mapper.refinement as refinement
    truth = generate(tmp_path, "PINHOLE", noise_px, 1.0, seed)
    optimum_rotations = aligned_rotations(least_squares_optimum(truth), truth)
    db = read_database(tmp_path / "database.db")
    timer = StageTimer()
    model = reconstruct(db, MapperOptions(seed=0), timer=timer, progress=False)[0]
    assert (timer.counts["retriangulations left out"] == 1) == left_out
    monkeypatch.setattr(refinement, "points_off_matches",
                        lambda model, matches, max_error_px: model.point_ids)
    every_point = reconstruct(db, MapperOptions(seed=0), progress=False)[0]
    assert model.num_points3D() == every_point.num_points3D()
    assert model.compute_num_observations() >= every_point.compute_num_observations() - \
        0.001 * truth.compute_num_observations()
    from_optimum, every_from_optimum = (
        angles_between(aligned_rotations(m, truth), optimum_rotations).max()
        for m in (model, every_point))
    assert from_optimum <= every_from_optimum + (0.002 if noise_px > 1 else 1e-4)


def test_descriptor_searches_are_given_up_before_every_global_adjustment(tmp_path,
                                                                           monkeypatch):
    """Memory: a global adjustment is the growing model's peak, and the finished model's
    exact one, after the retriangulation's searches, the mapper's (drive800: 958 -> 798
    MiB there). The descriptor searches kept between guided matchings are given up before
    each; local adjustments keep them."""
    import colmap_ext.mapper.refinement as refinement
    kept: dict[bool, list[int]] = {True: [], False: []}
    bundle_adjust = refinement.bundle_adjust

    def recording(model, image_ids, ba, local, *args, **kwargs):
        kept[local].append(model.nearest.pairs.bytes + model.nearest.units.bytes)
        return bundle_adjust(model, image_ids, ba, local, *args, **kwargs)

    monkeypatch.setattr(refinement, "bundle_adjust", recording)
    generate(tmp_path, "PINHOLE", 1.5, 0.7, 0)
    timer = StageTimer()
    reconstruct(read_database(tmp_path / "database.db"), MapperOptions(seed=0), timer=timer,
                progress=False)
    assert timer.counts["retriangulations left out"] == 0
    assert max(kept[True]) > 0  # the local adjustments' searches stay
    assert len(kept[False]) >= 3 and max(kept[False]) == 0


@pytest.mark.parametrize("freq", [1, 500])
def test_global_adjustments_come_at_least_every_global_images_freq_images(tmp_path,
                                                                         monkeypatch, freq):
    """--Mapper.ba_global_frames_freq, as COLMAP's: a global adjustment whenever the model
    has grown by global_images_ratio or by global_images_freq images, whichever comes
    first; on 12 images the ratio alone leaves gaps of 2."""
    from colmap_ext.mapper.options import BundleAdjustmentOptions
    from colmap_ext.mapper.pipeline import IncrementalMapper
    sizes: list[int] = []
    global_adjustment = IncrementalMapper._global_adjustment

    def recording(self):
        sizes.append(self.model.num_registered)
        global_adjustment(self)

    monkeypatch.setattr(IncrementalMapper, "_global_adjustment", recording)
    generate(tmp_path, "PINHOLE", 0.5, 1.0, 0)
    options = MapperOptions(seed=0, bundle_adjustment=BundleAdjustmentOptions(
        global_images_freq=freq))
    model = reconstruct(read_database(tmp_path / "database.db"), options, progress=False)[0]
    assert model.num_reg_images() == 12
    gaps = np.diff(sizes)
    assert (gaps.max() == 1) == (freq == 1), sizes


@pytest.mark.parametrize("window_num_images", [0, 3])
def test_the_last_registered_images_are_adjusted_together_every_window_images_freq_images(
        tmp_path, monkeypatch, window_num_images):
    """BundleAdjustmentOptions.window_num_images: between global adjustments (here the
    initial pair's alone: ratio 10), the last 3 registered images are adjusted together
    whenever the model has grown by 2 images, once it holds twice the window; 0: never."""
    from colmap_ext.mapper.options import BundleAdjustmentOptions
    from colmap_ext.mapper.refinement import ModelAdjuster
    windows: list[int] = []
    local_adjustment = ModelAdjuster.local_adjustment

    def recording(self, image_ids):
        if list(image_ids) == self.model.registration_order[-3:]:
            windows.append(self.model.num_registered)
        local_adjustment(self, image_ids)

    monkeypatch.setattr(ModelAdjuster, "local_adjustment", recording)
    generate(tmp_path, "PINHOLE", 0.5, 1.0, 0)
    options = MapperOptions(seed=0, bundle_adjustment=BundleAdjustmentOptions(
        global_images_ratio=10.0, window_num_images=window_num_images, window_images_freq=2))
    model = reconstruct(read_database(tmp_path / "database.db"), options, progress=False)[0]
    assert model.num_reg_images() == 12
    assert windows == ([6, 8, 10, 12] if window_num_images else [])
