"""Camera sequences: `colmap-ext mapper` against COLMAP's incremental and global mappers
on driving sequences (forward motion, low parallax, stops, corners, a loop), each mapper a
whole process on its own copy of the same database (as mapper_speed.py runs them).

Sets (--sets, all by default):
- kitti03_600-800: 201 frames of the real KITTI odometry sequence 03 under --data
  ($COLMAP_EXT_DATA); its database: pycolmap's default SIFT, one PINHOLE camera with the
  known intrinsics of its *_par.txt, sequential matching (each frame with the next 10), CPU;
- drive200, drive800, drive2000, drive10000: synthetic drives (`driving_scene`: steps of 1 m, the
  camera looking forward, a 90 deg corner every 60 m or so taken over 6 frames, a stop of
  10 frames every 300), about 1000 keypoints an image within 40 m, 0.5 px noise, 20 % wrong
  matches, each frame matched with the next 10; placeholder images; the verified matches and
  two-view geometries the generator's (the true matches and relative poses) or, with
  --verification colmap, COLMAP's geometric verification of the raw matches
  (`pycolmap.verify_matches`, intrinsics known), as a user's database holds them;
- loop500: a synthetic drive round a block, its last frame one step behind its first; the
  last frames are matched with the first ones too;
- stereo_drive200, stereo_drive800: the drives of drive200 and drive800 seen by a KITTI-like
  stereo rig (two forward-looking cameras 0.54 m apart, images left/ and right/), its rig
  configuration JSON applied to the database as COLMAP's `apply_rig_config` does; each image
  matched with the images of the next 10 frames and its own frame's other image (COLMAP's
  sequential matching of a rig). The rig's baseline makes the models metric: their centres
  are also compared after a rigid alignment (ATE rigid).

With --end_to_end (kitti03_600-800 alone), each run starts from the images: ours
`colmap-ext reconstruct`, COLMAP's SIFT extraction, sequential matching and mapper.

Per set, --runs rounds; in each round every mapper runs once, the order turning from round
to round. Per mapper: frames in the largest model / all, the number of models, R_err max
and median (`colmap-ext evaluate`'s, over the images), ATE median and max (metres: camera
centres after the similarity that best aligns them onto the ground truth; for a rig, after
the rigid transform too), and the medians of wall time, CPU time (user and system) and peak
memory, their ratios to COLMAP incremental's, and per frame, so that the synthetic sizes
show how the cost grows. A mapper that exits with an error is a failed row. On a single
camera's drive, the row "true tracks, least squares" is the maximum-likelihood reference:
every true observation (the database's keypoints) adjusted from the truth to convergence,
which a mapper can approach but not be expected to beat; its tracks join observations that
matching never links (a point unseen for more than the matched frames and seen again).

    python benchmarks/sequences.py [--sets kitti03_600-800,drive200,...] [--runs 3] [--seed 0]
        [--mappers ours,colmap_incremental,colmap_global] [--data DIR] [--work_dir DIR]
        [--markdown BENCHMARKS.md] [--section sequences] [--end_to_end]
        [--verification generator|colmap]
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve()
sys.path.insert(0, str(SCRIPT.parent))  # mapper_speed.py, accuracy.py

from mapper_speed import (MAPPERS, PreparedSet, add_run_arguments, largest_model,  # noqa: E402
                          run_rounds, summarize)

KITTI = "kitti03_600-800"
SEQUENTIAL_OVERLAP = 10  # frames each frame is matched with, as COLMAP's sequential matching
KEYPOINTS_PER_IMAGE = 1000
MAX_DISTANCE = 40.0  # metres: farther points are not observed
STEREO_BASELINE = 0.54  # metres between the stereo drives' cameras (KITTI's)
STEREO_PREFIXES = ["left/", "right/"]
# A single camera's drive: its true tracks (every true observation, the database's keypoints)
# at the truth, in this folder beside the database, and the row of their least squares.
TRUE_TRACKS = "true_tracks"
TRUE_TRACKS_ROW = "true tracks, least squares"
DRIVES = {"drive200": {"num_images": 200}, "drive800": {"num_images": 800},
          "drive2000": {"num_images": 2000},
          "drive10000": {"num_images": 10000}, "loop500": {"num_images": 500, "loop": True},
          "stereo_drive200": {"num_images": 200, "stereo": True},
          "stereo_drive800": {"num_images": 800, "stereo": True}}


def prepare_kitti(data: Path, work: Path) -> tuple[PreparedSet, str]:
    """The KITTI frames' database (sequential matching), and a line saying what it holds."""
    from accuracy import build_database, dataset_in

    dataset = dataset_in(data / KITTI)
    if dataset is None:
        raise SystemExit(f"{data / KITTI}: no data set with a ground truth there")
    database = work / KITTI / "database.db"
    if database.exists():
        stats = None
    else:
        database.parent.mkdir(parents=True, exist_ok=True)
        stats = build_database(dataset, database, sequential_overlap=SEQUENTIAL_OVERLAP)
    prepared = PreparedSet(KITTI, database, dataset.image_path, dataset.ground_truth,
                           len(dataset.image_names), dataset.camera_model,
                           ",".join(repr(p) for p in dataset.camera_params), SEQUENTIAL_OVERLAP)
    note = f"{KITTI}: {prepared.num_images} frames, pycolmap SIFT, {dataset.camera_model} known, " \
           f"sequential matching (overlap {SEQUENTIAL_OVERLAP})"
    if stats:
        note += (f": {stats['keypoints_mean']:.0f} keypoints an image, {stats['verified_pairs']} "
                 f"verified pairs; extraction {stats['extraction_s']:.0f} s, matching "
                 f"{stats['matching_s']:.0f} s")
    return prepared, note


