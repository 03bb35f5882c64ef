"""`colmap-ext mapper`: every flag of `colmap mapper` (flags.FLAGS), and `--project_path`,
with our calibrated mapper behind them."""

from __future__ import annotations

import argparse
import json
from typing import Any

from colmap_ext.errors import UserError
from colmap_ext.mapper.flags import (FLAGS, PATH_ALIASES, help_text, lookup, mapper_options,
                                     read_project)
from colmap_ext.mapper.options import MapperOptions, RegistrationOptions
from colmap_ext.mapper.pipeline import run


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.usage = ("colmap-ext mapper --database_path DB --image_path IMAGES --output_path OUT "
                    "[--project_path FILE.ini] [--Mapper.OPTION VALUE ...]")
    parser.allow_abbrev = False  # as COLMAP: a misspelt option is an error, not a guess
    parser.add_argument("--project_path", default=None,
                        help="COLMAP project file (.ini): its top-level keys and [Mapper] "
                             "section; flags given here win")
    parser.add_argument("--database_path", default=None)
    parser.add_argument("--image_path", default=None)
    parser.add_argument("--output_path", default=None)
    parser.add_argument("--input_path", default=None,
                        help="a model (BIN or TXT) to continue: the database's other images "
                             "are registered into it; it is read, never written")
    parser.add_argument("--image_list_path", *(f"--{name}" for name in PATH_ALIASES),
                        dest="image_list_path", default=None,
                        help="text file with one image name per line: map only these")
    parser.add_argument("--output_type", default="BIN", choices=["BIN", "TXT", "bin", "txt"])
    parser.add_argument("--order", choices=["visibility", "sequence"], default="visibility",
                        help="registration order: COLMAP's (most visible points) or the "
                             "image sequence's (the paper's)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a model already in OUTPUT_PATH/0")
    add_option_flags(parser)


def add_option_flags(parser: argparse.ArgumentParser, base: MapperOptions | None = None) -> None:
    """COLMAP's mapper options (flags.FLAGS) as flags whose destinations are the options'
    names, None when not given: what `options_from_flags` reads over `base`, the
    command's defaults (shown in the help)."""
    group = parser.add_argument_group("COLMAP's mapper options",
                                      "COLMAP 3.8's and 4.x's names; 0/1 or false/true for "
                                      "booleans. Not applicable: accepted, and named in the "
                                      "log when given another value than the default")
    for flag in FLAGS:
        group.add_argument(*(f"--{name}" for name in flag.names), dest=flag.name,
                           type=flag.parse, default=None, metavar="VALUE",
                           help=help_text(flag, base))


def options_from_flags(flags: dict[str, Any], project_values: dict[str, Any] | None = None,
                       base: MapperOptions | None = None) -> MapperOptions:
    """MapperOptions from the options given by name (None: not given), over the project
    file's values, over `base`."""
    values = dict(project_values or {})
    for name, value in flags.items():
        if value is not None:
            values[lookup(name).name] = value
    return mapper_options(values, base)


def _read_image_list(path: str | None) -> list[str] | None:
    if path is None:
        return None
    try:
        with open(path) as f:
            names = [line.strip() for line in f if line.strip()]
    except OSError as exc:
        raise UserError(f"cannot read image list {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise UserError(f"image list {path} is not text: expected one image name per "
                        "line") from None
    if not names:
        raise UserError(f"image list {path} is empty")
    return names


def main(database_path: str | None = None, image_path: str | None = None,
         output_path: str | None = None, project_path: str | None = None,
         input_path: str | None = None, image_list_path: str | None = None,
         output_type: str = "BIN", order: str = "visibility", overwrite: bool = False,
         **flags: Any) -> dict:
    """`flags`: COLMAP's options by any accepted name (`seed=0`, `**{"Mapper.min_model_size": 5}`);
    None stands for not given. Values given here win over the project file's."""
    values: dict[str, Any] = {}
    paths: dict[str, str] = {}
    if project_path is not None:
        values, paths = read_project(project_path)
    given = {"database_path": database_path, "image_path": image_path,
             "output_path": output_path, "input_path": input_path,
             "image_list_path": image_list_path}
    paths.update({key: value for key, value in given.items() if value is not None})
    missing = [key for key in ("database_path", "image_path", "output_path") if key not in paths]
    if missing:
        raise UserError(f"the option '--{missing[0]}' is required but missing")
    options = options_from_flags(flags, values,
                                 MapperOptions(registration=RegistrationOptions(order=order)))
    reconstructions = run(paths["database_path"], paths["image_path"], paths["output_path"],
                          options, overwrite=overwrite, output_type=output_type.upper(),
                          image_names=_read_image_list(paths.get("image_list_path")),
                          input_path=paths.get("input_path"))
    with open(f"{paths['output_path']}/mapper_summary.json") as f:
        summary = json.load(f)
    print(format_summary(summary, paths["output_path"]))
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
                     f"{counts['bundle adjustment iterations']} iterations")
    return "\n".join(lines)
