"""`colmap-ext hierarchical_mapper`: COLMAP's command for large sets, with our mapper.

The view graph (images joined by verified pairs, weighted by their inliers) is cut into
clusters of at most `--leaf_max_num_images` images by recursive bisection, and each
cluster grows by the `--image_overlap` outside images most connected to it. Each
cluster is mapped on its own by the calibrated mapper (mapper.pipeline.reconstruct, with
fewer global adjustments: MAPPER_DEFAULTS): a Ray task with `--ray_address`, else a process
of a local pool of `--num_workers`.
The cluster models are then brought into one frame along a maximum spanning tree of
their overlaps, each link the similarity their shared images agree on (merging.py's
rule: rotations and directions of the centres within a few degrees; the rotation
from the shared images' own rotations, which fix it where their centres, along a
walk, nearly lie on a line), points that
share an observation become one, and a global bundle adjustment finishes the model.
Output as COLMAP's: OUTPUT/0, OUTPUT/1, ... (one per group of clusters that joined).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from colmap_ext.angles import mean_rotation, rotation_angles_deg, vector_angles_deg
from colmap_ext.database import DatabaseContents, check_database_file, read_database
from colmap_ext.errors import UserError
from colmap_ext.mapper.cli import add_option_flags, format_summary, options_from_flags
from colmap_ext.mapper.bundle_adjustment import adjustment_options, posed_images
from colmap_ext.mapper.initial_pair import check_requested_pair
from colmap_ext.mapper.options import BundleAdjustmentOptions, MapperOptions, MergingOptions
from colmap_ext.mapper.pipeline import StageTimer, colours_readable, reconstruct, summarize
from colmap_ext.model_io import MAPPER_OUTPUT, OUTPUT_TYPES, replacing, write_json, write_models


# The clusters' mapper options where no --Mapper.* flag is given: the flat mapper's, but
# a global adjustment each time a cluster's model grows by half (the flat mapper's, as
# COLMAP's, each time it grows by a tenth). Every cluster is adjusted again within the
# joined model, and the sparser schedule is most of what makes a cluster task cheaper
# than COLMAP's (BENCHMARKS.md, scale-out). Small models need the frequent schedule,
# so `mapper` keeps it.
MAPPER_DEFAULTS = MapperOptions(bundle_adjustment=BundleAdjustmentOptions(global_images_ratio=1.5))


@dataclass(frozen=True)
class HierarchicalOptions:
    """How the view graph is cut and the cluster models joined."""

    # COLMAP's SceneClustering defaults: leaves of at most 500 images, each grown by the
    # 50 outside images most connected to it.
    leaf_max_num_images: int = 500
    image_overlap: int = 50
    # Processes of the local pool (without Ray); -1: one per core.
    num_workers: int = -1
    # A pair joins the view graph with this many verified inliers (two-view default).
    min_num_inliers: int = 15
    # Two cluster models are joined when this many shared images agree on their
    # similarity: rotation and centre direction within merge_max_angle_deg (merging.py's
    # rule and default), centre within max_centre_error of the overlap's extent.
    min_shared_images: int = 3
    merge_max_angle_deg: float = MergingOptions.max_angle_deg
    max_centre_error: float = 0.05
    # Observations reprojecting farther than this after the adjustment are dropped.
    max_reproj_error_px: float = 4.0

    def __post_init__(self) -> None:
        if self.leaf_max_num_images < 3:
            raise UserError(f"--leaf_max_num_images must be at least 3, got "
                            f"{self.leaf_max_num_images}")
        if self.image_overlap < 0:
            raise UserError(f"--image_overlap must be >= 0, got {self.image_overlap}")
        if self.num_workers == 0 or self.num_workers < -1:
            raise UserError(f"--num_workers must be positive or -1 (one per core), got "
                            f"{self.num_workers}")

    def workers(self) -> int:
        return (os.cpu_count() or 1) if self.num_workers == -1 else self.num_workers


# ------------------------------------------------------------------ the view graph


def view_graph(db: DatabaseContents, min_num_inliers: int) -> dict[int, dict[int, int]]:
    """image id -> {neighbour id: verified inliers}, every image a node; the raw matches
    stand in for a database without two-view geometries (the mapper verifies them)."""
    graph: dict[int, dict[int, int]] = {image_id: {} for image_id in db.images}
    for (id1, id2), matches in (db.verified_matches or db.raw_matches).items():
        if len(matches) >= min_num_inliers:
            graph[id1][id2] = graph[id2][id1] = len(matches)
    return graph


def components(graph: dict[int, dict[int, int]], nodes: list[int]) -> list[list[int]]:
    """Connected components of the subgraph on `nodes`, largest first."""
    inside, seen, found = set(nodes), set(), []
    for start in sorted(nodes):
        if start in seen:
            continue
        seen.add(start)
        component, queue = [], deque([start])
        while queue:
            node = queue.popleft()
            component.append(node)
            for other in graph[node]:
                if other in inside and other not in seen:
                    seen.add(other)
                    queue.append(other)
        found.append(sorted(component))
    return sorted(found, key=len, reverse=True)


def breadth_first_order(graph: dict[int, dict[int, int]], nodes: set[int], start: int) -> list[int]:
    """`nodes` reachable from `start` in breadth-first order, the stronger edges first."""
    order, seen, queue = [], {start}, deque([start])
    while queue:
        node = queue.popleft()
        order.append(node)
        for other in sorted(graph[node], key=lambda o: (-graph[node][o], o)):
            if other in nodes and other not in seen:
                seen.add(other)
                queue.append(other)
    return order


def bisect(graph: dict[int, dict[int, int]], nodes: list[int]) -> tuple[list[int], list[int]]:
    """Two halves of a connected set: breadth-first levels from a pseudo-peripheral image
    (the far end of a search from the far end of a search, as in George and Liu's
    ordering), cut at the middle. On sequences, rings and grids the halves are
    contiguous stretches, and the cut crosses few edges; linear time."""
    inside = set(nodes)
    far = breadth_first_order(graph, inside, nodes[0])[-1]
    order = breadth_first_order(graph, inside, far)
    order = order + sorted(inside - set(order))  # (connected: nothing is left)
    middle = len(order) // 2
    return sorted(order[:middle]), sorted(order[middle:])


def leaf_clusters(graph: dict[int, dict[int, int]], nodes: list[int],
                  max_size: int) -> list[list[int]]:
    """Recursive bisection into connected clusters of at most `max_size` images."""
    leaves, stack = [], [nodes]
    while stack:
        cluster = stack.pop()
        if len(cluster) <= max_size:
            leaves.append(cluster)
            continue
        for half in bisect(graph, cluster):
            stack.extend(components(graph, half))
    return sorted(leaves, key=lambda c: c[0])


def grow(graph: dict[int, dict[int, int]], cluster: list[int], overlap: int) -> list[int]:
    """The cluster and the `overlap` outside images with most inliers to it."""
    members = set(cluster)
    links: dict[int, int] = {}
    for node in cluster:
        for other, weight in graph[node].items():
            if other not in members:
                links[other] = links.get(other, 0) + weight
    extra = sorted(links, key=lambda o: (-links[o], o))[:overlap]
    return sorted(members | set(extra))


def partition(db: DatabaseContents, options: HierarchicalOptions) -> list[list[int]]:
    """Overlapping clusters of image ids covering every image with a verified pair."""
    graph = view_graph(db, options.min_num_inliers)
    connected = [c for c in components(graph, list(graph)) if len(c) >= 2]
    clusters = []
    for component in connected:
        for leaf in leaf_clusters(graph, component, options.leaf_max_num_images):
            clusters.append(grow(graph, leaf, options.image_overlap))
    return clusters


# ------------------------------------------------------------------ mapping a cluster


@dataclass
class ClusterModel:
    """One model of one cluster, as arrays (what a task returns): poses, and points with
    their tracks as flat observation lists."""

    image_ids: np.ndarray  # (k,)
    cams_from_world: np.ndarray  # (k, 3, 4)
    xyz: np.ndarray  # (p, 3)
    track_point: np.ndarray  # (m,) index into xyz of each observation
    track_image: np.ndarray  # (m,) image id
    track_keypoint: np.ndarray  # (m,) keypoint index

    @classmethod
    def from_reconstruction(cls, reconstruction: pycolmap.Reconstruction) -> ClusterModel:
        image_ids = np.array(sorted(reconstruction.reg_image_ids()), np.int64)
        poses = np.array([reconstruction.images[i].cam_from_world().matrix() for i in image_ids])
        point_ids = sorted(reconstruction.point3D_ids())
        xyz = np.array([reconstruction.points3D[p].xyz for p in point_ids]).reshape(-1, 3)
        observations = [(index, element.image_id, element.point2D_idx)
                        for index, point_id in enumerate(point_ids)
                        for element in reconstruction.points3D[point_id].track.elements]
        columns = np.array(observations, np.int64).reshape(-1, 3).T
        return cls(image_ids, poses.reshape(-1, 3, 4), xyz, *columns)

    def centres(self) -> np.ndarray:
        rotations, translations = self.cams_from_world[:, :, :3], self.cams_from_world[:, :, 3]
        return -np.einsum("kji,kj->ki", rotations, translations)

    def observations_per_image(self) -> dict[int, int]:
        images, counts = np.unique(self.track_image, return_counts=True)
        return dict(zip(images.tolist(), counts.tolist()))


def database_subset(db: DatabaseContents, image_ids: list[int]) -> DatabaseContents:
    """The cameras, images and matches of `image_ids` alone: what a task needs."""
    keep = set(image_ids)
    images = {i: db.images[i] for i in image_ids}
    return DatabaseContents(
        {c: db.cameras[c] for c in {image.camera_id for image in images.values()}}, images,
        {i: db.descriptors[i] for i in image_ids},
        {p: m for p, m in db.verified_matches.items() if p[0] in keep and p[1] in keep},
        {p: m for p, m in db.raw_matches.items() if p[0] in keep and p[1] in keep})


def map_cluster(index: int, db: DatabaseContents, options: MapperOptions,
                threads: int) -> tuple[int, list[ClusterModel], float]:
    """The task: the calibrated mapper on one cluster, on `threads` threads (its options'
    for Ceres, and as many for BLAS, so that workers sharing a machine do not
    oversubscribe it); (index, models, seconds). Without the models' closing global
    adjustments: the joined model's adjustment (bundle_adjust) replaces them."""
    from threadpoolctl import threadpool_limits

    start = time.perf_counter()
    with threadpool_limits(threads):
        reconstructions = reconstruct(db, options, progress=False, final_adjustment=False)
    return index, [ClusterModel.from_reconstruction(r) for r in reconstructions], \
        time.perf_counter() - start


