"""`colmap-ext demo`: the whole pipeline on a scene the project renders itself.

A textured object in a textured room, seen by 24 cameras on a ring through a lens with
radial distortion (so undistortion is exercised), rendered to 640x480 PNGs with the
ground truth beside them; then `reconstruct` and `evaluate` on it.
"""

from __future__ import annotations

import argparse
import time
from functools import partial
from pathlib import Path

from colmap_ext import evaluate, reconstruct
from colmap_ext.errors import UserError
from colmap_ext.features import FeatureOptions, list_images
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.mapper.flags import random_seed
from colmap_ext.matching import MatchingOptions
from colmap_ext.model_io import (OutputLayout, holds_only, is_file, is_model_folder, moved,
                                 read_model, replacing)
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
    start = time.perf_counter()
    root = Path(output_path)
    with replacing(output_path, DEMO_OUTPUT, overwrite) as new_root:
        images, truth = new_root / "images", new_root / "ground_truth"
        workspace = new_root / "workspace"
        scene = ring_scene(num_images=num_images, seed=seed)
        print(f"Rendering {num_images} views of the demo scene to {root / 'images'}/ ...")
        render_images(scene, images, seed=seed)
        write_ground_truth(scene, truth)
        workspace.mkdir()
        summary = reconstruct.run_stages(
            images, workspace, partial(moved, new=new_root, final=root), list_images(images),
            FeatureOptions(scene.camera.model.name, list(scene.camera.params)),
            MatchingOptions(seed=seed), start)
        print(reconstruct.format_summary(summary, root / "workspace"))
        print()
        report = evaluate.evaluate_and_write(
            read_model(workspace / "sparse" / "0"), read_ground_truth(truth),
            new_root / "report.json", new_root / "errors.png",
            label=str(root / "workspace" / "sparse" / "0"))
    print(f"\nModel: {root / 'workspace' / 'sparse' / '0'}   report: {root / 'report.json'}   "
          f"plots: {root / 'errors.png'}, {evaluate.scene_plot_path(root / 'errors.png')}")
    return report