def prepare_drive(name: str, work: Path, seed: int,
                  verification: str = "generator") -> tuple[PreparedSet, str]:
    """A synthetic drive's database with placeholder images (a stereo drive's with its rig
    configuration applied; with `verification` "colmap", a single camera's verified by
    COLMAP), and a line saying what it holds."""
    import numpy as np

    from colmap_ext.rigs import apply_rig_config, read_rig_config
    from colmap_ext.synthetic import (driving_scene, points_for_keypoints, rig_scene,
                                      sequential_pairs, side_by_side_rig,
                                      true_tracks_reconstruction, write_ground_truth,
                                      write_placeholder_images, write_rig_config,
                                      write_synthetic_database)
    from colmap_ext.synthetic.pycolmap_generator import verify_with_colmap

    options = dict(DRIVES[name])
    stereo = options.pop("stereo", False)
    if stereo and verification != "generator":
        raise SystemExit(f"{name}: --verification {verification} is for a single camera's drives")
    folder = work / (name if verification == "generator" else f"{name}_{verification}_verified")
    drive = driving_scene(seed=seed, **options)
    cams_from_rig = side_by_side_rig(len(STEREO_PREFIXES), STEREO_BASELINE)
    scene = rig_scene(drive, cams_from_rig, STEREO_PREFIXES) if stereo else drive
    note = f"{name}: {drive.num_images} frames" + (", a loop" if options.get("loop") else "") + \
        (f" of a stereo rig ({STEREO_BASELINE} m)" if stereo else "") + \
        (", COLMAP's verification" if verification == "colmap" else "")
    written = (folder / "database.db").exists() and (stereo or (folder / TRUE_TRACKS).is_dir())
    if not written:
        start = time.perf_counter()
        shutil.rmtree(folder, ignore_errors=True)
        (folder / "images").mkdir(parents=True)
        points = points_for_keypoints(scene, KEYPOINTS_PER_IMAGE, seed=seed, max_distance=MAX_DISTANCE)
        pairs = sequential_pairs(drive.num_images, SEQUENTIAL_OVERLAP, closed=bool(options.get("loop")),
                                 images_per_frame=len(STEREO_PREFIXES) if stereo else 1)
        truth = write_synthetic_database(folder / "database.db", scene, points, noise_px=0.5,
                                         outlier_ratio=0.2, max_distance=MAX_DISTANCE, seed=seed,
                                         two_view_geometries=True, pairs=pairs)
        if verification == "colmap":
            names = scene.image_names
            verify_with_colmap(folder / "database.db",
                               [(names[i], names[j]) for i, j in sorted(pairs)])
        if stereo:
            write_rig_config(folder / "rig.json", scene.camera, cams_from_rig, STEREO_PREFIXES)
            apply_rig_config(folder / "database.db", read_rig_config(folder / "rig.json"))
        else:
            (folder / TRUE_TRACKS).mkdir()
            true_tracks_reconstruction(folder / "database.db", scene, points, truth).write(
                folder / TRUE_TRACKS)
        write_placeholder_images(folder / "images", scene.image_names)
        write_ground_truth(scene, folder / "ground_truth")
        keypoints = np.mean([len(ids) for ids in truth.point_ids])
        note += (f": {keypoints:.0f} keypoints an image, {len(truth.matches)} matched pairs; "
                 f"written in {time.perf_counter() - start:.0f} s")
    return PreparedSet(name, folder / "database.db", folder / "images", folder / "ground_truth",
                       drive.num_images), note