# ------------------------------------------------------------------ joining models


def similarity(target: ClusterModel, source: ClusterModel,
               options: HierarchicalOptions) -> tuple[pycolmap.Sim3d, int] | None:
    """target_from_source and the number of shared images that agree on it, or None.

    The centres of the shared images give a robust similarity (pycolmap's LO-RANSAC);
    an image agrees when, moved by it, its rotation and its direction from the centre
    of the overlap are within merge_max_angle_deg of the target's, and its centre
    within max_centre_error of the overlap's extent. The agreeing images then give the
    similarity again, its rotation from their own rotations (refine_similarity), and
    the images that agree with that one are the answer's."""
    shared, in_target, in_source = np.intersect1d(target.image_ids, source.image_ids,
                                                  return_indices=True)
    if len(shared) < options.min_shared_images:
        return None
    target_poses = target.cams_from_world[in_target]
    source_poses = source.cams_from_world[in_source]
    centres_target = target.centres()[in_target]
    centres_source = source.centres()[in_source]
    extent = np.sqrt(np.mean(np.sum((centres_target - centres_target.mean(0)) ** 2, axis=1)))
    if extent <= 0:
        return None
    ransac = pycolmap.RANSACOptions(max_error=options.max_centre_error * extent)
    ransac.random_seed = 0
    found = pycolmap.estimate_sim3d_robust(centres_source, centres_target, ransac)
    if found is None:
        return None

    def agreeing(target_from_source: pycolmap.Sim3d) -> np.ndarray:
        moved = target_from_source * centres_source
        # cam_from_target of each shared image, through the source: R_source @ R^T.
        through_source = source_poses[:, :, :3] @ target_from_source.rotation.matrix().T
        rotation_error = rotation_angles_deg(
            np.transpose(target_poses[:, :, :3], (0, 2, 1)) @ through_source)
        middle = centres_target.mean(axis=0)
        direction_error = vector_angles_deg(centres_target - middle, moved - middle)
        centre_error = np.linalg.norm(moved - centres_target, axis=1) / extent
        return (rotation_error <= options.merge_max_angle_deg) & \
            (direction_error <= options.merge_max_angle_deg) & \
            (centre_error <= options.max_centre_error)

    target_from_source = found["tgt_from_src"]
    for _ in range(2):
        agree = agreeing(target_from_source)
        if agree.sum() < options.min_shared_images:
            return None
        target_from_source = refine_similarity(target_poses[agree], source_poses[agree],
                                               centres_target[agree], centres_source[agree])
    return target_from_source, int(agree.sum())


