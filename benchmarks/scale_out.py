"""Scale-out: our flat mapper, our hierarchical mapper with 1 and 2 workers, and COLMAP's
hierarchical mapper, each a whole process on its own copy of the same database.

Sets: synthetic walks along a facade (mapper_speed.py's `trajectory_scene` sets, about
1000 keypoints an image, 0.5 px noise, 20 % wrong matches, two-view geometries from the
true poses) of 1000, 2000 and 5000 images (--sizes). Mappers:
- flat: `colmap-ext mapper`;
- hier1, hier2: `colmap-ext hierarchical_mapper --num_workers 1 / 2`;
- colmap_hier: `pycolmap.hierarchical_mapping`, intrinsics fixed as colmap_mappers.py
  fixes them for the incremental mapper, 2 workers;
both hierarchical mappers with the same --leaf_max_num_images and --image_overlap.
Wall time is the child's; peak memory the largest resident set of any one of its
processes (GNU time's %M). From our 2-worker run's per-cluster times (one thread per
task, as a Ray task with one CPU runs) the section projects the time on 8, 32 and 128
workers.

    python benchmarks/scale_out.py [--sizes 1000,2000] [--leaf_max_num_images 250]
        [--image_overlap 50] [--runs 1] [--work_dir DIR] [--markdown BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import shutil
import statistics
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve()
MAPPERS = ("flat", "hier1", "hier2", "colmap_hier")
PROJECTED_WORKERS = (8, 32, 128)
# Smaller leaves than this map poorly (too few images to grow a model): more workers
# than num_images / MIN_LEAF_IMAGES clusters stay idle.
MIN_LEAF_IMAGES = 50


def colmap_worker(args: argparse.Namespace) -> int:
    """In the child: COLMAP's hierarchical mapper, intrinsics fixed."""
    import numpy  # noqa: F401  (before pycolmap: README, "Known problem")
    import pycolmap

    from colmap_ext.colmap_mappers import colmap_incremental_options, fix_intrinsics_in_database

    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.WARNING)
    camera_ids, _ = fix_intrinsics_in_database(Path(args.database))
    options = pycolmap.HierarchicalPipelineOptions()
    options.incremental_options = colmap_incremental_options(camera_ids, args.seed, num_threads=1)
    options.clustering_options.leaf_max_num_images = args.leaf_max_num_images
    options.clustering_options.image_overlap = args.image_overlap
    options.num_workers = 2
    options.image_path = args.images
    Path(args.output).mkdir(parents=True, exist_ok=True)
    pycolmap.hierarchical_mapping(args.database, args.images, args.output, options)
    return 0


def command(mapper: str, database: Path, images: Path, output: Path, args) -> list[str]:
    executable = str(Path(sys.executable).with_name("colmap-ext"))
    common = ["--database_path", str(database), "--image_path", str(images),
              "--output_path", str(output), "--seed", str(args.seed)]
    hierarchical = ["--leaf_max_num_images", str(args.leaf_max_num_images),
                    "--image_overlap", str(args.image_overlap)]
    if mapper == "flat":
        return [executable, "mapper", *common]
    if mapper in ("hier1", "hier2"):
        return [executable, "hierarchical_mapper", *common, *hierarchical,
                "--num_workers", mapper[-1]]
    return [sys.executable, str(SCRIPT), "--worker", "--database", str(database),
            "--images", str(images), "--output", str(output), "--seed", str(args.seed),
            *hierarchical]


def measure(name: str, size: int, args, work: Path) -> tuple[dict, dict]:
    import mapper_speed

    from colmap_ext.ground_truth import read_ground_truth

    mapper_speed.SYNTHETIC_SIZES.setdefault(name, size)
    print(f"=== {name}: preparing the database ...", file=sys.stderr, flush=True)
    prepared = mapper_speed.prepare_synthetic(name, work, args.seed)
    truth = read_ground_truth(prepared.ground_truth)
    results: dict[str, dict] = {}
    times: dict[str, list[float]] = {mapper: [] for mapper in args.mappers}
    for round_index in range(args.runs):
        # The order turns each round, so that no mapper always runs first (or after a
        # given one) on a machine whose speed drifts.
        shift = round_index % len(args.mappers)
        for mapper in args.mappers[shift:] + args.mappers[:shift]:
            run = measure_once(name, mapper, prepared, truth, args, work)
            times[mapper].append(run["time_s"])
            if mapper in results:
                run["peak_mib"] = max(run["peak_mib"], results[mapper]["peak_mib"])
            results[mapper] = run  # the last round's model and stages
    for mapper, run in results.items():
        run.update(time_s=statistics.median(times[mapper]), times_s=times[mapper])
    return prepared.__dict__, results


def measure_once(name: str, mapper: str, prepared, truth, args, work: Path) -> dict:
    """One mapper's whole process on a fresh copy of the database; its time, peak
    memory, and the largest model's registered images and errors."""
    import mapper_speed

    from colmap_ext.evaluate import evaluate

    folder = work / name / "runs" / mapper
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    shutil.copyfile(prepared.database, folder / "database.db")
    run = mapper_speed.timed_run(
        command(mapper, folder / "database.db", prepared.image_path, folder / "out", args),
        folder / "log.txt")
    print(f"  {name} {mapper}: {run['time_s']:.1f} s, {run['peak_mib']:.0f} MiB, exit "
          f"{run['exit_code']}", file=sys.stderr, flush=True)
    model = mapper_speed.largest_model(folder / "out") if (folder / "out").is_dir() else None
    if model is not None and model.num_reg_images() >= 2:
        report = evaluate(model, truth)
        run.update(num_registered=model.num_reg_images(),
                   num_models=sum(1 for p in (folder / "out").iterdir() if p.name.isdigit()),
                   R_err_max_deg=report["R_err_max_deg"], C_err_max=report["C_err_max"])
    summary = folder / "out" / "mapper_summary.json"
    if summary.is_file():
        run["summary"] = json.loads(summary.read_text())
    return run