def evaluate_models(output: Path, truth, metric: bool) -> dict:
    """The number of models in `output`, and the largest one against the ground truth
    (evaluate_model)."""
    model = largest_model(output) if output.is_dir() else None
    if model is None or model.num_reg_images() < 3:
        return {"error": "no model"}
    num_models = sum(1 for folder in output.iterdir() if (folder / "images.bin").is_file())
    return {"num_models": num_models, **evaluate_model(model, truth, metric)}


def evaluate_model(model, truth, metric: bool) -> dict:
    """A model against the ground truth: frames, R_err (evaluate's) and ATE (centres after
    a similarity onto the truth's; a `metric` model's after a rigid transform too)."""
    import numpy as np

    from colmap_ext.errors import UserError
    from colmap_ext.evaluate import aligned_to_ground_truth, evaluate

    entry = {"num_registered": model.num_reg_frames()}
    try:
        report = evaluate(model, truth)
    except UserError as error:
        entry["evaluation_error"] = str(error)
    else:
        entry.update(R_err_max_deg=report["R_err_max_deg"], R_err_median_deg=report["R_err_median_deg"])
    alignments = {"ate": True, "ate_rigid": False} if metric else {"ate": True}  # key: with scale
    for key, with_scale in alignments.items():
        cameras, _ = aligned_to_ground_truth(model, truth, with_scale=with_scale)
        errors = [np.linalg.norm(pose.inverse().translation - truth.poses[name].inverse().translation)
                  for name, pose in cameras.items()]
        entry.update({f"{key}_median": float(np.median(errors)), f"{key}_max": float(np.max(errors))})
    return entry


def failure(log: Path) -> str:
    """The last line a failed run wrote (ours: the one error line)."""
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1] if lines else "no output"


def measure(prepared: PreparedSet, mappers: list[str], runs: int, seed: int, work: Path,
            end_to_end: bool) -> dict[str, dict]:
    from colmap_ext.ground_truth import read_ground_truth

    results, models = run_rounds(prepared, mappers, runs, seed, work, end_to_end)
    summarize(results)
    truth = read_ground_truth(prepared.ground_truth)
    for mapper, entry in results.items():
        entry.update(evaluate_models(models[mapper], truth,
                                     metric=bool(DRIVES.get(prepared.name, {}).get("stereo"))))
        if entry["runs"][-1]["exit_code"] != 0:
            entry["error"] = failure(models[mapper].parent / "log.txt")
    true_tracks = prepared.database.parent / TRUE_TRACKS
    if true_tracks.is_dir():
        import pycolmap
        from neutral import true_tracks_least_squares

        reference = true_tracks_least_squares(pycolmap.Reconstruction(true_tracks))
        results[TRUE_TRACKS_ROW] = {"num_models": 1, "time_s": None, "peak_mib": None,
                                    **evaluate_model(reference, truth, metric=False)}
    return results


def table(all_results: dict[str, tuple[PreparedSet, dict[str, dict]]]) -> str:
    from accuracy import markdown_table

    headings = ["set", "mapper", "frames in largest / all", "models", "R_err max / median [deg]",
                "ATE median / max [m]", "ATE rigid median / max [m]", "time [s] median (min-max)",
                "time / COLMAP inc.", "CPU [s]", "CPU / COLMAP inc.", "peak memory [MiB]",
                "memory / COLMAP inc.",
                "time / frame [ms]", "memory / frame [KiB]"]
    rows = []
    for name, (prepared, results) in all_results.items():
        for mapper, entry in results.items():
            def cell(template: str, *keys: str) -> str:
                return template.format(*(entry[k] for k in keys)) if all(k in entry for k in keys) else "–"

            frames = f"{entry['num_registered']} / {prepared.num_images}" if "num_registered" in entry \
                else f"failed: {entry['error']}"
            if "num_registered" in entry and "error" in entry:
                frames += f" (exit {entry['runs'][-1]['exit_code']}: {entry['error']})"
            time_s, peak = entry["time_s"], entry["peak_mib"]
            rows.append([
                name, mapper, frames, cell("{}", "num_models"),
                cell("{:.3f} / {:.3f}", "R_err_max_deg", "R_err_median_deg"),
                cell("{:.3f} / {:.3f}", "ate_median", "ate_max"),
                cell("{:.3f} / {:.3f}", "ate_rigid_median", "ate_rigid_max"),
                ("failed" if "runs" in entry else "–") if time_s is None else
                f"{time_s:.1f} ({entry['time_range'][0]:.1f}-{entry['time_range'][1]:.1f})",
                cell("{:.2f}x", "time_s_ratio"), cell("{:.0f}", "cpu_s"), cell("{:.2f}x", "cpu_s_ratio"),
                "–" if peak is None else f"{peak:.0f}", cell("{:.2f}x", "peak_mib_ratio"),
                "–" if time_s is None else f"{1000 * time_s / prepared.num_images:.1f}",
                "–" if peak is None else f"{1024 * peak / prepared.num_images:.0f}"])
    return markdown_table(headings, rows)