def refine_similarity(target_poses: np.ndarray, source_poses: np.ndarray,
                      centres_target: np.ndarray, centres_source: np.ndarray) -> pycolmap.Sim3d:
    """target_from_source from the images both models pose (cams_from_world (k,3,4) and
    centres in each frame): the rotation, the mean of what each image's two rotations
    imply; scale and translation, the least-squares fit of the centres under it.

    The centres alone fix the rotation poorly where they are nearly collinear, as on a
    walk or along a sequence (about the line they lie on); each image's two rotations
    fix it to their noise. A wrong rotation at a junction is a bend that the final
    adjustment straightens only slowly."""
    rotation = mean_rotation(np.transpose(target_poses[:, :, :3], (0, 2, 1))
                             @ source_poses[:, :, :3])
    moved = centres_source @ rotation.T
    offsets_target = centres_target - centres_target.mean(axis=0)
    offsets_moved = moved - moved.mean(axis=0)
    scale = np.sum(offsets_target * offsets_moved) / max(np.sum(offsets_moved ** 2), 1e-300)
    translation = centres_target.mean(axis=0) - scale * moved.mean(axis=0)
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), translation)


def spanning_trees(models: list[ClusterModel], options: HierarchicalOptions
                   ) -> list[dict[int, pycolmap.Sim3d]]:
    """Groups of models that join: per group, model index -> root_from_model, along a
    maximum spanning tree of the agreeing shared images; the largest model of each
    group is its root. Largest groups first."""
    links: dict[int, dict[int, tuple[pycolmap.Sim3d, int]]] = {i: {} for i in range(len(models))}
    for a in range(len(models)):
        for b in range(a + 1, len(models)):
            found = similarity(models[a], models[b], options)
            if found is not None:
                links[a][b] = found
                links[b][a] = (found[0].inverse(), found[1])
    unvisited = set(range(len(models)))
    groups = []
    while unvisited:
        root = max(unvisited, key=lambda i: (len(models[i].image_ids), -i))
        placed = {root: pycolmap.Sim3d()}
        unvisited.discard(root)
        while True:  # Prim: the strongest link from the tree to a model outside it
            candidates = [(support, -outside, inside, outside)
                          for inside in placed for outside, (_, support) in links[inside].items()
                          if outside in unvisited]
            if not candidates:
                break
            _, _, inside, outside = max(candidates)
            placed[outside] = placed[inside] * links[inside][outside][0]
            unvisited.discard(outside)
        groups.append(placed)
    return sorted(groups, key=lambda g: -len({i for m in g for i in models[m].image_ids}))


