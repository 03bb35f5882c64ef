"""`colmap-ext evaluate`: a model's camera poses against a ground truth, by the paper's measures.

Poses on both sides are taken relative to the first registered image (cam_i from cam_1, in
ground-truth order), which removes the gauge without fitting anything:
- R_err: angle of R_i^T R^_i, in degrees;
- T_err: angle between t_i and t^_i, in degrees (translation is known only up to scale;
  0 where t_i = 0, i.e. for the reference and any view taken from the same place);
- C_err: |s C^_i - C_i| / |C_2 - C_1|, centres in the first camera's frame, s matching their spread.
C_err_aligned replaces the first camera's frame and spread by the best similarity
(Umeyama) from the estimated onto the ground-truth centres, in the same unit.

Beside them, the field's measure (COLMAP's benchmark/reconstruction/evaluation, the GLOMAP
paper, the Image Matching Challenge): the AUC of relative-pose errors. Per ordered pair of
ground-truth images, the larger of the rotation error and the translation-direction error of
tgt_from_src; a pair with an image outside the evaluated model counts as an infinite error;
the area under the recall curve up to 0.5, 1, 5 and 10 degrees, in percent.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path, PurePosixPath

import numpy as np
import pycolmap

from colmap_ext.errors import UserError
from colmap_ext.geometry import fit_similarity, rotation_angles_deg, vector_angles_deg
from colmap_ext.ground_truth import FORMATS, GroundTruth, read_ground_truth
from colmap_ext.model_io import check_output_file, read_model, write_json
from colmap_ext.plots import plot_errors, plot_scene
from colmap_ext.rig_consistency import format_rig_consistency, rig_consistency, rig_frames_of

logger = logging.getLogger(__name__)

# Relative distance below which two camera centres count as one: a view from the reference's
# centre has no T_err (distance in |C2 - C1|), and C2 on C1 gives no unit (in the set's size).
_SAME_CENTRE = 1e-6

# Per-image measures (report keys) and their units in the printed table.
MEASURES = {"R_err_deg": "deg", "T_err_deg": "deg", "C_err": "|C2-C1|", "C_err_aligned": "|C2-C1|"}

# Thresholds of the relative-pose AUC in degrees, COLMAP's benchmark's, and its report key.
AUC_THRESHOLDS_DEG = (0.5, 1.0, 5.0, 10.0)
AUC_KEY = "AUC_percent"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Define the options of `colmap-ext evaluate`."""
    parser.add_argument("--model_path", type=Path, required=True,
                        help="COLMAP model folder to evaluate (e.g. OUTPUT/0)")
    parser.add_argument("--ground_truth", type=Path, required=True,
                        help="Middlebury *_par.txt, a folder of Strecha *.camera files, or a COLMAP model")
    parser.add_argument("--output", type=Path, help="write the report as JSON to this file")
    parser.add_argument("--plot", type=Path,
                        help="draw the per-image errors to this image (.png, .pdf, .svg), and "
                             "the points and cameras against the ground truth (top and side "
                             "view) beside it: errors.png gives errors_scene.png")
    parser.add_argument("--format", choices=FORMATS, help="ground-truth format (default: detected)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing files at --output and --plot (and its _scene figure)")
    parser.add_argument("--rig_config", type=Path, default=None,
                        help="COLMAP's rig configuration JSON to measure the model's rig "
                             "consistency against (default: the model's own rigs)")


def main(model_path: str | os.PathLike, ground_truth: str | os.PathLike,
         output: str | os.PathLike | None = None, plot: str | os.PathLike | None = None,
         format: str | None = None, rig_config: str | os.PathLike | None = None,
         overwrite: bool = False) -> dict:
    """Evaluate the model at `model_path`, print a table, optionally write JSON and the plots
    (`plot` and `scene_plot_path(plot)`); with frames of several images, the rig's
    consistency too (against `rig_config`, else the model's own rigs). Existing files are
    replaced only with `overwrite`, and an input never."""
    inputs = [Path(path) for path in (model_path, ground_truth, rig_config) if path is not None]
    outputs = [output] if output is not None else []
    outputs += [plot, scene_plot_path(plot)] if plot is not None else []
    for path in outputs:
        check_output_file(path, inputs, overwrite)
    return evaluate_and_write(read_model(Path(model_path)), read_ground_truth(ground_truth, format),
                              output, plot, label=str(model_path), rig_config=rig_config)


