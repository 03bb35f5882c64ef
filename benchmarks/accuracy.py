"""Pose accuracy and mapper time: ours against COLMAP's mappers on real and synthetic data.

For every data set folder under $COLMAP_EXT_DATA (images and one Middlebury *_par.txt
ground truth) and for a demo scene (`colmap_ext.synthetic.ring_scene`, rendered, with
its true poses as a COLMAP model):
1. a database as COLMAP users make it: pycolmap's default SIFT, exhaustive matching,
   one camera with the ground-truth intrinsics (PINHOLE for Middlebury, the scene's
   OPENCV camera for the demo);
2. `colmap-ext compare` on it (ours, COLMAP incremental, COLMAP global; intrinsics fixed);
3. optionally our end-to-end `reconstruct` from the images (our features and matching).
Writes the accuracy section of BENCHMARKS.md at the repository root (other sections,
e.g. the speed benchmark's, are kept) and prints it.

    COLMAP_EXT_DATA=/path/to/data python benchmarks/accuracy.py [--seed 0] [--work_dir DIR]
        [--mappers ours,colmap_incremental,colmap_global] [--no_reconstruct] [--no_demo]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import os
import platform
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import closing
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pycolmap

import colmap_ext
from colmap_ext.compare import MAPPERS, compare
from colmap_ext.evaluate import AUC_KEY, evaluate, format_auc
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.synthetic import render_images, ring_scene, write_ground_truth

REPO = Path(__file__).resolve().parent.parent
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm"}


# ---------------------------------------------------------------------------------------
# Machine, versions, and BENCHMARKS.md sections (shared with mapper_speed.py)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def memory_gib() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return None


def machine_line() -> str:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    memory = memory_gib()
    line = f"{cpu_model()}, {cores} cores available ({os.cpu_count()} logical)"
    if memory is not None:
        line += f", {memory:.0f} GiB RAM"
    return line + f", {platform.system()} {platform.release()}"


def versions_line() -> str:
    def package(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "?"

    try:
        commit = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"],
                                capture_output=True, text=True, timeout=10).stdout.strip()
    except OSError:
        commit = ""
    return (f"colmap-ext {colmap_ext.__version__}" + (f" (commit {commit})" if commit else "")
            + f", pycolmap {pycolmap.__version__}, numpy {package('numpy')}, "
            f"opencv {package('opencv-contrib-python-headless')}, Python {platform.python_version()}")


def update_section(path: Path, name: str, body: str) -> None:
    """Replace the section `name` of a Markdown file (between its begin/end markers), or
    append it; the rest of the file is kept."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    block = f"{begin}\n{body.rstrip()}\n{end}\n"
    text = path.read_text() if path.exists() else "# Benchmarks\n\n"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        text = head + block + ("\n" + tail if tail else "")
    else:
        text = text.rstrip("\n") + "\n\n" + block
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


@contextlib.contextmanager
def work_folder(path: str | None, prefix: str) -> Iterator[Path]:
    """The folder `path` (kept afterwards, for inspection), or a temporary one removed at the end."""
    if path:
        Path(path).mkdir(parents=True, exist_ok=True)
        yield Path(path)
    else:
        with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
            yield Path(tmp)


# ---------------------------------------------------------------------------------------
# Data sets and databases


@dataclass
class Dataset:
    name: str
    image_path: Path
    ground_truth: Path
    camera_model: str
    camera_params: list[float]
    image_names: list[str]


def find_datasets(root: Path) -> list[Dataset]:
    """The data sets under `root`: every folder with a ground truth (dataset_in)."""
    return [dataset for folder in sorted(p for p in root.iterdir() if p.is_dir())
            if (dataset := dataset_in(folder)) is not None]


def dataset_in(folder: Path) -> Dataset | None:
    """The data set of a folder holding one Middlebury *_par.txt or a Strecha gt_cameras/,
    its images beside it or in images/; None without a ground truth."""
    pars = sorted(folder.glob("*_par.txt"))
    if len(pars) == 1:
        ground_truth = pars[0]
    elif not pars and (folder / "gt_cameras").is_dir():
        ground_truth = folder / "gt_cameras"
    else:
        return None
    truth = read_ground_truth(ground_truth)
    camera = next(iter(truth.cameras.values()))
    images = folder / "images" if (folder / "images").is_dir() else folder
    names = [n for n in truth.poses if (images / n).suffix.lower() in IMAGE_SUFFIXES
             and (images / n).is_file()]
    return Dataset(folder.name, images, ground_truth, camera.model.name,
                   [float(p) for p in camera.params], names)


def demo_dataset(work: Path, seed: int) -> Dataset:
    """The synthetic ring scene, rendered, with its true poses as a COLMAP model."""
    scene = ring_scene(seed=seed)
    folder = work / "demo_ring"
    render_images(scene, folder / "images", seed=seed)
    write_ground_truth(scene, folder / "ground_truth")
    return Dataset("demo ring (synthetic)", folder / "images", folder / "ground_truth",
                   scene.camera.model.name, [float(p) for p in scene.camera.params],
                   list(scene.image_names))


