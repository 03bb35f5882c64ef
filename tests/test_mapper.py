"""The calibrated mapper: accuracy on synthetic databases and real data, the COLMAP
output layout, and the user's files left as they were."""

from __future__ import annotations

import copy
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext.database import read_database
from colmap_ext.evaluate import align_similarity, evaluate, rotation_angles_deg
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper import MapperOptions, descriptors, pipeline, run
from colmap_ext.mapper.options import BundleAdjustmentOptions
from colmap_ext.mapper.cli import main as mapper_cli
from colmap_ext.mapper.merging import find_similarity
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.pipeline import StageTimer, merge_models, reconstruct
from colmap_ext.mapper.descriptors import NearestDescriptors
from colmap_ext.mapper.filtering import rotation_uncertainty
from colmap_ext.mapper.initial_pair import (MAX_CANDIDATE_PAIRS, PARALLAX_SHARE,
                                             choose_initial_pair, parallax_deg, reconstruct_pair)
from colmap_ext.mapper.two_view import pair_graph, verified_matches

# Bounds on the 12-view synthetic ring for the tests added with them (orders, image
# lists, losses, merging): worst measured over seeds 0-4, R_err max 0.070 deg and
# C_err max 0.0022 |C2-C1| (image list); about 3x that.
RING_MAX_R_ERR_DEG = 0.2
RING_MAX_C_ERR = 0.007


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def ring_truth(scene) -> GroundTruth:
    return GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})


def true_centres(scene) -> dict[str, np.ndarray]:
    return {name: pose.inverse().translation
            for name, pose in zip(scene.image_names, scene.cams_from_world)}


@pytest.fixture(scope="module")
def synthetic(synthetic_ring):
    """A 12-view ring database (0.5 px noise, 20 % wrong matches) and its truth."""
    return synthetic_ring


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
    report = evaluate(model, ring_truth(scene))
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
    """Each loss reaches Ceres (trivial converges in fewer iterations than soft-L1, soft-L1
    in fewer than Cauchy) and each recovers the whole ring (0.5 px noise, 20 % wrong
    matches); an unknown loss is refused. Measured over seeds 0-4: iterations 117
    (Cauchy), 59 (soft-L1), 31-32 (trivial); R_err max 0.059, 0.058, 0.056 deg; C_err max
    0.0018, 0.0017, 0.0016."""
    folder, scene = synthetic
    db = read_database(folder / "database.db")
    truth = ring_truth(scene)
    iterations = {}
    for loss in ("cauchy", "soft_l1", "trivial"):
        timer = StageTimer()
        options = MapperOptions(bundle_adjustment=BundleAdjustmentOptions(loss=loss), seed=0)
        reconstructions = reconstruct(db, options, timer=timer, progress=False)
        assert len(reconstructions) == 1, loss
        report = evaluate(reconstructions[0], truth)
        assert report["num_registered"] == scene.num_images, loss
        assert report["R_err_max_deg"] < 0.1, loss
        assert report["C_err_max"] < RING_MAX_C_ERR, loss
        iterations[loss] = timer.counts["bundle adjustment iterations"]
    assert iterations["trivial"] < iterations["soft_l1"] < iterations["cauchy"]
    with pytest.raises(ValueError, match="BundleAdjustmentOptions.loss must be one of "
                                         "cauchy, soft_l1, trivial, got 'huber'"):
        MapperOptions(bundle_adjustment=BundleAdjustmentOptions(loss="huber")).check()


def test_synthetic_ring_from_database_matches_alone(synthetic, monkeypatch):
    """With no exact search allowed (max_search_pairs 0), the guided matching and the
    registration take their candidates from the database's matches, and the ring is
    still recovered within the bounds of the tests above."""
    folder, scene = synthetic

    def no_search(*args, **kwargs):
        raise AssertionError("an exact descriptor search ran")

    monkeypatch.setattr(descriptors, "nearest_descriptors", no_search)
    options = MapperOptions(seed=0)
    options.guided_matching.max_search_pairs = 0
    reconstructions = reconstruct(read_database(folder / "database.db"), options, progress=False)
    assert len(reconstructions) == 1
    report = evaluate(reconstructions[0], ring_truth(scene))
    assert report["num_registered"] == scene.num_images
    assert report["R_err_max_deg"] < RING_MAX_R_ERR_DEG
    assert report["C_err_max"] < RING_MAX_C_ERR


