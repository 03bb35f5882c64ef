"""Bundle adjustment through pycolmap (Ceres): intrinsics constant unless a global
adjustment is asked to refine them (BundleAdjustmentOptions.refine_*).

The model is copied into a pycolmap.Reconstruction holding just the images and
points of the problem, adjusted, and the refined poses, points and cameras copied back.
"""

from __future__ import annotations

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


def to_reconstruction(model: Model, image_ids: list[int], point_ids: list[int],
                      long_track_image_ids: set[int] | None = None,
                      max_track_length: int = 0) -> pycolmap.Reconstruction:
    """A reconstruction of the given registered images and points (ids kept); every
    image observing one of the points must be among `image_ids`, except that points
    seen by more than `max_track_length` images keep just their observations by
    `long_track_image_ids` when that is given (and are left out with fewer than two)."""
    reconstruction = posed_images(model.db, model.cameras,
                                  {image_id: model.poses[image_id] for image_id in image_ids})
    for point_id in point_ids:
        observations = model.tracks[point_id]
        if long_track_image_ids is not None and len(observations) > max_track_length:
            observations = {i: kp for i, kp in observations.items() if i in long_track_image_ids}
            if len(observations) < 2:
                continue  # one observation alone does not constrain the point
        track = pycolmap.Track()
        for image_id, kp in observations.items():
            track.add_element(image_id, kp)
        # Attributes set one by one: 2.5x faster than Point3D's keyword constructor, which
        # made this loop a tenth of the mapper's time on 4400-keypoint images.
        point = pycolmap.Point3D()
        point.xyz = model.xyz[point_id]
        point.track = track
        reconstruction.add_point3D_with_id(point_id, point)
    return reconstruction


def adjustment_options(options: MapperOptions, max_iterations: int,
                       refine_intrinsics: bool = False,
                       num_threads: int | None = None) -> pycolmap.BundleAdjustmentOptions:
    """pycolmap's options for one adjustment with ours: the robust loss, Ceres's limits
    and threads (default: options.threads()), and the intrinsics refined only where
    `refine_intrinsics` and the options ask for it."""
    ba = options.bundle_adjustment
    refine = refine_intrinsics and ba.refines_intrinsics
    ba_options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=refine and ba.refine_focal_length,
        refine_principal_point=refine and ba.refine_principal_point,
        refine_extra_params=refine and ba.refine_extra_params,
        print_summary=False)
    ba_options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, ba.loss.upper())
    ba_options.ceres.loss_function_scale = ba.loss_scale_px
    ba_options.ceres.solver_options.max_num_iterations = max_iterations
    ba_options.ceres.solver_options.function_tolerance = ba.function_tolerance
    ba_options.ceres.solver_options.num_threads = num_threads or options.threads()
    ba_options.ceres.min_num_residuals_for_cpu_multi_threading = \
        ba.min_num_residuals_for_multi_threading
    return ba_options


def bundle_adjust(model: Model, image_ids: list[int], options: MapperOptions,
                  max_iterations: int, refine_intrinsics: bool = False) -> int:
    """Adjust every point `image_ids` observe and the poses of those images, except the
    model's fixed images. The other registered images observing a point with at most
    BundleAdjustmentOptions.local_max_track_length observations add them with their poses constant; longer
    tracks are already well determined and enter through `image_ids`' observations
    alone (COLMAP's local adjustment). Without two constant images, two cameras fix
    the gauge. With `refine_intrinsics`, the intrinsics the options name are refined
    too. Returns the number of Ceres iterations."""
    ba = options.bundle_adjustment
    requested = set(image_ids)
    point_ids = sorted({int(p) for i in requested for p in model.observations(i)[1]})
    observing = {i for p in point_ids if len(model.tracks[p]) <= ba.local_max_track_length
                 for i in model.tracks[p]}
    problem_image_ids = sorted(requested | observing)
    variable = requested - model.fixed_image_ids
    constant = set(problem_image_ids) - variable
    reconstruction = to_reconstruction(model, problem_image_ids, point_ids, requested,
                                       ba.local_max_track_length)
    refine_intrinsics = refine_intrinsics and ba.refines_intrinsics

    config = pycolmap.BundleAdjustmentConfig()
    for image_id in problem_image_ids:
        config.add_image(image_id)
    if not refine_intrinsics:
        for camera_id in reconstruction.cameras:
            config.set_constant_cam_intrinsics(camera_id)
    for image_id in constant:
        config.set_constant_rig_from_world_pose(reconstruction.images[image_id].frame_id)
    if len(constant) < 2:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)

    ba_options = adjustment_options(options, max_iterations, refine_intrinsics)
    summary = pycolmap.create_default_bundle_adjuster(ba_options, config, reconstruction).solve()
    if not summary.is_solution_usable():
        return 0  # not solved (e.g. COLMAP could not fix the gauge): the model stays as it was

    for image_id in variable:
        model.poses[image_id] = reconstruction.images[image_id].cam_from_world()
    for point_id, point in reconstruction.points3D.items():
        model.xyz[point_id] = point.xyz
    if refine_intrinsics:
        for camera_id, camera in reconstruction.cameras.items():
            model.set_camera(camera_id, camera)
    return summary.ceres_summary.num_successful_steps + summary.ceres_summary.num_unsuccessful_steps
