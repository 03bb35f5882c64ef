"""Synthetic COLMAP databases without images: known points projected into known cameras.

Keypoints are exact projections (with the camera's distortion) plus Gaussian noise,
descriptors are SIFT-like perturbations of one random descriptor per 3D point, and
matches are the true correspondences plus a chosen share of wrong ones. The returned
ground truth says which 3D point every keypoint sees, so a mapper's tracks can be checked.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.model_io import write_json
from colmap_ext.rigs import RigCamera, rig_config
from colmap_ext.synthetic.scene import GridIndex, Scene, cast_rays

DESCRIPTOR_NOISE = 0.25  # L2 norm of the per-observation perturbation of a unit descriptor
MIN_NUM_INLIERS = 15  # COLMAP's TwoViewGeometryOptions.min_num_inliers
NEAR = 0.05  # metres: nearer points are not observed
SAME_CENTRE = 1e-9  # metres: views whose centres are nearer share one (a stop)
PROBE_POINTS = 2_000_000  # at most this many points sampled to count what views see


@dataclass
class Observations:
    """What one view sees: indices into points3D, their exact (noise-free) pixel positions and depths."""

    point_ids: np.ndarray
    pixels: np.ndarray
    depths: np.ndarray


@dataclass
class SyntheticDatabase:
    """Ground truth of a written database; per-view lists are in scene order.

    keypoint k of view i sees points3D[point_ids[i][k]] and projects exactly to
    projections[i][k] (the database holds it with noise). `matches` holds what was
    written per pair (image_id1 < image_id2), `inlier_matches` the subset that is true.
    """

    image_ids: list[int]
    point_ids: list[np.ndarray]
    projections: list[np.ndarray]
    matches: dict[tuple[int, int], np.ndarray]
    inlier_matches: dict[tuple[int, int], np.ndarray]


def scene_points(scene: Scene, num_points: int, seed: int = 0) -> np.ndarray:
    """Points sampled uniformly on the scene's quads, weighted by area / detail^2 (texture richness)."""
    rng = np.random.default_rng(seed)
    weights = np.array([q.area / q.detail**2 for q in scene.quads])
    which = rng.choice(len(scene.quads), num_points, p=weights / weights.sum())
    origins = np.stack([q.origin for q in scene.quads])[which]
    edges_u = np.stack([q.edge_u for q in scene.quads])[which]
    edges_v = np.stack([q.edge_v for q in scene.quads])[which]
    a, b = rng.random((2, num_points, 1))
    return origins + a * edges_u + b * edges_v


def points_for_keypoints(
    scene: Scene, keypoints_per_image: int, seed: int = 0, max_distance: float | None = None
) -> np.ndarray:
    """Scene points (scene_points) so many that a view sees about keypoints_per_image of them:
    their number is scaled from what a dozen views spread over the scene see of a probe."""
    size = scene.num_images
    probe = scene_points(scene, min(keypoints_per_image * size, PROBE_POINTS), seed=seed)
    grid = None if max_distance is None else GridIndex(probe[:, :2], max_distance)
    views = np.unique(np.linspace(0, size - 1, min(size, 12)).astype(int))
    seen = np.mean([len(observe(scene, i, probe, max_distance, grid).point_ids) for i in views])
    return scene_points(scene, max(1, round(len(probe) * keypoints_per_image / seen)), seed=seed)


def sequential_pairs(num_frames: int, overlap: int, closed: bool = False,
                     images_per_frame: int = 1) -> set[tuple[int, int]]:
    """Pairs (i, j), i < j, of each image with the images of the next `overlap` frames and
    the other images of its own frame, as sequential matching pairs a sequence's frames
    (image frame * images_per_frame + camera: a rig's, rig_scene's order); closed, the
    last frames pair with the first ones too (a loop found again)."""
    pairs = set()
    cameras = range(images_per_frame)
    for frame in range(num_frames):
        for other in range(frame, frame + overlap + 1):
            if other < num_frames or (closed and other - num_frames < frame):
                first, second = frame * images_per_frame, other % num_frames * images_per_frame
                pairs.update(tuple(sorted((first + a, second + b))) for a in cameras for b in cameras
                             if (other, b) != (frame, a))
    return pairs


