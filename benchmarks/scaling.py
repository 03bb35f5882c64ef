"""Mapper time and peak memory against the number of images: ours and COLMAP's incremental.

Synthetic databases, no images needed: a walk along a long facade
(`colmap_ext.synthetic.trajectory_scene`), its points projected into every view with
0.5 px noise and 20 % wrong matches, and the verified two-view geometries COLMAP's
mapper reads (`write_synthetic_database(..., two_view_geometries=True)`). The images
folder holds tiny placeholder PNGs (our mapper reads point colours from it).

Each mapper runs in its own subprocess on its own copy of the database, with the
intrinsics fixed (the settings of `colmap-ext compare`); the parent reads the child's
peak resident memory from os.wait4 (ru_maxrss), and the child reports the time of the
mapping call and the pose errors against the true poses. "python + imports" is the
peak of a child that only imports what the mappers import: the floor under both.

    python benchmarks/scaling.py [--sizes 50 200 [1000]] [--keypoints_per_image 1000]
        [--mappers ours,colmap_incremental] [--seed 0] [--work_dir DIR] [--markdown BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).resolve()
REPO = SCRIPT.parent.parent
MAPPERS = ("ours", "colmap_incremental")


def worker(args: argparse.Namespace) -> int:
    """In the child: run one mapper (or only import, for the baseline); write the result JSON."""
    from colmap_ext.compare import run_mapper  # noqa: F401  (the imports are the baseline)
    from colmap_ext.evaluate import evaluate
    from colmap_ext.ground_truth import read_ground_truth

    if args.worker == "baseline":
        Path(args.result).write_text(json.dumps({}))
        return 0
    result = run_mapper(args.worker, Path(args.database), Path(args.images), Path(args.output),
                        args.seed, progress=not args.quiet)
    entry = {"time_s": result.time_s, "error": result.error, "num_models": len(result.reconstructions)}
    if result.reconstructions:
        model = result.reconstructions[0]
        entry.update(num_registered=model.num_reg_images(), num_points3D=model.num_points3D())
        try:
            report = evaluate(model, read_ground_truth(args.ground_truth))
        except Exception as exc:  # noqa: BLE001  (reported in the table)
            entry["evaluation_error"] = str(exc)
        else:
            entry.update(R_err_max_deg=report["R_err_max_deg"],
                         C_err_aligned_max=report["C_err_aligned_max"])
    Path(args.result).write_text(json.dumps(entry))
    return 0


def run_child(argv: list[str]) -> tuple[int, float]:
    """Run this script as a child; returns (exit code, peak resident memory in MiB)."""
    process = subprocess.Popen([sys.executable, str(SCRIPT), *argv])
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return process.returncode, usage.ru_maxrss / 1024  # Linux: KiB


def make_database(folder: Path, size: int, keypoints_per_image: int, seed: int) -> dict:
    """The synthetic database, placeholder images and ground truth of `size` views.

    The street's ends make a larger share of a short scene, so the number of scene points
    is set from a few views' counts to give about `keypoints_per_image` at every size."""
    import cv2
    import numpy as np

    from colmap_ext.synthetic import scene_points, trajectory_scene, write_ground_truth, write_synthetic_database
    from colmap_ext.synthetic.database import observe

    start = time.perf_counter()
    scene = trajectory_scene(num_images=size, seed=seed)
    probe_size = keypoints_per_image * size
    probe = scene_points(scene, probe_size, seed=seed)
    views = np.unique(np.linspace(0, size - 1, min(size, 12)).astype(int))
    seen = np.mean([len(observe(scene, i, probe).point_ids) for i in views])
    points = scene_points(scene, max(1, round(probe_size * keypoints_per_image / seen)), seed=seed)
    truth = write_synthetic_database(folder / "database.db", scene, points, noise_px=0.5,
                                     outlier_ratio=0.2, seed=seed, two_view_geometries=True)
    (folder / "images").mkdir()
    placeholder = cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()
    for name in scene.image_names:
        (folder / "images" / name).write_bytes(placeholder)
    write_ground_truth(scene, folder / "ground_truth")
    return {"keypoints_per_image": float(np.mean([len(p) for p in truth.point_ids])),
            "matched_pairs": len(truth.matches),
            "verified_pairs": sum(len(m) >= 15 for m in truth.inlier_matches.values()),
            "seconds": time.perf_counter() - start}


