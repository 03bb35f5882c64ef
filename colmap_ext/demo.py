"""`colmap-ext demo`: the whole pipeline on a scene the project renders itself.

A textured object in a textured room, seen by 24 cameras on a ring through a lens with
radial distortion (so undistortion is exercised), rendered to 640x480 PNGs with the
ground truth beside them; then `reconstruct` and `evaluate` on it.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from colmap_ext import evaluate, reconstruct
from colmap_ext.errors import UserError
from colmap_ext.synthetic.render import render_images, write_ground_truth
from colmap_ext.synthetic.scene import ring_scene


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--output_path", required=True,
                        help="folder for the images, ground truth, workspace, report.json and "
                             "the figures errors.png and errors_scene.png")
    parser.add_argument("--num_images", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a demo already in OUTPUT_PATH")


def main(output_path: str, num_images: int = 24, seed: int = 0, overwrite: bool = False) -> dict:
    if num_images < 3:
        raise UserError(f"--num_images must be at least 3, got {num_images}")
    root = Path(output_path)
    if root.exists() and not root.is_dir():
        raise UserError(f"output path is a file, not a folder: {root}")
    if (root / "workspace").exists():
        if not overwrite:
            raise UserError(f"{root} already holds a demo; pass --overwrite to replace it")
        for name in ("images", "ground_truth", "workspace"):
            shutil.rmtree(root / name, ignore_errors=True)
    images, truth, workspace = root / "images", root / "ground_truth", root / "workspace"
    scene = ring_scene(num_images=num_images, seed=seed)
    print(f"Rendering {num_images} views of the demo scene to {images}/ ...")
    render_images(scene, images, seed=seed)
    truth.mkdir(parents=True, exist_ok=True)
    write_ground_truth(scene, truth)
    camera = scene.camera
    reconstruct.main(image_path=str(images), workspace_path=str(workspace),
                     camera_model=camera.model.name,
                     camera_params=",".join(f"{p:.17g}" for p in camera.params),
                     seed=seed, overwrite=overwrite)
    print()
    report = evaluate.main(model_path=workspace / "sparse" / "0", ground_truth=truth,
                           output=root / "report.json", plot=root / "errors.png")
    print(f"\nModel: {workspace / 'sparse' / '0'}   report: {root / 'report.json'}   "
          f"plots: {root / 'errors.png'}, {evaluate.scene_plot_path(root / 'errors.png')}")
    return report
