"""Neutral ground: our mapper against COLMAP's incremental and global mappers on databases
from COLMAP's own generator (`pycolmap.synthesize_dataset` and `synthesize_noise`, the
generator of COLMAP's mapper tests), where nothing in the data is chosen by us.

Cases: every combination of --camera_models, --rigs (rigs x cameras per rig: 1x1 is one
camera; the images are the rigs' frames, each rig's cameras in a calibrated rig, held fixed
by every mapper), --sizes (images in all), --noise
(keypoint standard deviation in pixels), --inlier_ratios (`inlier_match_ratio`: the
share of each pair's matches that are true; the generator puts its wrong matches among
the raw matches alone) and --verification: "generator" keeps the generator's two-view
geometries, which hold the true matches alone (what COLMAP's mappers read is then the same
at every ratio; ours also reads the raw matches where registration falls short); "colmap"
replaces them by COLMAP's own geometric verification of the raw matches
(`pycolmap.verify_matches` on every pair, the cameras' focal lengths marked known, as a
calibrated user's database is made), which lets the wrong matches that happen to agree
with a pair's geometry through, as on real images. Each case is generated once per seed of --seeds
(`pycolmap.set_random_seed` before generating and before adding noise); --num_points scene
points, every one seen by every image, as the generator makes them.

Each mapper runs as a whole process on its own copy of the database, as mapper_speed.py runs
them (ours `colmap-ext mapper`; COLMAP's through pycolmap with the intrinsics fixed), the
order turning from seed to seed; wall time from start to exit, peak memory from GNU time.
The largest model is aligned to the truth by the least-squares similarity of its camera
centres (`colmap_ext.evaluate.aligned_to_ground_truth`, as pycolmap.estimate_sim3d), and
R_err is the angle between each aligned and true rotation; AUC@1 deg is `colmap-ext
evaluate`'s relative-pose AUC (unregistered images count as infinite errors); points and
observations are the model's against the truth's (one point per true track, every true
observation kept would give 1.00 / 1.00).

Beside the mappers, a reference that is no mapper: the truth's own tracks (every true
observation, with its noise) adjusted in least squares to convergence from the true poses,
intrinsics and rigs fixed (`true_tracks_least_squares`): the maximum-likelihood poses that a
perfect association of keypoints gives, the measuring stick for every mapper's accuracy.

The table gives, per case and mapper, the median over the seeds and, in brackets, the worst
seed; and for ours and the reference, on how many seeds each is within 1 % of COLMAP's
better mapper (the better of the two on that seed and measure) on R_err median, R_err max
and AUC@1 deg.

    python benchmarks/neutral.py [--seeds 0-9] [--rigs 1x1,2x3] [--sizes 30,150] [--noise 0.5,1.5]
        [--inlier_ratios 1.0,0.7,0.5] [--verification generator,colmap]
        [--camera_models PINHOLE,SIMPLE_RADIAL]
        [--mappers ours,colmap_incremental,colmap_global] [--work_dir DIR]
        [--markdown BENCHMARKS.md] [--section neutral]
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import shutil
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np  # before pycolmap (README, "Known problem")
import pycolmap

from accuracy import machine_line, markdown_table, update_section, versions_line, work_folder
from mapper_speed import MAPPERS, PreparedSet, largest_model, mapper_command, timed_run

from colmap_ext.geometry import rotation_angles_deg
from colmap_ext.synthetic import write_placeholder_images
from colmap_ext.evaluate import aligned_to_ground_truth, evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper.bundle_adjustment import adjust_reconstruction
from colmap_ext.mapper.options import BundleAdjustmentOptions
from colmap_ext.rig_consistency import model_rig_frames, rig_consistency
from colmap_ext.synthetic.pycolmap_generator import verify_with_colmap, wrong_observations

# The generator's image size, and each camera model's calibrated parameters in it.
IMAGE_SIZE = (1024, 768)
CAMERA_PARAMS = {"PINHOLE": [1280.0, 1280.0, 512.0, 384.0],
                 "SIMPLE_RADIAL": [1280.0, 512.0, 384.0, 0.05]}
# Whose two-view geometries the mappers read (the module's docstring).
VERIFICATIONS = ("generator", "colmap")
# Ours is within this fraction of COLMAP's better mapper (the target).
TOLERANCE = 0.01
# The row of the reference (true_tracks_least_squares), measured in this process.
TRUE_TRACKS = "true tracks, least squares"
# A global adjustment in least squares run to convergence (Ceres's function tolerance 0,
# at most 1000 iterations; intrinsics and rigs held by adjust_reconstruction).
LEAST_SQUARES_TO_CONVERGENCE = BundleAdjustmentOptions(loss="trivial", function_tolerance=0.0,
                                                       global_max_iterations=1000)


@dataclass(frozen=True)
class Case:
    camera_model: str
    rig: str  # "RxC": R rigs of C cameras each
    num_images: int
    noise_px: float
    inlier_ratio: float
    verification: str  # one of VERIFICATIONS

    @property
    def name(self) -> str:
        rig = "" if self.rig == "1x1" else f"_rig{self.rig}"
        verified = "" if self.verification == "generator" else f"_{self.verification}_verified"
        return (f"{self.camera_model.lower()}{rig}_{self.num_images}_noise{self.noise_px:g}"
                f"_inliers{self.inlier_ratio:g}{verified}")

    @property
    def rigs_and_cameras(self) -> tuple[int, int]:
        num_rigs, num_cameras = map(int, self.rig.split("x"))
        return num_rigs, num_cameras


def generate(case: Case, seed: int, num_points: int, folder: Path) -> PreparedSet:
    """The database, the true model (folder/truth) and placeholder images of one case and
    seed; reused when folder already holds them."""
    database, truth, images = folder / "database.db", folder / "truth", folder / "images"
    if not (truth / "images.bin").exists():
        shutil.rmtree(folder, ignore_errors=True)
        truth.mkdir(parents=True)
        options = pycolmap.SyntheticDatasetOptions()
        options.num_rigs, options.num_cameras_per_rig = case.rigs_and_cameras
        options.num_frames_per_rig = case.num_images // (options.num_rigs *
                                                         options.num_cameras_per_rig)
        options.num_points3D = num_points
        options.camera_width, options.camera_height = IMAGE_SIZE
        options.camera_model_id = getattr(pycolmap.CameraModelId, case.camera_model)
        options.camera_params = CAMERA_PARAMS[case.camera_model]
        options.inlier_match_ratio = case.inlier_ratio
        noise = pycolmap.SyntheticNoiseOptions()
        noise.point2D_stddev = case.noise_px
        with pycolmap.Database.open(database) as db:
            pycolmap.set_random_seed(seed)
            reconstruction = pycolmap.synthesize_dataset(options, db)
            pycolmap.set_random_seed(seed)
            pycolmap.synthesize_noise(noise, reconstruction, db)
        if case.verification == "colmap":
            verify_with_colmap(database)
        reconstruction.write(truth)
        images.mkdir()
        write_placeholder_images(images, [image.name for image in reconstruction.images.values()])
    return PreparedSet(f"{case.name}_seed{seed}", database, images, truth, case.num_images)


def measure(model: pycolmap.Reconstruction | None, truth: GroundTruth,
            truth_model: pycolmap.Reconstruction) -> dict:
    """The largest model's accuracy and size against the truth (its image count alone
    for no model, or one too small to align)."""
    if model is None or model.num_reg_images() < 3:
        return {"registered": 0 if model is None else model.num_reg_images(),
                "images": truth_model.num_images()}
    cameras, _ = aligned_to_ground_truth(model, truth)
    R_err = rotation_angles_deg(np.array([
        truth.poses[name].rotation.matrix().T @ pose.rotation.matrix()
        for name, pose in cameras.items()]))
    report = evaluate(model, truth)
    consistency = rig_consistency(model, model_rig_frames(truth_model))
    return {"registered": model.num_reg_images(), "images": truth_model.num_images(),
            "rig_max_deg": consistency["rotation_max_deg"] if consistency else 0.0,
            "R_err_median_deg": float(np.median(R_err)), "R_err_max_deg": float(R_err.max()),
            "AUC_1deg": report["AUC_percent"]["1"],
            "points": model.num_points3D() / truth_model.num_points3D(),
            "observations": model.compute_num_observations() / truth_model.compute_num_observations(),
            "wrong_percent": 100 * wrong_observations(model, truth_model)
            / model.compute_num_observations()}


def true_tracks_least_squares(truth_model: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
    """The truth's tracks, every true observation with its noise, adjusted in least squares
    from the true poses to convergence, intrinsics and rigs constant: the poses a perfect
    association of keypoints gives, which no mapper's poses can be expected to beat."""
    model = pycolmap.Reconstruction(truth_model)
    adjust_reconstruction(model, LEAST_SQUARES_TO_CONVERGENCE, num_threads=1)
    return model


