"""Every option of `colmap mapper`, in one table: COLMAP 3.8's flags (`colmap mapper -h`)
and 4.x's (the fields of `pycolmap.IncrementalPipelineOptions`, its `mapper` and
`triangulation`), under COLMAP's names.

The command-line flags, the keys of a `--project_path` file and the reading of a
pycolmap options object all come from `FLAGS`. An option either sets a field of
`MapperOptions` (its default is that field's), or does not apply to this mapper: it is
accepted, and a value other than its default is named once in the log with the reason.
"""

from __future__ import annotations

import argparse
import copy
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from colmap_ext.errors import UserError
from colmap_ext.mapper.options import MapperOptions, OptionError

logger = logging.getLogger(__name__)

# Command-line arguments and top-level project-file keys that are paths, not options.
PATH_KEYS = ("database_path", "image_path", "input_path", "output_path", "image_list_path")
# COLMAP 4's names of those paths among its mapper options (flag or [Mapper] key).
PATH_ALIASES = {"Mapper.image_list_path": "image_list_path"}


def boolean(text: str) -> bool:
    """COLMAP's booleans: 1/0, true/false (any case)."""
    value = {"1": True, "true": True, "0": False, "false": False}.get(text.strip().lower())
    if value is None:
        raise ValueError(f"expected 0, 1, true or false, got {text!r}")
    return value


# What the library underneath takes for an integer option (a C int: threads, iterations, the seed).
INT32_RANGE = (-2**31, 2**31 - 1)


def int32(text: str) -> int:
    """An integer within a C int."""
    value = int(text)
    low, high = INT32_RANGE
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"expected an integer from {low} to {high}, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A number, neither infinite nor NaN (thresholds and ratios)."""
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def random_seed(text: str) -> int:
    """A RANSAC seed: 0 to the largest C int (pycolmap's random_seed)."""
    value = int32(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a seed from 0 to {INT32_RANGE[1]}, "
                                         f"got {text!r}")
    return value


def shown(value: Any) -> Any:
    """A value as COLMAP prints it: booleans as 0/1."""
    return int(value) if isinstance(value, bool) else value


def _seed(value: int) -> int | None:
    return None if value < 0 else value


def _iterations(value: int) -> int | None:
    return None if value <= 0 else value  # COLMAP 4.x: -1 is the solver's default


def _id_list(kind: str) -> Callable[[str], tuple[int, ...]]:
    """The reader of a file of `kind` ids ("camera", "rig"), one per line, as COLMAP 4
    reads them; "": none."""
    def read(path: str) -> tuple[int, ...]:
        if not path:
            return ()
        try:
            lines = [line.strip() for line in Path(path).read_text().splitlines()]
        except (OSError, UnicodeDecodeError) as exc:
            raise UserError(f"cannot read {kind} list {path}: "
                            f"{getattr(exc, 'strerror', None) or exc}") from None
        try:
            return tuple(int(line) for line in lines if line)
        except ValueError:
            raise UserError(f"{kind} list {path}: expected one {kind} id per line") from None
    return read


@dataclass(frozen=True)
class Flag:
    name: str  # COLMAP's: "random_seed" (top level) or "Mapper.<key>"
    type: type  # int, float, bool or str
    pycolmap: str | None  # its attribute in IncrementalPipelineOptions; None: COLMAP 3.8 only,
    # or a list file whose contents pycolmap takes as a set (constant_cameras)
    field: str | None = None  # the MapperOptions field it sets; None: not applicable
    help: str = ""  # what it does here (applied) or why it does not apply
    default: Any = None  # not applicable: the value that asks for nothing we do not do
    aliases: tuple[str, ...] = ()  # the same option's name in other COLMAP versions or ours
    convert: Callable[[Any], Any] | None = None  # COLMAP's value -> the field's; None keeps ours

    @property
    def names(self) -> tuple[str, ...]:
        return (self.name, *self.aliases)

    def effective_default(self, base: MapperOptions | None = None) -> Any:
        """The value used when the option is not given, over `base` (default: MapperOptions())."""
        if self.field is None:
            return self.default
        return get_field(base or MapperOptions(), self.field)

    @property
    def parse(self) -> Callable[[str], Any]:
        """The option's value from its text (command line or project file)."""
        return {bool: boolean, int: int32, float: finite_float}.get(self.type, self.type)


