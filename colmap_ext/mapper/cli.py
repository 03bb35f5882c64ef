"""`colmap-ext mapper`: COLMAP's `mapper` flags, our calibrated mapper behind them."""

from __future__ import annotations

import argparse
import json

from colmap_ext.errors import UserError
from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.pipeline import run


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--database_path", required=True)
    parser.add_argument("--image_path", required=True)
    parser.add_argument("--output_path", required=True)
    parser.add_argument("--image_list_path", default=None,
                        help="text file with one image name per line: map only these")
    parser.add_argument("--output_type", default="BIN", choices=["BIN", "TXT", "bin", "txt"])
    parser.add_argument("--Mapper.init_image_id1", dest="init_image_id1", type=int, default=-1)
    parser.add_argument("--Mapper.init_image_id2", dest="init_image_id2", type=int, default=-1)
    parser.add_argument("--order", choices=["visibility", "sequence"], default="visibility",
                        help="registration order: COLMAP's (most visible points) or the "
                             "image sequence's (the paper's)")
    parser.add_argument("--seed", type=int, default=None, help="RANSAC seed, for repeatable runs")
    parser.add_argument("--num_threads", type=int, default=-1)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a model already in OUTPUT_PATH/0")


def _read_image_list(path: str | None) -> list[str] | None:
    if path is None:
        return None
    try:
        with open(path) as f:
            names = [line.strip() for line in f if line.strip()]
    except OSError as exc:
        raise UserError(f"cannot read image list {path}: {exc.strerror}") from None
    if not names:
        raise UserError(f"image list {path} is empty")
    return names


def main(database_path: str, image_path: str, output_path: str, image_list_path: str | None = None,
         output_type: str = "BIN", init_image_id1: int = -1, init_image_id2: int = -1,
         order: str = "visibility", seed: int | None = None, num_threads: int = -1,
         overwrite: bool = False) -> dict:
    options = MapperOptions(order=order, init_image_id1=init_image_id1,
                            init_image_id2=init_image_id2, seed=seed, num_threads=num_threads)
    reconstructions = run(database_path, image_path, output_path, options, overwrite=overwrite,
                          output_type=output_type.upper(),
                          image_names=_read_image_list(image_list_path))
    with open(f"{output_path}/mapper_summary.json") as f:
        summary = json.load(f)
    print(format_summary(summary, output_path))
    return {"reconstructions": reconstructions, "summary": summary}


def format_summary(summary: dict, output_path: str) -> str:
    lines = [f"Registered {summary['num_registered']} images in {summary['num_models']} "
             f"model(s), written to {output_path}/"]
    for index, model in enumerate(summary["models"]):
        lines.append(f"  {index}: {model['num_registered']} images, {model['num_points3D']} points, "
                     f"mean track length {model['mean_track_length']:.2f}, "
                     f"mean reprojection error {model['mean_reprojection_error']:.3f} px")
    times = ", ".join(f"{stage} {seconds:.2f}s" for stage, seconds in summary["time_s"].items())
    lines.append(f"Time: {times}")
    counts = summary.get("counts", {})
    if counts.get("bundle adjustment solves"):
        lines.append(f"Bundle adjustment: {counts['bundle adjustment solves']} solves, "
                     f"{counts['bundle adjustment iterations']} Ceres iterations")
    return "\n".join(lines)