def evaluate_and_write(reconstruction: pycolmap.Reconstruction, truth: GroundTruth,
                       output: str | os.PathLike | None, plot: str | os.PathLike | None,
                       label: str, rig_config: str | os.PathLike | None = None) -> dict:
    """`main` on a model read already: the plots name it `label`."""
    report = evaluate(reconstruction, truth)
    consistency = rig_consistency(reconstruction, rig_frames_of(reconstruction, rig_config))
    print(format_table(report))
    if consistency is not None:
        report["rig_consistency"] = consistency
        print(format_rig_consistency(consistency))
    if output is not None:
        write_json(report, Path(output))
    if plot is not None:
        plot_errors({label: report}, plot)
        plot_scene(truth.poses, *aligned_to_ground_truth(reconstruction, truth),
                   scene_plot_path(plot), title=label)
    return report


def scene_plot_path(plot: str | os.PathLike) -> Path:
    """Where the scene figure goes beside the errors figure `plot`: errors.png -> errors_scene.png."""
    plot = Path(plot)
    return plot.with_name(f"{plot.stem}_scene{plot.suffix}")


def evaluate(reconstruction: pycolmap.Reconstruction, ground_truth: GroundTruth) -> dict:
    """The report: per-image errors in ground-truth order (None if unregistered) and their max/median.

    Max and median run over the registered images, the reference included (its errors are 0
    by construction, as in the paper's plots).
    """
    names = list(ground_truth.poses)
    matches = match_images(reconstruction, names)
    registered = [name for name in names if name in matches]
    if len(registered) < 2:
        raise UserError(f"only {len(registered)} registered image(s) match the {len(names)} "
                        "ground-truth images by name; at least 2 are needed")
    unmatched = sum(image.has_pose for image in reconstruction.images.values()) - len(matches)
    if unmatched:
        logger.warning("%d registered model image(s) have no ground truth and are ignored", unmatched)
    errors = pose_errors(
        [ground_truth.poses[name] for name in registered],
        [matches[name].cam_from_world() for name in registered],
    )
    per_image = {name: {key: None for key in MEASURES} for name in names}
    for index, name in enumerate(registered):
        per_image[name] = {key: float(values[index]) for key, values in errors.items()}
    report = {"num_gt_images": len(names), "num_registered": len(registered)}
    for key, values in errors.items():
        report[summary_key(key, "max")] = float(np.max(values))
        report[summary_key(key, "median")] = float(np.median(values))
    pair_errors = relative_pose_errors([ground_truth.poses[name] for name in names],
                                       [matches[name].cam_from_world() if name in matches else None
                                        for name in names])
    report[AUC_KEY] = {f"{threshold:g}": float(auc) for threshold, auc
                       in zip(AUC_THRESHOLDS_DEG, auc_percent(pair_errors, AUC_THRESHOLDS_DEG))}
    report["per_image"] = [{"name": name, **per_image[name]} for name in names]
    return report


def relative_pose_errors(gt_poses: list[pycolmap.Rigid3d],
                         est_poses: list[pycolmap.Rigid3d | None]) -> np.ndarray:
    """Per ordered pair (src, tgt) of ground-truth images, the larger of the rotation error
    and the angle between the translation directions of tgt_from_src, in degrees (COLMAP's
    benchmark); infinite where either image has no estimate (None). The translation
    direction is not compared where the two ground-truth centres coincide."""
    registered = np.array([pose is not None for pose in est_poses])
    R_gt = np.array([pose.rotation.matrix() for pose in gt_poses])
    t_gt = np.array([pose.translation for pose in gt_poses])
    R_est, t_est = np.tile(np.eye(3), (len(gt_poses), 1, 1)), np.zeros((len(gt_poses), 3))
    for index, pose in enumerate(est_poses):
        if pose is not None:
            R_est[index], t_est[index] = pose.rotation.matrix(), pose.translation
    centres = _centres(R_gt, t_gt)
    same_centre = _SAME_CENTRE * np.sqrt(_spread(centres) / len(centres))
    errors = []
    for src in range(len(gt_poses)):
        tgt = np.arange(len(gt_poses)) != src
        R_rel_gt, R_rel_est = R_gt[tgt] @ R_gt[src].T, R_est[tgt] @ R_est[src].T
        t_rel_gt, t_rel_est = t_gt[tgt] - R_rel_gt @ t_gt[src], t_est[tgt] - R_rel_est @ t_est[src]
        rotation_error = rotation_angles_deg(np.swapaxes(R_rel_est, 1, 2) @ R_rel_gt)
        direction_error = vector_angles_deg(t_rel_est, t_rel_gt)
        direction_error[np.linalg.norm(t_rel_gt, axis=1) < same_centre] = 0.0
        error = np.maximum(rotation_error, direction_error)
        error[~(registered[src] & registered[tgt])] = np.inf
        errors.append(error)
    return np.concatenate(errors) if errors else np.zeros(0)


