"""Mapper time and peak memory: `colmap-ext mapper` against COLMAP's incremental and
global mappers, each a whole process on its own copy of the same database.

Sets (--sets, all by default):
- the real sets under --data ($COLMAP_EXT_DATA): every folder with images (in it or in
  images/) and a Middlebury *_par.txt or a Strecha gt_cameras/ folder; the database is
  pycolmap's default SIFT and exhaustive matching with the ground-truth intrinsics;
- demo: the rendered ring of `make demo`, built the same way;
- turntable: a synthetic ring of 363 views (long tracks), no images;
- synthetic200, synthetic1000, synthetic2000: a synthetic walk along a facade
  (`trajectory_scene`, about 1000 keypoints an image, 0.5 px noise, 20 % wrong matches).

Per set, --runs rounds; in each round every mapper runs once, the order turning from
round to round, on a fresh copy of the database. Ours runs as a user runs it
(`colmap-ext mapper`); COLMAP's through `pycolmap.incremental_mapping` /
`global_mapping` with the intrinsics fixed (colmap_ext.colmap_mappers), in a child
that imports pycolmap alone. Wall time is the child's, from start to exit; peak memory
its maximum resident set (GNU time). The table gives medians and ratios to COLMAP
incremental in the same run, and the last round's model against the ground truth.

With --end_to_end (real sets and demo), each run starts from the images instead: ours
`colmap-ext reconstruct` with the known intrinsics (our features, matching and mapper),
COLMAP's pycolmap extraction (default SIFT, the same intrinsics), exhaustive matching
and mapper, in one child.

    python benchmarks/mapper_speed.py [--sets temple,dino,...] [--runs 3] [--seed 0]
        [--mappers ours,colmap_incremental] [--end_to_end]
        [--work_dir DIR] [--markdown BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where used: a COLMAP worker child loads pycolmap alone
    from accuracy import Dataset

SCRIPT = Path(__file__).resolve()
MAPPERS = ("ours", "colmap_incremental", "colmap_global")
SYNTHETIC_SIZES = {"synthetic200": 200, "synthetic1000": 1000, "synthetic2000": 2000}
TURNTABLE_VIEWS = 363


@dataclass
class PreparedSet:
    name: str
    database: Path
    image_path: Path
    ground_truth: Path
    num_images: int
    camera_model: str = ""  # the known intrinsics, for --end_to_end
    camera_params: str = ""
    sequential_overlap: int = 0  # end to end, COLMAP's sequential matching (0: exhaustive)


def colmap_worker(args: argparse.Namespace) -> int:
    """In the child: one of COLMAP's mappers, as `colmap-ext compare` sets it up."""
    import numpy  # noqa: F401  (before pycolmap: README, "Known problem")
    import pycolmap

    from colmap_ext.colmap_mappers import (colmap_global_options, colmap_incremental_options,
                                           fix_intrinsics_in_database)

    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.WARNING)
    if args.camera_model:  # end to end: COLMAP's own extraction and matching first
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = args.camera_model
        reader.camera_params = args.camera_params
        pycolmap.extract_features(args.database, args.images, reader_options=reader,
                                  camera_mode=pycolmap.CameraMode.SINGLE, device=pycolmap.Device.cpu)
        if args.sequential_overlap:
            pairing = pycolmap.SequentialPairingOptions(overlap=args.sequential_overlap)
            pycolmap.match_sequential(args.database, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(args.database, device=pycolmap.Device.cpu)
    camera_ids, num_images = fix_intrinsics_in_database(Path(args.database))
    Path(args.output).mkdir(parents=True, exist_ok=True)
    if args.worker == "colmap_incremental":
        pycolmap.incremental_mapping(args.database, args.images, args.output,
                                     colmap_incremental_options(camera_ids, args.seed))
    else:
        pycolmap.global_mapping(args.database, args.images, args.output,
                                colmap_global_options(args.seed, num_images))
    return 0


def mapper_command(mapper: str, prepared: PreparedSet, folder: Path, seed: int,
                   end_to_end: bool) -> tuple[list[str], Path]:
    """The command of one run in `folder`, and the folder its models end up in. End to end,
    from the images: ours `colmap-ext reconstruct`, COLMAP's extraction, exhaustive (or
    the set's sequential) matching and mapper; otherwise each mapper on its copy of the
    prepared database."""
    database = folder / "database.db"
    if not end_to_end:
        shutil.copyfile(prepared.database, database)
    executable = str(Path(sys.executable).with_name("colmap-ext"))
    if mapper == "ours" and end_to_end:
        return [executable, "reconstruct", "--image_path", str(prepared.image_path),
                "--workspace_path", str(folder / "out"), "--camera_model", prepared.camera_model,
                "--camera_params", prepared.camera_params, "--seed", str(seed)], folder / "out" / "sparse"
    if mapper == "ours":
        return [executable, "mapper", "--database_path", str(database), "--image_path",
                str(prepared.image_path), "--output_path", str(folder / "out"),
                "--seed", str(seed)], folder / "out"
    camera = ["--camera_model", prepared.camera_model, "--camera_params", prepared.camera_params,
              "--sequential_overlap", str(prepared.sequential_overlap)] if end_to_end else []
    return [sys.executable, str(SCRIPT), "--worker", mapper, "--database", str(database),
            "--images", str(prepared.image_path), "--output", str(folder / "out"),
            "--seed", str(seed), *camera], folder / "out"


def timed_run(command: list[str], log: Path) -> dict:
    """Wall seconds, CPU seconds (user and system), peak resident MiB and exit code of one
    child process, from GNU time (Debian's `time`): a child forked from this process would
    count this process's own memory as its peak."""
    usage = log.with_suffix(".usage")
    with log.open("w") as out:
        start = time.perf_counter()
        process = subprocess.run(["/usr/bin/time", "-f", "%M %U %S", "-o", str(usage), *command],
                                 stdout=out, stderr=subprocess.STDOUT)
        seconds = time.perf_counter() - start
    peak_kib, user_s, system_s = usage.read_text().split()[-3:]
    return {"time_s": seconds, "cpu_s": float(user_s) + float(system_s),
            "peak_mib": int(peak_kib) / 1024, "exit_code": process.returncode}


# ---------------------------------------------------------------------------------------
# Sets


def real_sets(root: Path) -> dict[str, Dataset]:
    """The data sets under `root` (accuracy.find_datasets), by name."""
    from accuracy import find_datasets

    return {dataset.name: dataset for dataset in find_datasets(root)}


def prepare_real(dataset: Dataset, work: Path) -> PreparedSet:
    from accuracy import build_database

    database = work / dataset.name / "database.db"
    if not database.exists():
        database.parent.mkdir(parents=True, exist_ok=True)
        build_database(dataset, database)
    return PreparedSet(dataset.name, database, dataset.image_path, dataset.ground_truth,
                       len(dataset.image_names), dataset.camera_model,
                       ",".join(repr(p) for p in dataset.camera_params))


def prepare_demo(work: Path, seed: int) -> PreparedSet:
    from accuracy import build_database, demo_dataset

    database = work / "demo" / "database.db"
    dataset = demo_dataset(work / "demo", seed)
    if not database.exists():
        build_database(dataset, database)
    return PreparedSet("demo", database, dataset.image_path, dataset.ground_truth,
                       len(dataset.image_names), dataset.camera_model,
                       ",".join(repr(p) for p in dataset.camera_params))


def prepare_synthetic(name: str, work: Path, seed: int) -> PreparedSet:
    """A synthetic database with placeholder images (our mapper reads colours from them)."""
    from colmap_ext.synthetic import (points_for_keypoints, ring_scene, scene_points, trajectory_scene,
                                      write_ground_truth, write_placeholder_images,
                                      write_synthetic_database)

    folder = work / name
    if name == "turntable":
        scene = ring_scene(num_images=TURNTABLE_VIEWS, seed=seed)
        points = scene_points(scene, 8000, seed=seed)
    else:
        scene = trajectory_scene(num_images=SYNTHETIC_SIZES[name], seed=seed)
        points = points_for_keypoints(scene, 1000, seed=seed)
    if not (folder / "database.db").exists():
        shutil.rmtree(folder, ignore_errors=True)
        (folder / "images").mkdir(parents=True)
        write_synthetic_database(folder / "database.db", scene, points, noise_px=0.5,
                                 outlier_ratio=0.2, seed=seed, two_view_geometries=True)
        write_placeholder_images(folder / "images", scene.image_names)
        write_ground_truth(scene, folder / "ground_truth")
    return PreparedSet(name, folder / "database.db", folder / "images",
                       folder / "ground_truth", scene.num_images)


def prepare(name: str, data: dict[str, Dataset], work: Path, seed: int) -> PreparedSet:
    if name in data:
        return prepare_real(data[name], work)
    if name == "demo":
        return prepare_demo(work, seed)
    return prepare_synthetic(name, work, seed)


# ---------------------------------------------------------------------------------------
# Runs and the table


def largest_model(output: Path):
    import pycolmap

    models = [pycolmap.Reconstruction(folder) for folder in sorted(output.iterdir())
              if (folder / "images.bin").is_file() or (folder / "images.txt").is_file()]
    return max(models, key=lambda m: m.num_reg_images(), default=None)


def measure_set(prepared: PreparedSet, mappers: list[str], runs: int, seed: int,
                work: Path, end_to_end: bool = False) -> dict[str, dict]:
    from colmap_ext.evaluate import evaluate
    from colmap_ext.ground_truth import read_ground_truth

    results, models = run_rounds(prepared, mappers, runs, seed, work, end_to_end)
    truth = read_ground_truth(prepared.ground_truth)
    for mapper, entry in results.items():
        output = models[mapper]
        model = largest_model(output) if output.is_dir() else None
        if model is None or model.num_reg_images() < 2:
            entry["error"] = "no model"
            continue
        report = evaluate(model, truth)
        entry.update(num_registered=model.num_reg_images(),
                     R_err_max_deg=report["R_err_max_deg"],
                     R_err_median_deg=report["R_err_median_deg"],
                     C_err_max=report["C_err_max"])
    return results


def run_rounds(prepared: PreparedSet, mappers: list[str], runs: int, seed: int, work: Path,
               end_to_end: bool = False) -> tuple[dict[str, dict], dict[str, Path]]:
    """`runs` rounds of every mapper on the set, the order turning each round: per mapper
    {"runs": [timed_run results]}, and the folder of its last round's models."""
    results: dict[str, dict] = {m: {"runs": []} for m in mappers}
    models: dict[str, Path] = {}
    for round_index in range(runs):
        turn = round_index % len(mappers)
        for mapper in mappers[turn:] + mappers[:turn]:
            folder = work / prepared.name / "runs" / mapper
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            command, models[mapper] = mapper_command(mapper, prepared, folder, seed, end_to_end)
            run = timed_run(command, folder / "log.txt")
            print(f"  {prepared.name} {mapper} round {round_index + 1}: {run['time_s']:.1f} s, "
                  f"{run['peak_mib']:.0f} MiB, exit {run['exit_code']}", file=sys.stderr, flush=True)
            results[mapper]["runs"].append(run)
    return results, models


def summarize(results: dict[str, dict]) -> None:
    """Medians of each mapper's runs, and ratios to COLMAP incremental's medians."""
    for entry in results.values():
        ok = [r for r in entry["runs"] if r["exit_code"] == 0]
        entry["time_s"] = statistics.median(r["time_s"] for r in ok) if ok else None
        entry["time_range"] = (min(r["time_s"] for r in ok), max(r["time_s"] for r in ok)) if ok else None
        entry["cpu_s"] = statistics.median(r["cpu_s"] for r in ok) if ok else None
        entry["peak_mib"] = statistics.median(r["peak_mib"] for r in ok) if ok else None
    reference = results.get("colmap_incremental", {})
    for entry in results.values():
        for key in ("time_s", "cpu_s", "peak_mib"):
            if entry.get(key) and reference.get(key):
                entry[f"{key}_ratio"] = entry[key] / reference[key]


def table(all_results: dict[str, tuple[PreparedSet, dict[str, dict]]]) -> str:
    from accuracy import markdown_table

    headings = ["set", "images", "mapper", "registered", "R_err max / median [deg]", "C_err max",
                "time [s] median (min-max)", "time / COLMAP inc.", "peak memory [MiB]",
                "memory / COLMAP inc."]
    rows = []
    for name, (prepared, results) in all_results.items():
        for mapper, entry in results.items():
            def ratio(key: str) -> str:
                return f"{entry[key]:.2f}x" if key in entry else "–"
            time_cell = "failed" if entry["time_s"] is None else \
                f"{entry['time_s']:.1f} ({entry['time_range'][0]:.1f}-{entry['time_range'][1]:.1f})"
            accuracy = "error" in entry
            rows.append([
                name, str(prepared.num_images), mapper,
                "–" if accuracy else str(entry["num_registered"]),
                "–" if accuracy else f"{entry['R_err_max_deg']:.3f} / {entry['R_err_median_deg']:.3f}",
                "–" if accuracy else f"{entry['C_err_max']:.4f}",
                time_cell, ratio("time_s_ratio"),
                "–" if entry["peak_mib"] is None else f"{entry['peak_mib']:.0f}",
                ratio("peak_mib_ratio")])
    return markdown_table(headings, rows)


def growth_exponents(all_results: dict[str, tuple[PreparedSet, dict[str, dict]]]) -> list[str]:
    """Per mapper, the exponent b of time ~ images^b between the smallest and the largest
    synthetic walk measured."""
    sizes = [(prepared.num_images, results) for prepared, results in all_results.values()
             if prepared.name in SYNTHETIC_SIZES]
    if len(sizes) < 2:
        return []
    (n0, first), (n1, last) = min(sizes, key=lambda s: s[0]), max(sizes, key=lambda s: s[0])
    lines = []
    for mapper in first:
        t0, t1 = first[mapper].get("time_s"), last.get(mapper, {}).get("time_s")
        if t0 and t1:
            lines.append(f"{mapper}: time grows as images^{math.log(t1 / t0) / math.log(n1 / n0):.2f} "
                         f"from {n0} to {n1} images")
    return lines


def add_run_arguments(parser: argparse.ArgumentParser, section: str) -> None:
    """The mappers, rounds, seed, work folder and Markdown output of the timed benchmarks
    (this one and sequences.py); `section`: the default section written."""
    parser.add_argument("--mappers", default=",".join(MAPPERS))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work_dir", default=None,
                        help="keep databases and models here; databases found there are reused")
    parser.add_argument("--markdown", default=None,
                        help="also write the table as a section of this file (e.g. BENCHMARKS.md)")
    parser.add_argument("--section", default=section,
                        help="that section's name, so that runs of different sets keep theirs")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=os.environ.get("COLMAP_EXT_DATA"),
                        help="folder of real data sets (default: $COLMAP_EXT_DATA)")
    parser.add_argument("--sets", default=None,
                        help="comma-separated names (default: every real set, demo, turntable, "
                             + ", ".join(SYNTHETIC_SIZES) + ")")
    add_run_arguments(parser, section="speed")
    parser.add_argument("--end_to_end", action="store_true",
                        help="from the images (real sets and demo): `colmap-ext reconstruct` "
                             "against COLMAP's extraction, exhaustive matching and mapper")
    # The child's side.
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--database", help=argparse.SUPPRESS)
    parser.add_argument("--images", help=argparse.SUPPRESS)
    parser.add_argument("--output", help=argparse.SUPPRESS)
    parser.add_argument("--camera_model", help=argparse.SUPPRESS)
    parser.add_argument("--camera_params", help=argparse.SUPPRESS)
    parser.add_argument("--sequential_overlap", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return colmap_worker(args)

    from accuracy import machine_line, update_section, versions_line, work_folder

    data = real_sets(Path(args.data)) if args.data else {}
    names = args.sets.split(",") if args.sets else \
        [*data, "demo", "turntable", *SYNTHETIC_SIZES]
    unknown = [n for n in names if n not in data and n not in ("demo", "turntable", *SYNTHETIC_SIZES)]
    mappers = [m for m in args.mappers.split(",") if m]
    if unknown or not set(mappers) <= set(MAPPERS) or args.runs < 1:
        parser.error(f"unknown sets or mappers: {', '.join(unknown) or args.mappers}")
    without_images = [n for n in names if n not in data and n != "demo"]
    if args.end_to_end and without_images:
        parser.error(f"--end_to_end needs images; these sets have none: {', '.join(without_images)}")
    start = time.perf_counter()
    all_results = {}
    with work_folder(args.work_dir, "colmap-ext-speed-") as work:
        for name in names:
            print(f"=== {name}: preparing the database ...", file=sys.stderr, flush=True)
            prepared = prepare(name, data, work, args.seed)
            results = measure_set(prepared, mappers, args.runs, args.seed, work, args.end_to_end)
            summarize(results)
            all_results[name] = (prepared, results)
            body = section(all_results, args, time.perf_counter() - start,
                           machine_line(), versions_line())
            if args.markdown:  # after every set: a long run keeps what it measured
                update_section(Path(args.markdown), args.section, body)
    print()
    print(body)
    if args.markdown:
        print(f"\nwritten to {args.markdown}")
    return 0


def section(all_results: dict[str, tuple[PreparedSet, dict[str, dict]]], args: argparse.Namespace,
            elapsed_s: float, machine: str, versions: str) -> str:
    names = ",".join(all_results)
    flags = f" --mappers {args.mappers}" if args.mappers != ",".join(MAPPERS) else ""
    flags += " --end_to_end" if args.end_to_end else ""
    runs = ("each pipeline a whole process from the images: ours `colmap-ext reconstruct`, "
            "COLMAP's pycolmap extraction (default SIFT, the known intrinsics), exhaustive "
            "matching and mapper" if args.end_to_end else
            "each mapper a whole process on a fresh copy of the same database")
    return "\n".join([
        "## Speed and memory: ours against COLMAP's "
        + ("pipelines, end to end" if args.end_to_end else "mappers"), "",
        f"`python benchmarks/mapper_speed.py --sets {names} --runs {args.runs}{flags}` on "
        f"{datetime.date.today().isoformat()} ({elapsed_s / 60:.1f} min in all), seed {args.seed}.",
        f"- machine: {machine}", f"- versions: {versions}",
        f"- {runs}, the order turning each round; medians over the rounds; ratios to COLMAP "
        "incremental's medians. R_err / C_err: the last round's largest model against the "
        "ground truth.",
        *[f"- {line}" for line in growth_exponents(all_results)], "", table(all_results)])


if __name__ == "__main__":
    sys.path.insert(0, str(SCRIPT.parent))  # accuracy.py: data sets, machine line, tables
    sys.exit(main())