def prepared_datasets(data: str | None, work: Path, seed: int,
                      demo: bool) -> Iterator[tuple[Dataset, Path, dict]]:
    """Every data set under `data`, then the demo scene unless `demo` is False, each with
    a database built afresh in its folder of `work`: (data set, database, its statistics)."""
    datasets = find_datasets(Path(data)) if data else []
    if not data:
        print("COLMAP_EXT_DATA is not set: only the demo scene", file=sys.stderr)
    if demo:
        print("rendering the demo scene ...", file=sys.stderr, flush=True)
        datasets.append(demo_dataset(work, seed))
    for dataset in datasets:
        print(f"\n=== {dataset.name} ===", file=sys.stderr, flush=True)
        folder = work / dataset.name.split()[0]
        folder.mkdir(parents=True, exist_ok=True)
        database = folder / "database.db"
        database.unlink(missing_ok=True)
        yield dataset, database, build_database(dataset, database)


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """The data, seed, work folder and output arguments of the data-set benchmarks."""
    parser.add_argument("--data", default=os.environ.get("COLMAP_EXT_DATA"),
                        help="folder of data sets (default: $COLMAP_EXT_DATA)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work_dir", default=None,
                        help="keep databases, models and reports here (default: a temporary folder)")
    parser.add_argument("--output", default=str(REPO / "BENCHMARKS.md"))
    parser.add_argument("--no_demo", action="store_true", help="skip the synthetic demo scene")


