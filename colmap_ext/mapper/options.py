"""The mapper's options, one class per component as COLMAP arranges them: two-view
geometry, initialization, registration, guided matching, triangulation, filtering,
bundle adjustment and merging, gathered in `MapperOptions`. Each field has one default
and one comment; `check()` names the first field out of its range. Why the defaults are
what they are is measured in BENCHMARKS.md ("Why the defaults").
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields

# Registration orders: COLMAP's (the image seeing most model points first) and the
# paper's (the image next in name order to a registered one).
ORDERS = ("visibility", "sequence")
# Robust losses of bundle adjustment (pycolmap.LossFunctionType, lower case).
BA_LOSSES = ("cauchy", "soft_l1", "trivial")


class OptionError(ValueError):
    """An option out of its range; `path` names it in MapperOptions ("registration.order")."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(message)
        self.path = path


def _require(condition: bool, component: object, name: str, rule: str) -> None:
    if not condition:
        value = getattr(component, name)
        raise OptionError(name, f"{type(component).__name__}.{name} must be {rule}, "
                                f"got {value!r}")


@dataclass
class TwoViewOptions:
    """Verification of image pairs the database left unverified (two_view.py)."""

    # Sampson error threshold (px) of the 5-point RANSAC, also the initial pair's.
    max_error_px: float = 2.0
    # Inliers a pair needs to be used.
    min_num_inliers: int = 15

    def check(self) -> None:
        _require(self.max_error_px > 0, self, "max_error_px", "> 0")
        _require(self.min_num_inliers >= 5, self, "min_num_inliers", ">= 5")


@dataclass
class InitializationOptions:
    """Choosing and reconstructing the first two images (initial_pair.py)."""

    # The initial pair's image ids; -1: the mapper chooses.
    image_id1: int = -1
    image_id2: int = -1
    # Inliers of the pair's relative pose that triangulate.
    min_num_inliers: int = 30
    # Median triangulation angle (deg) the pair needs: it fixes the depth. Halved while
    # no pair reaches it (down to triangulation.min_tri_angle_deg), as COLMAP does.
    min_tri_angle_deg: float = 8.0

    def check(self) -> None:
        _require(self.image_id1 >= -1, self, "image_id1", ">= -1")
        _require(self.image_id2 >= -1, self, "image_id2", ">= -1")
        _require(self.min_num_inliers >= 5, self, "min_num_inliers", ">= 5")
        _require(0 <= self.min_tri_angle_deg < 180, self, "min_tri_angle_deg", "in [0, 180)")


@dataclass
class RegistrationOptions:
    """Posing the next image by P3P RANSAC on 2D-3D correspondences (registration.py)."""

    # Which image next: one of ORDERS.
    order: str = "visibility"
    # Reprojection error threshold (px) of the P3P RANSAC.
    abs_pose_max_error_px: float = 4.0
    # P3P inliers an image needs to register.
    abs_pose_min_num_inliers: int = 15
    # P3P inliers as a fraction of the image's correspondences.
    abs_pose_min_inlier_ratio: float = 0.2
    # Reprojection error (px) of the P3P inliers the pose is computed from, where
    # abs_pose_max_error_px is larger (COLMAP's 12 px): the pose is least squares on its
    # inliers, and 12 px ones put it degrees off. Also the epipolar check's distance.
    pose_max_error_px: float = 4.0
    # Fraction of the image's verified matches to registered images that its pose must
    # keep on their epipolar lines (within pose_max_error_px); 0 turns the check off.
    min_epipolar_support: float = 0.85
    # Times an image that failed to register is tried again as the model grows.
    max_trials: int = 3

    def check(self) -> None:
        _require(self.order in ORDERS, self, "order", f"one of {', '.join(ORDERS)}")
        _require(self.abs_pose_max_error_px > 0, self, "abs_pose_max_error_px", "> 0")
        _require(self.abs_pose_min_num_inliers >= 4, self, "abs_pose_min_num_inliers", ">= 4")
        _require(0 <= self.abs_pose_min_inlier_ratio <= 1, self, "abs_pose_min_inlier_ratio",
                 "in [0, 1]")
        _require(self.pose_max_error_px > 0, self, "pose_max_error_px", "> 0")
        _require(0 <= self.min_epipolar_support <= 1, self, "min_epipolar_support", "in [0, 1]")
        _require(self.max_trials >= 1, self, "max_trials", ">= 1")


