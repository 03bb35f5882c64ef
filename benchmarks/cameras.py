"""Every central camera family: ours against COLMAP's mappers on COLMAP's own generator,
and a 360-degree image set end to end.

1. Generated (`pycolmap.synthesize_dataset`, colmap_ext.synthetic.pycolmap_generator):
   per camera model and seed, one database of 30 images with 0.5 px keypoint noise and
   no image files (and a 360-degree fisheye that OPENCV_FISHEYE describes up to 90
   degrees from its axis, about half its keypoints beyond); `colmap-ext mapper`, COLMAP's incremental and global mappers (the
   intrinsics fixed), each a whole process on its own copy of it (mapper_speed.py's
   runs). Per model: images registered over the seeds, R_err median (the median over
   seeds of each run's median) and max (over all seeds), and on how many seeds ours is
   no worse than COLMAP's better mapper on that seed (median and max both).
2. Panoramas end to end: `colmap-ext reconstruct --camera_model EQUIRECTANGULAR` with
   SIFT on the panoramas and on their cube faces (--panorama_features), against COLMAP's
   pipeline (pycolmap extraction with the same camera, exhaustive matching, incremental
   mapper), each a whole process: registered images, points, mean track length and
   reprojection error, the agreement of the per-image rotations relative to the first
   image with COLMAP's, and the times. On rendered panoramas with known poses (the
   synthetic ring scene seen by an EQUIRECTANGULAR camera) also R_err; with --data, on
   `360_flat` (photographs, no ground truth).

Writes the `cameras` section at the end of BENCHMARKS.md and prints it.

    python benchmarks/cameras.py [--models EQUIRECTANGULAR,...] [--seeds 0,1,2,3,4]
        [--data $COLMAP_EXT_DATA] [--work_dir DIR] [--markdown BENCHMARKS.md]

With --loss_probe LOSS (and the --work_dir of an earlier run), ours runs again on each
generated database with that bundle adjustment loss (MapperOptions.bundle_adjustment.loss),
in this process, and prints R_err median / max per seed; nothing is written.
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np  # noqa: F401  (before pycolmap: README, "Known problem")
import pycolmap

from accuracy import machine_line, markdown_table, update_section, versions_line, work_folder
from mapper_speed import MAPPERS, PreparedSet, largest_model, mapper_command, timed_run

from colmap_ext.evaluate import evaluate
from colmap_ext.features import PANORAMA_FEATURES
from colmap_ext.ground_truth import read_colmap
from colmap_ext.synthetic import render_images, ring_scene, write_ground_truth
from colmap_ext.synthetic.pycolmap_generator import (wide_fisheye_from_panoramas,
                                                     write_pycolmap_dataset)

REPO = Path(__file__).resolve().parent.parent
# A 360-degree equidistant fisheye described by OPENCV_FISHEYE, which reaches 90 degrees
# from its axis: the panoramas' databases turned by pycolmap_generator.wide_fisheye_from_panoramas.
WIDE_FISHEYE = "360-degree fisheye"
MODELS = ("EQUIRECTANGULAR", "OPENCV_FISHEYE", "RADIAL_FISHEYE", "FOV", "EUCM", "SIMPLE_DIVISION",
          WIDE_FISHEYE)
NUM_IMAGES = 30
FLAT_360 = "360_flat"
# The rendered panoramas: images of the synthetic ring scene, and their width.
RENDERED_360 = ("rendered ring", 16, 2048)
# Per panorama pipeline: ours with each --panorama_features, and COLMAP's (None).
PANORAMA_RUNS = {**{f"ours, SIFT on {features}": ["--panorama_features", features]
                    for features in PANORAMA_FEATURES}, "COLMAP incremental": None}


def run_generated(model: str, seed: int, work: Path) -> dict[str, dict]:
    """Every mapper on one generated database: registered, R_err median and max, time."""
    folder = work / model.replace(" ", "_") / f"seed{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "images").mkdir(exist_ok=True)
    database = folder / "database.db"
    database.unlink(missing_ok=True)
    if model == WIDE_FISHEYE:
        truth = write_pycolmap_dataset(database, "EQUIRECTANGULAR", seed, num_images=NUM_IMAGES)
        wide_fisheye_from_panoramas(database, truth)
    else:
        truth = write_pycolmap_dataset(database, model, seed, num_images=NUM_IMAGES)
    (folder / "truth").mkdir(exist_ok=True)
    truth.write(folder / "truth")
    ground_truth = read_colmap(folder / "truth")
    prepared = PreparedSet(model, database, folder / "images", folder / "truth", NUM_IMAGES)
    results = {}
    for mapper in MAPPERS:
        run_folder = folder / mapper
        run_folder.mkdir(exist_ok=True)
        command, output = mapper_command(mapper, prepared, run_folder, seed, end_to_end=False)
        run = timed_run(command, run_folder / "log.txt")
        model_found = largest_model(output) if output.is_dir() else None
        if run["exit_code"] != 0 or model_found is None or model_found.num_reg_images() < 2:
            results[mapper] = {**run, "num_registered": 0}
            continue
        report = evaluate(model_found, ground_truth)
        results[mapper] = {**run, "num_registered": report["num_registered"],
                           "R_err_median_deg": report["R_err_median_deg"],
                           "R_err_max_deg": report["R_err_max_deg"]}
        print(f"  {model} seed {seed} {mapper}: {report['num_registered']}/{NUM_IMAGES}, "
              f"R_err {report['R_err_median_deg']:.4f} / {report['R_err_max_deg']:.4f} deg, "
              f"{run['time_s']:.1f} s", file=sys.stderr, flush=True)
    return results


def no_worse_than_colmap(runs: dict[str, dict]) -> bool:
    """Whether ours registers as many images as COLMAP's better mapper on this seed, with
    an R_err median and max no larger."""
    ours = runs["ours"]
    colmap = [runs[m] for m in MAPPERS if m != "ours" and runs[m]["num_registered"]]
    if not ours["num_registered"]:
        return False
    best = min(colmap, key=lambda r: (-r["num_registered"], r["R_err_median_deg"]), default=None)
    return best is None or (ours["num_registered"] >= best["num_registered"] and
                            ours["R_err_median_deg"] <= best["R_err_median_deg"] and
                            ours["R_err_max_deg"] <= best["R_err_max_deg"])


def generated_table(results: dict[str, dict[int, dict[str, dict]]]) -> str:
    rows = []
    for model, by_seed in results.items():
        seeds = sorted(by_seed)
        for mapper in MAPPERS:
            runs = [by_seed[seed][mapper] for seed in seeds]
            done = [r for r in runs if r["num_registered"]]
            registered = sum(r["num_registered"] for r in runs)
            accuracy = "–" if not done else (
                f"{statistics.median(r['R_err_median_deg'] for r in done):.4f} / "
                f"{max(r['R_err_max_deg'] for r in done):.4f}")
            wins = "" if mapper != "ours" else \
                f"{sum(no_worse_than_colmap(by_seed[seed]) for seed in seeds)}/{len(seeds)}"
            rows.append([model, mapper, f"{registered}/{NUM_IMAGES * len(seeds)}", accuracy,
                         wins, f"{statistics.median(r['time_s'] for r in runs):.2f}"])
    return markdown_table(["camera model", "mapper", "registered (all seeds)",
                           "R_err median / max [deg]", "seeds no worse than COLMAP's better",
                           "time [s] (median)"], rows)


def run_panoramas(name: str, images: Path, work: Path, seed: int,
                  truth: Path | None = None) -> dict:
    """Every PANORAMA_RUNS pipeline end to end on the panoramas in `images`, whole
    processes: per run its time, peak memory and model figures, its rotations against
    COLMAP's, and with `truth` (a COLMAP model) its R_err."""
    width, height = first_image_size(images)
    prepared = PreparedSet(name, work / "unused.db", images, Path(),
                           len([p for p in images.iterdir() if p.is_file()]),
                           "EQUIRECTANGULAR", f"{width},{height}")
    runs, models = {}, {}
    for run_name, flags in PANORAMA_RUNS.items():
        folder = work / name.replace(" ", "_") / run_name.replace(", ", "_").replace(" ", "_")
        folder.mkdir(parents=True, exist_ok=True)
        command, output = mapper_command("colmap_incremental" if flags is None else "ours",
                                         prepared, folder, seed, end_to_end=True)
        runs[run_name] = timed_run(command + (flags or []), folder / "log.txt")
        models[run_name] = model = largest_model(output) if output.is_dir() else None
        if model is not None:
            runs[run_name].update(
                registered=model.num_reg_images(), points=model.num_points3D(),
                track_length=model.compute_mean_track_length(),
                reprojection_error_px=model.compute_mean_reprojection_error())
        print(f"  {name} {run_name}: {runs[run_name]}", file=sys.stderr, flush=True)
    colmap = models["COLMAP incremental"]
    if colmap is not None:
        reference = work / name.replace(" ", "_") / "colmap_reference"
        reference.mkdir(exist_ok=True)
        colmap.write(reference)
    for run_name, model in models.items():
        if model is None or model.num_reg_images() < 2:
            continue
        if colmap is not None and model is not colmap:
            report = evaluate(model, read_colmap(reference))
            runs[run_name]["agreement_deg"] = (report["R_err_median_deg"],
                                               report["R_err_max_deg"])
        if truth is not None:
            report = evaluate(model, read_colmap(truth))
            runs[run_name]["R_err_deg"] = (report["R_err_median_deg"], report["R_err_max_deg"])
    return {"name": name, "size": f"{width}x{height}", "num_images": prepared.num_images,
            "runs": runs}