def write_rig_config(path: str | Path, camera: pycolmap.Camera, cams_from_rig: list[pycolmap.Rigid3d],
                     image_prefixes: list[str]) -> None:
    """Write COLMAP's rig configuration JSON of a rig_scene's rig (each camera with `camera`'s
    intrinsics): what `apply_rig_config` makes the rig and frames of its database from."""
    cameras = [RigCamera(prefix, camera.model.name, camera.params.tolist(), cam_from_rig)
               for prefix, cam_from_rig in zip(image_prefixes, cams_from_rig)]
    write_json(rig_config(cameras, image_prefixes), path)


def normalised_bounds(camera: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (plus 1 %) of the image unprojected to normalised coordinates: a cheap visibility pre-test."""
    grid = np.meshgrid(np.linspace(0.0, camera.width, 33), np.linspace(0.0, camera.height, 33))
    xy = camera.cam_from_img(np.stack(grid, axis=-1).reshape(-1, 2))
    margin = 0.01 * (xy.max(axis=0) - xy.min(axis=0))
    return xy.min(axis=0) - margin, xy.max(axis=0) + margin


def observe(
    scene: Scene,
    image_index: int,
    points3D: np.ndarray,
    max_distance: float | None = None,
    grid: GridIndex | None = None,
) -> Observations:
    """Points visible in one view: in front, projecting inside the image, not hidden by a quad, within max_distance.

    With a max_distance and `grid` (the points' x, y by GridIndex), only the points in the
    cells near the camera are looked at, so a view costs the same however large the scene.
    """
    pose = scene.cams_from_world[image_index]
    camera = scene.camera
    lo, hi = normalised_bounds(camera)
    if grid is not None and max_distance is not None:
        longest_ray = np.sqrt(np.max(np.square([lo, hi]).sum(axis=1)) + 1.0)  # per unit of depth
        near_camera = grid.near(pose.inverse().translation[:2], max_distance * longest_ray)
    else:
        near_camera = np.arange(len(points3D))
    cam = pose.rotation.matrix() @ points3D[near_camera].T + pose.translation[:, None]
    x, y, z = cam
    in_view = (z > NEAR) & (z <= (np.inf if max_distance is None else max_distance))
    in_view &= (x >= lo[0] * z) & (x <= hi[0] * z) & (y >= lo[1] * z) & (y <= hi[1] * z)
    candidates = np.flatnonzero(in_view)
    cam = cam[:, candidates].T
    rays = cam[:, :2] / cam[:, 2:]
    pixels = camera.img_from_cam(cam)
    inside = np.all((pixels >= 0) & (pixels < [camera.width, camera.height]), axis=1)
    candidates, cam, rays, pixels = near_camera[candidates[inside]], cam[inside], rays[inside], pixels[inside]
    if not len(candidates):
        return Observations(candidates, pixels, cam[:, 2])
    # One row of rays sorted by x: cast_rays then tests each quad on the columns its
    # projection spans only.
    by_x = np.argsort(rays[:, 0], kind="stable")
    hits = cast_rays(scene, pose, rays[by_x][None], near=NEAR, far=float(cam[:, 2].max()))
    depths = np.empty(len(rays), np.float32)
    depths[by_x] = hits.depth[0]
    unoccluded = depths >= cam[:, 2] * (1 - 1e-4) - 1e-6
    return Observations(candidates[unoccluded], pixels[unoccluded], cam[unoccluded, 2])


def keep_tracks(observations: list[Observations], num_points: int, min_track: int) -> list[Observations]:
    """Drop the observations of points seen in fewer than min_track views."""
    counts = np.bincount(np.concatenate([o.point_ids for o in observations]), minlength=num_points)
    kept = []
    for o in observations:
        keep = counts[o.point_ids] >= min_track
        kept.append(Observations(o.point_ids[keep], o.pixels[keep], o.depths[keep]))
    return kept


def sift_like(base: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """uint8 descriptors near unit `base` rows: perturb, clip at 0, L2-normalise, *512, clip at 255 (as SIFT)."""
    noisy = base + rng.normal(0.0, DESCRIPTOR_NOISE / np.sqrt(base.shape[1]), base.shape)
    noisy = np.maximum(noisy, 0.0)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    return np.minimum(np.round(noisy * 512), 255).astype(np.uint8)


@dataclass
class PointAppearance:
    """What a 3D point looks like to a feature extractor: unit descriptor, physical size (m), orientation."""

    descriptors: np.ndarray
    sizes: np.ndarray
    orientations: np.ndarray

    @classmethod
    def random(cls, num_points: int, rng: np.random.Generator) -> PointAppearance:
        descriptors = rng.exponential(1.0, (num_points, 128))
        descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
        sizes = np.exp(rng.uniform(np.log(0.01), np.log(0.05), num_points))
        return cls(descriptors, sizes, rng.uniform(-np.pi, np.pi, num_points))


def affine_shapes(scales: np.ndarray, orientations: np.ndarray) -> np.ndarray:
    """COLMAP's keypoint affine columns a11, a12, a21, a22 for a similarity (scale, orientation)."""
    c, s = scales * np.cos(orientations), scales * np.sin(orientations)
    return np.stack([c, -s, s, c], axis=1)


def view_pairs(
    point_ids: list[np.ndarray], num_points: int, wanted: Collection[tuple[int, int]] | None = None
) -> Iterator[tuple[tuple[int, int], np.ndarray]]:
    """Yields the true matches (keypoint index pairs) of every pair of views i < j that share
    a point (only the pairs in `wanted`, if given), by i then j.

    Walks the point -> observations index once per view, so the cost grows with the
    number of observations times the track length, not with the number of view pairs;
    one view's pairs are held at a time.
    """
    views = np.concatenate([np.full(len(p), i) for i, p in enumerate(point_ids)])
    keypoints = np.concatenate([np.arange(len(p)) for p in point_ids])
    points = np.concatenate(point_ids)
    order = np.argsort(points, kind="stable")
    starts = np.searchsorted(points[order], np.arange(num_points + 1))
    wanted = None if wanted is None else set(wanted)
    for i, ids in enumerate(point_ids):
        lengths = starts[ids + 1] - starts[ids]
        offsets = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        rows = order[np.repeat(starts[ids], lengths) + offsets]
        keypoints_i = np.repeat(np.arange(len(ids)), lengths)
        later = views[rows] > i
        rows, keypoints_i = rows[later], keypoints_i[later]
        by_view = np.argsort(views[rows], kind="stable")
        others, splits = np.unique(views[rows][by_view], return_index=True)
        for j, chunk in zip(others, np.split(by_view, splits[1:])):
            if wanted is not None and (i, int(j)) not in wanted:
                continue
            yield (i, int(j)), np.stack([keypoints_i[chunk], keypoints[rows[chunk]]], axis=1)


def add_outliers(
    true_matches: np.ndarray, num_keypoints: tuple[int, int], outlier_ratio: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Matches of a pair with a share `outlier_ratio` of wrong ones, one-to-one like cross-checked matching.

    Wrong matches pair keypoints left unmatched in both views; when too few are left
    (strongly overlapping views), some true matches are corrupted by rotating their
    second keypoints. Returns (matches, inlier mask).
    """
    wanted = round(outlier_ratio / (1 - outlier_ratio) * len(true_matches))
    free = [np.ones(n, bool) for n in num_keypoints]
    for k in range(2):
        free[k][true_matches[:, k]] = False
    free = [np.flatnonzero(f) for f in free]
    extra = min(wanted, len(free[0]), len(free[1]))
    wrong = np.stack([rng.choice(free[0], extra, replace=False), rng.choice(free[1], extra, replace=False)], axis=1)
    matches = np.concatenate([true_matches, wrong]).astype(np.uint32)
    inliers = np.arange(len(matches)) < len(true_matches)
    corrupt = round(outlier_ratio * len(matches)) - extra
    if corrupt >= 2:
        chosen = rng.choice(len(true_matches), corrupt, replace=False)
        matches[chosen, 1] = np.roll(matches[chosen, 1], 1)
        inliers[chosen] = False
    return matches, inliers


def two_view_geometry(scene: Scene, i: int, j: int, inlier_matches: np.ndarray) -> pycolmap.TwoViewGeometry:
    """Two-view geometry of views i, j from the true poses: CALIBRATED, E = [t]x R (x2^T E x1 = 0);
    PANORAMIC, H = K R K^-1, where the views share their centre (a stop), as COLMAP finds them."""
    cam2_from_cam1 = scene.cams_from_world[j] * scene.cams_from_world[i].inverse()
    t = cam2_from_cam1.translation
    rotation = cam2_from_cam1.rotation.matrix()
    k = scene.camera.calibration_matrix()
    k_inv = np.linalg.inv(k)
    geometry = pycolmap.TwoViewGeometry()
    if np.linalg.norm(t) < SAME_CENTRE:
        geometry.config = pycolmap.TwoViewGeometryConfiguration.PANORAMIC
        geometry.H = k @ rotation @ k_inv
        cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), np.zeros(3))
    else:
        essential = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rotation
        geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        geometry.E = essential
        geometry.F = k_inv.T @ essential @ k_inv
    geometry.cam2_from_cam1 = cam2_from_cam1
    geometry.inlier_matches = inlier_matches.astype(np.uint32)
    return geometry


def true_tracks_reconstruction(database_path: str | Path, scene: Scene, points3D: np.ndarray,
                               truth: SyntheticDatabase) -> pycolmap.Reconstruction:
    """The database's images at the scene's true poses (trivial frames) and the true
    points with every true observation, each keypoint as the database holds it (with its
    noise): the tracks a perfect association of keypoints gives."""
    reconstruction = pycolmap.Reconstruction()
    with pycolmap.Database.open(database_path) as db:
        for camera in db.read_all_cameras():
            reconstruction.add_camera_with_trivial_rig(camera)
        images = {image.image_id: image for image in db.read_all_images()}
        keypoints = {image_id: db.read_keypoints(image_id)[:, :2] for image_id in truth.image_ids}
    for view, image_id in enumerate(truth.image_ids):
        image = pycolmap.Image(name=images[image_id].name, camera_id=images[image_id].camera_id,
                               image_id=image_id)
        image.points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(xy) for xy in keypoints[image_id].astype(np.float64)])
        reconstruction.add_image_with_trivial_frame(image, scene.cams_from_world[view])
    tracks: dict[int, list[pycolmap.TrackElement]] = {}
    for image_id, point_ids in zip(truth.image_ids, truth.point_ids):
        for kp, point in enumerate(point_ids.tolist()):
            tracks.setdefault(point, []).append(pycolmap.TrackElement(image_id, kp))
    for point, elements in sorted(tracks.items()):
        if len(elements) >= 2:
            track = pycolmap.Track()
            track.add_elements(elements)
            reconstruction.add_point3D(points3D[point], track)
    return reconstruction


def write_images(db: pycolmap.Database, scene: Scene) -> list[int]:
    """Write the cameras (the scene's intrinsics, one per folder of the image names, as
    COLMAP's per-folder import makes them: a rig's cameras, see rig_scene), each with its
    trivial rig, and one image with a trivial frame per view; returns the image ids."""
    sensors: dict[str, tuple[int, int]] = {}  # folder -> camera id, rig id
    image_ids = []
    for name in scene.image_names:
        folder = name.rpartition("/")[0]
        if folder not in sensors:
            camera = pycolmap.Camera(scene.camera.todict())
            camera.has_prior_focal_length = True  # known intrinsics: COLMAP then verifies pairs as CALIBRATED
            camera.camera_id = db.write_camera(camera)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(camera.sensor_id)
            sensors[folder] = camera.camera_id, db.write_rig(rig)
        camera_id, rig_id = sensors[folder]
        image = pycolmap.Image(name=name, camera_id=camera_id)
        image.image_id = db.write_image(image)
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(image.data_id)
        db.write_frame(frame)
        image_ids.append(image.image_id)
    return image_ids


def write_features(
    db: pycolmap.Database,
    image_id: int,
    seen: Observations,
    appearance: PointAppearance,
    camera: pycolmap.Camera,
    noise_px: float,
    rng: np.random.Generator,
) -> None:
    """Keypoints (noisy x, y; affine shape whose scale follows depth) and SIFT-like descriptors of one view."""
    size = np.array([camera.width, camera.height])
    noisy = np.clip(seen.pixels + rng.normal(0.0, noise_px, seen.pixels.shape), 0.0, size - 1e-3)
    scales = appearance.sizes[seen.point_ids] * camera.mean_focal_length() / seen.depths
    angles = appearance.orientations[seen.point_ids] + rng.normal(0.0, 0.05, len(seen.point_ids))
    db.write_keypoints(image_id, np.hstack([noisy, affine_shapes(scales, angles)]).astype(np.float32))
    descriptors = sift_like(appearance.descriptors[seen.point_ids], rng)
    db.write_descriptors(image_id, pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, descriptors))


def write_synthetic_database(
    path: str | Path,
    scene: Scene,
    points3D: np.ndarray,
    *,
    noise_px: float = 0.5,
    outlier_ratio: float = 0.2,
    min_track: int = 2,
    max_distance: float | None = None,
    seed: int = 0,
    two_view_geometries: bool = False,
    pairs: Collection[tuple[int, int]] | None = None,
) -> SyntheticDatabase:
    """Write a new COLMAP database of the scene's views observing points3D; returns the ground truth.

    Per view: keypoints and descriptors (see write_features) of the points it sees, in
    shuffled order; points seen by fewer than min_track views are left out. Per pair of views sharing points
    (of `pairs`, views i < j by scene index, if given): matches with
    a share `outlier_ratio` of wrong ones. With two_view_geometries, also the verified
    geometry (CALIBRATED, true poses, inliers = the true matches; PANORAMIC between views
    from one place) of pairs with at least 15 true matches, so COLMAP's mapper can run on
    the database directly. With max_distance, a view only looks at the points near it,
    so the time grows with the number of views, not views times points.
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; a synthetic database is written to a new file")
    if not 0.0 <= outlier_ratio < 1.0:
        raise ValueError(f"outlier_ratio must be in [0, 1), got {outlier_ratio}")
    rng = np.random.default_rng(seed)
    points3D = np.asarray(points3D, np.float64)
    appearance = PointAppearance.random(len(points3D), rng)
    grid = None if max_distance is None else GridIndex(points3D[:, :2], max_distance)
    observations = [observe(scene, i, points3D, max_distance, grid) for i in range(scene.num_images)]
    observations = keep_tracks(observations, len(points3D), min_track)
    orders = [rng.permutation(len(o.point_ids)) for o in observations]
    observations = [Observations(o.point_ids[k], o.pixels[k], o.depths[k]) for o, k in zip(observations, orders)]
    point_ids = [o.point_ids for o in observations]
    with pycolmap.Database.open(path) as db, pycolmap.DatabaseTransaction(db):
        image_ids = write_images(db, scene)
        for image_id, seen in zip(image_ids, observations):
            write_features(db, image_id, seen, appearance, scene.camera, noise_px, rng)
        matches, inlier_matches = {}, {}
        for (i, j), true_matches in view_pairs(point_ids, len(points3D), pairs):
            pair = (image_ids[i], image_ids[j])
            counts = (len(point_ids[i]), len(point_ids[j]))
            matches[pair], inliers = add_outliers(true_matches, counts, outlier_ratio, rng)
            inlier_matches[pair] = matches[pair][inliers]
            db.write_matches(*pair, matches[pair])
            if two_view_geometries and len(inlier_matches[pair]) >= MIN_NUM_INLIERS:
                db.write_two_view_geometry(*pair, two_view_geometry(scene, i, j, inlier_matches[pair]))
    projections = [o.pixels for o in observations]
    return SyntheticDatabase(image_ids, point_ids, projections, matches, inlier_matches)