def build_database(dataset: Dataset, database_path: Path, sequential_overlap: int | None = None) -> dict:
    """pycolmap default SIFT and exhaustive matching, one camera with the known intrinsics;
    with sequential_overlap, sequential matching instead (each image with that many next ones)."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = dataset.camera_model
    reader.camera_params = ",".join(repr(p) for p in dataset.camera_params)
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(previous, int(pycolmap.logging.Level.WARNING))
    start = time.perf_counter()
    try:
        pycolmap.extract_features(database_path, dataset.image_path, image_names=dataset.image_names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  device=pycolmap.Device.cpu)
        extracted = time.perf_counter()
        if sequential_overlap is None:
            pycolmap.match_exhaustive(database_path, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_sequential(database_path, device=pycolmap.Device.cpu,
                                      pairing_options=pycolmap.SequentialPairingOptions(overlap=sequential_overlap))
    finally:
        pycolmap.logging.minloglevel = previous
    matched = time.perf_counter()
    with closing(sqlite3.connect(f"file:{database_path}?mode=ro", uri=True)) as conn:
        keypoints = [row[0] for row in conn.execute("SELECT rows FROM keypoints")]
        verified = conn.execute("SELECT COUNT(*) FROM two_view_geometries WHERE rows > 0").fetchone()[0]
    return {"extraction_s": extracted - start, "matching_s": matched - extracted,
            "keypoints_mean": sum(keypoints) / max(len(keypoints), 1),
            "keypoints_min": min(keypoints, default=0), "verified_pairs": verified}


def run_reconstruct(dataset: Dataset, workspace: Path, seed: int) -> dict:
    """Our end-to-end `reconstruct` (our features and matching); its largest model evaluated."""
    from colmap_ext import reconstruct  # optional: may not exist in every checkout

    with contextlib.redirect_stdout(io.StringIO()):
        summary = reconstruct.main(image_path=str(dataset.image_path), workspace_path=str(workspace),
                                   camera_model=dataset.camera_model,
                                   camera_params=",".join(repr(p) for p in dataset.camera_params),
                                   seed=seed, overwrite=True)
    models = sorted(summary["models"], key=lambda m: -m["num_registered"])
    entry = {"time_s": summary["time_s"]["mapper"], "total_s": summary["time_s"]["total"],
             "num_images": len(dataset.image_names), "num_models": len(models),
             "num_registered": models[0]["num_registered"] if models else 0,
             "num_registered_all_models": sum(m["num_registered"] for m in models)}
    if models:
        report = evaluate(pycolmap.Reconstruction(models[0]["path"]),
                          read_ground_truth(dataset.ground_truth))
        entry.update({k: v for k, v in report.items() if k != "num_registered"})
    return entry


# ---------------------------------------------------------------------------------------
# The table


def _cell(entry: dict, key: str, digits: int) -> str:
    value = entry.get(key)
    return "–" if value is None else f"{value:.{digits}f}"


def result_rows(dataset: str, mappers: dict[str, dict]) -> list[list[str]]:
    reference = mappers.get("colmap_incremental", {}).get("time_s")
    rows = []
    for name, entry in mappers.items():
        if "error" in entry:
            registered = f"failed: {entry['error']}"
        else:
            registered = f"{entry['num_registered']}/{entry['num_images']}"
            others = entry.get("num_registered_all_models", entry["num_registered"]) - entry["num_registered"]
            if entry.get("num_models", 1) > 1:
                more = entry["num_models"] - 1
                registered += f" (+{others} in {more} other model{'s' if more > 1 else ''})"
        time_s = entry.get("time_s")
        ratio = "–" if not reference or time_s is None or "error" in entry else f"{time_s / reference:.1f}x"
        rows.append([dataset, name, registered,
                     _cell(entry, "R_err_max_deg", 3), _cell(entry, "R_err_median_deg", 3),
                     _cell(entry, "T_err_max_deg", 3), _cell(entry, "T_err_median_deg", 3),
                     _cell(entry, "C_err_max", 4), _cell(entry, "C_err_median", 4),
                     format_auc(entry) if AUC_KEY in entry else "–",
                     "–" if time_s is None else f"{time_s:.2f}", ratio])
    return rows


HEADINGS = ["data set", "mapper", "registered", "R_err max [deg]", "R_err median [deg]",
            "T_err max [deg]", "T_err median [deg]", "C_err max", "C_err median",
            "AUC@0.5/1/5/10 deg [%]", "mapper time [s]", "time / COLMAP incremental"]


def markdown_table(headings: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headings)]
    lines = ["| " + " | ".join(h.ljust(w) for h, w in zip(headings, widths)) + " |",
             "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    lines += ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |" for row in rows]
    return "\n".join(lines)


def section(rows: list[list[str]], notes: list[str], seed: int, elapsed_s: float) -> str:
    today = datetime.date.today().isoformat()
    return "\n".join([
        "## Accuracy: ours against COLMAP's mappers", "",
        f"`python benchmarks/accuracy.py` on {today} ({elapsed_s / 60:.1f} min in all), seed {seed}.",
        f"- machine: {machine_line()}",
        f"- versions: {versions_line()}",
        "- databases: pycolmap's default SIFT, exhaustive matching, one camera with the "
        "ground-truth intrinsics; every mapper runs on a private copy of the same database "
        "(`colmap-ext compare`) with the intrinsics held fixed.",
        "- registered: images in the largest model (the one evaluated) / images. Errors "
        "(the paper's, relative to the first registered image): R_err, T_err in degrees; "
        "C_err in units of the distance between the first two ground-truth cameras.",
        "- mapper time: wall time of the mapping call (database read to model written); the "
        "ratio divides it by COLMAP's incremental mapper's time on the same database in the "
        "same run. `reconstruct` rows: our features and matching on the images, then our "
        "mapper (its mapper stage is timed; ratio against COLMAP incremental on the pycolmap "
        "database).",
        "", markdown_table(HEADINGS, rows), "",
        *[f"- {note}" for note in notes],
    ])


# ---------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    parser.add_argument("--mappers", default=",".join(MAPPERS))
    parser.add_argument("--no_reconstruct", action="store_true",
                        help="skip our end-to-end reconstruct rows")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    with work_folder(args.work_dir, "colmap-ext-accuracy-") as work:
        rows, notes = [], []
        for dataset, database, stats in prepared_datasets(args.data, work, args.seed,
                                                          not args.no_demo):
            folder = database.parent
            notes.append(f"{dataset.name}: {len(dataset.image_names)} images, "
                         f"{stats['keypoints_mean']:.0f} SIFT keypoints per image on average "
                         f"(min {stats['keypoints_min']}), {stats['verified_pairs']} verified pairs; "
                         f"extraction {stats['extraction_s']:.1f} s, matching {stats['matching_s']:.1f} s")
            report = compare(database, dataset.image_path, folder / "compare",
                             ground_truth=dataset.ground_truth, mappers=args.mappers,
                             seed=args.seed, overwrite=True)
            mappers = dict(report["mappers"])
            for name, entry in mappers.items():
                if "evaluation_error" in entry:
                    notes.append(f"{dataset.name}, {name}: not evaluated: {entry['evaluation_error']}")
            if not args.no_reconstruct:
                print(f"reconstruct (ours end to end) on {dataset.name} ...", file=sys.stderr, flush=True)
                try:
                    entry = run_reconstruct(dataset, folder / "reconstruct", args.seed)
                except ImportError:
                    notes.append("`colmap_ext.reconstruct` is not available: no end-to-end rows")
                except Exception as exc:  # optional rows: report, do not stop the benchmark
                    notes.append(f"{dataset.name}: `reconstruct` failed: {type(exc).__name__}: {exc}")
                else:
                    mappers["ours reconstruct"] = entry
                    notes.append(f"{dataset.name}: `reconstruct` end to end (features, matching, "
                                 f"mapper) {entry['total_s']:.1f} s")
            rows += result_rows(dataset.name, mappers)
        text = section(rows, notes, args.seed, time.perf_counter() - start)
    update_section(Path(args.output), "accuracy", text)
    print()
    print(text)
    print(f"\nwritten to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