@dataclass
class GuidedMatchingOptions:
    """Features of a new image matched to registered images near it (paper, step 4c;
    guided_matching.py), for triangulation, registration and merging."""

    # Nearest descriptors per keypoint in each registered image (the paper takes 20).
    num_neighbors: int = 3
    # Registered images matched: those most connected to the new image.
    num_images: int = 8
    # Largest descriptor angle (radians, as COLMAP's SIFT matcher) of a compatible feature.
    max_descriptor_distance: float = 0.7
    # Largest distance (px) of a compatible feature from the epipolar line.
    max_epipolar_error_px: float = 3.0
    # An image pair's candidates come from an exact nearest-descriptor search while it
    # compares at most this many keypoint pairs (keypoints x keypoints; 2**24: 4096 each),
    # and from the database's matches beyond (descriptors.NearestDescriptors).
    max_search_pairs: int = 2**24
    # Where verified matches already give this share of the keypoints a correspondence (a
    # new image's to model points, a pair's free keypoints to the other image's), they
    # stand in for the descriptor search, which could add next to nothing; 1: always search.
    skip_search_verified_share: float = 0.8

    def check(self) -> None:
        _require(self.num_neighbors >= 1, self, "num_neighbors", ">= 1")
        _require(self.num_images >= 1, self, "num_images", ">= 1")
        _require(0 < self.max_descriptor_distance <= 3.15, self, "max_descriptor_distance",
                 "in (0, pi]")
        _require(self.max_epipolar_error_px > 0, self, "max_epipolar_error_px", "> 0")
        _require(self.max_search_pairs >= 0, self, "max_search_pairs", ">= 0")
        _require(0 <= self.skip_search_verified_share <= 1, self, "skip_search_verified_share",
                 "in [0, 1]")


@dataclass
class TriangulationOptions:
    """New points and longer tracks from compatible features (triangulation.py)."""

    # An observation joins a point when it reprojects within this error (px).
    max_reproj_error_px: float = 3.0
    # Smallest angle (deg) between a new point's widest pair of rays.
    min_tri_angle_deg: float = 1.5
    # A finished model's points are triangulated again from its poses, each observation
    # within this many times the model's median reprojection error (at most
    # max_reproj_error_px) but where its errors look Gaussian
    # (FilteringOptions.gaussian_max_outlier_share); 0: the model keeps the points it grew with.
    retriangulation_max_error_ratio: float = 4.0

    @property
    def retriangulates(self) -> bool:
        return self.retriangulation_max_error_ratio > 0

    def check(self) -> None:
        _require(self.max_reproj_error_px > 0, self, "max_reproj_error_px", "> 0")
        _require(0 <= self.min_tri_angle_deg < 180, self, "min_tri_angle_deg", "in [0, 180)")
        _require(self.retriangulation_max_error_ratio >= 0, self,
                 "retriangulation_max_error_ratio", ">= 0")


