"""`colmap-ext compare`: our mapper and COLMAP's side by side on the same database.

Every mapper runs on its own private copy of the user's database, so all of them see the
same features and matches and the user's file stays byte for byte as it was (pycolmap
upgrades a schema in place, and COLMAP's global mapper writes relative poses into it).
All mappers hold the intrinsics fixed:
- ours: always (the method assumes calibrated cameras);
- colmap_incremental: `IncrementalPipelineOptions.constant_cameras` = every camera id,
  and `ba_refine_focal_length/principal_point/extra_params` = False;
- colmap_global: `GlobalPipelineOptions.mapper.bundle_adjustment.refine_focal_length/
  principal_point/extra_params` = False (pycolmap 4.2.1 refines focal length and
  distortion there by default; the pipeline has no constant-camera set and runs no view
  graph calibration of its own, so these flags are all it takes).
In the COLMAP copies every camera is also marked `has_prior_focal_length` (the intrinsics
are known), as pycolmap's extractor does when it is given camera parameters.

Output, in CMP:
- CMP/<mapper>/0, 1, ...: the models, largest first (like `colmap mapper`);
- CMP/report.json: per mapper the wall time, the largest model's statistics (the one
  evaluated and compared: `num_registered` counts its images) and, with a ground truth,
  every key of `colmap-ext evaluate`'s report on it; and how far each model lies from
  ours (`pycolmap.compare_reconstructions`);
- CMP/report.md: the same as tables; CMP/errors.png: the per-image errors of all mappers.
A mapper that fails is reported as failed, and the others still run.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import secrets
import shutil
import sqlite3
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_ext.colmap_mappers import (colmap_global_options, colmap_incremental_options,
                                       fix_intrinsics_in_database)
from colmap_ext.database import check_database_file, colmap_tables, copy_database
from colmap_ext.errors import UserError
from colmap_ext.features import quiet_colmap_logs
from colmap_ext.evaluate import (AUC_KEY, AUC_THRESHOLDS_DEG, MEASURES, evaluate, format_auc,
                                  summary_key)
from colmap_ext.rig_consistency import database_rig_frames, rig_consistency
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper import MapperOptions
from colmap_ext.mapper import run as run_ours
from colmap_ext.mapper.flags import random_seed
from colmap_ext.model_io import (MAPPER_OUTPUT, TEMPORARY_PREFIX, OutputLayout, is_file,
                                 replacing, write_json, write_models)
from colmap_ext.plots import plot_errors
from colmap_ext.timing import StageTimer

MAPPERS = ("ours", "colmap_incremental", "colmap_global")
REPORT_NAME = "report.json"
COMPARISON = OutputLayout("a comparison", {
    **{name: MAPPER_OUTPUT.is_output for name in MAPPERS},
    REPORT_NAME: is_file, "report.md": is_file, "errors.png": is_file})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--database_path", required=True,
                        help="COLMAP database with features and matches (left unchanged)")
    parser.add_argument("--image_path", required=True)
    parser.add_argument("--output_path", required=True,
                        help="gets <mapper>/0, ..., report.json, report.md, errors.png")
    parser.add_argument("--ground_truth", default=None,
                        help="Middlebury *_par.txt, a folder of Strecha *.camera files, or a "
                             "COLMAP model: adds the paper's pose errors")
    parser.add_argument("--mappers", default=",".join(MAPPERS),
                        help=f"comma-separated, from {', '.join(MAPPERS)} (default: all)")
    parser.add_argument("--seed", type=random_seed, default=None,
                        help="random seed of every mapper (default: random, recorded in the report)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the report and models of an earlier comparison")


def main(database_path: str, image_path: str, output_path: str, ground_truth: str | None = None,
         mappers: str = ",".join(MAPPERS), seed: int | None = None,
         overwrite: bool = False) -> dict:
    report = compare(database_path, image_path, output_path, ground_truth=ground_truth,
                     mappers=mappers, seed=seed, overwrite=overwrite)
    print()
    print(format_mapper_table(report))
    distances = format_distance_table(report)
    if distances:
        print()
        print(distances)
    print(f"\nReport: {Path(output_path) / 'report.md'}")
    return report


# ---------------------------------------------------------------------------------------
# Running one mapper


@dataclass
class MapperRun:
    """A mapper's models (largest first; empty if it failed), wall time and failure."""

    reconstructions: list[pycolmap.Reconstruction]
    time_s: float
    error: str | None = None