def run_seed(case: Case, seed: int, mappers: list[str], num_points: int, work: Path) -> dict:
    """Every mapper once on the case's database of `seed`; its measures and resources."""
    folder = work / case.name / f"seed{seed}"
    prepared = generate(case, seed, num_points, folder)
    truth = read_ground_truth(prepared.ground_truth)
    truth_model = pycolmap.Reconstruction(prepared.ground_truth)
    results = {}
    turn = seed % len(mappers)
    for mapper in mappers[turn:] + mappers[:turn]:
        run_folder = folder / "runs" / mapper
        shutil.rmtree(run_folder, ignore_errors=True)
        run_folder.mkdir(parents=True)
        command, output = mapper_command(mapper, prepared, run_folder, seed=0, end_to_end=False)
        run = timed_run(command, run_folder / "log.txt")
        model = largest_model(output) if run["exit_code"] == 0 and output.is_dir() else None
        results[mapper] = {**run, **measure(model, truth, truth_model)}
        (run_folder / "database.db").unlink(missing_ok=True)
        entry = results[mapper]
        print(f"  {case.name} seed {seed} {mapper}: {entry['time_s']:.1f} s, "
              f"{entry['registered']}/{entry['images']} registered, R_err max "
              f"{entry.get('R_err_max_deg', float('nan')):.4f} deg", file=sys.stderr, flush=True)
    results[TRUE_TRACKS] = measure(true_tracks_least_squares(truth_model), truth, truth_model)
    return results


