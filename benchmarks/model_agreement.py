"""How far several models of the same images are from each other, against how far each is
from the ground truth.

Where every mapper lands within a small distance of the others and all of them share one
error against the ground truth, the ground truth (or what all mappers assume alike, such
as the intrinsics) sets the error, and no mapper can be told better by it. For models
(any COLMAP model folders, e.g. `colmap-ext compare`'s and `reconstruct`'s) this prints:
- each model's R_err and C_err (max / median, as `colmap-ext evaluate`) against the ground
  truth, and for each pair of models against each other;
- for each pair, the correlation of their rotation errors against the ground truth, each
  image's taken as a vector (axis x angle, relative to the first image). Near 1: the
  models err alike.

    python benchmarks/model_agreement.py --ground_truth GT NAME=MODEL NAME=MODEL [...] [--per_image]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.errors import UserError
from colmap_ext.evaluate import evaluate, match_images, relative_to_first
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.model_io import read_model


def rotation_vector_deg(R: np.ndarray) -> np.ndarray:
    """The axis x angle (deg) of a rotation matrix (angles well below 180 deg)."""
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    norm = np.linalg.norm(axis)
    return np.degrees(axis / norm * angle) if norm > 1e-15 else np.zeros(3)


def error_vectors(model: pycolmap.Reconstruction, truth: GroundTruth,
                  names: list[str]) -> np.ndarray:
    """(n, 3) rotation error of each named image relative to the first, as R_err measures it
    (evaluate.pose_errors) but keeping its axis."""
    matches = match_images(model, names)
    R_gt, _ = relative_to_first([truth.poses[name] for name in names])
    R_est, _ = relative_to_first([matches[name].cam_from_world() for name in names])
    return np.array([rotation_vector_deg(est @ gt.T) for est, gt in zip(R_est, R_gt)])


def main(ground_truth: str, models: dict[str, str], per_image: bool = False) -> None:
    truth = read_ground_truth(ground_truth)
    reconstructions = {name: read_model(Path(path)) for name, path in models.items()}
    print("Against the ground truth:\n")
    print("| model | registered | R_err max / median [deg] | C_err max / median |")
    print("|---|---|---|---|")
    for name, model in reconstructions.items():
        print(f"| {name} | " + _errors(evaluate(model, truth)) + " |")
    names = [name for name in truth.poses
             if all(match_images(model, [name]) for model in reconstructions.values())]
    vectors = {name: error_vectors(model, truth, names) for name, model in reconstructions.items()}
    print(f"\nAgainst each other (the second model as the reference), and the correlation of their "
          f"rotation error vectors against the ground truth over the {len(names)} images in every "
          "model:\n")
    print("| models | registered | R_err max / median [deg] | C_err max / median | correlation |")
    print("|---|---|---|---|---|")
    for a, b in itertools.combinations(reconstructions, 2):
        report = evaluate(reconstructions[a], read_ground_truth(models[b]))
        correlation = np.corrcoef(vectors[a].ravel(), vectors[b].ravel())[0, 1]
        print(f"| {a} / {b} | " + _errors(report) + f" | {correlation:.3f} |")
    if per_image:
        print("\n| image | " + " | ".join(f"{name} R_err [deg]" for name in vectors) + " |")
        print("|---|" + "---|" * len(vectors))
        for k, image_name in enumerate(names):
            print(f"| {image_name} | "
                  + " | ".join(f"{np.linalg.norm(v[k]):.4f}" for v in vectors.values()) + " |")


def _errors(report: dict) -> str:
    return (f"{report['num_registered']} | {report['R_err_max_deg']:.4f} / "
            f"{report['R_err_median_deg']:.4f} | {report['C_err_max']:.5f} / "
            f"{report['C_err_median']:.5f}")


def parse_model(text: str) -> tuple[str, str]:
    name, separator, path = text.partition("=")
    if not separator or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=MODEL_FOLDER, got {text!r}")
    return name, path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ground_truth", required=True, help="Middlebury _par.txt (or its "
                        "folder), Strecha gt_cameras/, or a COLMAP model")
    parser.add_argument("models", nargs="+", type=parse_model,
                        help="NAME=MODEL_FOLDER, two or more")
    parser.add_argument("--per_image", action="store_true",
                        help="also each image's R_err in every model")
    args = parser.parse_args()
    if len(dict(args.models)) < 2:
        parser.error("give two or more models with distinct names")
    try:
        main(args.ground_truth, dict(args.models), args.per_image)
    except UserError as exc:
        parser.error(str(exc))