@dataclass
class FilteringOptions:
    """Dropping observations, points and images the model no longer supports
    (paper, step 4e; filtering.py)."""

    # An observation is kept while it reprojects within this error (px) ...
    max_reproj_error_px: float = 3.0
    # ... or within this many times the median error, where the keypoint noise reaches
    # max_reproj_error_px: 4 x the median is 4.7 standard deviations of Gaussian noise,
    # beyond which one true observation in 65 000 lies (3 x, 3.5: one in 500, which
    # split tracks and cost the poses; BENCHMARKS.md, "Why the defaults").
    noise_max_error_ratio: float = 4.0
    # A point is kept while its widest pair of rays spans this angle (deg).
    min_tri_angle_deg: float = 1.5
    # Images a point must be seen in ...
    min_track_length: int = 3
    # ... once this many images registered after its creation could observe it.
    track_grace_registrations: int = 3
    # A finished model keeps an image whose points fix its rotation to within this many
    # times the keypoint noise (filtering.rotation_uncertainty).
    max_rotation_uncertainty: float = 15.0
    # A finished model's filter also drops observations beyond this many times its median
    # reprojection error (3 would be 3.5 standard deviations of Gaussian noise), and the
    # model is adjusted again without them; 0: max_reproj_error_px alone.
    final_max_error_ratio: float = 10.0
    # A model's reprojection errors look like Gaussian keypoint noise where at most this
    # share of them lie beyond 3x their median (filtering.errors_look_gaussian; Gaussian noise
    # puts 0.2 % there). Such a model has no near-miss matches to leave out: it is adjusted
    # in least squares (BundleAdjustmentOptions.gaussian_loss), and its retriangulation keeps
    # the observations within the noise's limits, without
    # TriangulationOptions.retriangulation_max_error_ratio, which would cut the noise's tail.
    gaussian_max_outlier_share: float = 0.01

    def check(self) -> None:
        _require(self.max_reproj_error_px > 0, self, "max_reproj_error_px", "> 0")
        _require(0 <= self.min_tri_angle_deg < 180, self, "min_tri_angle_deg", "in [0, 180)")
        _require(self.min_track_length >= 2, self, "min_track_length", ">= 2")
        _require(self.track_grace_registrations >= 0, self, "track_grace_registrations", ">= 0")
        _require(self.max_rotation_uncertainty > 0, self, "max_rotation_uncertainty", "> 0")
        _require(self.final_max_error_ratio >= 0, self, "final_max_error_ratio", ">= 0")
        _require(self.noise_max_error_ratio >= 0, self, "noise_max_error_ratio", ">= 0")
        _require(0 <= self.gaussian_max_outlier_share <= 1, self, "gaussian_max_outlier_share",
                 "in [0, 1]")


