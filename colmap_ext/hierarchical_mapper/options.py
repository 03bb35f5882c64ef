"""The hierarchical mapper's options: how the view graph is cut and the cluster models
joined, and the mapper options its clusters run with."""

from __future__ import annotations

import os
from dataclasses import dataclass

from colmap_ext.errors import UserError
from colmap_ext.mapper.options import BundleAdjustmentOptions, MapperOptions, MergingOptions

# The clusters' mapper options where no --Mapper.* flag is given: the flat mapper's, but
# a global adjustment each time a cluster's model grows by half (the flat mapper's, as
# COLMAP's, each time it grows by a tenth). Every cluster is adjusted again within the
# joined model, and the sparser schedule is most of what makes a cluster task cheaper
# than COLMAP's (docs/experiments/benchmarks-history.md, "Scale-out"). Small models need
# the frequent schedule, so `mapper` keeps it.
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