def ring_model(synthetic) -> tuple[Model, dict, MapperOptions]:
    """The synthetic ring's empty model, its verified matches and the default options."""
    folder, _ = synthetic
    db = read_database(folder / "database.db")
    options = MapperOptions(seed=0)
    store = NearestDescriptors(db.descriptors, {i: len(db.images[i].keypoints) for i in db.images},
                               options.guided_matching.num_neighbors, 2**26, num_threads=2)
    model = Model(db, store)
    return model, verified_matches(model, options.two_view, options.seed, progress=False), options


def test_initial_pair_has_most_points_among_the_wide_and_relaxes_as_colmap(synthetic):
    """The initial pair: most triangulated points among the candidates (the pairs with
    most matches among those whose parallax reaches PARALLAX_SHARE of the angle) whose
    median triangulation angle reaches initialization.min_tri_angle_deg. Where no
    candidate is that wide the angle halves, as COLMAP relaxes it, and the mapper still
    starts."""
    model, matches, options = ring_model(synthetic)
    ranked = sorted(matches, key=lambda pair: -len(matches[pair]))
    parallax = {pair: parallax_deg(model, pair, matches[pair], options.two_view, options.seed)
                for pair in ranked}
    two_views = {pair: t for pair in ranked
                 if (t := reconstruct_pair(model, pair, matches[pair], options.initialization,
                                           options.two_view, options.triangulation,
                                           options.seed)) is not None}
    angles = sorted(t.median_angle_deg for t in two_views.values())
    assert len(two_views) >= 12 and angles[-1] > 2 * angles[0]

    def choose():
        return choose_initial_pair(model, matches, options.initialization, options.two_view,
                                   options.triangulation, set(), options.seed)

    for min_angle in (angles[0], angles[len(angles) // 2], angles[-1]):
        options.initialization.min_tri_angle_deg = min_angle
        candidates = [pair for pair in ranked
                      if parallax[pair] >= PARALLAX_SHARE * min_angle][:MAX_CANDIDATE_PAIRS]
        wide = [two_views[pair] for pair in candidates if pair in two_views
                and two_views[pair].median_angle_deg >= min_angle]
        chosen = choose()
        assert chosen.median_angle_deg >= min_angle
        assert len(chosen.matches) == max(len(t.matches) for t in wide)
    # Four times the widest pair's angle, halved twice: the widest pair.
    options.initialization.min_tri_angle_deg = 4 * angles[-1]
    assert choose().median_angle_deg == angles[-1]


def test_parallax_is_the_median_triangulation_angle(synthetic):
    """A pair's parallax (from a 64-match sample's relative rotation) is close to the
    median angle of its reconstructed points, and none for an image with itself."""
    model, matches, options = ring_model(synthetic)
    for pair, pair_matches in sorted(matches.items())[:10]:
        reconstructed = reconstruct_pair(model, pair, pair_matches, options.initialization,
                                         options.two_view, options.triangulation, options.seed)
        parallax = parallax_deg(model, pair, pair_matches, options.two_view, options.seed)
        assert parallax == pytest.approx(reconstructed.median_angle_deg, rel=0.15)
    image_id = pair[0]
    keypoints = np.arange(len(model.db.images[image_id].keypoints))
    same = np.stack([keypoints, keypoints], axis=1)
    assert parallax_deg(model, (image_id, image_id), same, options.two_view, options.seed) < 0.01


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

    points = sha256(out / "0" / "points3D.txt")
    replaced = run_cli(*args, "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert (out / "0" / "images.txt").is_file()
    # The same seed rewrites the same model, byte for byte.
    assert sha256(out / "0" / "images.txt") == written
    assert sha256(out / "0" / "points3D.txt") == points
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


def test_sequence_order_grows_by_name_and_is_accurate(synthetic, tmp_path, monkeypatch):
    """`mapper --order sequence` registers each next image beside the registered ones in
    name order, so the registered names always form one run (the visibility order wraps
    round the ring here: 4 5 6 3 2 1 0 then 10), and recovers the whole ring."""
    folder, scene = synthetic
    registered = []
    register_frame = Model.register_frame

    def record(model, image_id, rig_from_world):
        registered.append(scene.image_names.index(model.db.images[image_id].name))
        return register_frame(model, image_id, rig_from_world)

    monkeypatch.setattr(Model, "register_frame", record)
    result = mapper_cli(str(folder / "database.db"), str(folder / "images"),
                        str(tmp_path / "out"), order="sequence", seed=0)
    # Measured over seeds 0-4: 4 5 6 3 2 1 0 7 8 9 10 11.
    assert sorted(registered) == list(range(scene.num_images))
    for count in range(1, len(registered) + 1):
        assert max(registered[:count]) - min(registered[:count]) == count - 1, registered
    [model] = result["reconstructions"].values()
    report = evaluate(model, ring_truth(scene))
    assert report["num_registered"] == scene.num_images
    assert report["R_err_max_deg"] < RING_MAX_R_ERR_DEG  # measured 0.059 deg
    assert report["C_err_max"] < RING_MAX_C_ERR  # measured 0.0019


def test_image_list_maps_only_the_listed_images(synthetic, tmp_path):
    """`mapper --image_list_path` with an arc of 8 of the 12 images: the model holds
    exactly those, all registered and accurate; the other 4 are not in it at all."""
    folder, scene = synthetic
    listed = scene.image_names[:8]
    image_list = tmp_path / "image_list.txt"
    image_list.write_text("\n".join(listed) + "\n")
    result = mapper_cli(str(folder / "database.db"), str(folder / "images"),
                        str(tmp_path / "out"), image_list_path=str(image_list), seed=0)
    [model] = result["reconstructions"].values()
    assert sorted(image.name for image in model.images.values()) == listed
    assert model.num_reg_images() == len(listed)
    truth = GroundTruth({name: ring_truth(scene).poses[name] for name in listed}, {})
    report = evaluate(model, truth)
    assert report["R_err_max_deg"] < RING_MAX_R_ERR_DEG  # measured 0.068-0.070 deg
    assert report["C_err_max"] < RING_MAX_C_ERR  # measured 0.0022


def ring_arcs(db, options, monkeypatch) -> tuple[list[Model], dict]:
    """The model `reconstruct` makes of the whole ring, as it hands it to merge_models,
    cut into two models of 6 consecutive images each (points they see once dropped);
    and its verified matches."""
    handed = []
    monkeypatch.setattr(pipeline, "merge_models",
                        lambda models, matches, *_, **__: handed.append((models, matches)) or models)
    reconstruct(db, options, progress=False)
    monkeypatch.undo()
    [([model], matches)] = handed
    names = sorted(db.images[i].name for i in model.registered)
    arcs = []
    for arc_names in (names[:len(names) // 2], names[len(names) // 2:]):
        arc = copy.deepcopy(model)
        for image_id in arc.registered:
            if arc.db.images[image_id].name not in arc_names:
                arc.deregister(image_id)
        arcs.append(arc)
    return arcs, matches


def true_from_model(model: Model, scene) -> pycolmap.Sim3d:
    """The similarity that puts the model's camera centres best onto the true ones."""
    registered = model.registered
    true = true_centres(scene)
    return pycolmap.estimate_sim3d(
        np.array([model.centre(i) for i in registered]),
        np.array([true[model.db.images[i].name] for i in registered]))


def test_merging_recovers_a_known_similarity(synthetic, monkeypatch):
    """The ring's model cut into two arcs of 6 images, each put in the true frame, the
    second then moved by a known similarity: find_similarity recovers its inverse, and
    merge_models joins the arcs into one model of the 12 images, in the first arc's
    (the true) frame, matching the true poses."""
    folder, scene = synthetic
    db = read_database(folder / "database.db")
    options = MapperOptions(seed=0)
    (target, source), matches = ring_arcs(db, options, monkeypatch)
    for model in (target, source):
        model.transform(true_from_model(model, scene))
    applied = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(np.array([0.3, -0.5, 0.8])),
                             np.array([4.0, -3.0, 1.0]))
    source.transform(applied)

    found = find_similarity(target, source, pair_graph(db.raw_matches), options.merging,
                            options.registration, options.guided_matching, options.seed)
    assert found is not None
    similarity = found[0]
    # Measured over seeds 0-4: rotation 0.022-0.023 deg off, scale ratio within 0.00013
    # of 1, translation 0.0021 off (ring radius 3).
    rotation = similarity.rotation.matrix() @ applied.rotation.matrix()
    assert rotation_angles_deg(rotation[None])[0] < 0.07
    assert similarity.scale * applied.scale == pytest.approx(1, abs=0.0004)
    expected_translation = applied.inverse().translation
    assert np.linalg.norm(similarity.translation - expected_translation) < 0.0065

    joined = merge_models([target, source], matches, options, StageTimer())
    assert len(joined) == 1
    model = joined[0].export()
    report = evaluate(model, ring_truth(scene))
    assert report["num_registered"] == scene.num_images
    assert report["R_err_max_deg"] < RING_MAX_R_ERR_DEG  # measured 0.060 deg
    assert report["C_err_max"] < RING_MAX_C_ERR  # measured 0.0019
    # The centres, in the frame of the target: the true frame (measured 0.0038 off).
    true = true_centres(scene)
    offsets = [np.linalg.norm(image.projection_center() - true[image.name])
               for image in model.images.values()]
    assert max(offsets) < 0.012


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
        # The exact nearest descriptors and a seeded verification: the same database on
        # every run. pycolmap's default CPU matcher (an approximate index) gave 7723 raw
        # matches on templeSparseRing in most runs and 7584 in one; its RANSAC, unseeded,
        # draws anew each run.
        matching = pycolmap.FeatureMatchingOptions()
        matching.sift.cpu_brute_force_matcher = True
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = 0
        pycolmap.match_exhaustive(database, matching_options=matching,
                                  verification_options=verification, device=pycolmap.Device.cpu)
        databases[name] = (database, images, truth)
    return databases


def test_temple_sparse_ring(real_databases, tmp_path):
    database, images, truth = real_databases["templeSparseRing"]
    reconstructions = run(database, images, tmp_path, MapperOptions(seed=0), progress=False)
    report = evaluate(reconstructions[0], truth)
    # COLMAP 4.2.1's incremental mapper registers 13 of 16 here, R_err max 0.82 deg. Ours
    # registers all 16; R_err max measured 0.204 deg (seed 0).
    assert report["num_registered"] == 16
    assert report["R_err_max_deg"] < 0.5
    assert report["C_err_max"] < 0.02


def test_temple_final_stage_over_seeds(real_databases, tmp_path):
    """The finished model's two steps against near-miss observations, which each seed's
    RANSAC draws keep or not and which pull on the poses: the final adjustment's filter
    (FilteringOptions.final_max_error_ratio) and the retriangulation from the final poses
    (TriangulationOptions.retriangulation_max_error_ratio). R_err max measured on seeds
    0 / 1 / 2: 0.204 / 0.204 / 0.213 deg. On a database from pycolmap's approximate matcher
    (7723 raw matches): 0.208 / 0.234 / 0.208; without the retriangulation 0.274 / 0.292 /
    0.273; without both 0.308 / 0.333 / 0.307; without the filter alone 0.236 / 0.238 /
    0.233: on these features the retriangulation does nearly all of it (on our own, see
    docs/experiments/retriangulation.md, the filter still takes the worst seed from 0.286 to
    0.226). Its one run with 7584 raw matches gave 0.222 / 0.342 / 0.222."""
    database, images, truth = real_databases["templeSparseRing"]
    errors = []
    for seed in (0, 1, 2):
        reconstructions = run(database, images, tmp_path / str(seed), MapperOptions(seed=seed),
                              progress=False)
        report = evaluate(reconstructions[0], truth)
        assert report["num_registered"] == 16
        errors.append(report["R_err_max_deg"])
    assert max(errors) < 0.25


def test_dino_sparse_ring(real_databases, tmp_path):
    """Two models of 6 images, 7-12 first, then 1-4 with 15-16, over seeds 0-9."""
    database, images, truth = real_databases["dinoSparseRing"]
    sizes = []
    for seed in range(10):
        reconstructions = run(database, images, tmp_path / str(seed), MapperOptions(seed=seed),
                              progress=False)
        report = evaluate(reconstructions[0], truth)
        # COLMAP 4.2.1's incremental mapper registers 6 of 16 here, R_err max 0.65 deg. With
        # ~240 keypoints an image, no stored pair links images 1-5 and 14-16 to 7-13 (image 6
        # has none). Image 5 ends on 21 points that fix its rotation poorly (uncertainty 18.7)
        # and 2 deg off: it is deregistered. The model with more points, 7-12, comes first,
        # measured R_err max 0.31 to 0.33 deg over seeds 0-9.
        assert report["num_registered"] == 6
        assert report["R_err_max_deg"] < 0.5
        assert sorted(image.name for image in reconstructions[0].images.values()) == \
            [f"dinoSR{k:04d}.png" for k in range(7, 13)]
        # The second model (1-4, 15, 16): R_err max measured 0.41 to 0.59 deg over seeds 0-9.
        assert evaluate(reconstructions[1], truth)["R_err_max_deg"] < 2.2
        sizes.append([r.num_reg_images() for r in reconstructions.values()])
    # Measured: [6, 6] on every seed but 2, whose second arc starts from images 1 and 2
    # (those with most points among pairs 8 deg apart or more) and ends with 1, 2 and 16:
    # P3P poses images 3 and 15 off the verified matches' epipolar lines (support
    # 0.80-0.84), and the check turns them down.
    assert sizes.count([6, 6]) >= 9 and all(size[0] == 6 for size in sizes)


def test_requested_initial_pair_starts_the_first_model_only(real_databases, tmp_path):
    """--Mapper.init_image_id1/2 start the first model; later models choose their own
    pair (as COLMAP's), rather than asking again for a pair the first model holds.
    Requesting the pair the mapper chooses itself (images 9 and 10 on the builds measured)
    gives its models. The pair is taken from the mapper's choice rather than written here:
    each run of the tests extracts and matches this database afresh."""
    database, images, truth = real_databases["dinoSparseRing"]
    chosen = run(database, images, tmp_path / "chosen", MapperOptions(seed=0), progress=False)
    options = MapperOptions(seed=0)
    db = read_database(database)
    model = Model(db, NearestDescriptors(db.descriptors, {i: len(db.images[i].keypoints)
                                                          for i in db.images}, 3, 2**26, 1))
    matches = verified_matches(model, options.two_view, options.seed, progress=False)
    first = choose_initial_pair(model, matches, options.initialization, options.two_view,
                                options.triangulation, set(), options.seed)
    options.initialization.image_id1, options.initialization.image_id2 = first.pair
    requested = run(database, images, tmp_path / "requested", options, progress=False)
    assert [r.num_reg_images() for r in requested.values()] == [6, 6]
    for a, b in zip(chosen.values(), requested.values()):
        assert evaluate(a, truth)["per_image"] == evaluate(b, truth)["per_image"]