# Options that refine the intrinsics; off unless asked for on the command line or in
# MapperOptions.
INTRINSICS_REFINEMENT = ("Mapper.ba_refine_focal_length", "Mapper.ba_refine_principal_point",
                         "Mapper.ba_refine_extra_params", "Mapper.ba_refine_sensor_from_rig")
# Reasons shared by several options.
_INTRINSICS = ("the intrinsics (and a rig's calibration) are known and held constant, as the "
               "method assumes")
_BOUNDS = ("the intrinsics are known; refined ones (--Mapper.ba_refine_*) are not checked "
           "against bounds")
_TRIANGULATOR = ("points come from the method's guided matching (features compatible in at "
                 "least three images), not from COLMAP's triangulator")
_BA_SCHEDULE = ("global adjustment runs whenever the model grows by --Mapper.ba_global_frames_"
                "ratio or --Mapper.ba_global_frames_freq, each adjustment followed by filtering")
_GPU = "bundle adjustment runs on the CPU (ours, and pycolmap's Ceres)"
_NO_PRIORS = "position priors are not used"


def _na(name: str, type_: type, pycolmap: str | None, default: Any, reason: str,
        aliases: tuple[str, ...] = ()) -> Flag:
    return Flag(name, type_, pycolmap, help=reason, default=default, aliases=aliases)