@dataclass
class BundleAdjustmentOptions:
    """Local and global refinement (bundle_adjustment.py): our calibrated adjuster, and
    pycolmap's Ceres for the finished model and where intrinsics or rigs are refined."""

    # Images of a local adjustment: the new one and its most connected registered images.
    local_num_images: int = 6
    # Points seen by more images enter a local adjustment through the local images'
    # observations alone; shorter tracks bring their other images in, poses constant.
    local_max_track_length: int = 15
    # Iterations (successful and unsuccessful steps, as Ceres counts) of a local adjustment ...
    local_max_iterations: int = 25
    # ... which also stops when no parameter's gradient exceeds this: COLMAP's incremental
    # mapper's value; pycolmap's default 1e-4 kept solves iterating on steps far below the noise.
    local_gradient_tolerance: float = 10.0
    # A global adjustment whenever the registered images have grown by this ratio
    # (COLMAP's 1.1 gave the same poses where the errors look Gaussian, in more solves).
    global_images_ratio: float = 1.2
    # ... or by this many images (COLMAP's ba_global_frames_freq): on a long sequence the
    # ratio's steps grow long, and with them the drift that local adjustments leave.
    global_images_freq: int = 500
    # Between global adjustments, whenever the model has grown by window_images_freq
    # images, its last window_num_images registered images are adjusted together, by the
    # local rule (the images beyond them constant), in a model of at least twice as many:
    # a sequence's turns leave its newest images off by tenths of a degree, which six
    # images' local adjustments do not spread and the next global adjustment would unwind
    # over the whole model (BENCHMARKS.md, "Sequences"). 0: never.
    window_num_images: int = 100
    window_images_freq: int = 50
    # Iterations of a global adjustment, and its gradient tolerance (as local).
    global_max_iterations: int = 50
    global_gradient_tolerance: float = 1.0
    # The robust loss, one of BA_LOSSES, and its scale (px) ...
    loss: str = "cauchy"
    loss_scale_px: float = 1.0
    # ... raised to this many times the model's median reprojection error (measured at
    # each global adjustment) where the keypoint noise reaches it: a scale below the
    # noise down-weights good observations and slows the adjustment down; 1.7 x the median is
    # twice the standard deviation of Gaussian noise.
    noise_loss_scale_ratio: float = 1.7
    # The loss where a model's reprojection errors look Gaussian, measured before each
    # global adjustment (FilteringOptions.gaussian_max_outlier_share): least squares
    # ("trivial") gives the maximum-likelihood poses on the observations kept, which the
    # robust loss down-weights, in fewer iterations. Elsewhere (wrong or poorly localised
    # matches) the robust loss stays, which least squares would let them pull
    # (BENCHMARKS.md, "Why the defaults").
    gaussian_loss: str = "trivial"
    # Each step our adjuster (solvers.bundle_adjust) takes is tried at 2, 4, ... up to
    # this many times its length while the cost falls (1: never): under a robust loss a
    # reweighted step falls short of the minimum along it (BENCHMARKS.md, "Why the defaults").
    max_step_scale: float = 16.0
    # The adjustment stops when an iteration lowers the cost by less than this fraction; 0: never.
    function_tolerance: float = 1e-5
    # ... and in least squares: run to the gradient tolerance, as COLMAP's adjustments are.
    least_squares_function_tolerance: float = 0.0
    # The first step is damped by the inverse of this (Ceres's initial_trust_region_radius
    # and its default) ...
    initial_trust_region_radius: float = 1e4
    # ... and in a global adjustment in least squares, nearly not: a Gauss-Newton step on
    # a cost nearly quadratic about the model's optimum, where damped steps take many
    # iterations to unwind a long sequence's drift, which the observations fix weakly
    # (BENCHMARKS.md, "Why the defaults"). The robust loss keeps the damping: there the
    # real sets' models moved with it.
    least_squares_global_initial_trust_region_radius: float = 1e8
    # Smaller problems (residuals) are solved on one thread, larger on MapperOptions.threads().
    min_num_residuals_for_multi_threading: int = 50000
    # Refine the intrinsics in global adjustments (the method holds them constant).
    refine_focal_length: bool = False
    refine_principal_point: bool = False
    refine_extra_params: bool = False
    # Cameras whose intrinsics stay constant when the others are refined.
    constant_camera_ids: tuple[int, ...] = ()
    # Refine the poses of a rig's cameras relative to the rig (the method holds the
    # calibrated rig constant), but for the rigs in constant_rig_ids.
    refine_sensor_from_rig: bool = False
    constant_rig_ids: tuple[int, ...] = ()

    def function_tolerance_for(self, loss: str) -> float:
        """The function tolerance of an adjustment under `loss`."""
        return self.least_squares_function_tolerance if loss == "trivial" \
            else self.function_tolerance

    def trust_region_radius(self, loss: str, local: bool) -> float:
        """The initial trust region radius of an adjustment under `loss`."""
        return self.least_squares_global_initial_trust_region_radius \
            if loss == "trivial" and not local else self.initial_trust_region_radius

    @property
    def refines_intrinsics(self) -> bool:
        return self.refine_focal_length or self.refine_principal_point or \
            self.refine_extra_params

    def check(self) -> None:
        _require(self.local_num_images >= 2, self, "local_num_images", ">= 2")
        _require(self.local_max_iterations >= 1, self, "local_max_iterations", ">= 1")
        _require(self.local_max_track_length >= 2, self, "local_max_track_length", ">= 2")
        _require(self.global_images_ratio > 1, self, "global_images_ratio", "> 1")
        _require(self.global_images_freq >= 1, self, "global_images_freq", ">= 1")
        _require(self.global_max_iterations >= 1, self, "global_max_iterations", ">= 1")
        _require(self.window_num_images >= 0, self, "window_num_images", ">= 0")
        _require(self.window_images_freq >= 1, self, "window_images_freq", ">= 1")
        for name in ("initial_trust_region_radius",
                     "least_squares_global_initial_trust_region_radius"):
            _require(getattr(self, name) > 0, self, name, "> 0")
        for name in ("local_gradient_tolerance", "global_gradient_tolerance"):
            _require(getattr(self, name) >= 0, self, name, ">= 0")
        _require(self.loss in BA_LOSSES, self, "loss", f"one of {', '.join(BA_LOSSES)}")
        _require(self.gaussian_loss in BA_LOSSES, self, "gaussian_loss",
                 f"one of {', '.join(BA_LOSSES)}")
        _require(self.loss_scale_px > 0, self, "loss_scale_px", "> 0")
        _require(self.noise_loss_scale_ratio >= 0, self, "noise_loss_scale_ratio", ">= 0")
        _require(self.max_step_scale >= 1, self, "max_step_scale", ">= 1")
        _require(self.function_tolerance >= 0, self, "function_tolerance", ">= 0")
        _require(self.least_squares_function_tolerance >= 0, self,
                 "least_squares_function_tolerance", ">= 0")
        _require(self.min_num_residuals_for_multi_threading >= 0, self,
                 "min_num_residuals_for_multi_threading", ">= 0")
        for name in ("constant_camera_ids", "constant_rig_ids"):
            ids = getattr(self, name)
            _require(isinstance(ids, tuple) and all(isinstance(i, int) and i >= 1 for i in ids),
                     self, name, "a tuple of ids >= 1")