def first_image_size(images: Path) -> tuple[int, int]:
    """(width, height) of the first image of a folder."""
    first = cv2.imread(str(min(p for p in images.iterdir() if p.is_file())), cv2.IMREAD_GRAYSCALE)
    return first.shape[1], first.shape[0]


def rendered_panoramas(work: Path) -> tuple[Path, Path]:
    """The synthetic ring scene rendered by an EQUIRECTANGULAR camera: its images and
    its ground truth (a COLMAP model), made once in `work`."""
    _, num_images, width = RENDERED_360
    folder = work / "rendered_ring"
    if not (folder / "truth").is_dir():
        camera = pycolmap.Camera(camera_id=1, model="EQUIRECTANGULAR", width=width,
                                 height=width // 2, params=[width, width // 2])
        scene = ring_scene(num_images=num_images, camera=camera)
        render_images(scene, folder / "images")
        write_ground_truth(scene, folder / "truth")
    return folder / "images", folder / "truth"


def panorama_table(sets: list[dict]) -> str:
    def pair(values: tuple[float, float] | None) -> str:
        return "–" if values is None else f"{values[0]:.3f} / {values[1]:.3f}"

    rows = []
    for entry in sets:
        for run_name, run in entry["runs"].items():
            registered = run.get("registered", 0)
            rows.append([f"{entry['name']} ({entry['num_images']} x {entry['size']})", run_name,
                         f"{registered}/{entry['num_images']}", str(run.get("points", 0)),
                         f"{run['track_length']:.2f}" if registered else "–",
                         f"{run['reprojection_error_px']:.3f}" if registered else "–",
                         pair(run.get("agreement_deg")), pair(run.get("R_err_deg")),
                         f"{run['time_s']:.0f}", f"{run['peak_mib']:.0f}"])
    return markdown_table(["panoramas", "pipeline", "registered", "points", "mean track length",
                           "mean reproj. error [px]", "rotations vs COLMAP's, median / max [deg]",
                           "R_err median / max [deg]", "time [s]", "peak [MiB]"], rows)


def loss_probe(work: Path, models: list[str], seeds: list[int], loss: str) -> None:
    """Ours with another bundle adjustment loss on the databases of an earlier run."""
    from colmap_ext.mapper import MapperOptions
    from colmap_ext.mapper.pipeline import run

    for model in models:
        for seed in seeds:
            folder = work / model.replace(" ", "_") / f"seed{seed}"
            options = MapperOptions(seed=seed)
            options.bundle_adjustment.loss = loss
            found = run(folder / "database.db", folder / "images", folder / f"ours_{loss}",
                        options, overwrite=True, progress=False)
            report = evaluate(found[0], read_colmap(folder / "truth"))
            print(f"{model} seed {seed} ours, {loss} loss: R_err median / max "
                  f"{report['R_err_median_deg']:.4f} / {report['R_err_max_deg']:.4f} deg")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--data", default=None,
                        help="folder holding 360_flat/ for the end-to-end run (skipped without)")
    parser.add_argument("--work_dir", default=None)
    parser.add_argument("--markdown", default=str(REPO / "BENCHMARKS.md"))
    parser.add_argument("--loss_probe", default=None,
                        help="rerun ours with this bundle adjustment loss (see above)")
    args = parser.parse_args(argv)
    seeds = [int(seed) for seed in args.seeds.split(",")]
    if args.loss_probe:
        loss_probe(Path(args.work_dir), args.models.split(","), seeds, args.loss_probe)
        return 0
    start = time.perf_counter()
    with work_folder(args.work_dir, "colmap-ext-cameras-") as work:
        results = {model: {seed: run_generated(model, seed, work) for seed in seeds}
                   for model in args.models.split(",") if model}
        rendered, truth = rendered_panoramas(work)
        panoramas = [run_panoramas(RENDERED_360[0], rendered, work, seeds[0], truth)]
        if args.data:
            panoramas.append(run_panoramas(FLAT_360, Path(args.data) / FLAT_360 / "images",
                                           work, seeds[0]))
        (work / "results.json").write_text(json.dumps({"generated": results,
                                                       "panoramas": panoramas}, indent=1))
    command = "python benchmarks/cameras.py " + " ".join(argv or sys.argv[1:])
    lines = [
        "## Camera models: ours against COLMAP's mappers, every central camera family",
        "",
        f"`{command.strip()}` on {datetime.date.today()} "
        f"({(time.perf_counter() - start) / 60:.1f} min in all).",
        f"- machine: {machine_line()}",
        f"- versions: {versions_line()}",
        f"- databases: `pycolmap.synthesize_dataset` ({NUM_IMAGES} images of one camera, 100 "
        "points seen by every image, 0.5 px keypoint noise, no image files; intrinsics in "
        "`colmap_ext/synthetic/pycolmap_generator.py`), seeds " + args.seeds + "; every mapper "
        "a whole process on its own copy of each database, the intrinsics held fixed.",
        f"- {WIDE_FISHEYE}: the EQUIRECTANGULAR databases seen through an equidistant lens "
        "of every direction (r = f * angle, f 200 px), its axis turned 90 degrees from the "
        "panoramas' so that the scene straddles the edge of its front half, described as "
        "OPENCV_FISHEYE, which reaches 90 degrees from the axis (pycolmap 4.2.1 returns "
        "wrong rays, not NaN, beyond): about half the keypoints lie beyond "
        "(`wide_fisheye_from_panoramas`).",
        "",
        generated_table(results),
        "",
        f"Panoramas end to end (`reconstruct`, SIFT on the panoramas or on their cube faces, "
        f"against COLMAP's pipeline; {RENDERED_360[0]}: the synthetic ring scene rendered by "
        "an EQUIRECTANGULAR camera, R_err against its poses; 360_flat: no ground truth):",
        "",
        panorama_table(panoramas),
    ]
    section = "\n".join(lines)
    update_section(Path(args.markdown), "cameras", section)
    print(section)
    return 0


if __name__ == "__main__":
    sys.exit(main())
