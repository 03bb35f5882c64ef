"""Bundle adjustment through pycolmap (Ceres): intrinsics constant unless a global
adjustment is asked to refine them (BundleAdjustmentOptions.refine_*), the rigs'
`sensor_from_rig` constant unless BundleAdjustmentOptions.refine_sensor_from_rig.

Each adjustment is a BundleAdjustmentConfig solved on the model's pycolmap.Reconstruction
in place (model.py); a solve that fails puts back what it changed.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import BundleAdjustmentOptions


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
    ba_options.ceres.solver_options.function_tolerance = \
        ba.least_squares_function_tolerance if (loss or ba.loss) == "trivial" \
        else ba.function_tolerance
    ba_options.ceres.solver_options.num_threads = num_threads
    ba_options.ceres.min_num_residuals_for_cpu_multi_threading = \
        ba.min_num_residuals_for_multi_threading
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


def bundle_adjust(model: Model, image_ids: list[int], ba: BundleAdjustmentOptions,
                  local: bool, num_threads: int, refine_intrinsics: bool = False,
                  loss: str | None = None, loss_scale_px: float | None = None) -> int:
    """Adjust, on the model's reconstruction in place, the frame poses of `image_ids`
    (except the model's fixed frames) and the points they observe, as COLMAP's
    adjustments do: a point seen by at most BundleAdjustmentOptions.local_max_track_length
    images brings its other observations in, their poses constant; a longer track is
    already well determined and enters through the observations of `image_ids` alone,
    held constant where they are just one; the rigs and the gauge as
    `hold_rigs_and_fix_gauge` says; Ceres's limits are the options' local_* or global_*
    ones. With `refine_intrinsics`, the intrinsics the options name are refined
    too, but for the cameras in BundleAdjustmentOptions.constant_camera_ids; `loss` and
    `loss_scale_px` replace the options' robust loss and its scale. Returns the number of
    Ceres iterations."""
    reconstruction = model.reconstruction
    requested = {i for image_id in image_ids for i in model.frame_images(image_id)}
    refine_intrinsics = refine_intrinsics and ba.refines_intrinsics
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(requested):
        config.add_image(image_id)
    fixed = {i for i in requested if model.frame_id(i) in model.fixed_frame_ids}
    for frame_id in {model.frame_id(i) for i in fixed}:
        config.set_constant_rig_from_world_pose(frame_id)
    for camera_id in reconstruction.cameras:
        if not refine_intrinsics or camera_id in ba.constant_camera_ids:
            config.set_constant_cam_intrinsics(camera_id)

    if len(requested) == model.num_registered:
        # A global adjustment: the images hold every observation of every point.
        variable_point_ids, outside = model.point_ids, set()
    else:
        variable_point_ids, outside = _add_local_points(model, requested, config,
                                                        ba.local_max_track_length)
    constant = {model.frame_id(i) for i in (outside - requested) | fixed}
    hold_rigs_and_fix_gauge(config, reconstruction,
                            [i for i in model.registration_order if i in requested], constant, ba)

    ba_options = adjustment_options(ba, local, num_threads, refine_intrinsics,
                                    loss=loss, loss_scale_px=loss_scale_px)
    frame_ids = {model.frame_id(i) for i in requested - fixed}
    before = _variables(reconstruction, frame_ids)
    summary = pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()
    if not summary.is_solution_usable():
        # Not solved (e.g. COLMAP could not fix the gauge): the model stays as it was (the
        # points' positions before the solve are model.xyz's).
        _restore(reconstruction, *before)
        for point_id in variable_point_ids:
            reconstruction.points3D[point_id].xyz = model.xyz[point_id]
        return 0
    model.refresh_points(variable_point_ids)
    if refine_intrinsics:
        model.refresh_cameras()
    return summary.ceres_summary.num_successful_steps + summary.ceres_summary.num_unsuccessful_steps


def hold_rigs_and_fix_gauge(config: pycolmap.BundleAdjustmentConfig,
                            reconstruction: pycolmap.Reconstruction, image_ids: list[int],
                            constant_frame_ids: set[int], ba: BundleAdjustmentOptions) -> None:
    """Hold the rigs' sensor_from_rig constant (unless refine_sensor_from_rig, but for
    constant_rig_ids), and fix the gauge of an adjustment of `image_ids` whose frames
    `constant_frame_ids` are held: where a frame holds two cameras of a constant rig at
    different centres, the rig's baseline gives the scale and one constant frame (the
    first image's) is enough; two cameras would fix the scale to whatever the model had.
    Otherwise two constant frames, or two cameras."""
    constant_rigs = {rig_id for rig_id in reconstruction.rigs
                     if not ba.refine_sensor_from_rig or rig_id in ba.constant_rig_ids}
    for rig_id in constant_rigs:
        for sensor_id in reconstruction.rigs[rig_id].non_ref_sensors:
            config.set_constant_sensor_from_rig_pose(sensor_id)
    frames = [reconstruction.frames[reconstruction.images[i].frame_id] for i in image_ids]
    if any(frame.rig_id in constant_rigs and _has_baseline(reconstruction, frame)
           for frame in frames):
        if not constant_frame_ids and frames:
            config.set_constant_rig_from_world_pose(frames[0].frame_id)
    elif len(constant_frame_ids) < 2:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)


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


def _add_local_points(model: Model, image_ids: set[int], config: pycolmap.BundleAdjustmentConfig,
                      max_track_length: int) -> tuple[list[int], set[int]]:
    """Add the points of a local adjustment's images to `config` by COLMAP's rule (see
    bundle_adjust). Returns the variable points and the images their tracks reach."""
    point_ids = np.unique(np.concatenate(
        [model.observations(image_id)[1] for image_id in image_ids]))
    # Every track at once (Model.track_images): reading them point by point through
    # pycolmap costs more than the adjustment's own setup.
    lengths, track_images = model.track_images(point_ids)
    owner = np.repeat(np.arange(len(point_ids)), lengths)
    local_observations = np.bincount(owner, weights=np.isin(track_images, list(image_ids)),
                                     minlength=len(point_ids))
    short = lengths <= max_track_length
    constant = ~short & (local_observations < 2)
    for point_id in point_ids[short].tolist():
        config.add_variable_point(point_id)
    for point_id in point_ids[constant].tolist():
        config.add_constant_point(point_id)
    reached = set(track_images[short[owner]].tolist())
    return point_ids[~constant].tolist(), reached
