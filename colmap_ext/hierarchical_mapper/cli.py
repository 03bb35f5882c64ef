"""`colmap-ext hierarchical_mapper`: COLMAP's command for large sets, with our mapper."""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from colmap_ext.database import check_database_file, read_database
from colmap_ext.errors import UserError
from colmap_ext.hierarchical_mapper.options import MAPPER_DEFAULTS, HierarchicalOptions
from colmap_ext.hierarchical_mapper.pipeline import hierarchical_mapping
from colmap_ext.mapper.cli import add_option_flags, format_summary, options_from_flags
from colmap_ext.mapper.pipeline import colours_readable, write_result
from colmap_ext.model_io import MAPPER_OUTPUT, OUTPUT_TYPES, replacing
from colmap_ext.timing import StageTimer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.usage = ("colmap-ext hierarchical_mapper --database_path DB --image_path IMAGES "
                    "--output_path OUT [--leaf_max_num_images N] [--image_overlap N] "
                    "[--num_workers N] [--ray_address ADDRESS] [--Mapper.OPTION VALUE ...]")
    parser.allow_abbrev = False
    defaults = HierarchicalOptions()
    parser.add_argument("--database_path", required=True)
    parser.add_argument("--image_path", required=True)
    parser.add_argument("--output_path", required=True)
    parser.add_argument("--leaf_max_num_images", type=int, default=defaults.leaf_max_num_images,
                        help="largest cluster, before the overlap is added")
    parser.add_argument("--image_overlap", type=int, default=defaults.image_overlap,
                        help="images each cluster shares with its neighbours")
    parser.add_argument("--num_workers", type=int, default=defaults.num_workers,
                        help="clusters mapped at once without Ray; -1: one per core")
    parser.add_argument("--ray_address", default=None,
                        help="map the clusters as Ray tasks: auto (the running cluster), "
                             "local (start one here) or HOST:PORT")
    parser.add_argument("--output_type", default="BIN", choices=["BIN", "TXT", "bin", "txt"])
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a model already in OUTPUT_PATH/0")
    add_option_flags(parser, base=MAPPER_DEFAULTS)


def main(database_path: str, image_path: str, output_path: str,
         leaf_max_num_images: int = HierarchicalOptions.leaf_max_num_images,
         image_overlap: int = HierarchicalOptions.image_overlap,
         num_workers: int = HierarchicalOptions.num_workers, ray_address: str | None = None,
         output_type: str = "BIN", overwrite: bool = False, progress: bool = True,
         **flags: Any) -> dict:
    """Map the database cluster by cluster and write OUTPUT/0, ... and
    OUTPUT/mapper_summary.json; `flags`: COLMAP's mapper options by name (None: not
    given), as for `colmap-ext mapper`."""
    from colmap_ext.distributed import check_address, connect

    start = time.perf_counter()
    options = HierarchicalOptions(leaf_max_num_images, image_overlap, num_workers)
    if output_type.upper() not in OUTPUT_TYPES:
        raise UserError(f"--output_type must be BIN or TXT, got {output_type!r}")
    if ray_address is not None:
        check_address(ray_address)
    mapper_options = options_from_flags(flags, base=MAPPER_DEFAULTS)
    check_database_file(Path(database_path))
    images = Path(image_path)
    if not images.is_dir():
        raise UserError(f"image path not found: {images}")
    with replacing(output_path, MAPPER_OUTPUT, overwrite) as new_output:
        timer = StageTimer()
        with timer("read database"):
            db = read_database(database_path)
        extract_colors = mapper_options.extract_colors and colours_readable(db, images)
        if ray_address is None:
            reconstructions, reports = hierarchical_mapping(db, mapper_options, options, None,
                                                            timer, progress)
        else:
            with connect(ray_address) as cluster:
                reconstructions, reports = hierarchical_mapping(db, mapper_options, options,
                                                                cluster, timer, progress)
        if not reconstructions:
            raise UserError("no model could be reconstructed: no cluster gave a relative pose "
                            "with enough well-triangulated points")
        summary = write_result(reconstructions, new_output, images, extract_colors,
                               output_type.upper(), timer, start,
                               clusters=[asdict(report) for report in reports])
    print(format_summary(summary, str(output_path)))
    return {"reconstructions": dict(enumerate(reconstructions)), "summary": summary}