def table(rows: list[dict]) -> str:
    from accuracy import markdown_table

    headings = ["images", "keypoints / image", "mapper", "registered", "models", "time [s]",
                "time / COLMAP incremental", "peak memory [MiB]", "R_err max [deg]", "C_err_aligned max"]
    cells = []
    for row in rows:
        entry = row["entry"]
        if entry.get("error"):
            registered = f"failed: {entry['error']}"
        elif "num_registered" in entry:
            registered = f"{entry['num_registered']}/{row['size']}"
        else:
            registered = "–"
        reference = row.get("reference_time")
        time_s = entry.get("time_s")
        cells.append([
            str(row["size"]), f"{row['keypoints_per_image']:.0f}", row["mapper"], registered,
            str(entry.get("num_models", "–")),
            "–" if time_s is None else f"{time_s:.2f}",
            f"{time_s / reference:.1f}x" if reference and time_s is not None and not entry.get("error") else "–",
            f"{row['peak_mib']:.0f}",
            f"{entry['R_err_max_deg']:.3f}" if "R_err_max_deg" in entry else "–",
            f"{entry['C_err_aligned_max']:.4f}" if "C_err_aligned_max" in entry else "–",
        ])
    return markdown_table(headings, cells)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 200],
                        help="numbers of images (1000 is opt-in: it takes long)")
    parser.add_argument("--keypoints_per_image", type=int, default=1000,
                        help="about this many keypoints per image, at every size")
    parser.add_argument("--mappers", default=",".join(MAPPERS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work_dir", default=None, help="keep the databases and models here")
    parser.add_argument("--markdown", default=None,
                        help="also write the table as the scaling section of this file (e.g. BENCHMARKS.md)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    # The child's side.
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--database", help=argparse.SUPPRESS)
    parser.add_argument("--images", help=argparse.SUPPRESS)
    parser.add_argument("--output", help=argparse.SUPPRESS)
    parser.add_argument("--ground_truth", help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)

    from accuracy import machine_line, update_section, versions_line, work_folder

    mappers = [m.strip() for m in args.mappers.split(",") if m.strip()]
    unknown = [m for m in mappers if m not in ("ours", "colmap_incremental", "colmap_global")]
    if unknown or not mappers:
        parser.error(f"unknown mapper(s) in --mappers: {', '.join(unknown) or '(none)'}")
    start = time.perf_counter()
    rows: list[dict] = []
    with work_folder(args.work_dir, "colmap-ext-scaling-") as work:
        result_path = work / "result.json"
        code, baseline_mib = run_child(["--worker", "baseline", "--result", str(result_path)])
        if code != 0:
            print("the baseline child failed", file=sys.stderr)
            return 1
        for size in args.sizes:
            folder = work / f"images_{size}"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            print(f"\n=== {size} images: writing the synthetic database ...", file=sys.stderr, flush=True)
            stats = make_database(folder, size, args.keypoints_per_image, args.seed)
            print(f"    {stats['keypoints_per_image']:.0f} keypoints per image, "
                  f"{stats['verified_pairs']} verified pairs ({stats['seconds']:.1f} s)",
                  file=sys.stderr, flush=True)
            size_rows = []
            for mapper in mappers:
                print(f"--- {mapper}, {size} images", file=sys.stderr, flush=True)
                copy = folder / mapper / "database.db"
                copy.parent.mkdir()
                shutil.copyfile(folder / "database.db", copy)
                result_path.unlink(missing_ok=True)
                child = ["--worker", mapper, "--database", str(copy), "--images", str(folder / "images"),
                         "--output", str(folder / mapper / "out"), "--ground_truth",
                         str(folder / "ground_truth"), "--seed", str(args.seed), "--result",
                         str(result_path)] + (["--quiet"] if args.quiet else [])
                code, peak = run_child(child)
                if code != 0 or not result_path.exists():
                    entry = {"error": f"the child exited with code {code}"}
                else:
                    entry = json.loads(result_path.read_text())
                size_rows.append({"size": size, "mapper": mapper, "entry": entry, "peak_mib": peak,
                                  "keypoints_per_image": stats["keypoints_per_image"]})
            reference = next((r["entry"].get("time_s") for r in size_rows
                              if r["mapper"] == "colmap_incremental" and not r["entry"].get("error")), None)
            for row in size_rows:
                row["reference_time"] = reference
            rows += size_rows
    elapsed = time.perf_counter() - start
    machine = f"Machine: {machine_line()}. Versions: {versions_line()}."
    text = table(rows)
    notes = (f"Peak memory is the child process's maximum resident set size; python + imports "
             f"alone take {baseline_mib:.0f} MiB. Time: the mapping call (database read to model "
             f"written). Scene: `trajectory_scene`, about {args.keypoints_per_image} keypoints per image, "
             f"0.5 px noise, 20 % wrong matches, seed {args.seed}.")
    print()
    print(machine)
    print()
    print(text)
    print()
    print(notes)
    if args.markdown:
        body = "\n".join([
            "## Scaling: time and memory against the number of images", "",
            f"`python benchmarks/scaling.py --sizes {' '.join(map(str, args.sizes))}` on "
            f"{datetime.date.today().isoformat()} ({elapsed / 60:.1f} min in all).",
            f"- machine: {machine_line()}", f"- versions: {versions_line()}", f"- {notes}",
            "", text])
        update_section(Path(args.markdown), "scaling", body)
        print(f"\nwritten to {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(SCRIPT.parent))  # accuracy.py: machine line, tables, sections
    sys.exit(main())
