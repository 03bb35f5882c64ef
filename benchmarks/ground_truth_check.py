"""How far a model's poses are from the ground truth, against how well its own
observations determine them.

For a finished model (any COLMAP model folder) and its ground truth:
- the reprojection error of the model, and of the ground-truth poses with the model's
  points triangulated again from them (the ground truth's residuals on the matches);
- a bundle adjustment started at the ground-truth poses on the model's observations (our
  loss, intrinsics constant): how far it ends from the model and from the ground truth.
  Ending at the model means the model is the optimum of its observations;
- each image's rotation standard deviation (1 sigma, about its least determined axis,
  relative to the first ground-truth image), from the adjustment's covariance
  (pycolmap's estimate_ba_covariance) scaled by the keypoint noise that the residuals
  show (1.4826 x their median absolute value), against the image's R_err.

    python benchmarks/ground_truth_check.py --model_path MODEL --ground_truth GT [--loss cauchy]
"""

from __future__ import annotations

import argparse

import numpy as np
import pycolmap

import solvers
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper.bundle_adjustment import adjustment_options
from colmap_ext.mapper.options import BA_LOSSES, MapperOptions

MAX_ITERATIONS = 300
GRADIENT_TOLERANCE = 1e-4  # to convergence, below the mapper's


def residuals(reconstruction: pycolmap.Reconstruction) -> np.ndarray:
    """(n, 2) reprojection residuals (px) of every observation."""
    out = []
    for point in reconstruction.points3D.values():
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            camera = reconstruction.cameras[image.camera_id]
            projected = camera.img_from_cam(image.cam_from_world() * point.xyz)
            out.append(projected - image.points2D[element.point2D_idx].xy)
    return np.array(out).reshape(-1, 2)


def with_poses(reconstruction: pycolmap.Reconstruction,
               poses: dict[str, pycolmap.Rigid3d]) -> pycolmap.Reconstruction:
    """A copy posed by `poses` (cam_from_world by image name), its points triangulated
    again from its observations."""
    posed = pycolmap.Reconstruction(reconstruction)
    for image in posed.images.values():
        posed.frames[image.frame_id].rig_from_world = poses[image.name]
    image_ids = sorted(posed.images)
    index = {image_id: k for k, image_id in enumerate(image_ids)}
    point_ids = sorted(posed.points3D)
    views, points, rays = [], [], []
    for k, point_id in enumerate(point_ids):
        for element in posed.points3D[point_id].track.elements:
            image = posed.images[element.image_id]
            xy = posed.cameras[image.camera_id].cam_from_img(image.points2D[element.point2D_idx].xy)
            views.append(index[element.image_id])
            points.append(k)
            rays.append([xy[0], xy[1], 1.0])
    rays = np.array(rays)
    xyz, _ = solvers.triangulate_tracks([posed.images[i].cam_from_world() for i in image_ids],
                                        views, points, rays / np.linalg.norm(rays, axis=1, keepdims=True),
                                        num_points=len(point_ids), min_angle_deg=0.0)
    for k, point_id in enumerate(point_ids):
        posed.points3D[point_id].xyz = xyz[k]
    return posed


def adjustment(reconstruction: pycolmap.Reconstruction, loss: str,
               constant_image_id: int | None = None) -> pycolmap.CeresBundleAdjuster:
    """Every pose and point variable, intrinsics constant; the gauge by two cameras, or
    by `constant_image_id`'s pose held (scale is then free: covariance only)."""
    options = MapperOptions()
    options.bundle_adjustment.loss = loss
    options.bundle_adjustment.function_tolerance = 0.0
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.images:
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    if constant_image_id is None:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    else:
        config.set_constant_rig_from_world_pose(reconstruction.images[constant_image_id].frame_id)
    ba_options = adjustment_options(options.bundle_adjustment, local=False,
                                    num_threads=options.threads())
    ba_options.ceres.solver_options.max_num_iterations = MAX_ITERATIONS
    ba_options.ceres.solver_options.gradient_tolerance = GRADIENT_TOLERANCE
    return pycolmap.create_default_ceres_bundle_adjuster(ba_options, config, reconstruction)


def rotation_deviations(reconstruction: pycolmap.Reconstruction, names: list[str],
                        loss: str) -> dict[str, float]:
    """The rotation standard deviation (deg, 1 sigma) of each image in `names` (registered
    images, the first held constant) relative to the first."""
    first_name = names[0]
    by_name = {image.name: image_id for image_id, image in reconstruction.images.items()}
    adjuster = adjustment(reconstruction, loss, constant_image_id=by_name[first_name])
    covariance = pycolmap.estimate_ba_covariance(
        pycolmap.BACovarianceOptions(params=pycolmap.BACovarianceOptionsParams.POSES),
        reconstruction, adjuster)
    if covariance is None:
        raise SystemExit("the covariance could not be estimated")
    noise = 1.4826 * float(np.median(np.abs(residuals(reconstruction))))
    deviations = {}
    for name in names:
        if name == first_name:
            continue
        image_id = by_name[name]
        rotation = covariance.get_cam_cov_from_world(image_id)[:3, :3]
        deviations[name] = float(np.degrees(np.sqrt(np.linalg.eigvalsh(rotation)[-1])) * noise)
    return deviations


def main(model_path: str, ground_truth: str, loss: str = "cauchy") -> None:
    model = pycolmap.Reconstruction(model_path)
    truth = read_ground_truth(ground_truth)
    report = evaluate(model, truth)
    errors = {row["name"]: row["R_err_deg"] for row in report["per_image"]
              if row["R_err_deg"] is not None}
    print(f"model: {report['num_registered']} images, R_err max {report['R_err_max_deg']:.3f} deg, "
          f"reprojection median {np.median(np.linalg.norm(residuals(model), axis=1)):.3f} px")

    posed = with_poses(model, truth.poses)
    print(f"ground-truth poses, points triangulated again: reprojection median "
          f"{np.median(np.linalg.norm(residuals(posed), axis=1)):.3f} px")
    adjustment(posed, loss).solve()
    adjusted = GroundTruth({image.name: image.cam_from_world() for image in posed.images.values()}, {})
    to_model = evaluate(model, adjusted)
    to_truth = evaluate(posed, truth)
    print(f"adjusted from the ground truth ({loss}): R_err max to the model "
          f"{to_model['R_err_max_deg']:.3f} deg, to the ground truth {to_truth['R_err_max_deg']:.3f} deg")

    deviations = rotation_deviations(model, [name for name in truth.poses if name in errors], loss)
    ratios = np.array([errors[name] / deviations[name] for name in deviations])
    print(f"rotation sd (1 sigma) median {np.median(list(deviations.values())):.3f}, max "
          f"{max(deviations.values()):.3f} deg; R_err / sd median {np.median(ratios):.1f}, "
          f"max {ratios.max():.1f}")
    print("| image | R_err [deg] | rotation sd [deg] |")
    print("|---|---|---|")
    for name, deviation in deviations.items():
        print(f"| {name} | {errors[name]:.3f} | {deviation:.3f} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model_path", required=True, help="a COLMAP model folder")
    parser.add_argument("--ground_truth", required=True,
                        help="Middlebury _par.txt (or its folder), Strecha gt_cameras/, or a COLMAP model")
    parser.add_argument("--loss", default="cauchy", choices=BA_LOSSES)
    args = parser.parse_args()
    main(args.model_path, args.ground_truth, args.loss)