def join(db: DatabaseContents, models: list[ClusterModel],
         root_from_model: dict[int, pycolmap.Sim3d]) -> pycolmap.Reconstruction:
    """One reconstruction of a group: each image posed by the model that observes most
    through it; points that share an observation (image, keypoint) merged into one, at
    the mean of their positions, keeping one keypoint per image (the first model's)."""
    pose_of: dict[int, tuple[int, pycolmap.Rigid3d]] = {}
    for m, sim in root_from_model.items():
        counts = models[m].observations_per_image()
        for image_id, matrix in zip(models[m].image_ids.tolist(), models[m].cams_from_world):
            support = counts.get(image_id, 0)
            if image_id not in pose_of or support > pose_of[image_id][0]:
                pose_of[image_id] = (support, sim.transform_camera_world(pycolmap.Rigid3d(matrix)))
    reconstruction = posed_images(db, db.cameras, {image_id: pose_of[image_id][1]
                                                   for image_id in sorted(pose_of)})
    # Every model's points in the root's frame, numbered globally, and their observations.
    group = list(root_from_model)
    xyz = np.concatenate([np.zeros((0, 3))] + [root_from_model[m] * models[m].xyz
                                               for m in group if len(models[m].xyz)])
    offsets = np.cumsum([0] + [len(models[m].xyz) for m in group])
    point = np.concatenate([models[m].track_point + offset for m, offset in zip(group, offsets)])
    image = np.concatenate([models[m].track_image for m in group])
    keypoint = np.concatenate([models[m].track_keypoint for m in group])
    merged = shared_observation_groups(point, image, keypoint, len(xyz))
    # One keypoint per image and merged point: the first observation's.
    owner = merged[point]
    _, first = np.unique(owner * (image.max(initial=0) + 1) + image, return_index=True)
    first.sort()
    owner, image, keypoint = owner[first], image[first], keypoint[first]
    observed = np.zeros(len(xyz), bool)
    observed[point] = True
    sums = np.zeros_like(xyz)
    np.add.at(sums, merged[observed], xyz[observed])
    members = np.bincount(merged[observed], minlength=len(xyz))
    order = np.argsort(owner, kind="stable")
    owners, starts, lengths = np.unique(owner[order], return_index=True, return_counts=True)
    elements = [pycolmap.TrackElement(i, k) for i, k in zip(image[order].tolist(),
                                                           keypoint[order].tolist())]
    for owner_id, start, length in zip(owners.tolist(), starts.tolist(), lengths.tolist()):
        if length >= 2:
            reconstruction.add_point3D(sums[owner_id] / members[owner_id],
                                       pycolmap.Track(elements[start:start + length]))
    return reconstruction


