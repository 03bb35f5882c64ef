"""The hierarchical mapper from a database in memory to its models: partition, map the
clusters, join, and end each joined model as the flat mapper ends one."""

from __future__ import annotations

import os
from dataclasses import dataclass

import pycolmap

from colmap_ext.database import DatabaseContents
from colmap_ext.errors import UserError
from colmap_ext.executors import Executor, LocalExecutor
from colmap_ext.hierarchical_mapper.clusters import ClusterModel, database_subset, map_cluster
from colmap_ext.hierarchical_mapper.joining import join, spanning_trees
from colmap_ext.hierarchical_mapper.options import HierarchicalOptions
from colmap_ext.hierarchical_mapper.partition import partition
from colmap_ext.mapper.cli import options_from_flags
from colmap_ext.mapper.initial_pair import check_requested_pair
from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.pipeline import options_for_model, reconstruct
from colmap_ext.timing import StageTimer


@dataclass(frozen=True)
class ClusterReport:
    """What one cluster task did: its images, the images its models registered, and
    its wall time in the worker."""

    num_images: int
    num_registered: int
    seconds: float


def hierarchical_mapping(db: DatabaseContents, mapper_options: MapperOptions,
                         options: HierarchicalOptions, cluster: Executor | None = None,
                         timer: StageTimer | None = None, progress: bool = True
                         ) -> tuple[list[pycolmap.Reconstruction], list[ClusterReport]]:
    """Partition, map every cluster (Ray tasks on `cluster`, a distributed.Cluster, else
    a pool of local processes), join and finish. Returns the models, largest first (nothing
    written), and a report per cluster. The command maps with MAPPER_DEFAULTS under its
    flags."""
    timer = timer or StageTimer()
    check_requested_pair(db.images, mapper_options.initialization)
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
    arguments = [(index, database_subset(db, ids), options_for_model(task_options, ids),
                  threads) for index, ids in enumerate(clusters)]
    models: list[ClusterModel] = []
    cluster_of_model: list[int] = []
    reports: list[ClusterReport] = []
    with timer("cluster mapping"):
        executor = cluster or LocalExecutor(workers, processes=True)
        results = executor.map(map_cluster, arguments, len(arguments),
                               desc=f"map {len(clusters)} clusters", progress=progress)
        for index, cluster_models, seconds in sorted(results, key=lambda r: r[0]):
            models += cluster_models
            cluster_of_model += [index] * len(cluster_models)
            reports.append(ClusterReport(
                len(clusters[index]), sum(len(m.image_ids) for m in cluster_models), seconds))
    with timer("merging"):
        groups = spanning_trees(models, options)
        joined = [join(db, models, group) for group in groups]
    # Each joined model ends as the flat mapper ends a model, which the clusters left out:
    # the flat mapper continues it over its clusters' images (registering those a cluster
    # missed), adjusts it, triangulates it again from the final poses and filters it. Its
    # poses are the mapper's own, not a given model's to hold (fix_existing_frames).
    finish_options = options_from_flags({"Mapper.multiple_models": False,
                                         "Mapper.fix_existing_frames": False},
                                        base=mapper_options)
    reconstructions: list[pycolmap.Reconstruction] = []
    held: set[int] = set()
    for group, reconstruction in zip(groups, joined):  # the largest first
        if set(reconstruction.reg_image_ids()) <= held:
            # Nothing a larger model does not hold: a cluster's second model, whose
            # images the larger model's end registered.
            continue
        names = sorted({db.images[i].name for m in group for i in clusters[cluster_of_model[m]]})
        finished = reconstruct(db, finish_options, names, timer, progress=False,
                               existing=reconstruction)
        reconstructions += finished
        held.update(*(model.reg_image_ids() for model in finished))
    return sorted(reconstructions, key=lambda r: (-r.num_reg_images(), -r.num_points3D())), \
        reports