def run_mapper(name: str, database_path: Path, image_path: Path, output_path: Path,
               seed: int, progress: bool = True, num_threads: int = -1) -> MapperRun:
    """Run mapper `name` on `database_path` (a private copy: it may be modified) and write
    its models to output_path/0, 1, ... (largest first). Failures are returned, not raised.

    The time covers the mapping call: loading the database, mapping, point colours and
    writing the models once (COLMAP's are then copied into place, untimed).
    """
    runner = {"ours": _run_ours, "colmap_incremental": _run_colmap_incremental,
              "colmap_global": _run_colmap_global}[name]
    timing = StageTimer()
    try:
        reconstructions = runner(database_path, image_path, output_path, seed, progress,
                                 num_threads, timing)
    except Exception as exc:  # a failing mapper is a result of the comparison, not its end
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        if not isinstance(exc, UserError):
            message = f"{type(exc).__name__}: {message}"
        return MapperRun([], timing.seconds["mapping"], message)
    if not reconstructions:
        return MapperRun([], timing.seconds["mapping"], "no model could be reconstructed")
    return MapperRun(reconstructions, timing.seconds["mapping"])


def _largest_first(reconstructions: dict[int, pycolmap.Reconstruction]) -> list[pycolmap.Reconstruction]:
    models = [r for _, r in sorted(reconstructions.items()) if r.num_reg_images() > 0]
    return sorted(models, key=lambda r: -r.num_reg_images())


def _run_ours(database_path: Path, image_path: Path, output_path: Path, seed: int,
              progress: bool, num_threads: int, timing: StageTimer) -> list[pycolmap.Reconstruction]:
    options = MapperOptions(seed=seed, num_threads=num_threads)
    with timing("mapping"):
        reconstructions = run_ours(database_path, image_path, output_path, options,
                                   overwrite=True, progress=progress)
    return _largest_first(reconstructions)


def _write_largest_first(reconstructions: dict[int, pycolmap.Reconstruction],
                         output_path: Path) -> list[pycolmap.Reconstruction]:
    models = _largest_first(reconstructions)
    if models:
        try:
            output_path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"cannot create {output_path}: {exc.strerror}") from None
        write_models(models, output_path)
    return models


def _run_colmap_incremental(database_path: Path, image_path: Path, output_path: Path, seed: int,
                            progress: bool, num_threads: int,
                            timing: StageTimer) -> list[pycolmap.Reconstruction]:
    camera_ids, num_images = fix_intrinsics_in_database(database_path)
    options = colmap_incremental_options(camera_ids, seed, num_threads)
    bar = tqdm(total=num_images, desc="registered", unit="image", disable=not progress)

    def advance(n: int) -> Callable[[], None]:
        return lambda: bar.update(min(n, bar.total - bar.n))

    staging = Path(tempfile.mkdtemp(prefix=".colmap-ext-incremental-", dir=database_path.parent))
    try:
        with quiet_colmap_logs(), timing("mapping"):
            reconstructions = pycolmap.incremental_mapping(
                database_path, image_path, staging, options,
                initial_image_pair_callback=advance(2), next_image_callback=advance(1))
        return _write_largest_first(reconstructions, output_path)
    finally:
        bar.close()
        shutil.rmtree(staging, ignore_errors=True)