def shared_observation_groups(point: np.ndarray, image: np.ndarray, keypoint: np.ndarray,
                              num_points: int) -> np.ndarray:
    """Per point id, the smallest id of its group: points that share an observation
    (image, keypoint), directly or through other points. Observation k is keypoint
    `keypoint[k]` of image `image[k]` seeing point `point[k]`. Minimum labels spread
    along the links, with pointer jumping, until nothing changes."""
    key = image.astype(np.int64) * (int(keypoint.max(initial=0)) + 1) + keypoint
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    other = point[first][inverse]
    linked = point != other
    a, b = point[linked], other[linked]
    label = np.arange(num_points)
    while True:
        previous = label.copy()
        low = np.minimum(label[a], label[b])
        np.minimum.at(label, a, low)
        np.minimum.at(label, b, low)
        while True:
            jumped = label[label]
            if (jumped == label).all():
                break
            label = jumped
        if (label == previous).all():
            return label


def bundle_adjust(reconstruction: pycolmap.Reconstruction, mapper_options: MapperOptions,
                  options: HierarchicalOptions, num_threads: int) -> None:
    """Global adjustment of poses and points as the mapper's (its loss and Ceres
    limits), intrinsics constant, the gauge fixed by two cameras; then observations
    beyond max_reproj_error_px are dropped (and with them points left with one:
    COLMAP's ObservationManager)."""
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    ba_options = adjustment_options(
        mapper_options, mapper_options.bundle_adjustment.global_max_iterations,
        num_threads=num_threads)
    pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()
    manager = pycolmap.ObservationManager(reconstruction)
    manager.filter_points3D_with_large_reprojection_error(
        options.max_reproj_error_px, set(reconstruction.point3D_ids()))
    reconstruction.update_point_3d_errors()


# ------------------------------------------------------------------ the command


@dataclass(frozen=True)
class ClusterReport:
    """What one cluster task did: its images, the images its models registered, and
    its wall time in the worker."""

    num_images: int
    num_registered: int
    seconds: float


