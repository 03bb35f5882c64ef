"""Matching by pycolmap, verification by our 5-point RANSAC: poses, E, inliers in the database."""

from __future__ import annotations

import contextlib
import itertools
import shutil
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext import matching, rigs
from colmap_ext.errors import UserError
from colmap_ext.executors import LocalExecutor
from colmap_ext.features import FeatureOptions, extract_features, quiet_colmap_logs
from colmap_ext.matching import MatchingOptions, loop_closure_pairs, match_features
from colmap_ext.synthetic import (Scene, driving_scene, points_for_keypoints, rig_scene,
                                  side_by_side_rig, write_rig_config, write_synthetic_database)

WIDTH, HEIGHT, FOCAL = 480, 360, 500.0
K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
PARAMS = f"{FOCAL},{FOCAL},{WIDTH / 2},{HEIGHT / 2}"
TEXTURE_SIZE = 1200
# The scene (not planar, so that the relative pose is unique): a 2.4 x 2.4 textured floor
# at z = 0 and the 1.2 x 1.2 textured top of a box at z = 0.4, each (half-size, height).
FLOOR, BOX_TOP = (1.2, 0.0), (0.6, 0.4)


def texture(seed: int) -> np.ndarray:
    """Random discs and noise: plenty of distinctive SIFT keypoints."""
    rng = np.random.default_rng(seed)
    image = (rng.random((TEXTURE_SIZE // 8, TEXTURE_SIZE // 8)) * 255).astype(np.uint8)
    image = cv2.resize(image, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_CUBIC)
    for _ in range(600):
        centre = tuple(int(v) for v in rng.integers(0, TEXTURE_SIZE, 2))
        cv2.circle(image, centre, int(rng.integers(4, 30)), int(rng.integers(0, 256)), -1,
                   cv2.LINE_AA)
    return image


def look_at(centre: np.ndarray) -> pycolmap.Rigid3d:
    """cam_from_world of a camera at `centre` looking at the origin, image y roughly down."""
    z = -centre / np.linalg.norm(centre)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre)


def render_square(texture_image: np.ndarray, pose: pycolmap.Rigid3d, square: tuple[float, float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A textured horizontal square seen by the pinhole camera K at `pose`: a homography.
    Returns the image and where the square covers it."""
    half_size, height = square
    M = pose.matrix()
    scale = 2 * half_size / TEXTURE_SIZE
    plane_from_texture = np.array([[scale, 0, -half_size], [0, scale, -half_size], [0, 0, 1]])
    H = K @ np.column_stack([M[:, 0], M[:, 1], height * M[:, 2] + M[:, 3]]) @ plane_from_texture
    size = (WIDTH, HEIGHT)
    cover = cv2.warpPerspective(np.ones_like(texture_image), H, size, flags=cv2.INTER_NEAREST)
    return cv2.warpPerspective(texture_image, H, size, flags=cv2.INTER_LINEAR), cover > 0


def render(floor_texture: np.ndarray, box_texture: np.ndarray, pose: pycolmap.Rigid3d
           ) -> np.ndarray:
    """The floor with the box top in front of it (every camera looks down on both)."""
    image, _ = render_square(floor_texture, pose, FLOOR)
    top, cover = render_square(box_texture, pose, BOX_TOP)
    image[cover] = top[cover]
    return image


def ring_poses(num_views: int) -> list[pycolmap.Rigid3d]:
    """Cameras 2.5 from the floor's centre, 35 deg off vertical, 8 deg apart around it."""
    poses = []
    for k in range(num_views):
        azimuth, tilt = np.radians(8.0 * k), np.radians(35.0)
        centre = 2.5 * np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                                 np.cos(tilt)])
        poses.append(look_at(centre))
    return poses


@pytest.fixture(scope="module")
def scene_database(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    """Features of four views of the scene plus one view of a differently textured one."""
    root = tmp_path_factory.mktemp("scene")
    (root / "images").mkdir()
    poses = ring_poses(4)
    floor, box = texture(0), texture(1)
    for k, pose in enumerate(poses):
        cv2.imwrite(str(root / "images" / f"view{k}.png"), render(floor, box, pose))
    cv2.imwrite(str(root / "images" / "zother.png"), render(texture(2), texture(3), poses[0]))
    extract_features(root / "database.db", root / "images",
                     FeatureOptions("PINHOLE", PARAMS, min_num_keypoints=0), progress=False)
    return root / "database.db", poses


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_verified_geometry_matches_the_true_relative_pose(scene_database, tmp_path: Path) -> None:
    source, poses = scene_database
    database_path = tmp_path / "database.db"
    shutil.copy(source, database_path)
    summary = match_features(database_path, MatchingOptions(matcher="exhaustive"), progress=False)
    by_pair = {(p.name1, p.name2): p for p in summary.pairs}
    for (name1, name2), pair in by_pair.items():
        if "zother" in name1 + name2:
            assert pair.num_inliers == 0
        else:
            assert pair.num_inliers >= 100 and pair.num_inliers >= 0.8 * pair.num_matches

    db = pycolmap.Database.open(database_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        for k1, k2 in [(0, 1), (0, 3), (2, 3)]:
            geometry = db.read_two_view_geometry(ids[f"view{k1}.png"], ids[f"view{k2}.png"])
            assert geometry.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            truth = poses[k2] * poses[k1].inverse()
            estimate = geometry.cam2_from_cam1
            error = estimate.rotation.matrix() @ truth.rotation.matrix().T
            assert rotation_angle_deg(error) < 0.5
            cosine = estimate.translation @ truth.translation / np.linalg.norm(truth.translation)
            assert np.degrees(np.arccos(min(1.0, cosine))) < 3.0
            # x2^T E x1 = 0 on the inliers, in normalized coordinates.
            keypoints1 = db.read_keypoints(ids[f"view{k1}.png"])[:, :2]
            keypoints2 = db.read_keypoints(ids[f"view{k2}.png"])[:, :2]
            matches = geometry.inlier_matches
            x1 = np.linalg.solve(K, np.column_stack([keypoints1[matches[:, 0]],
                                                     np.ones(len(matches))]).T)
            x2 = np.linalg.solve(K, np.column_stack([keypoints2[matches[:, 1]],
                                                     np.ones(len(matches))]).T)
            residuals = np.abs(np.einsum("in,ij,jn->n", x2, geometry.E, x1))
            assert np.median(residuals) < 1e-3
    finally:
        db.close()
    assert summary.to_dict()["num_verified_pairs"] == 6


def test_same_seed_same_result(scene_database, tmp_path: Path) -> None:
    """Exact matching (FAISS's index is rarely not built the same twice) and one seed:
    the same inliers on every run."""
    source, _ = scene_database
    results = []
    for run in range(2):
        database_path = tmp_path / f"run{run}.db"
        shutil.copy(source, database_path)
        options = MatchingOptions(matcher="exhaustive", seed=7, exact=True)
        results.append(match_features(database_path, options, progress=False).pairs)
    assert results[0] == results[1]


def database_rows(database_path: Path) -> dict[str, list[tuple]]:
    """The matches and two-view geometries tables, row for row."""
    with contextlib.closing(sqlite3.connect(database_path)) as connection:
        return {table: connection.execute(f"SELECT * FROM {table} ORDER BY 1").fetchall()
                for table in ("matches", "two_view_geometries")}


def test_blocks_and_executors_do_not_change_the_database(scene_database, tmp_path: Path,
                                                        monkeypatch) -> None:
    """The pairs cut into blocks of 2 images, run in one thread: the same rows as one
    block in this process's threads (the default)."""
    source, _ = scene_database
    options = MatchingOptions(matcher="exhaustive", exact=True)
    shutil.copy(source, tmp_path / "threads.db")
    expected = match_features(tmp_path / "threads.db", options, progress=False)
    monkeypatch.setattr(matching, "PAIR_BLOCK_IMAGES", 2)
    shutil.copy(source, tmp_path / "blocks.db")
    got = match_features(tmp_path / "blocks.db", options, executor=LocalExecutor(1),
                         progress=False)
    assert got.pairs == expected.pairs and got.num_verified == 6
    assert database_rows(tmp_path / "blocks.db") == database_rows(tmp_path / "threads.db")


def colmap_brute_force_matches(source: Path, database_path: Path) -> dict[int, np.ndarray]:
    """pair id -> matches of pycolmap's own brute-force SIFT matcher on a copy of `source`."""
    shutil.copy(source, database_path)
    options = pycolmap.FeatureMatchingOptions()
    options.sift.cpu_brute_force_matcher = True
    options.skip_geometric_verification = True
    with quiet_colmap_logs():
        pycolmap.match_exhaustive(database_path, matching_options=options,
                                  device=pycolmap.Device.cpu)
    with pycolmap.Database.open(database_path) as db:
        return dict(zip(*db.read_all_matches()))


@pytest.mark.parametrize("block_products", [matching.EXACT_BLOCK_PRODUCTS, 1000])
def test_exact_matching_is_colmaps_brute_force(scene_database, tmp_path: Path, monkeypatch,
                                               block_products: int) -> None:
    """`exact`: the matches of pycolmap's brute-force matcher, pair for pair, also when
    the descriptor products are taken a few rows at a time."""
    source, _ = scene_database
    expected = colmap_brute_force_matches(source, tmp_path / "colmap.db")
    monkeypatch.setattr(matching, "EXACT_BLOCK_PRODUCTS", block_products)
    database_path = tmp_path / "database.db"
    shutil.copy(source, database_path)
    match_features(database_path, MatchingOptions(matcher="exhaustive", exact=True),
                   progress=False)
    with pycolmap.Database.open(database_path) as db:
        got = dict(zip(*db.read_all_matches()))
        assert min(db.num_keypoints_for_image(i.image_id) for i in db.read_all_images()) > 3000
    assert got.keys() == expected.keys() and sum(len(m) > 100 for m in got.values()) >= 3
    for pair_id, matches in expected.items():
        assert set(map(tuple, got[pair_id].tolist())) == set(map(tuple, matches.tolist())), pair_id


def test_sequential_matching_closes_the_loop(scene_database, tmp_path: Path) -> None:
    source, _ = scene_database
    database_path = tmp_path / "database.db"
    shutil.copy(source, database_path)
    summary = match_features(database_path, MatchingOptions(matcher="sequential", overlap=1,
                                                            loop_detection=False),
                             progress=False)
    assert summary.matcher == "sequential"
    names = ["view0.png", "view1.png", "view2.png", "view3.png", "zother.png"]
    db = pycolmap.Database.open(database_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        tried = {(a, b) for a, b in itertools.combinations(names, 2)
                 if db.exists_matches(ids[a], ids[b])}
    finally:
        db.close()
    # Neighbours in name order, and the loop: the last image with the first.
    assert tried == set(zip(names, names[1:])) | {("view0.png", "zother.png")}


def test_loop_closure_pairs() -> None:
    names = [f"{k}" for k in range(6)]
    assert loop_closure_pairs(names, 2) == [("4", "0"), ("5", "0"), ("5", "1")]
    assert loop_closure_pairs(names[:2], 5) == []


def random_feature_database(path: Path, num_images: int) -> list[str]:
    """A database of images with 20 random keypoints and descriptors each, written in
    shuffled name order so that image ids do not follow the names; returns the names,
    sorted."""
    names = [f"frame{k:04d}.png" for k in range(num_images)]
    rng = np.random.default_rng(0)
    with pycolmap.Database.open(path) as db:
        camera = pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                                 params=[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2])
        camera.camera_id = db.write_camera(camera)
        for name in rng.permutation(names):
            image_id = db.write_image(pycolmap.Image(name=str(name), camera_id=camera.camera_id))
            db.write_keypoints(image_id, rng.uniform(0, HEIGHT, (20, 2)).astype(np.float32))
            db.write_descriptors(image_id, pycolmap.FeatureDescriptors(
                pycolmap.FeatureExtractorType.SIFT, rng.integers(0, 256, (20, 128), np.uint8)))
    return names


def matched_pairs(database_path: Path, names: list[str]) -> set[tuple[str, str]]:
    """The pairs of names (in name order) that matching tried, with or without matches."""
    db = pycolmap.Database.open(database_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        return {(a, b) for a, b in itertools.combinations(names, 2)
                if db.exists_matches(ids[a], ids[b])}
    finally:
        db.close()


@pytest.fixture(scope="module")
def long_sequence(tmp_path_factory):
    """101 images matched by the "auto" matcher with overlap 3, without loop detection
    (test_loop_detection.py): (names, summary, tried pairs)."""
    database_path = tmp_path_factory.mktemp("long_sequence") / "database.db"
    names = random_feature_database(database_path, 101)
    summary = match_features(database_path, MatchingOptions(overlap=3, loop_detection=False),
                             progress=False)
    return names, summary, matched_pairs(database_path, names)


def test_auto_matcher_is_exhaustive_up_to_100_images(tmp_path: Path) -> None:
    names = random_feature_database(tmp_path / "database.db", 100)
    assert match_features(tmp_path / "database.db", progress=False).matcher == "exhaustive"
    assert len(matched_pairs(tmp_path / "database.db", names)) == 100 * 99 // 2


def test_sequential_matching_above_100_images(long_sequence) -> None:
    """Above 100 images "auto" matches sequentially in name order (not image-id order):
    each image with the next 3 and with the ones 1, 2 and 4 after it (COLMAP's quadratic
    overlap: 2^k for k < overlap), and the last images with the first (loop closure),
    nothing else."""
    names, summary, tried = long_sequence
    assert summary.matcher == "sequential"
    quadratic = {(names[i], names[i + step]) for i in range(len(names)) for step in (1, 2, 3, 4)
                 if i + step < len(names)}
    loop = {tuple(sorted(pair)) for pair in loop_closure_pairs(names, 3)}
    assert loop == {(names[0], names[-3]), (names[0], names[-2]), (names[0], names[-1]),
                    (names[1], names[-2]), (names[1], names[-1]), (names[2], names[-1])}
    assert tried == quadratic | loop


def test_sequential_matching_pairs_each_image_with_the_next_overlap(long_sequence) -> None:
    names, _, tried = long_sequence
    linear = {(names[i], names[i + step]) for i in range(len(names)) for step in (1, 2, 3)
              if i + step < len(names)}
    assert linear <= tried


SEQUENCE_FRAMES = 40
# Quadratic overlap beyond the linear one: frames 8 and 16 apart (2^k, k < 5).
SEQUENCE_OVERLAP = 5
STEREO_PREFIXES = ["left/", "right/"]


def drive_database(folder: Path, layout: str, missing: str | None = None
                   ) -> tuple[Path, list[list[str]]]:
    """A drive's database (synthetic features, nothing matched) seen as `layout`: a "stereo
    rig" (left/ and right/ cameras, its rig configuration applied), "one camera", or "two
    cameras, no rig" (the stereo images, a camera per folder, a frame per image); without
    image `missing`. Returns it and its sequence: the frames' image names, in order."""
    drive = driving_scene(SEQUENCE_FRAMES, seed=1, stop_every=0)
    prefixes = [""] if layout == "one camera" else STEREO_PREFIXES
    cams_from_rig = side_by_side_rig(len(prefixes), 0.54)
    scene = rig_scene(drive, cams_from_rig, prefixes)
    kept = [index for index, name in enumerate(scene.image_names) if name != missing]
    scene = Scene(scene.camera, [scene.cams_from_world[i] for i in kept],
                  [scene.image_names[i] for i in kept], scene.quads)
    database_path = folder / "database.db"
    write_synthetic_database(database_path, scene, points_for_keypoints(scene, 100, seed=1),
                             pairs=set())
    if layout != "stereo rig":
        return database_path, [[name] for name in sorted(scene.image_names)]
    write_rig_config(folder / "rig.json", scene.camera, cams_from_rig, prefixes)
    rigs.apply_rig_config(database_path, rigs.read_rig_config(folder / "rig.json"))
    return database_path, [[prefix + name for prefix in prefixes if prefix + name != missing]
                           for name in drive.image_names]


@pytest.mark.parametrize("layout", ["stereo rig", "one camera", "two cameras, no rig"])
def test_sequential_matching_pairs_whole_frames_in_the_sequences_order(
        tmp_path: Path, layout: str) -> None:
    """A stereo rig's frames, whose left/ names all sort before the right/ ones, are matched
    as frames: each frame with the next SEQUENCE_OVERLAP, the ones 8 and 16 ahead
    (quadratic) and the first ones round the ring (loop closure), every image of one with
    every image of the other, and with nothing else. Without a rig (one camera, or a
    camera per folder with a frame per image) the sequence is the images' name order, as
    before."""
    database_path, sequence = drive_database(tmp_path, layout)
    match_features(database_path, MatchingOptions(matcher="sequential", overlap=SEQUENCE_OVERLAP,
                                                  loop_detection=False), progress=False)
    n = len(sequence)
    steps = set(range(SEQUENCE_OVERLAP + 1)) | {8, 16} | {n - step for step in range(
        1, SEQUENCE_OVERLAP + 1)}
    expected = {tuple(sorted((a, b))) for i, j in itertools.combinations_with_replacement(
        range(n), 2) if j - i in steps for a in sequence[i] for b in sequence[j] if a != b}
    assert matched_pairs(database_path, sorted(sum(sequence, []))) == expected


def test_a_frame_without_its_first_cameras_image_keeps_its_place_in_the_sequence(
        tmp_path: Path) -> None:
    """Frame 10 has no left/ image: it stays between frames 9 and 11 (its right/ image
    sorts after every left/ one), so its quadratic and loop closure partners are frames'
    8 and 16 away, not the sequence's last ones."""
    database_path, sequence = drive_database(tmp_path, "stereo rig", "left/drive00010.png")
    with pycolmap.Database.open(database_path) as db:
        name_of = {image.image_id: image.name for image in db.read_all_images()}
        frames = [[name_of[image_id] for image_id in frame]
                  for frame in matching.sequence_frames(db)]
    assert frames[10] == ["right/drive00010.png"]
    assert frames == sequence


def test_frames_that_contradict_their_cameras_name_orders_follow_their_first_names(
        tmp_path: Path) -> None:
    """Frames {a/1, b/2} and {a/2, b/1}: camera a puts the first before the second, camera
    b the second before the first; no order keeps both, so the frames go by first name."""
    with pycolmap.Database.open(tmp_path / "database.db") as db:
        rig = pycolmap.Rig()
        cameras = {}
        for folder in ("a", "b"):
            camera = pycolmap.Camera(model="PINHOLE", width=WIDTH, height=HEIGHT,
                                     params=[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2])
            camera.camera_id = cameras[folder] = db.write_camera(camera)
            if folder == "a":
                rig.add_ref_sensor(camera.sensor_id)
            else:
                rig.add_sensor(camera.sensor_id, pycolmap.Rigid3d())
        rig_id = db.write_rig(rig)
        for names in (["a/1.png", "b/2.png"], ["a/2.png", "b/1.png"]):
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            for name in names:
                image = pycolmap.Image(name=name, camera_id=cameras[name[0]])
                image.image_id = db.write_image(image)
                frame.add_data_id(image.data_id)
            db.write_frame(frame)
        name_of = {image.image_id: image.name for image in db.read_all_images()}
        frames = [[name_of[image_id] for image_id in frame]
                  for frame in matching.sequence_frames(db)]
    assert frames == [["a/1.png", "b/2.png"], ["a/2.png", "b/1.png"]]


def test_bad_options_and_databases(scene_database, tmp_path: Path) -> None:
    source, _ = scene_database
    with pytest.raises(UserError, match="unknown matcher 'vocab'"):
        match_features(source, MatchingOptions(matcher="vocab"))
    with pytest.raises(UserError, match="max_ratio must be in"):
        match_features(source, MatchingOptions(max_ratio=1.5))
    with pytest.raises(UserError, match="database not found"):
        match_features(tmp_path / "missing.db")
    pycolmap.Database.open(tmp_path / "empty.db").close()
    with pytest.raises(UserError, match="no features in .*extract features first"):
        match_features(tmp_path / "empty.db")


def test_temple_pairs_verify_and_colmap_maps_our_database(tmp_path: Path,
                                                          real_data: Path) -> None:
    """Four neighbouring temple views: our inliers agree with COLMAP's verification, and
    COLMAP's own incremental mapper reads the database we verified."""
    names = [f"templeSR{k:04d}.png" for k in (6, 7, 8, 9)]
    image_path = real_data / "templeSparseRing"
    ours, theirs = tmp_path / "ours.db", tmp_path / "colmap.db"
    extract_features(ours, image_path, FeatureOptions("PINHOLE", "1520.4,1525.9,302.32,246.87"),
                     image_names=names, progress=False)
    shutil.copy(ours, theirs)
    summary = match_features(ours, MatchingOptions(matcher="exhaustive"), progress=False)
    with quiet_colmap_logs():
        pycolmap.match_exhaustive(theirs, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(theirs)
    ids = {image.name: image.image_id for image in db.read_all_images()}
    ours_by_pair = {(pair.name1, pair.name2): pair.num_inliers for pair in summary.pairs}
    for name1, name2 in zip(names, names[1:]):
        colmap_inliers = len(db.read_two_view_geometry(ids[name1], ids[name2]).inlier_matches)
        assert ours_by_pair[name1, name2] >= 0.95 * colmap_inliers > 100
    db.close()

    options = pycolmap.IncrementalPipelineOptions(random_seed=0, constant_cameras={1})
    (tmp_path / "sparse").mkdir()
    with quiet_colmap_logs():
        models = pycolmap.incremental_mapping(ours, image_path, tmp_path / "sparse", options)
    assert max(model.num_reg_images() for model in models.values()) == 4