@dataclass
class MergingOptions:
    """Joining models that fell apart (merging.py)."""

    # Two images of one model, posed among the other's points, must imply the same
    # similarity: rotations and directions between centres within this angle (deg).
    max_angle_deg: float = 5.0
    # Rounds of retriangulation and global adjustment after a join.
    refinement_rounds: int = 3

    def check(self) -> None:
        _require(0 < self.max_angle_deg < 180, self, "max_angle_deg", "in (0, 180)")
        _require(self.refinement_rounds >= 0, self, "refinement_rounds", ">= 0")


@dataclass
class MapperOptions:
    """Everything the mapper takes: its components, and the run's own settings."""

    two_view: TwoViewOptions = field(default_factory=TwoViewOptions)
    initialization: InitializationOptions = field(default_factory=InitializationOptions)
    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    guided_matching: GuidedMatchingOptions = field(default_factory=GuidedMatchingOptions)
    triangulation: TriangulationOptions = field(default_factory=TriangulationOptions)
    filtering: FilteringOptions = field(default_factory=FilteringOptions)
    bundle_adjustment: BundleAdjustmentOptions = field(default_factory=BundleAdjustmentOptions)
    merging: MergingOptions = field(default_factory=MergingOptions)
    # Start new models from the images left over; False: only the first model.
    multiple_models: bool = True
    # Most models reconstructed.
    max_num_models: int = 50
    # A model with fewer registered images is not kept.
    min_model_size: int = 3
    # Read the points' colours from the images when writing the models.
    extract_colors: bool = True
    # Continuing a model (--input_path): hold its images' poses constant.
    fix_existing_images: bool = False
    # Every snapshot_frames_freq registered images, write the model to a new folder of
    # snapshot_path (COLMAP's snapshots); 0: never.
    snapshot_path: str = ""
    snapshot_frames_freq: int = 0
    # RANSAC seed: with one, two runs give the same model bit for bit; None: unseeded.
    seed: int | None = None
    # Threads of the descriptor searches and of pycolmap's Ceres; -1: every core.
    num_threads: int = -1

    def threads(self) -> int:
        """The threads to use: num_threads, or every core this process may run on (-1)."""
        if self.num_threads > 0:
            return self.num_threads
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else os.cpu_count() or 1

    def components(self) -> dict[str, object]:
        """The component options by field name."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if hasattr(getattr(self, f.name), "check")}

    def check(self) -> None:
        """An OptionError (a ValueError) naming the first option out of its range."""
        for name, component in self.components().items():
            try:
                component.check()
            except OptionError as exc:
                raise OptionError(f"{name}.{exc.path}", str(exc)) from None
        _require(self.max_num_models >= 1, self, "max_num_models", ">= 1")
        _require(self.min_model_size >= 0, self, "min_model_size", ">= 0")
        _require(self.snapshot_frames_freq >= 0, self, "snapshot_frames_freq", ">= 0")
        _require(self.seed is None or self.seed >= 0, self, "seed", "None or >= 0")
        _require(self.num_threads == -1 or self.num_threads >= 1, self, "num_threads",
                 "-1 or >= 1")
