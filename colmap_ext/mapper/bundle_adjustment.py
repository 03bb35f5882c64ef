"""Bundle adjustment of the model's pycolmap.Reconstruction in place (model.py).

With the intrinsics and the rigs' `sensor_from_rig` constant, as the method has them,
our calibrated adjuster solves it on the keypoints' rays (solvers.bundle_adjust): one
residual for every camera model, Ceres's losses and stopping rules, and steps lengthened
while the cost falls, which a robust loss's reweighted steps leave to gain. Where a global
adjustment is asked to refine intrinsics (BundleAdjustmentOptions.refine_*) or rigs
(refine_sensor_from_rig), pycolmap's Ceres adjuster, on a BundleAdjustmentConfig. A
solve that fails leaves the model as it was.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pycolmap

import solvers
from colmap_ext.cameras import pixels_from_tangent
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import BundleAdjustmentOptions

UNLIMITED_IMAGES = 2**31 - 1  # images of one adjustment


def adjustment_options(ba: BundleAdjustmentOptions, local: bool, num_threads: int,
                       refine_intrinsics: bool = False, loss: str | None = None,
                       loss_scale_px: float | None = None) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap's options for one adjustment, local or global, with ours: the loss and its
    scale (default: the robust one, BundleAdjustmentOptions.loss and loss_scale_px; least
    squares has its own function tolerance), Ceres's limits (local_* or global_*) and
    threads, and the intrinsics refined only where `refine_intrinsics` and the options ask
    for it."""
    refine = refine_intrinsics and ba.refines_intrinsics
    ba_options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine and ba.refine_focal_length,
        refine_principal_point=refine and ba.refine_principal_point,
        refine_extra_params=refine and ba.refine_extra_params,
        print_summary=False)
    ba_options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType,
                                                  (loss or ba.loss).upper())
    ba_options.ceres.loss_function_scale = loss_scale_px or ba.loss_scale_px
    ba_options.ceres.solver_options.max_num_iterations = \
        ba.local_max_iterations if local else ba.global_max_iterations
    ba_options.ceres.solver_options.gradient_tolerance = \
        ba.local_gradient_tolerance if local else ba.global_gradient_tolerance
    ba_options.ceres.solver_options.initial_trust_region_radius = \
        ba.trust_region_radius(loss or ba.loss, local)
    ba_options.ceres.solver_options.function_tolerance = \
        ba.function_tolerance_for(loss or ba.loss)
    ba_options.ceres.solver_options.num_threads = num_threads
    ba_options.ceres.min_num_residuals_for_cpu_multi_threading = \
        ba.min_num_residuals_for_multi_threading
    # A direct sparse Schur solver at every size, as our own adjuster has: beyond its
    # default 1000 images pycolmap's turns to ITERATIVE_SCHUR, whose conjugate gradients
    # crawl along a long sequence's drift, where the Schur complement is banded and cheap
    # to factorise (BENCHMARKS.md, "Sequences").
    ba_options.ceres.max_num_images_direct_sparse_cpu_solver = UNLIMITED_IMAGES
    return ba_options


def adjust_reconstruction(reconstruction: pycolmap.Reconstruction, ba: BundleAdjustmentOptions,
                          num_threads: int) -> None:
    """Global adjustment, in place, of every registered pose and every point of a
    reconstruction that no Model holds (a joined one): the options' loss and Ceres limits
    (global_*), intrinsics constant, rigs as `hold_rigs_and_fix_gauge` says."""
    config = pycolmap.BundleAdjustmentConfig()
    image_ids = sorted(reconstruction.reg_image_ids())
    for image_id in image_ids:
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    hold_rigs_and_fix_gauge(config, reconstruction, image_ids, set(), ba)
    ba_options = adjustment_options(ba, local=False, num_threads=num_threads)
    pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()


@dataclass
class _Selection:
    """What one adjustment holds: its images (all their observations enter), the points
    they observe, those among them whose every observation enters (the others enter
    through the images' observations alone, and stay constant), and the frames held
    constant."""

    image_ids: set[int]
    point_ids: np.ndarray
    complete_point_ids: np.ndarray
    constant_frame_ids: set[int]