# ---------------------------------------------------------------------------------------
# The table

# Measure, direction of "worse", cell digits.
COLUMNS = {"R_err_median_deg": (max, 4), "R_err_max_deg": (max, 4), "AUC_1deg": (min, 2),
           "rig_max_deg": (max, 6),
           "points": (max, 2), "observations": (min, 2), "wrong_percent": (max, 3),
           "time_s": (max, 1), "peak_mib": (max, 0)}


def median_and_worst(values: list[float], worst, digits: int) -> str:
    if not values:
        return "–"
    return f"{statistics.median(values):.{digits}f} ({worst(values):.{digits}f})"


def seeds_within_tolerance(per_seed: list[dict], key: str, ours: str) -> str:
    """On how many seeds `ours` is within TOLERANCE of COLMAP's better mapper on `key`."""
    better_is_lower = COLUMNS[key][0] is max
    count = total = 0
    for results in per_seed:
        theirs = [r[key] for m, r in results.items() if m.startswith("colmap_") and key in r]
        if not theirs:
            continue
        total += 1
        if key in results[ours]:
            if better_is_lower:
                count += results[ours][key] <= min(theirs) * (1 + TOLERANCE)
            else:
                count += results[ours][key] >= max(theirs) * (1 - TOLERANCE)
    return f"{count}/{total}"


def case_rows(case: Case, per_seed: list[dict], mappers: list[str]) -> list[list[str]]:
    reference = [r["colmap_incremental"]["time_s"] for r in per_seed if "colmap_incremental" in r]
    rows = []
    for mapper in [*mappers, TRUE_TRACKS]:
        entries = [results[mapper] for results in per_seed]
        cells = [median_and_worst([e[key] for e in entries if key in e], worst, digits)
                 for key, (worst, digits) in COLUMNS.items()]
        times = [e["time_s"] for e in entries if "time_s" in e]
        ratio = "–"
        if reference and times:  # the medians' ratio (the largest ratio on one seed)
            worst = max(r[mapper]["time_s"] / r["colmap_incremental"]["time_s"]
                        for r in per_seed if "colmap_incremental" in r)
            ratio = f"{statistics.median(times) / statistics.median(reference):.2f}x ({worst:.2f}x)"
        within = " / ".join(seeds_within_tolerance(per_seed, key, mapper)
                            for key in ("R_err_median_deg", "R_err_max_deg", "AUC_1deg")) \
            if mapper in ("ours", TRUE_TRACKS) and len(mappers) > 1 else "–"
        registered = min(e["registered"] for e in entries)
        num_images = entries[0]["images"]  # a rig's frames may hold fewer than asked
        rows.append([case.camera_model, case.rig, str(case.num_images), f"{case.noise_px:g}",
                     f"{case.inlier_ratio:g}", case.verification, mapper, f"{registered}/{num_images}",
                     *cells[:7], cells[7], ratio, cells[8], within])
    return rows


HEADINGS = ["camera", "rigs x cameras", "images", "noise [px]", "inlier ratio",
            "two-view geometries", "mapper",
            "registered (fewest)", "R_err median [deg]", "R_err max [deg]", "AUC@1deg [%]",
            "rig kept [deg]", "points / truth",
            "observations / truth", "wrong observations [%]", "time [s]", "time / COLMAP inc.", "peak memory [MiB]",
            "within 1 % of COLMAP's better on seeds (R_err med / max / AUC@1)"]


