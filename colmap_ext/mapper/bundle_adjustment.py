"""Bundle adjustment through pycolmap (Ceres): intrinsics constant unless a global
adjustment is asked to refine them (BundleAdjustmentOptions.refine_*).

Each adjustment is a BundleAdjustmentConfig solved on the model's own
pycolmap.Reconstruction (model.py); the refined poses and points are then read into
the model's arrays.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from colmap_ext.database import DatabaseContents
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions


def posed_images(db: DatabaseContents, cameras: dict[int, pycolmap.Camera],
                 poses: dict[int, pycolmap.Rigid3d]) -> pycolmap.Reconstruction:
    """A reconstruction of the database's images posed by `poses` (cam_from_world by
    image id, ids kept), with their keypoints and cameras, and no points yet."""
    reconstruction = pycolmap.Reconstruction()
    for camera_id in sorted({db.images[i].camera_id for i in poses}):
        reconstruction.add_camera_with_trivial_rig(cameras[camera_id])
    for image_id, pose in poses.items():
        features = db.images[image_id]
        image = pycolmap.Image(name=features.name, keypoints=features.keypoints,
                               camera_id=features.camera_id, image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pose)
    return reconstruction


def adjustment_options(options: MapperOptions, max_iterations: int,
                       refine_intrinsics: bool = False, num_threads: int | None = None,
                       loss: str | None = None,
                       loss_scale_px: float | None = None) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap's options for one adjustment with ours: the loss and its scale (default:
    the robust one, BundleAdjustmentOptions.loss and loss_scale_px), Ceres's limits and
    threads (default: options.threads()), and the intrinsics refined only where
    `refine_intrinsics` and the options ask for it."""
    ba = options.bundle_adjustment
    refine = refine_intrinsics and ba.refines_intrinsics
    ba_options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine and ba.refine_focal_length,
        refine_principal_point=refine and ba.refine_principal_point,
        refine_extra_params=refine and ba.refine_extra_params,
        print_summary=False)
    ba_options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType,
                                                  (loss or ba.loss).upper())
    ba_options.ceres.loss_function_scale = loss_scale_px or ba.loss_scale_px
    ba_options.ceres.solver_options.max_num_iterations = max_iterations
    ba_options.ceres.solver_options.function_tolerance = ba.function_tolerance
    ba_options.ceres.solver_options.num_threads = num_threads or options.threads()
    ba_options.ceres.min_num_residuals_for_cpu_multi_threading = \
        ba.min_num_residuals_for_multi_threading
    return ba_options


def adjust_reconstruction(reconstruction: pycolmap.Reconstruction, options: MapperOptions,
                          num_threads: int | None = None) -> None:
    """Global adjustment, in place, of every registered pose and every point of a
    reconstruction that no Model holds (a joined one): the options' loss and Ceres limits
    (global_max_iterations), intrinsics constant, the gauge fixed by two cameras."""
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    ba_options = adjustment_options(options, options.bundle_adjustment.global_max_iterations,
                                    num_threads=num_threads)
    pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()


def bundle_adjust(model: Model, image_ids: list[int], options: MapperOptions,
                  max_iterations: int, refine_intrinsics: bool = False,
                  loss: str | None = None, loss_scale_px: float | None = None) -> int:
    """Adjust, on the model's reconstruction in place, the poses of `image_ids` (except
    the model's fixed images) and the points they observe, as COLMAP's adjustments do:
    a point seen by at most BundleAdjustmentOptions.local_max_track_length images brings
    its other observations in, their poses constant; a longer track is already well
    determined and enters through the observations of `image_ids` alone, held constant
    where they are just one. Without two constant images, two cameras fix the gauge.
    With `refine_intrinsics`, the intrinsics the options name are refined too, but for
    the cameras in BundleAdjustmentOptions.constant_camera_ids; `loss` and
    `loss_scale_px` replace the options' robust loss and its scale. Returns the number of
    Ceres iterations."""
    ba = options.bundle_adjustment
    requested = set(image_ids)
    reconstruction = model.reconstruction
    refine_intrinsics = refine_intrinsics and ba.refines_intrinsics
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in sorted(requested):
        config.add_image(image_id)
        if image_id in model.fixed_image_ids:
            config.set_constant_rig_from_world_pose(reconstruction.images[image_id].frame_id)
    for camera_id in reconstruction.cameras:
        if not refine_intrinsics or camera_id in ba.constant_camera_ids:
            config.set_constant_cam_intrinsics(camera_id)

    if requested >= model.poses.keys():
        # A global adjustment: the images hold every observation of every point.
        variable_point_ids, outside = list(model.tracks), set()
    else:
        variable_point_ids, outside = _add_local_points(model, requested, config,
                                                        ba.local_max_track_length)
    constant = (outside - requested) | (requested & model.fixed_image_ids)
    if len(constant) < 2:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)

    ba_options = adjustment_options(options, max_iterations, refine_intrinsics, loss=loss,
                                    loss_scale_px=loss_scale_px)
    summary = pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()
    variable_image_ids = requested - model.fixed_image_ids
    if not summary.is_solution_usable():
        # Not solved (e.g. COLMAP could not fix the gauge): the model stays as it was.
        for image_id in variable_image_ids:
            model.set_pose(image_id, model.poses[image_id])
        for point_id in variable_point_ids:
            reconstruction.points3D[point_id].xyz = model.xyz[point_id]
        return 0
    for image_id in variable_image_ids:
        model.poses[image_id] = reconstruction.images[image_id].cam_from_world()
    for point_id in variable_point_ids:
        model.xyz[point_id] = reconstruction.points3D[point_id].xyz
    if refine_intrinsics:
        for camera_id, camera in reconstruction.cameras.items():
            model.set_camera(camera_id, camera)
    return summary.ceres_summary.num_successful_steps + summary.ceres_summary.num_unsuccessful_steps


def _add_local_points(model: Model, image_ids: set[int], config: pycolmap.BundleAdjustmentConfig,
                      max_track_length: int) -> tuple[list[int], set[int]]:
    """Add the points of a local adjustment's images to `config` by COLMAP's rule (see
    bundle_adjust). Returns the variable points and the images their tracks reach."""
    point_ids = np.unique(np.concatenate(
        [model.observations(image_id)[1] for image_id in image_ids])).tolist()
    variable_point_ids, reached = [], set()
    for point_id in point_ids:
        track = model.tracks[point_id]
        if len(track) <= max_track_length:
            config.add_variable_point(point_id)
            reached.update(track)
        elif sum(image_id in image_ids for image_id in track) < 2:
            config.add_constant_point(point_id)
            continue
        variable_point_ids.append(point_id)
    return variable_point_ids, reached