def bundle_adjust(model: Model, image_ids: list[int], ba: BundleAdjustmentOptions,
                  local: bool, num_threads: int, refine_intrinsics: bool = False,
                  loss: str | None = None, loss_scale_px: float | None = None,
                  exact: bool = False) -> int:
    """Adjust, on the model's reconstruction in place, the frame poses of `image_ids`
    (except the model's fixed frames) and the points they observe, as COLMAP's
    adjustments do: a point seen by at most BundleAdjustmentOptions.local_max_track_length
    images brings its other observations in, their poses constant; a longer track is
    already well determined: it enters through the observations of `image_ids` alone
    and stays constant, as every point with observations outside the problem does in
    COLMAP's adjuster; the rigs and the gauge as `hold_rigs_and_fix_gauge` says; the
    limits are the options' local_* or global_* ones; `loss` and `loss_scale_px` replace
    the options' robust loss and its scale. With the intrinsics and rigs constant, as the
    method has them, our calibrated adjuster solves it (solvers.bundle_adjust); pycolmap's
    Ceres adjuster where the options refine intrinsics (`refine_intrinsics`, but for
    BundleAdjustmentOptions.constant_camera_ids) or rigs, and where `exact`: ours
    minimises the reprojection errors to first order, whose optimum can lie a hundredth
    of a degree away along a direction the errors hardly fix; the finished model's
    adjustments, whose optimum is the answer, take the camera model's own.
    Returns the number of iterations."""
    requested = {i for image_id in image_ids for i in model.frame_images(image_id)}
    fixed = {i for i in requested if model.frame_id(i) in model.fixed_frame_ids}
    if len(requested) == model.num_registered:
        # A global adjustment: the images hold every observation of every point.
        point_ids = np.array(model.point_ids, np.int64)
        selection = _Selection(requested, point_ids, point_ids,
                               {model.frame_id(i) for i in fixed})
    else:
        selection = _local_selection(model, requested, fixed, ba.local_max_track_length)
    ordered = [i for i in model.registration_order if i in requested]
    loss, loss_scale_px = loss or ba.loss, loss_scale_px or ba.loss_scale_px
    if exact or (refine_intrinsics and ba.refines_intrinsics) or ba.refine_sensor_from_rig:
        return _adjust_with_ceres(model, selection, ordered, ba, local, num_threads,
                                  refine_intrinsics, loss, loss_scale_px)
    return _adjust_calibrated(model, selection, ordered, ba, local, num_threads, loss,
                              loss_scale_px)


def _adjust_calibrated(model: Model, selection: _Selection, ordered: list[int],
                       ba: BundleAdjustmentOptions, local: bool, num_threads: int, loss: str,
                       loss_scale_px: float) -> int:
    """bundle_adjust with solvers.bundle_adjust, on the keypoints' rays."""
    reconstruction = model.reconstruction
    # Every observation of the points the images observe lies in this span: their
    # tracks, whole, and the other images' observations of them.
    flat = model.observed_flat(model.flat_span(selection.point_ids, selection.image_ids))
    observed_images = model.image_of_flat[flat]
    observed_points = model.point_of_flat[flat]
    track_lengths = np.bincount(observed_points, minlength=len(model.xyz))
    lookup_size = max(model.image_ids) + 1
    in_images = np.zeros(lookup_size, bool)
    in_images[list(selection.image_ids)] = True
    complete = np.zeros(len(model.xyz), bool)
    complete[selection.complete_point_ids] = True
    keep = in_images[observed_images] | complete[observed_points]
    flat, observed_images, observed_points = (flat[keep], observed_images[keep],
                                              observed_points[keep])
    image_ids, image_index = np.unique(observed_images, return_inverse=True)
    point_ids, point_index = np.unique(observed_points, return_inverse=True)
    rays = model.rays_flat[flat]
    # The Jacobians camera by camera: they depend on the camera and the ray alone.
    camera_ids = np.array([model.db.images[i].camera_id for i in image_ids.tolist()])
    observed_cameras = camera_ids[image_index]
    jacobians = np.zeros((len(flat), 2, 3))
    for camera_id in np.unique(camera_ids).tolist():
        at = observed_cameras == camera_id
        jacobians[at] = pixels_from_tangent(model.reconstruction.cameras[camera_id], rays[at])
    frame_ids = [model.frame_id(image_id) for image_id in image_ids.tolist()]
    frame_order = sorted(set(frame_ids))
    position = {frame_id: index for index, frame_id in enumerate(frame_order)}
    frame_index = np.array([position[f] for f in frame_ids], np.int32)
    frames = reconstruction.frames
    rigs_from_world = [frames[f].rig_from_world for f in frame_order]
    free = np.zeros((len(frame_order), 6), bool)
    requested_frames = {model.frame_id(i) for i in selection.image_ids}
    for index, frame_id in enumerate(frame_order):
        free[index] = frame_id in requested_frames and \
            frame_id not in selection.constant_frame_ids
    # The gauge from the images the problem holds (a frame left without observations,
    # as filtering can leave one at a model's end, has no row and stays as it is).
    observed = [i for i in ordered if model.frame_id(i) in position]
    held, two_cams = _gauge(reconstruction, observed, selection.constant_frame_ids, ba)
    for frame_id in held:
        free[position[frame_id]] = False
    if two_cams:
        _hold_scale(model, observed, position, free, rigs_from_world)
    # A point with observations outside the problem stays constant.
    constant = np.bincount(observed_points, minlength=len(model.xyz)) < track_lengths

    max_iterations, gradient_tolerance = (
        (ba.local_max_iterations, ba.local_gradient_tolerance) if local
        else (ba.global_max_iterations, ba.global_gradient_tolerance))
    try:
        result = solvers.bundle_adjust(
            rigs_from_world, free, [model.cam_from_rig(i) for i in image_ids.tolist()],
            frame_index, model.xyz[point_ids], ~constant[point_ids], image_index,
            point_index, rays, jacobians, loss=loss, loss_scale=loss_scale_px,
            max_iterations=max_iterations, gradient_tolerance=gradient_tolerance,
            function_tolerance=ba.function_tolerance_for(loss), max_step_scale=ba.max_step_scale,
            initial_trust_region_radius=ba.trust_region_radius(loss, local),
            num_threads=num_threads if 2 * len(flat) >= ba.min_num_residuals_for_multi_threading
            else 1)
    except solvers.EstimationError:
        return 0  # nothing was changed
    for index, frame_id in enumerate(frame_order):
        if free[index].any():
            frames[frame_id].rig_from_world = result.rigs_from_world[index]
    variable = ~constant[point_ids]
    model.move_points(point_ids[variable], result.points3D[variable])
    return result.iterations