def projection(num_images: int, run: dict) -> dict[int, float] | None:
    """Seconds on N workers from a hierarchical run: its serial stages (process start,
    reading, partition, merging, bundle adjustment, export) as measured, plus the
    mapping of max(N, num_images / MIN_LEAF_IMAGES) clusters in rounds of N, each
    cluster a leaf of num_images / clusters images grown by the measured overlap, at
    the measured per-image cost of a one-thread task."""
    summary = run.get("summary")
    if not summary or not summary.get("clusters"):
        return None
    clusters = summary["clusters"]
    per_image = sum(c["seconds"] for c in clusters) / sum(c["num_images"] for c in clusters)
    overlap = sum(c["num_images"] for c in clusters) / len(clusters) - num_images / len(clusters)
    serial = run["time_s"] - summary["time_s"].get("cluster mapping", 0.0)
    projected = {}
    for workers in PROJECTED_WORKERS:
        count = min(workers, max(1, num_images // MIN_LEAF_IMAGES))
        rounds = math.ceil(count / workers)
        projected[workers] = serial + rounds * per_image * (num_images / count + overlap)
    return projected


def section(all_results: dict, args, elapsed_s: float) -> str:
    from accuracy import machine_line, markdown_table, versions_line

    rows, notes = [], []
    for name, (prepared, results) in all_results.items():
        flat = results.get("flat", {})
        for mapper, run in results.items():
            ok = "num_registered" in run
            rows.append([
                name, str(prepared["num_images"]), mapper,
                f"{run['num_registered']} ({run['num_models']} models)" if ok else "failed",
                f"{run['R_err_max_deg']:.3f}" if ok else "–",
                f"{run['C_err_max']:.4f}" if ok else "–",
                f"{run['time_s']:.1f}" + (f" ({min(run['times_s']):.1f}-{max(run['times_s']):.1f})"
                                          if len(run["times_s"]) > 1 else ""),
                f"{run['time_s'] / flat['time_s']:.2f}x" if flat.get("time_s") else "–",
                f"{run['peak_mib']:.0f}"])
            stages = run.get("summary", {}).get("time_s", {})
            if mapper.startswith("hier") and stages:
                notes.append(f"{name} {mapper}: " + ", ".join(
                    f"{stage} {seconds:.1f} s" for stage, seconds in stages.items()))
            if mapper == "hier2":
                projected = projection(prepared["num_images"], run)
                clusters = run.get("summary", {}).get("clusters", [])
                if clusters:
                    notes.append(f"{name} hier2 tasks: " + ", ".join(
                        f"{c['num_images']} images {c['seconds']:.1f} s" for c in clusters))
                if projected:
                    notes.append(f"{name} projected: " + ", ".join(
                        f"{n} workers {seconds:.0f} s" for n, seconds in projected.items()))
    headings = ["set", "images", "mapper", "registered", "R_err max [deg]", "C_err max",
                "time [s]" if args.runs == 1 else "time [s] median (min-max)", "time / flat",
                "peak memory per process [MiB]"]
    return "\n".join([
        "## Scale-out: hierarchical mapping", "",
        f"`python benchmarks/scale_out.py --sizes {','.join(map(str, args.sizes))} "
        f"--leaf_max_num_images {args.leaf_max_num_images} --image_overlap {args.image_overlap} "
        f"--runs {args.runs}` on {datetime.date.today().isoformat()} ({elapsed_s / 60:.1f} min in "
        f"all), seed {args.seed}; "
        + ("one run each." if args.runs == 1 else
           f"{args.runs} runs each, the order turning each round: median time (min-max), "
           "the largest peak, the last round's model."),
        f"- machine: {machine_line()}; shared with other engineers' test runs while measured, "
        "so times carry that noise", f"- versions: {versions_line()}", "",
        markdown_table(headings, rows), "", *[f"- {note}" for note in notes]])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1000,2000,5000")
    parser.add_argument("--mappers", default=",".join(MAPPERS))
    parser.add_argument("--leaf_max_num_images", type=int, default=250)
    parser.add_argument("--image_overlap", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--runs", type=int, default=1,
                        help="runs of each mapper, alternating; medians are reported")
    parser.add_argument("--work_dir", default=None,
                        help="keep databases and models here; databases found there are reused")
    parser.add_argument("--markdown", default=None, help="also write the section to this file")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--database", help=argparse.SUPPRESS)
    parser.add_argument("--images", help=argparse.SUPPRESS)
    parser.add_argument("--output", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return colmap_worker(args)
    args.sizes = [int(size) for size in args.sizes.split(",")]
    args.mappers = [m for m in args.mappers.split(",") if m]
    if not set(args.mappers) <= set(MAPPERS):
        parser.error(f"unknown mappers in {args.mappers}; choose from {', '.join(MAPPERS)}")

    from accuracy import update_section, work_folder

    start = time.perf_counter()
    all_results = {}
    with work_folder(args.work_dir, "colmap-ext-scale-") as work:
        for size in args.sizes:
            name = f"synthetic{size}"
            all_results[name] = measure(name, size, args, work)
            body = section(all_results, args, time.perf_counter() - start)
            if args.markdown:  # after every set: a long run keeps what it measured
                update_section(Path(args.markdown), "scale_out", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(SCRIPT.parent))  # accuracy.py, mapper_speed.py
    sys.exit(main())