def _run_colmap_global(database_path: Path, image_path: Path, output_path: Path, seed: int,
                       progress: bool, num_threads: int,
                       timing: StageTimer) -> list[pycolmap.Reconstruction]:
    _, num_images = fix_intrinsics_in_database(database_path)
    options = colmap_global_options(seed, num_images, num_threads)
    staging = Path(tempfile.mkdtemp(prefix=".colmap-ext-global-", dir=database_path.parent))
    try:
        with quiet_colmap_logs(), timing("mapping"):
            reconstructions = pycolmap.global_mapping(database_path, image_path, staging, options)
        return _write_largest_first(reconstructions, output_path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def _no_native_stdout() -> Iterator[None]:
    """Silence what C++ prints on file descriptor 1 (compare_reconstructions' statistics)."""
    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


# ---------------------------------------------------------------------------------------
# The comparison


def parse_mappers(mappers: str | Sequence[str]) -> list[str]:
    names = [m.strip() for m in mappers.split(",")] if isinstance(mappers, str) else list(mappers)
    names = [m for m in names if m]
    if not names:
        raise UserError(f"--mappers is empty; choose from {', '.join(MAPPERS)}")
    unknown = [m for m in names if m not in MAPPERS]
    if unknown:
        raise UserError(f"unknown mapper {unknown[0]!r} in --mappers; choose from {', '.join(MAPPERS)}")
    if len(set(names)) != len(names):
        raise UserError("--mappers names a mapper twice")
    return names


def check_inputs(database_path: Path, image_path: Path,
                 ground_truth: str | os.PathLike | None) -> GroundTruth | None:
    """The checks that need no copy of the database; returns the ground truth."""
    check_database_file(database_path)
    if not image_path.is_dir():
        raise UserError(f"image path not found: {image_path}")
    return read_ground_truth(ground_truth) if ground_truth is not None else None


def read_image_names(copy: Path, database_path: Path) -> list[str]:
    """The image names of a COLMAP database (a private copy of `database_path`)."""
    try:
        with closing(sqlite3.connect(copy)) as conn:
            colmap_tables(conn, database_path)
            return [row[0] for row in conn.execute("SELECT name FROM images")]
    except sqlite3.Error as exc:
        raise UserError(f"cannot read database {database_path}: {exc}") from None


def check_ground_truth_names(names: list[str], truth: GroundTruth, database_path: Path) -> None:
    """At least two ground-truth images must be in the database (by name, or by a basename)."""
    exact, bases = set(names), {PurePosixPath(name).name for name in names}
    found = [n for n in truth.poses if n in exact or PurePosixPath(n).name in bases]
    if len(found) < 2:
        raise UserError(f"only {len(found)} of the {len(truth.poses)} ground-truth images are in "
                        f"the database {database_path}; is it the right ground truth?")


def compare(database_path: str | os.PathLike, image_path: str | os.PathLike,
            output_path: str | os.PathLike, *, ground_truth: str | os.PathLike | None = None,
            mappers: str | Sequence[str] = MAPPERS, seed: int | None = None,
            overwrite: bool = False, progress: bool = True) -> dict:
    """Run the mappers, write CMP/<mapper>/..., report.json, report.md (and errors.png with a
    ground truth); returns the report.

    The user's database is read once into a private copy (database.copy_database); every
    mapper gets a copy of that copy. Every check runs before the first mapper. The whole
    comparison is built beside OUTPUT_PATH and replaces an earlier one at the end
    (model_io.replacing).
    """
    database_path, image_path = Path(database_path), Path(image_path)
    names = parse_mappers(mappers)
    truth = check_inputs(database_path, image_path, ground_truth)
    with replacing(output_path, COMPARISON, overwrite) as new_output:
        work = Path(tempfile.mkdtemp(prefix=f"{TEMPORARY_PREFIX}compare-", dir=new_output.parent))
        try:
            source = work / "source" / "database.db"
            source.parent.mkdir()
            copy_database(database_path, source)
            image_names = read_image_names(source, database_path)
            if truth is not None:
                check_ground_truth_names(image_names, truth, database_path)
            return _compare(source, len(image_names), database_path, image_path, new_output,
                            ground_truth, truth, names, seed, progress, work)
        finally:
            shutil.rmtree(work, ignore_errors=True)


def _compare(source: Path, num_images: int, database_path: Path, image_path: Path,
             output_path: Path, ground_truth: str | os.PathLike | None, truth: GroundTruth | None,
             names: list[str], seed: int | None, progress: bool, work: Path) -> dict:
    seed = secrets.randbits(31) if seed is None else seed
    report: dict = {
        "database_path": str(database_path), "image_path": str(image_path),
        "ground_truth": None if ground_truth is None else str(ground_truth),
        "seed": seed, "intrinsics": "fixed in every mapper", "mappers": {},
    }
    models: dict[str, pycolmap.Reconstruction] = {}
    evaluations: dict[str, dict] = {}
    frames = database_rig_frames(source)
    for index, name in enumerate(names, start=1):
        copy = work / name / "database.db"
        copy.parent.mkdir()
        copy_database(source, copy)
        if progress:
            print(f"[{index}/{len(names)}] {name}", file=sys.stderr, flush=True)
        result = run_mapper(name, copy, image_path, output_path / name, seed, progress)
        shutil.rmtree(copy.parent, ignore_errors=True)
        entry = _mapper_entry(result, num_images)
        if result.error is None:
            models[name] = result.reconstructions[0]
            consistency = rig_consistency(result.reconstructions[0], frames)
            if consistency is not None:
                entry["rig_consistency"] = consistency
            if truth is not None:
                try:
                    evaluations[name] = evaluate(result.reconstructions[0], truth)
                except UserError as exc:
                    entry["evaluation_error"] = str(exc)
                else:
                    entry.update({k: v for k, v in evaluations[name].items()
                                  if k != "num_registered"})
        report["mappers"][name] = entry
        if progress:
            print(f"  {name}: {_one_line(entry)}", file=sys.stderr, flush=True)
    report["model_comparison"] = model_distances(models, names)
    errors_png = output_path / "errors.png"
    if evaluations:
        plot_errors(evaluations, errors_png)
    write_json(report, output_path / REPORT_NAME)
    _write_text(output_path / "report.md", format_markdown(report, has_plot=bool(evaluations)))
    return report


def _mapper_entry(result: MapperRun, num_images: int) -> dict:
    """Time and the largest model's statistics (per model too, under "models")."""
    per_model = [{
        "num_registered": r.num_reg_images(),
        "num_points3D": r.num_points3D(),
        "mean_track_length": float(r.compute_mean_track_length()),
        "mean_reprojection_error": float(r.compute_mean_reprojection_error()),
    } for r in result.reconstructions]
    largest = per_model[0] if per_model else {
        "num_registered": 0, "num_points3D": 0, "mean_track_length": None,
        "mean_reprojection_error": None}
    entry = {"time_s": round(result.time_s, 3), "num_images": num_images,
             "num_models": len(per_model), **largest,
             "num_registered_all_models": sum(m["num_registered"] for m in per_model),
             "models": per_model}
    if result.error is not None:
        entry["error"] = result.error
    return entry


def _one_line(entry: dict) -> str:
    if "error" in entry:
        return f"failed after {entry['time_s']:.1f} s: {entry['error']}"
    line = (f"{entry['num_registered']}/{entry['num_images']} registered in the largest of "
            f"{entry['num_models']} model(s), {entry['num_points3D']} points, {entry['time_s']:.1f} s")
    if "R_err_max_deg" in entry:
        line += f", R_err max {entry['R_err_max_deg']:.3f} deg"
    if "rig_consistency" in entry:
        line += f", rig kept to {entry['rig_consistency']['rotation_max_deg']:.3g} deg"
    return line


def model_distances(models: dict[str, pycolmap.Reconstruction], order: list[str]) -> dict:
    """Each model against the reference (ours, else the first mapper that gave a model) by
    `pycolmap.compare_reconstructions`: rotation errors in degrees, camera-centre errors in
    units of the reference's camera spread (RMS distance of its centres to their mean)."""
    available = [name for name in order if name in models]
    if len(available) < 2:
        return {}
    reference = "ours" if "ours" in available else available[0]
    ref = models[reference]
    centres = np.array([image.projection_center() for image in ref.images.values() if image.has_pose])
    spread = float(np.sqrt(np.mean(np.sum((centres - centres.mean(axis=0)) ** 2, axis=1))))
    result: dict = {"reference": reference, "centre_error_unit": "RMS distance of the reference's "
                    "camera centres to their mean", "mappers": {}}
    for name in available:
        if name == reference:
            continue
        try:
            with quiet_colmap_logs(), _no_native_stdout():
                comparison = pycolmap.compare_reconstructions(models[name], ref)
        except (RuntimeError, ValueError) as exc:
            comparison, failure = None, str(exc).strip().splitlines()[0]
        else:
            failure = ("compare_reconstructions found no alignment (too few common images or "
                       "points, or poses too far apart)")
        if comparison is None or not comparison["errors"]:
            result["mappers"][name] = {"error": failure}
            continue
        rotation = np.array([e.rotation_error_deg for e in comparison["errors"]])
        centre = np.array([e.proj_center_error for e in comparison["errors"]]) / max(spread, 1e-12)
        result["mappers"][name] = {
            "num_common_images": len(rotation),
            "rotation_error_max_deg": float(rotation.max()),
            "rotation_error_median_deg": float(np.median(rotation)),
            "centre_error_max": float(centre.max()),
            "centre_error_median": float(np.median(centre)),
        }
    return result


# ---------------------------------------------------------------------------------------
# Tables


def _number(value, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _max_median(entry: dict, measure: str, digits: int) -> str:
    maximum, median = entry.get(summary_key(measure, "max")), entry.get(summary_key(measure, "median"))
    if maximum is None:
        return "–"
    return f"{maximum:.{digits}f} / {median:.{digits}f}"


def format_mapper_table(report: dict) -> str:
    """One row per mapper: registration, model statistics, time and (with a ground truth)
    the pose errors as max / median."""
    with_gt = report.get("ground_truth") is not None
    reference = report["mappers"].get("colmap_incremental", {})
    reference_s = None if "error" in reference else reference.get("time_s")
    headings = ["mapper", "registered", "models", "points", "track length", "reproj. error [px]",
                "time [s]"] + (["time / COLMAP incremental"] if reference_s else [])
    if with_gt:
        headings += [f"{key.removesuffix('_deg')} max / median" + (" [deg]" if unit == "deg" else "")
                     for key, unit in MEASURES.items()]
        headings.append("AUC@" + "/".join(f"{t:g}" for t in AUC_THRESHOLDS_DEG) + " deg [%]")
    rows = []
    for name, entry in report["mappers"].items():
        registered = f"{entry['num_registered']}/{entry['num_images']}"
        if entry["num_models"] > 1:
            others, more = entry["num_registered_all_models"] - entry["num_registered"], entry["num_models"] - 1
            registered += f" (+{others} in {more} other model{'s' if more > 1 else ''})"
        if "error" in entry:
            registered = f"failed: {entry['error']}"
        row = [name, registered, str(entry["num_models"]), str(entry["num_points3D"]),
               _number(entry["mean_track_length"], 2), _number(entry["mean_reprojection_error"], 3),
               f"{entry['time_s']:.2f}"]
        if reference_s:
            row.append("–" if "error" in entry else f"{entry['time_s'] / reference_s:.2f}x")
        if with_gt:
            digits = {"R_err_deg": 3, "T_err_deg": 3, "C_err": 4, "C_err_aligned": 4}
            row += [_max_median(entry, key, digits[key]) for key in MEASURES]
            row.append(format_auc(entry) if AUC_KEY in entry else "–")
        rows.append(row)
    return _markdown_table(headings, rows)


def format_distance_table(report: dict) -> str:
    comparison = report.get("model_comparison") or {}
    if not comparison.get("mappers"):
        return ""
    reference = comparison["reference"]
    headings = ["mapper", "common images", "rotation max / median [deg]",
                "centre max / median [camera spread]"]
    rows = []
    for name, distance in comparison["mappers"].items():
        if "error" in distance:
            rows.append([name, "–", distance["error"], "–"])
            continue
        rows.append([name, str(distance["num_common_images"]),
                     f"{distance['rotation_error_max_deg']:.3f} / {distance['rotation_error_median_deg']:.3f}",
                     f"{distance['centre_error_max']:.4f} / {distance['centre_error_median']:.4f}"])
    return (f"Distance of each model from the reference, {reference} (pycolmap."
            "compare_reconstructions on the largest models, aligned by reprojection; centre "
            "errors in units of the reference's camera spread, the RMS distance of its camera "
            "centres to their mean):\n\n" + _markdown_table(headings, rows))


def _markdown_table(headings: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h)
              for i, h in enumerate(headings)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(headings, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |" for row in rows]
    return "\n".join(lines)


def format_markdown(report: dict, has_plot: bool) -> str:
    lines = [
        "# Mapper comparison", "",
        f"- database: `{report['database_path']}` (features and matches shared by all mappers, "
        "each on a private copy)",
        f"- images: `{report['image_path']}`",
        f"- ground truth: `{report['ground_truth']}`" if report["ground_truth"] else
        "- ground truth: none (no pose errors)",
        f"- seed: {report['seed']}; intrinsics held fixed in every mapper "
        "(COLMAP: constant cameras, no focal/principal point/distortion refinement)",
        "", "## Mappers", "", format_mapper_table(report), "",
        "*registered*: images in the largest model (the one evaluated and compared) / images "
        "in the database. *time*: wall time of the mapping call (reading the database, mapping, "
        "writing the model), and its ratio to COLMAP incremental's in this run; seconds on "
        "one machine say little about another, the ratio more.",
    ]
    if report["ground_truth"]:
        lines.append("Pose errors (the paper's measures, relative to the first registered "
                     "image): R_err, T_err in degrees; C_err, C_err_aligned in units of the "
                     "distance between the first two ground-truth cameras. AUC (COLMAP's "
                     "benchmark): per pair of images the larger of the relative rotation and "
                     "translation-direction errors, images outside the model as infinite "
                     "errors; area under the recall curve up to each threshold, in percent.")
    failed = {n: e["evaluation_error"] for n, e in report["mappers"].items() if "evaluation_error" in e}
    for name, message in failed.items():
        lines.append(f"- {name}: not evaluated: {message}")
    distances = format_distance_table(report)
    if distances:
        lines += ["", "## Distance between the models", "", distances]
    if has_plot:
        lines += ["", "## Per-image errors", "", "![per-image errors](errors.png)"]
    return "\n".join(lines) + "\n"


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise UserError(f"could not write {path}: {exc.strerror or exc}") from None