def _hold_scale(model: Model, image_ids: Iterable[int], position: dict[int, int],
                free: np.ndarray, rigs_from_world: list[pycolmap.Rigid3d]) -> None:
    """COLMAP's TWO_CAMS_FROM_WORLD gauge on `free` (a row per frame, at `position`):
    the first image's frame (by image id; a constant frame if there is one) constant,
    and of the next frame's translation the coordinate along which it lies farthest from
    the first, in the first frame's axes."""
    frames = list(dict.fromkeys(position[model.frame_id(i)] for i in sorted(image_ids)))
    if not frames:
        return
    held = [i for i in frames if not free[i].any()]
    first = held[0] if held else frames[0]
    free[first] = False
    for second in frames:
        if second == first or not free[second].any():
            continue
        baseline = (rigs_from_world[first] * rigs_from_world[second].inverse()).translation
        if np.abs(baseline).max() > 1e-9:
            free[second, 3 + int(np.argmax(np.abs(baseline)))] = False
            return


def _adjust_with_ceres(model: Model, selection: _Selection, ordered: list[int],
                       ba: BundleAdjustmentOptions, local: bool, num_threads: int,
                       refine_intrinsics: bool, loss: str, loss_scale_px: float) -> int:
    """bundle_adjust with pycolmap's Ceres adjuster, intrinsics and rigs as the options say."""
    model.write_points()
    reconstruction = model.reconstruction
    refine_intrinsics = refine_intrinsics and ba.refines_intrinsics
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(selection.image_ids):
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        if not refine_intrinsics or camera_id in ba.constant_camera_ids:
            config.set_constant_cam_intrinsics(camera_id)
    for point_id in selection.complete_point_ids.tolist():
        config.add_variable_point(point_id)  # the others stay constant: see bundle_adjust
    frame_ids = {model.frame_id(i) for i in selection.image_ids}
    for frame_id in selection.constant_frame_ids & frame_ids:
        config.set_constant_rig_from_world_pose(frame_id)
    hold_rigs_and_fix_gauge(config, reconstruction, ordered, selection.constant_frame_ids, ba)

    ba_options = adjustment_options(ba, local, num_threads, refine_intrinsics,
                                    loss=loss, loss_scale_px=loss_scale_px)
    before = _variables(reconstruction, frame_ids - selection.constant_frame_ids)
    summary = pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()
    if not summary.is_solution_usable():
        # Not solved (e.g. COLMAP could not fix the gauge): the model stays as it was (the
        # points' positions before the solve are model.xyz's).
        _restore(reconstruction, *before)
        for point_id in selection.point_ids.tolist():
            reconstruction.points3D[point_id].xyz = model.xyz[point_id]
        return 0
    model.refresh_points(selection.point_ids.tolist())
    if refine_intrinsics:
        model.refresh_cameras()
    return summary.ceres_summary.num_successful_steps + summary.ceres_summary.num_unsuccessful_steps