def section(all_results: dict[str, tuple[PreparedSet, dict[str, dict]]], notes: list[str],
            args: argparse.Namespace, elapsed_s: float) -> str:
    from accuracy import machine_line, versions_line

    flags = f" --mappers {args.mappers}" if args.mappers != ",".join(MAPPERS) else ""
    flags += " --end_to_end" if args.end_to_end else ""
    evaluation_notes = [f"{name}, {mapper}: not evaluated: {entry['evaluation_error']}"
                        for name, (_, results) in all_results.items()
                        for mapper, entry in results.items() if "evaluation_error" in entry]
    return "\n".join([
        "## Sequences: ours against COLMAP's " + ("pipelines, end to end" if args.end_to_end
                                                  else "mappers"), "",
        f"`python benchmarks/sequences.py --sets {','.join(all_results)} --runs {args.runs}{flags}` "
        f"on {datetime.date.today().isoformat()} ({elapsed_s / 60:.1f} min in all), seed {args.seed}.",
        f"- machine: {machine_line()}", f"- versions: {versions_line()}",
        *[f"- {note}" for note in notes],
        ("- each pipeline a whole process from the images: `colmap-ext reconstruct` (its default "
         "matcher: sequential beyond 100 images); COLMAP's SIFT extraction, sequential matching "
         f"(overlap {SEQUENTIAL_OVERLAP}) and incremental or global mapper"
         if args.end_to_end else
         "- each mapper a whole process on a fresh copy of the same database") + ", the order turning "
        "each round; medians over the rounds; ratios to COLMAP incremental's medians. The last "
        "round's largest model against the ground truth: R_err as `colmap-ext evaluate`; ATE: "
        "distances of the camera centres to the truth's after a similarity alignment (ATE "
        "rigid, on a rig's metric sets: after a rigid one, no scale fitted); a stereo frame is "
        "two images.",
        *[f"- {note}" for note in evaluation_notes], "", table(all_results)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=os.environ.get("COLMAP_EXT_DATA"),
                        help=f"folder holding {KITTI} (default: $COLMAP_EXT_DATA)")
    parser.add_argument("--sets", default=",".join([KITTI, *DRIVES]))
    add_run_arguments(parser, section="sequences")
    parser.add_argument("--end_to_end", action="store_true",
                        help=f"{KITTI} from its images: `colmap-ext reconstruct` against COLMAP's "
                             "extraction, sequential matching and mapper")
    parser.add_argument("--verification", default="generator", choices=("generator", "colmap"),
                        help="the synthetic drives' verified matches: the generator's true ones, "
                             "or COLMAP's verification of the raw matches")
    args = parser.parse_args(argv)
    names = [n for n in args.sets.split(",") if n]
    mappers = [m for m in args.mappers.split(",") if m]
    unknown = [n for n in names if n != KITTI and n not in DRIVES]
    if unknown or not mappers or not set(mappers) <= set(MAPPERS) or args.runs < 1:
        parser.error(f"unknown sets or mappers: {', '.join(unknown) or args.mappers}")
    if KITTI in names and not args.data:
        parser.error(f"{KITTI} needs --data or $COLMAP_EXT_DATA")
    if args.end_to_end and names != [KITTI]:
        parser.error(f"--end_to_end needs images: only {KITTI} has them")

    from accuracy import update_section, work_folder

    start = time.perf_counter()
    all_results, notes = {}, []
    with work_folder(args.work_dir, "colmap-ext-sequences-") as work:
        for name in names:
            print(f"=== {name}: preparing the database ...", file=sys.stderr, flush=True)
            prepared, note = prepare_kitti(Path(args.data), work) if name == KITTI \
                else prepare_drive(name, work, args.seed, args.verification)
            notes.append(note)
            all_results[name] = (prepared, measure(prepared, mappers, args.runs, args.seed, work,
                                                   args.end_to_end))
            body = section(all_results, notes, args, time.perf_counter() - start)
            if args.markdown:  # after every set: a long run keeps what it measured
                update_section(Path(args.markdown), args.section, body)
    print()
    print(body)
    if args.markdown:
        print(f"\nwritten to {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