def auc_percent(errors: np.ndarray, thresholds_deg: tuple[float, ...]) -> np.ndarray:
    """Area under the recall-error curve from 0 to each threshold, over the threshold, in
    percent: recall rises by 1/n at each sorted error, linearly in between (COLMAP's
    benchmark's compute_auc, without its ground-truth accuracy floor)."""
    errors = np.sort(np.asarray(errors, dtype=float))
    recalls = np.r_[0.0, np.arange(1, len(errors) + 1) / len(errors)]
    errors = np.r_[0.0, errors]
    aucs = []
    for threshold in thresholds_deg:
        last = np.searchsorted(errors, threshold, side="right")
        curve_errors = np.r_[errors[:last], threshold]
        curve_recalls = np.r_[recalls[:last], recalls[last - 1]]
        aucs.append(100 * np.trapezoid(curve_recalls, curve_errors) / threshold)
    return np.array(aucs)


def summary_key(measure: str, statistic: str) -> str:
    """The report key of a statistic of a measure: ('R_err_deg', 'max') -> 'R_err_max_deg'."""
    stem, deg, _ = measure.partition("_deg")
    return f"{stem}_{statistic}{deg}"


def match_images(reconstruction: pycolmap.Reconstruction, names: list[str]) -> dict[str, pycolmap.Image]:
    """Ground-truth name -> registered model image, by exact name, else by a basename unique on both sides.

    The basename fallback lets `sub/a.png` in a model meet `a.png` in a ground truth.
    Model images without ground truth are ignored (`evaluate` warns how many).
    """
    images = [image for image in reconstruction.images.values() if image.has_pose]
    by_name = {image.name: image for image in images}
    matches = {name: by_name[name] for name in names if name in by_name}

    def unique_by_basename(items: list[str]) -> dict[str, str]:
        bases: dict[str, list[str]] = {}
        for item in items:
            bases.setdefault(PurePosixPath(item).name, []).append(item)
        return {base: found[0] for base, found in bases.items() if len(found) == 1}

    gt_left = unique_by_basename([name for name in names if name not in matches])
    used = {image.name for image in matches.values()}
    model_left = unique_by_basename([image.name for image in images if image.name not in used])
    for base, name in gt_left.items():
        if base in model_left:
            matches[name] = by_name[model_left[base]]
    return matches


def pose_errors(gt_poses: list[pycolmap.Rigid3d], est_poses: list[pycolmap.Rigid3d]) -> dict[str, np.ndarray]:
    """Per-image R_err, T_err (deg), C_err and C_err_aligned of matched cam_from_world poses."""
    R_gt, t_gt = relative_to_first(gt_poses)
    R_est, t_est = relative_to_first(est_poses)
    C_gt, C_est = _centres(R_gt, t_gt), _centres(R_est, t_est)
    unit = np.linalg.norm(C_gt[1] - C_gt[0])
    if unit <= _SAME_CENTRE * np.sqrt(_spread(C_gt) / len(C_gt)):
        raise UserError("the first two ground-truth camera centres coincide: C_err has no unit")
    if _spread(C_est) == 0:
        raise UserError("all estimated camera centres coincide: C_err is undefined")
    scale = np.sqrt(_spread(C_gt) / _spread(C_est))
    t_err = vector_angles_deg(t_gt, t_est)
    # No direction to compare where the ground-truth camera sits on the reference's centre:
    # the reference itself, and e.g. the last view of a closed ring (templeSR0011).
    t_err[np.linalg.norm(t_gt, axis=1) <= _SAME_CENTRE * unit] = 0.0
    return {
        "R_err_deg": rotation_angles_deg(np.swapaxes(R_gt, 1, 2) @ R_est),
        "T_err_deg": t_err,
        "C_err": np.linalg.norm(scale * C_est - C_gt, axis=1) / unit,
        "C_err_aligned": np.linalg.norm(align_similarity(C_est, C_gt) - C_gt, axis=1) / unit,
    }