FLAGS: tuple[Flag, ...] = (
    # ---- top level
    Flag("random_seed", int, "random_seed", "seed", "RANSAC seed; -1: unseeded. With a seed, "
         "two runs give the same model bit for bit", aliases=("Mapper.random_seed", "seed"),
         convert=_seed),
    _na("log_to_stderr", bool, None, False, "log lines always go to stderr"),
    _na("log_level", int, None, 2, "COLMAP's glog verbosity; this mapper logs progress and "
        "a summary"),
    # ---- the pipeline (IncrementalPipelineOptions)
    Flag("Mapper.min_num_matches", int, "min_num_matches", "two_view.min_num_inliers",
         "verified matches an image pair needs to be used"),
    _na("Mapper.ignore_watermarks", bool, "ignore_watermarks", False,
        "the database's verified matches are used as they are"),
    Flag("Mapper.multiple_models", bool, "multiple_models", "multiple_models",
         "start new models from the images left over; 0: keep only the first model"),
    Flag("Mapper.max_num_models", int, "max_num_models", "max_num_models",
         "most models reconstructed"),
    _na("Mapper.max_model_overlap", int, "max_model_overlap", 20,
        "models share no images; models that fell apart are joined where two images agree"),
    Flag("Mapper.min_model_size", int, "min_model_size", "min_model_size",
         "fewest registered images a model needs to be kept"),
    Flag("Mapper.init_image_id1", int, "init_image_id1", "initialization.image_id1",
         "first image of the initial pair; -1: the mapper chooses"),
    Flag("Mapper.init_image_id2", int, "init_image_id2", "initialization.image_id2",
         "second image of the initial pair; -1: the mapper chooses"),
    _na("Mapper.init_num_trials", int, "init_num_trials", 200,
        "every candidate pair is tried once; a pair that fails is not tried again"),
    _na("Mapper.structure_less_registration_fallback", bool,
        "structure_less_registration_fallback", True,
        "images register by P3P on 2D-3D correspondences only"),
    _na("Mapper.structure_less_registration_only", bool, "structure_less_registration_only",
        False, "images register by P3P on 2D-3D correspondences only"),
    Flag("Mapper.extract_colors", bool, "extract_colors", "extract_colors",
         "read the points' colours from the images"),
    Flag("Mapper.num_threads", int, "num_threads", "num_threads",
         "threads (Ceres, BLAS); -1: all cores", aliases=("num_threads",)),
    _na("Mapper.min_focal_length_ratio", float, "min_focal_length_ratio", 0.1, _BOUNDS),
    _na("Mapper.max_focal_length_ratio", float, "max_focal_length_ratio", 10.0, _BOUNDS),
    _na("Mapper.max_extra_param", float, "max_extra_param", 1.0, _BOUNDS),
    Flag("Mapper.ba_refine_focal_length", bool, "ba_refine_focal_length",
         "bundle_adjustment.refine_focal_length", "refine the focal length in global "
         "adjustments; 0: known and constant, as the method assumes"),
    Flag("Mapper.ba_refine_principal_point", bool, "ba_refine_principal_point",
         "bundle_adjustment.refine_principal_point", "refine the principal point in global "
         "adjustments; 0: known and constant, as the method assumes"),
    Flag("Mapper.ba_refine_extra_params", bool, "ba_refine_extra_params",
         "bundle_adjustment.refine_extra_params", "refine the extra params in global "
         "adjustments; 0: known and constant, as the method assumes"),
    Flag("Mapper.ba_refine_sensor_from_rig", bool, "ba_refine_sensor_from_rig",
         "bundle_adjustment.refine_sensor_from_rig", "refine the poses of a rig's cameras "
         "relative to the rig; 0: the calibrated rig is held constant"),
    Flag("Mapper.constant_rig_list_path", str, None, "bundle_adjustment.constant_rig_ids",
         "file of rig ids, one per line, whose cameras' poses in the rig stay constant when "
         "--Mapper.ba_refine_sensor_from_rig refines the others", convert=_id_list("rig")),
    Flag("Mapper.constant_camera_list_path", str, None, "bundle_adjustment.constant_camera_ids",
         "file of camera ids, one per line, whose intrinsics stay constant when "
         "--Mapper.ba_refine_* refines the others", convert=_id_list("camera")),
    Flag("Mapper.ba_min_num_residuals_for_cpu_multi_threading", int,
         "ba_min_num_residuals_for_cpu_multi_threading",
         "bundle_adjustment.min_num_residuals_for_multi_threading",
         "bundle adjustments with fewer residuals run on one thread",
         aliases=("Mapper.ba_min_num_residuals_for_multi_threading",)),
    Flag("Mapper.ba_local_num_images", int, "mapper.ba_local_num_images",
         "bundle_adjustment.local_num_images", "images in a local bundle adjustment: the new one and its "
         "most connected registered images"),
    _na("Mapper.ba_local_function_tolerance", float, "ba_local_function_tolerance", 0.0,
        "local and global adjustment share --Mapper.ba_global_function_tolerance"),
    Flag("Mapper.ba_local_max_num_iterations", int, "ba_local_max_num_iterations",
         "bundle_adjustment.local_max_iterations", "iterations of a local adjustment; -1: ours",
         convert=_iterations),
    Flag("Mapper.ba_global_frames_ratio", float, "ba_global_frames_ratio",
         "bundle_adjustment.global_images_ratio", "global adjustment whenever the model has grown by this "
         "ratio", aliases=("Mapper.ba_global_images_ratio",)),
    _na("Mapper.ba_global_points_ratio", float, "ba_global_points_ratio", 1.1, _BA_SCHEDULE),
    Flag("Mapper.ba_global_frames_freq", int, "ba_global_frames_freq",
         "bundle_adjustment.global_images_freq", "global adjustment also whenever the model has "
         "grown by this many images", aliases=("Mapper.ba_global_images_freq",)),
    _na("Mapper.ba_global_points_freq", int, "ba_global_points_freq", 250000, _BA_SCHEDULE),
    Flag("Mapper.ba_global_function_tolerance", float, "ba_global_function_tolerance",
         "bundle_adjustment.function_tolerance", "an adjustment stops when an iteration lowers the cost by less "
         "than this fraction (local and global adjustment); 0: at the iteration limit"),
    Flag("Mapper.ba_global_max_num_iterations", int, "ba_global_max_num_iterations",
         "bundle_adjustment.global_max_iterations", "iterations of a global adjustment; -1: ours",
         convert=_iterations),
    _na("Mapper.ba_global_max_refinements", int, "ba_global_max_refinements", 5, _BA_SCHEDULE),
    _na("Mapper.ba_global_max_refinement_change", float, "ba_global_max_refinement_change",
        0.0005, _BA_SCHEDULE),
    _na("Mapper.ba_local_max_refinements", int, "ba_local_max_refinements", 2, _BA_SCHEDULE),
    _na("Mapper.ba_local_max_refinement_change", float, "ba_local_max_refinement_change",
        0.001, _BA_SCHEDULE),
    _na("Mapper.ba_use_gpu", bool, "ba_use_gpu", False, _GPU),
    _na("Mapper.ba_gpu_index", str, "ba_gpu_index", "-1", _GPU),
    _na("Mapper.ba_global_use_pba", bool, None, False, _GPU),
    _na("Mapper.ba_global_pba_gpu_index", int, None, -1, _GPU),
    _na("Mapper.ba_local_backend", str, "ba_local_backend", "CERES", _GPU),
    _na("Mapper.ba_global_backend", str, "ba_global_backend", "CERES", _GPU),
    _na("Mapper.use_prior_position", bool, "use_prior_position", False, _NO_PRIORS),
    _na("Mapper.use_robust_loss_on_prior_position", bool, "use_robust_loss_on_prior_position",
        False, _NO_PRIORS),
    _na("Mapper.prior_position_loss_scale", float, "prior_position_loss_scale", 7.815,
        _NO_PRIORS),
    Flag("Mapper.snapshot_path", str, "snapshot_path", "snapshot_path",
         "folder that gets a snapshot of the model every --Mapper.snapshot_frames_freq "
         "registered images"),
    Flag("Mapper.snapshot_frames_freq", int, "snapshot_frames_freq", "snapshot_frames_freq",
         "registered images between snapshots; 0: none",
         aliases=("Mapper.snapshot_images_freq",)),
    _na("Mapper.load_all_images", bool, "load_all_images", False,
        "a model holds its registered images"),
    Flag("Mapper.fix_existing_frames", bool, "fix_existing_frames", "fix_existing_images",
         "hold the poses of the --input_path model's images constant",
         aliases=("Mapper.fix_existing_images",)),
    _na("Mapper.max_runtime_seconds", int, "max_runtime_seconds", -1,
        "the mapper runs to the end"),
    # ---- the incremental mapper (IncrementalPipelineOptions.mapper)
    Flag("Mapper.init_min_num_inliers", int, "mapper.init_min_num_inliers",
         "initialization.min_num_inliers", "inliers the initial pair's relative pose needs"),
    Flag("Mapper.init_max_error", float, "mapper.init_max_error", "two_view.max_error_px",
         "error threshold (px) of the 5-point RANSAC: initial pair and pairs the database "
         "left unverified"),
    _na("Mapper.init_max_forward_motion", float, "mapper.init_max_forward_motion", 0.95,
        "the initial pair is judged by the median angle of its rays "
        "(--Mapper.init_min_tri_angle)"),
    Flag("Mapper.init_min_tri_angle", float, "mapper.init_min_tri_angle",
         "initialization.min_tri_angle_deg", "median triangulation angle (deg) the initial pair needs"),
    _na("Mapper.init_max_reg_trials", int, "mapper.init_max_reg_trials", 2,
        "a pair that fails to initialise is not tried again"),
    Flag("Mapper.abs_pose_max_error", float, "mapper.abs_pose_max_error",
         "registration.abs_pose_max_error_px", "reprojection threshold (px) of the P3P RANSAC"),
    Flag("Mapper.abs_pose_min_num_inliers", int, "mapper.abs_pose_min_num_inliers",
         "registration.abs_pose_min_num_inliers", "P3P inliers an image needs to register"),
    Flag("Mapper.abs_pose_min_inlier_ratio", float, "mapper.abs_pose_min_inlier_ratio",
         "registration.abs_pose_min_inlier_ratio", "P3P inlier ratio an image needs to register"),
    _na("Mapper.abs_pose_refine_focal_length", bool, "mapper.abs_pose_refine_focal_length",
        False, _INTRINSICS),
    _na("Mapper.abs_pose_refine_extra_params", bool, "mapper.abs_pose_refine_extra_params",
        False, _INTRINSICS),
    _na("Mapper.ba_local_min_tri_angle", float, "mapper.ba_local_min_tri_angle", 6.0,
        "a local adjustment takes the new image's most connected images",
        aliases=("Mapper.local_ba_min_tri_angle",)),
    _na("Mapper.ba_global_ignore_redundant_points3D", bool,
        "mapper.ba_global_ignore_redundant_points3D", False, "every point is adjusted"),
    _na("Mapper.ba_global_prune_points_min_coverage_gain", float,
        "mapper.ba_global_prune_points_min_coverage_gain", 0.05, "every point is adjusted",
        aliases=("Mapper.ba_global_ignore_redundant_points3D_min_coverage_gain",)),
    Flag("Mapper.filter_max_reproj_error", float, "mapper.filter_max_reproj_error",
         "filtering.max_reproj_error_px", "reprojection error (px) within which an "
         "observation is kept"),
    Flag("Mapper.filter_min_tri_angle", float, "mapper.filter_min_tri_angle",
         "filtering.min_tri_angle_deg", "angle (deg) a point needs between its widest rays "
         "to be kept"),
    Flag("Mapper.max_reg_trials", int, "mapper.max_reg_trials", "registration.max_trials",
         "times a failed image is tried again as the model grows"),
    _na("Mapper.image_selection_method", str, "mapper.image_selection_method",
        "MIN_UNCERTAINTY", "the registration order is --order"),
    # ---- the triangulator (IncrementalPipelineOptions.triangulation)
    _na("Mapper.tri_max_transitivity", int, "triangulation.max_transitivity", 1, _TRIANGULATOR),
    _na("Mapper.tri_create_max_angle_error", float, "triangulation.create_max_angle_error",
        2.0, _TRIANGULATOR),
    _na("Mapper.tri_continue_max_angle_error", float, "triangulation.continue_max_angle_error",
        2.0, _TRIANGULATOR),
    _na("Mapper.tri_merge_max_reproj_error", float, "triangulation.merge_max_reproj_error",
        4.0, _TRIANGULATOR),
    _na("Mapper.tri_complete_max_reproj_error", float,
        "triangulation.complete_max_reproj_error", 4.0, _TRIANGULATOR),
    _na("Mapper.tri_complete_max_transitivity", int, "triangulation.complete_max_transitivity",
        5, _TRIANGULATOR),
    _na("Mapper.tri_re_max_angle_error", float, "triangulation.re_max_angle_error", 5.0,
        _TRIANGULATOR),
    _na("Mapper.tri_re_min_ratio", float, "triangulation.re_min_ratio", 0.2, _TRIANGULATOR),
    _na("Mapper.tri_re_max_trials", int, "triangulation.re_max_trials", 1, _TRIANGULATOR),
    Flag("Mapper.tri_min_angle", float, "triangulation.min_angle",
         "triangulation.min_tri_angle_deg", "angle (deg) a new point needs between its "
         "widest rays"),
    _na("Mapper.tri_ignore_two_view_tracks", bool, "triangulation.ignore_two_view_tracks",
        True, "a point needs compatible features in at least three images"),
)

