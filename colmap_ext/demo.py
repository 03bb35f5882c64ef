"""`colmap-ext demo`: the whole pipeline on a scene the project renders itself.

A textured object in a textured room, seen by 24 cameras on a ring through a lens with
radial distortion (so undistortion is exercised), rendered to 640x480 PNGs with the
ground truth beside them; then `reconstruct` and `evaluate` on it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from colmap_ext import evaluate, reconstruct
from colmap_ext.errors import UserError
from colmap_ext.mapper.flags import random_seed
from colmap_ext.model_io import OutputLayout, holds_only, is_file, is_model_folder, replacing
from colmap_ext.synthetic.render import render_images, write_ground_truth
from colmap_ext.synthetic.scene import ring_scene

# The most views the demo renders: far more than a demo needs; without a bound, a typo
# renders until memory runs out.
MAX_NUM_IMAGES = 1000
DEMO_OUTPUT = OutputLayout("a demo", {
    "images": holds_only(r"ring\d{4}\.png"), "ground_truth": is_model_folder,
    "workspace": reconstruct.WORKSPACE.is_output, "report.json": is_file,
    "errors.png": is_file, "errors_scene.png": is_file})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--output_path", required=True,
                        help="folder for the images, ground truth, workspace, report.json and "
                             "the figures errors.png and errors_scene.png")
    parser.add_argument("--num_images", type=int, default=24)
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a demo already in OUTPUT_PATH")


def main(output_path: str, num_images: int = 24, seed: int = 0, overwrite: bool = False) -> dict:
    """Render, reconstruct and evaluate in a folder beside OUTPUT_PATH, then move the
    images, ground truth, workspace, report and figures into it together."""
    if not 3 <= num_images <= MAX_NUM_IMAGES:
        raise UserError(f"--num_images must be at least 3 and at most {MAX_NUM_IMAGES}, "
                        f"got {num_images}")
    with replacing(output_path, DEMO_OUTPUT, overwrite) as new_root:
        images, truth, workspace = new_root / "images", new_root / "ground_truth", new_root / "workspace"
        scene = ring_scene(num_images=num_images, seed=seed)
        print(f"Rendering {num_images} views of the demo scene ...")
        render_images(scene, images, seed=seed)
        write_ground_truth(scene, truth)
        camera = scene.camera
        reconstruct.main(image_path=str(images), workspace_path=str(workspace),
                         camera_model=camera.model.name,
                         camera_params=",".join(f"{p:.17g}" for p in camera.params), seed=seed)
        print()
        report = evaluate.main(model_path=workspace / "sparse" / "0", ground_truth=truth,
                               output=new_root / "report.json", plot=new_root / "errors.png")
    root = Path(output_path)
    print(f"\nModel: {root / 'workspace' / 'sparse' / '0'}   report: {root / 'report.json'}   "
          f"plots: {root / 'errors.png'}, {evaluate.scene_plot_path(root / 'errors.png')}")
    return report