def align_similarity(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """`source` points (n,3) moved by the least-squares similarity onto `target`."""
    return fit_similarity(source, target) * source


def aligned_to_ground_truth(reconstruction: pycolmap.Reconstruction, ground_truth: GroundTruth,
                            with_scale: bool = True) -> tuple[dict[str, pycolmap.Rigid3d], np.ndarray]:
    """The registered cameras (cam_from_world by ground-truth name) and the points (n,3, in
    point id order) of the model, moved into the ground truth's world by the similarity of
    C_err_aligned, for drawing them over the ground truth; without `with_scale`, by the
    rigid transform that best aligns the centres (a metric model: a rig's, at its scale).

    The similarity is fitted to world centres rather than to centres relative to the first
    camera, which moves both sides rigidly and so leaves the fit's residuals unchanged.
    """
    matches = match_images(reconstruction, list(ground_truth.poses))
    names = [name for name in ground_truth.poses if name in matches]
    gt_from_model = fit_similarity(
        np.array([matches[name].projection_center() for name in names]),
        np.array([ground_truth.poses[name].inverse().translation for name in names]),
        with_scale=with_scale)
    cameras = {name: gt_from_model.transform_camera_world(matches[name].cam_from_world())
               for name in names}
    xyz = [point.xyz for _, point in sorted(reconstruction.points3D.items())]  # in id order
    return cameras, gt_from_model * np.array(xyz).reshape(-1, 3)


def relative_to_first(poses: list[pycolmap.Rigid3d]) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (n,3,3) and translations (n,3) of cam_i_from_cam_1 = cam_i_from_world * world_from_cam_1."""
    R = np.array([pose.rotation.matrix() for pose in poses])
    t = np.array([pose.translation for pose in poses])
    R_rel = R @ R[0].T
    return R_rel, t - R_rel @ t[0]


def _centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres C = -R^T t (n,3)."""
    return -np.einsum("nji,nj->ni", R, t)


def _spread(points: np.ndarray) -> float:
    """Sum of squared distances of points (n,3) to their mean."""
    return float(np.sum((points - points.mean(axis=0)) ** 2))


def format_table(report: dict) -> str:
    """The report as a per-image table followed by summary lines."""
    width = max(len("image"), *(len(entry["name"]) for entry in report["per_image"]))
    headings = [key.removesuffix("_deg") for key in MEASURES]
    lines = [f"{'image':<{width}}" + "".join(f"{heading:>15}" for heading in headings)]
    for entry in report["per_image"]:
        cells = ["unregistered" if entry[key] is None else f"{entry[key]:.4f}" for key in MEASURES]
        lines.append(f"{entry['name']:<{width}}" + "".join(f"{cell:>15}" for cell in cells))
    lines += ["", f"registered: {report['num_registered']} / {report['num_gt_images']}"]
    for key, unit in MEASURES.items():
        maximum, median = report[summary_key(key, "max")], report[summary_key(key, "median")]
        lines.append(f"{key.removesuffix('_deg') + ':':<15}max {maximum:.4f}  median {median:.4f}  ({unit})")
    lines.append(f"AUC@{'/'.join(report[AUC_KEY])} deg: {format_auc(report)}  "
                 "(%, relative poses of image pairs)")
    return "\n".join(lines)


def format_auc(report: dict) -> str:
    """The AUC at each threshold, e.g. '98.12 / 99.06 / 99.81 / 99.91'."""
    return " / ".join(f"{auc:.2f}" for auc in report[AUC_KEY].values())