# Every accepted name (COLMAP 3.8's, 4.x's, ours) -> its option.
BY_NAME: dict[str, Flag] = {name: flag for flag in FLAGS for name in flag.names}


def lookup(name: str) -> Flag:
    """The option called `name`; a UserError, as COLMAP's, for a name it does not have."""
    flag = BY_NAME.get(name)
    if flag is None:
        raise UserError(f"unrecognised option '{name}'")
    return flag


def get_field(options: MapperOptions, path: str) -> Any:
    """The value of a field of MapperOptions or of its components ("registration.order")."""
    value: Any = options
    for name in path.split("."):
        value = getattr(value, name)
    return value


def mapper_options(values: dict[str, Any], base: MapperOptions | None = None) -> MapperOptions:
    """A copy of `base` (default: MapperOptions()) with the option values by name (parsed,
    any accepted name) applied and checked. Each not-applicable option given another value
    than its default is named once in the log."""
    options = copy.deepcopy(base or MapperOptions())
    for name, value in values.items():
        flag = lookup(name)
        if flag.field is not None:
            value = flag.convert(value) if flag.convert else value
            if value is not None:
                *components, field_name = flag.field.split(".")
                setattr(get_field(options, ".".join(components)) if components else options,
                        field_name, value)
        elif value != flag.default:
            logger.warning("colmap-ext: --%s %s: not applicable: %s", flag.name, shown(value),
                           flag.help)
    refined = [name.removeprefix("refine_").replace("_", " ")
               for name in ("refine_focal_length", "refine_principal_point", "refine_extra_params",
                            "refine_sensor_from_rig")
               if getattr(options.bundle_adjustment, name)]
    if refined:
        logger.warning("colmap-ext: refining the %s in global bundle adjustment, as asked "
                       "(the method assumes the intrinsics known)", " and ".join(refined))
    try:
        options.check()
    except OptionError as exc:
        given = [name for name in values if lookup(name).field == exc.path]
        raise UserError(f"--{lookup(given[0]).name} {shown(values[given[0]])}: {exc}"
                        if given else str(exc)) from None
    return options


