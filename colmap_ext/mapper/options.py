"""The mapper's parameters, with the defaults the method uses and why."""

from __future__ import annotations

import os
from dataclasses import dataclass

# Robust losses of bundle adjustment (pycolmap.LossFunctionType, lower case).
BA_LOSSES = ("cauchy", "soft_l1", "trivial")


@dataclass
class MapperOptions:
    # Registration order: "visibility" (COLMAP's: the image seeing most model points
    # first) or "sequence" (the paper's: the image next in name order to a registered one).
    order: str = "visibility"
    # Initial pair (COLMAP's --Mapper.init_image_id1/2); -1 lets the mapper choose.
    init_image_id1: int = -1
    init_image_id2: int = -1
    # Two-view geometry: Sampson error threshold and the support a pair needs.
    two_view_max_error_px: float = 2.0
    two_view_min_num_inliers: int = 15
    # Initial pair: enough inliers and a median triangulation angle that fixes depth.
    init_min_num_inliers: int = 30
    init_min_tri_angle_deg: float = 4.0
    # Absolute pose (P3P RANSAC): reprojection threshold and the support it needs.
    abs_pose_max_error_px: float = 4.0
    abs_pose_min_num_inliers: int = 15
    abs_pose_min_inlier_ratio: float = 0.2
    # Triangulation and pruning: an observation is geometrically compatible with a point
    # when it reprojects within this error; a point needs this angle between its rays.
    max_reproj_error_px: float = 3.0
    min_tri_angle_deg: float = 1.5
    # Guided matching (paper, step 4c) against the guided_num_images registered images
    # most connected to the new one: per keypoint, its guided_num_neighbors nearest
    # descriptors there; a feature is compatible when its descriptor angle is below
    # max_descriptor_distance (radians, as COLMAP's SIFT matcher measures it) and it lies
    # within max_reproj_error_px of the epipolar line. The closest descriptor wins.
    # The paper takes 20 neighbours; with SIFT that admits look-alike features along the
    # epipolar line, and 3 measured best (templeSparseRing R_err max 1.31 -> 0.31 deg).
    guided_num_neighbors: int = 3
    guided_num_images: int = 8
    max_descriptor_distance: float = 0.7
    # Pruning (paper, step 4e): a point needs support in this many images, once the
    # images registered after its creation have had their chance to observe it.
    min_track_length: int = 3
    track_grace_registrations: int = 3
    # Bundle adjustment (pycolmap/Ceres, intrinsics constant): local around each new
    # image, global whenever the model has grown by ba_global_images_ratio, and at the end.
    ba_local_num_images: int = 6
    ba_local_max_iterations: int = 25
    ba_global_images_ratio: float = 1.1
    ba_global_max_iterations: int = 50
    # The robust loss, one of BA_LOSSES; Cauchy at 1 px is what
    # makes the poses accurate, and what makes Ceres slow: it converges linearly,
    # ~27 iterations a solve where soft-L1 takes ~8 and the trivial loss ~6 (templeSparseRing
    # R_err max 0.31 deg against 0.84 and 1.73; benchmarks/mapper_profile.py measures it).
    ba_loss: str = "cauchy"
    ba_loss_scale_px: float = 1.0
    # Ceres stops when an iteration lowers the cost by less than this fraction. COLMAP
    # runs to the iteration limit (0); with the robust loss that only creeps (< 0.1 %
    # per iteration) and costs 2x the mapper's time for no measured gain.
    ba_function_tolerance: float = 1e-5
    # A finished model keeps an image only if its points fix its rotation to within this
    # many times the keypoint noise (pruning.rotation_uncertainty: it falls as
    # 1/sqrt(points) and rises as the field of view narrows). Measured on final models:
    # synthetic scenes (56 deg field of view) 3 or less, templeSparseRing (24 deg) and
    # dinoSparseRing end to end (11 deg) under 10; dinoSparseRing on COLMAP's features,
    # image 5 (21 points) 18.7: it ended 2 deg off, every other image under 10.
    max_rotation_uncertainty: float = 15.0
    # Images that fail to register are tried again this many times as the model grows.
    max_registration_trials: int = 3
    # A model smaller than this is not kept; the remaining images start a new model.
    min_model_size: int = 3
    max_num_models: int = 50
    # False: only the first model is reconstructed (COLMAP's --Mapper.multiple_models 0).
    multiple_models: bool = True
    # Read the points' colours from the images when writing the models.
    extract_colors: bool = True
    # Models are joined when two images of one, posed among the other's points, imply
    # the same similarity: rotations and directions between centres within this angle.
    # P3P from few points through a narrow field of view errs by a few degrees (dino
    # rings: 1-2.5); unrelated wrong poses differ by tens of degrees.
    merge_max_angle_deg: float = 5.0
    # Rounds of retriangulation and global adjustment after joining two models.
    merge_refinement_rounds: int = 3
    seed: int | None = None
    num_threads: int = -1

    def threads(self) -> int:
        """The threads to use: num_threads, or every core this process may run on (-1)."""
        if self.num_threads > 0:
            return self.num_threads
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else os.cpu_count() or 1

    def __post_init__(self) -> None:
        if self.order not in ("visibility", "sequence"):
            raise ValueError(f"order must be 'visibility' or 'sequence', got {self.order!r}")
        if self.ba_loss not in BA_LOSSES:
            raise ValueError(f"ba_loss must be one of {', '.join(BA_LOSSES)}, got {self.ba_loss!r}")