def hierarchical_mapping(db: DatabaseContents, mapper_options: MapperOptions,
                         options: HierarchicalOptions, cluster: Any = None,
                         timer: StageTimer | None = None, progress: bool = True
                         ) -> tuple[list[pycolmap.Reconstruction], list[ClusterReport]]:
    """Partition, map every cluster (Ray tasks on `cluster`, a distributed.Cluster, else
    a local pool), join and adjust. Returns the models, largest first (nothing
    written), and a report per cluster. The command maps with MAPPER_DEFAULTS under its
    flags."""
    from colmap_ext.distributed import run_local_or_on_cluster

    timer = timer or StageTimer()
    check_requested_pair(db.images, mapper_options)
    with timer("partition"):
        clusters = partition(db, options)
    if not clusters:
        raise UserError("no two images share a verified pair: nothing to map (run feature "
                        "matching first)")
    cores = os.cpu_count() or 1
    # A Ray task holds one CPU; a local pool shares this machine's cores.
    workers = 1 if cluster is not None else min(options.workers(), len(clusters))
    threads = 1 if cluster is not None else max(1, cores // workers)
    task_options = options_from_flags({"Mapper.num_threads": threads}, base=mapper_options)
    arguments = [(index, database_subset(db, ids), task_options.choosing_initial_pair(ids),
                  threads) for index, ids in enumerate(clusters)]
    models: list[ClusterModel] = []
    reports: list[ClusterReport] = []
    with timer("cluster mapping"):
        results = run_local_or_on_cluster(cluster, map_cluster, arguments, workers,
                                          desc=f"map {len(clusters)} clusters",
                                          progress=progress)
        for index, cluster_models, seconds in sorted(results, key=lambda r: r[0]):
            models += cluster_models
            reports.append(ClusterReport(
                len(clusters[index]), sum(len(m.image_ids) for m in cluster_models), seconds))
    with timer("merging"):
        groups = spanning_trees(models, options)
        reconstructions = [join(db, models, group) for group in groups]
    with timer("bundle adjustment"):
        for reconstruction in reconstructions:
            bundle_adjust(reconstruction, mapper_options, options, cores)
    reconstructions = [r for r in reconstructions if r.num_reg_images() >= 2]
    return sorted(reconstructions, key=lambda r: (-r.num_reg_images(), -r.num_points3D())), \
        reports


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.usage = ("colmap-ext hierarchical_mapper --database_path DB --image_path IMAGES "
                    "--output_path OUT [--leaf_max_num_images N] [--image_overlap N] "
                    "[--num_workers N] [--ray_address ADDRESS] [--Mapper.OPTION VALUE ...]")
    parser.allow_abbrev = False
    defaults = HierarchicalOptions()
    parser.add_argument("--database_path", required=True)
    parser.add_argument("--image_path", required=True)
    parser.add_argument("--output_path", required=True)
    parser.add_argument("--leaf_max_num_images", type=int, default=defaults.leaf_max_num_images,
                        help="largest cluster, before the overlap is added")
    parser.add_argument("--image_overlap", type=int, default=defaults.image_overlap,
                        help="images each cluster shares with its neighbours")
    parser.add_argument("--num_workers", type=int, default=defaults.num_workers,
                        help="clusters mapped at once without Ray; -1: one per core")
    parser.add_argument("--ray_address", default=None,
                        help="map the clusters as Ray tasks: auto (the running cluster), "
                             "local (start one here) or HOST:PORT")
    parser.add_argument("--output_type", default="BIN", choices=["BIN", "TXT", "bin", "txt"])
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a model already in OUTPUT_PATH/0")
    add_option_flags(parser, base=MAPPER_DEFAULTS)


def main(database_path: str, image_path: str, output_path: str,
         leaf_max_num_images: int = HierarchicalOptions.leaf_max_num_images,
         image_overlap: int = HierarchicalOptions.image_overlap,
         num_workers: int = HierarchicalOptions.num_workers, ray_address: str | None = None,
         output_type: str = "BIN", overwrite: bool = False, progress: bool = True,
         **flags: Any) -> dict:
    """Map the database cluster by cluster and write OUTPUT/0, ... and
    OUTPUT/mapper_summary.json; `flags`: COLMAP's mapper options by name (None: not
    given), as for `colmap-ext mapper`."""
    from colmap_ext.distributed import check_address, connect

    start = time.perf_counter()
    options = HierarchicalOptions(leaf_max_num_images, image_overlap, num_workers)
    if output_type.upper() not in OUTPUT_TYPES:
        raise UserError(f"--output_type must be BIN or TXT, got {output_type!r}")
    if ray_address is not None:
        check_address(ray_address)
    mapper_options = options_from_flags(flags, base=MAPPER_DEFAULTS)
    check_database_file(Path(database_path))
    images = Path(image_path)
    if not images.is_dir():
        raise UserError(f"image path not found: {images}")
    with replacing(output_path, MAPPER_OUTPUT, overwrite) as new_output:
        timer = StageTimer()
        with timer("read database"):
            db = read_database(database_path)
        extract_colors = flags.get("Mapper.extract_colors") is not False and \
            colours_readable(db, images)
        if ray_address is None:
            reconstructions, reports = hierarchical_mapping(db, mapper_options, options, None,
                                                            timer, progress)
        else:
            with connect(ray_address) as cluster:
                reconstructions, reports = hierarchical_mapping(db, mapper_options, options,
                                                                cluster, timer, progress)
        if not reconstructions:
            raise UserError("no model could be reconstructed: no cluster gave a relative pose "
                            "with enough well-triangulated points")
        with timer("export"):
            if extract_colors:
                for reconstruction in reconstructions:
                    reconstruction.extract_colors_for_all_images(str(images))
            write_models(reconstructions, new_output, output_type.upper())
        summary = summarize(reconstructions, timer, time.perf_counter() - start)
        summary["clusters"] = [asdict(report) for report in reports]
        write_json(summary, new_output / "mapper_summary.json")
    print(format_summary(summary, str(output_path)))
    return {"reconstructions": dict(enumerate(reconstructions)), "summary": summary}