def read_project(path: str | Path) -> tuple[dict[str, Any], dict[str, str]]:
    """A COLMAP project file (`colmap project_generator`, the GUI): its option values by
    name, parsed, and its paths. Other sections than [Mapper] configure other commands
    and are skipped; an unknown key or a bad value in ours is a UserError."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read project file {path}: "
                        f"{getattr(exc, 'strerror', None) or exc}") from None
    values: dict[str, Any] = {}
    paths: dict[str, str] = {}
    section = ""
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}, line {number}"
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1].strip()
            continue
        if section not in ("", "Mapper"):
            continue
        key, sep, text = (part.strip() for part in line.partition("="))
        if not sep:
            raise UserError(f"{where}: expected key=value, got '{line}'")
        name = f"{section}.{key}" if section else key
        if (section == "" and key in PATH_KEYS) or name in PATH_ALIASES:
            if text:
                paths[PATH_ALIASES.get(name, key)] = text
            continue
        flag = BY_NAME.get(name)
        if flag is None:
            raise UserError(f"{where}: unrecognised option '{name}'")
        try:
            values[name] = flag.parse(text)
        except (ValueError, argparse.ArgumentTypeError):
            raise UserError(f"{where}: invalid value '{text}' for option '{name}'") from None
    return values, paths


def pycolmap_values(options: Any) -> dict[str, Any]:
    """The option values of a `pycolmap.IncrementalPipelineOptions`, by name."""
    values = {}
    for flag in FLAGS:
        if flag.pycolmap is None:
            continue
        value = options
        for attribute in flag.pycolmap.split("."):
            value = getattr(value, attribute)
        if isinstance(value, Path):  # pycolmap's unset path is Path(".")
            value = "" if value == Path(".") else str(value)
        values[flag.name] = getattr(value, "name", value)  # enums by name, as COLMAP's CLI
    return values


def pycolmap_options(options: Any) -> MapperOptions:
    """MapperOptions from a `pycolmap.IncrementalPipelineOptions`. Its intrinsics and rig
    refinement (on by pycolmap's default, which cannot be told from a request) is not
    applied, and named in the log: the intrinsics are known. To refine them, set
    MapperOptions.bundle_adjustment.refine_* (or pass --Mapper.ba_refine_* 1)."""
    values = pycolmap_values(options)
    for name in INTRINSICS_REFINEMENT:
        if values.pop(name):
            logger.warning("colmap-ext: --%s 1: not applied from pycolmap's options: %s",
                           name, _INTRINSICS)
    return mapper_options(values)


def help_text(flag: Flag, base: MapperOptions | None = None) -> str:
    """The option's `-h` line: what it does here or why it does not apply, and its
    default over `base` (the command's defaults; MapperOptions() when None)."""
    default = flag.effective_default(base)
    if default is None:  # the seed: unseeded, COLMAP 4.x's -1
        default = -1
    elif isinstance(default, tuple):  # ids read from a list file: none unless `base` has some
        default = ",".join(map(str, default))
    text = flag.help if flag.field else f"not applicable: {flag.help}"
    return f"{text} (default: {shown(default)})"