def section(rows: list[list[str]], command: str, elapsed_s: float, num_points: int) -> str:
    return "\n".join([
        "## Neutral ground: COLMAP's own generator", "",
        f"`{command}` on {datetime.date.today().isoformat()} ({elapsed_s / 60:.1f} min in all).",
        f"- machine: {machine_line()}", f"- versions: {versions_line()}",
        f"- inputs: `pycolmap.synthesize_dataset` (rigs of cameras, {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, "
        f"PINHOLE {CAMERA_PARAMS['PINHOLE']} or SIMPLE_RADIAL {CAMERA_PARAMS['SIMPLE_RADIAL']}, "
        f"{num_points} points seen by every image, exhaustive matches of which the inlier ratio "
        "are true) and `synthesize_noise` (keypoint noise), "
        "`pycolmap.set_random_seed(seed)` before each; intrinsics and rigs fixed in every "
        "mapper, mapper seed 0. Two-view geometries: generator, the generator's, which hold "
        "the true matches alone (its wrong matches are among the raw matches only); colmap, "
        "COLMAP's geometric verification of the raw matches (`pycolmap.verify_matches`, focal "
        "lengths known), which lets the wrong matches through that agree with a pair's geometry.",
        "- each mapper a whole process on its own copy of the database (as "
        "`benchmarks/mapper_speed.py`); cells: median over the seeds (worst seed). R_err: "
        "after a similarity alignment on the camera centres; AUC@1deg: relative poses of "
        "image pairs, as `colmap-ext evaluate` reports it; points and observations of the "
        "largest model over the truth's; wrong observations: the share of the model's "
        "observations that see another true point than most of their track; rig kept: the "
        "largest deviation of a relative "
        "rotation between two images of one frame from the rig's (`rig_consistency`); time "
        "and peak memory of the whole process; time / COLMAP inc.: the medians' ratio (the "
        "largest ratio on one seed). "
        f"{TRUE_TRACKS}: no mapper, the truth's tracks (every true observation with its "
        "noise) adjusted in least squares to convergence from the true poses: the poses a "
        "perfect association gives.",
        "", markdown_table(HEADINGS, rows)])


def parse_list(text: str, kind=float) -> list:
    """'0.5,1.5' -> [0.5, 1.5]; for integers also ranges: '0-9' -> [0, ..., 9]."""
    values = []
    for part in text.split(","):
        if kind is int and "-" in part:
            first, last = part.split("-")
            values += list(range(int(first), int(last) + 1))
        elif part:
            values.append(kind(part))
    return values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0-9", help="generator seeds, e.g. 0-9 or 0,3")
    parser.add_argument("--rigs", default="1x1", help="rigs x cameras per rig, e.g. 1x1,2x3")
    parser.add_argument("--sizes", default="30,150", help="images per set")
    parser.add_argument("--noise", default="0.5,1.5", help="keypoint noise, pixels")
    parser.add_argument("--inlier_ratios", default="1.0,0.7,0.5")
    parser.add_argument("--verification", default="generator",
                        help=f"whose two-view geometries: {', '.join(VERIFICATIONS)}")
    parser.add_argument("--camera_models", default="PINHOLE,SIMPLE_RADIAL")
    parser.add_argument("--num_points", type=int, default=800)
    parser.add_argument("--mappers", default=",".join(MAPPERS))
    parser.add_argument("--work_dir", default=None,
                        help="keep databases, models and results.json here; databases found "
                             "there are reused")
    parser.add_argument("--markdown", default=None,
                        help="also write the table as a section of this file (BENCHMARKS.md)")
    parser.add_argument("--section", default="neutral",
                        help="that section's name, so that runs of different cases keep theirs")
    args = parser.parse_args(argv)
    mappers = [m for m in args.mappers.split(",") if m]
    camera_models = [m for m in args.camera_models.split(",") if m]
    verifications = [v for v in args.verification.split(",") if v]
    if not set(mappers) <= set(MAPPERS) or not set(camera_models) <= set(CAMERA_PARAMS) \
            or not set(verifications) <= set(VERIFICATIONS):
        parser.error(f"mappers from {', '.join(MAPPERS)}, camera models from "
                     f"{', '.join(CAMERA_PARAMS)}, verification from {', '.join(VERIFICATIONS)}")
    cases = [Case(*values) for values in itertools.product(
        camera_models, args.rigs.split(","), parse_list(args.sizes, int), parse_list(args.noise),
        parse_list(args.inlier_ratios), verifications)]
    seeds = parse_list(args.seeds, int)
    command = "python benchmarks/neutral.py " + " ".join(argv if argv is not None else sys.argv[1:])
    start = time.perf_counter()
    rows, raw = [], {}
    with work_folder(args.work_dir, "colmap-ext-neutral-") as work:
        for case in cases:
            per_seed = [run_seed(case, seed, mappers, args.num_points, work) for seed in seeds]
            raw[case.name] = dict(zip(map(str, seeds), per_seed))
            rows += case_rows(case, per_seed, mappers)
            (work / "results.json").write_text(json.dumps(raw, indent=1))
            body = section(rows, command.strip(), time.perf_counter() - start, args.num_points)
            if args.markdown:  # after every case: a long run keeps what it measured
                update_section(Path(args.markdown), args.section, body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