def hold_rigs_and_fix_gauge(config: pycolmap.BundleAdjustmentConfig,
                            reconstruction: pycolmap.Reconstruction, image_ids: list[int],
                            constant_frame_ids: set[int], ba: BundleAdjustmentOptions) -> None:
    """Hold the rigs' sensor_from_rig constant (unless refine_sensor_from_rig, but for
    constant_rig_ids), and fix the gauge as `_gauge` says."""
    for rig_id in _constant_rigs(reconstruction, ba):
        for sensor_id in reconstruction.rigs[rig_id].non_ref_sensors:
            config.set_constant_sensor_from_rig_pose(sensor_id)
    held, two_cams = _gauge(reconstruction, image_ids, constant_frame_ids, ba)
    for frame_id in held:
        config.set_constant_rig_from_world_pose(frame_id)
    if two_cams:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)


def _constant_rigs(reconstruction: pycolmap.Reconstruction,
                   ba: BundleAdjustmentOptions) -> set[int]:
    return {rig_id for rig_id in reconstruction.rigs
            if not ba.refine_sensor_from_rig or rig_id in ba.constant_rig_ids}


def _gauge(reconstruction: pycolmap.Reconstruction, image_ids: list[int],
           constant_frame_ids: set[int], ba: BundleAdjustmentOptions) -> tuple[list[int], bool]:
    """How an adjustment of `image_ids` (in registration order) whose frames
    `constant_frame_ids` are held fixes its gauge: the frames to hold as well, and
    whether two cameras fix it (COLMAP's TWO_CAMS_FROM_WORLD). Where a frame holds two
    cameras of a constant rig at different centres, the rig's baseline gives the scale
    and one constant frame (the first image's) is enough; two cameras would fix the
    scale to whatever the model had. Otherwise two constant frames, or two cameras."""
    constant_rigs = _constant_rigs(reconstruction, ba)
    frames = [reconstruction.frames[reconstruction.images[i].frame_id] for i in image_ids]
    if any(frame.rig_id in constant_rigs and _has_baseline(reconstruction, frame)
           for frame in frames):
        return ([frames[0].frame_id] if not constant_frame_ids and frames else []), False
    return [], len(constant_frame_ids) < 2


def _has_baseline(reconstruction: pycolmap.Reconstruction, frame: pycolmap.Frame) -> bool:
    """Whether the frame holds two images of cameras at different centres in its rig."""
    rig = reconstruction.rigs[frame.rig_id]
    centres = [np.zeros(3) if rig.is_ref_sensor(data_id.sensor_id)
               else rig.sensor_from_rig(data_id.sensor_id).inverse().translation
               for data_id in frame.image_ids]
    return len(centres) >= 2 and np.ptp(centres, axis=0).max() > 0


def _variables(reconstruction: pycolmap.Reconstruction,
               frame_ids: set[int]) -> tuple[dict, dict, dict]:
    """What a solve may change but the points: frame poses, intrinsics, rig poses."""
    return ({frame_id: reconstruction.frames[frame_id].rig_from_world for frame_id in frame_ids},
            {camera_id: camera.params.copy() for camera_id, camera in reconstruction.cameras.items()},
            {rig_id: dict(rig.non_ref_sensors) for rig_id, rig in reconstruction.rigs.items()})


def _restore(reconstruction: pycolmap.Reconstruction, poses: dict, params: dict,
             sensors: dict) -> None:
    for frame_id, rig_from_world in poses.items():
        reconstruction.frames[frame_id].rig_from_world = rig_from_world
    for camera_id, camera_params in params.items():
        reconstruction.cameras[camera_id].params = camera_params
    for rig_id, sensor_from_rig in sensors.items():
        for sensor, pose in sensor_from_rig.items():
            reconstruction.rigs[rig_id].set_sensor_from_rig(sensor, pose)


def _local_selection(model: Model, image_ids: set[int], fixed: set[int],
                     max_track_length: int) -> _Selection:
    """The points of a local adjustment of `image_ids` by COLMAP's rule (see
    bundle_adjust), and its constant frames: the fixed ones and those the complete
    tracks reach outside the images."""
    point_ids = np.unique(np.concatenate(
        [model.observations(image_id)[1] for image_id in image_ids]))
    # Every track at once (Model.track_images): reading them point by point through
    # pycolmap costs more than the adjustment's own setup.
    lengths, track_images = model.track_images(point_ids)
    short = lengths <= max_track_length
    owner = np.repeat(np.arange(len(point_ids)), lengths)
    reached = set(track_images[short[owner]].tolist())
    return _Selection(image_ids, point_ids, point_ids[short],
                      {model.frame_id(i) for i in (reached - image_ids) | fixed})
