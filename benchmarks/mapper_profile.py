"""Where our mapper's time goes, and what its robust loss costs and buys.

For every data set under $COLMAP_EXT_DATA and for the demo scene, on the database
accuracy.py builds (pycolmap's default SIFT, exhaustive matching, the known
intrinsics): COLMAP's incremental mapper once, for the reference time, then our mapper
with each bundle-adjustment loss: Cauchy (our default), soft-L1 (COLMAP's loss in local
bundle adjustment) and trivial (its loss in global bundle adjustment). Per run: the
time of each pipeline stage, the Ceres solves and iterations, and R_err max against
the ground truth. Writes the profile section of BENCHMARKS.md and prints it.

    COLMAP_EXT_DATA=/path/to/data python benchmarks/mapper_profile.py [--seed 0] [--work_dir DIR]
        [--no_demo]
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

from accuracy import (add_common_arguments, machine_line, markdown_table, prepared_datasets,
                      update_section, versions_line, work_folder)

from colmap_ext.compare import run_mapper
from colmap_ext.database import read_database
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.mapper.options import BA_LOSSES, BundleAdjustmentOptions, MapperOptions
from colmap_ext.mapper.pipeline import StageTimer, reconstruct

STAGES = ("registration", "triangulation", "bundle adjustment", "filtering")


def profile_ours(database: Path, ground_truth: Path, loss: str, seed: int) -> dict:
    """Our mapper in this process (no model written): stage times, Ceres work, R_err max."""
    db = read_database(database)
    timer = StageTimer()
    start = time.perf_counter()
    options = MapperOptions(bundle_adjustment=BundleAdjustmentOptions(loss=loss), seed=seed)
    reconstructions = reconstruct(db, options, timer=timer, progress=False)
    total = time.perf_counter() - start
    report = evaluate(reconstructions[0], read_ground_truth(ground_truth)) if reconstructions else {}
    return {"total_s": total, "stages": dict(timer.seconds), "counts": dict(timer.counts),
            "num_registered": reconstructions[0].num_reg_images() if reconstructions else 0,
            "num_images": len(db.images), "R_err_max_deg": report.get("R_err_max_deg")}


def rows_for(dataset: str, colmap_s: float, runs: dict[str, dict]) -> list[list[str]]:
    rows = []
    for loss, run in runs.items():
        solves = run["counts"].get("bundle adjustment solves", 0)
        iterations = run["counts"].get("bundle adjustment iterations", 0)
        rest = run["total_s"] - sum(run["stages"].get(stage, 0.0) for stage in STAGES)
        r_err = run["R_err_max_deg"]
        rows.append([dataset, loss, f"{run['num_registered']}/{run['num_images']}",
                     "–" if r_err is None else f"{r_err:.3f}",
                     f"{run['total_s']:.2f}", f"{run['total_s'] / colmap_s:.1f}x",
                     *(f"{run['stages'].get(stage, 0.0):.2f}" for stage in STAGES),
                     f"{rest:.2f}", f"{solves} / {iterations}"])
    return rows


HEADINGS = ["data set", "loss", "registered", "R_err max [deg]", "ours [s]",
            "ours / COLMAP inc.", "registration [s]", "triangulation [s]",
            "bundle adj. [s]", "filtering [s]", "other [s]", "Ceres solves / iterations"]


def section(rows: list[list[str]], notes: list[str], seed: int, elapsed_s: float) -> str:
    return "\n".join([
        "## Profile: where our mapper's time goes", "",
        f"`python benchmarks/mapper_profile.py` on {datetime.date.today().isoformat()} "
        f"({elapsed_s / 60:.1f} min in all), seed {seed}.",
        f"- machine: {machine_line()}",
        f"- versions: {versions_line()}",
        "- databases as in the accuracy section. *ours*: the mapping itself, in process "
        "(database read and model writing excluded); *COLMAP inc.*: its incremental mapper's "
        "mapping call on the same database in the same run. Stages: registration (descriptor "
        "matching to model points, P3P), triangulation (guided matching, new points), bundle "
        "adjustment (Ceres through pycolmap, with building its problem), filtering; other: "
        "two-view geometry, initial pair, merging, export.",
        "- loss: the robust loss of every bundle adjustment (`MapperOptions.bundle_adjustment.loss`); "
        "cauchy is the default.",
        "", markdown_table(HEADINGS, rows), "",
        *[f"- {note}" for note in notes],
    ])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    args = parser.parse_args(argv)

    start = time.perf_counter()
    with work_folder(args.work_dir, "colmap-ext-profile-") as work:
        rows, notes = [], []
        for dataset, database, _ in prepared_datasets(args.data, work, args.seed, not args.no_demo):
            folder = database.parent
            colmap = run_mapper("colmap_incremental", database, dataset.image_path,
                                folder / "colmap_incremental", args.seed, progress=False)
            if colmap.error:
                notes.append(f"{dataset.name}: COLMAP incremental failed: {colmap.error}")
                continue
            notes.append(f"{dataset.name}: COLMAP incremental {colmap.time_s:.2f} s, "
                         f"{colmap.reconstructions[0].num_reg_images()} images registered")
            runs = {}
            for loss in BA_LOSSES:
                print(f"ours, {loss} loss ...", file=sys.stderr, flush=True)
                runs[loss] = profile_ours(database, dataset.ground_truth, loss, args.seed)
            rows += rows_for(dataset.name, colmap.time_s, runs)
        text = section(rows, notes, args.seed, time.perf_counter() - start)
    update_section(Path(args.output), "profile", text)
    print(text)
    print(f"\nwritten to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
