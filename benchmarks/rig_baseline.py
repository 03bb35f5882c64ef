"""COLMAP's own pipeline on hilti_rig with its rig configuration: the baseline the rig mapper
is measured against.

hilti_rig names its images by number (image N is camera N mod 5 of rig pose N div 5), and
COLMAP's rig configuration finds a frame as the images with the same name under each
camera's prefix, so the images are first linked as camC/POSE.jpg into the work folder.
The rig configuration comes from the Kalibr files (`colmap-ext rig_config_from_kalibr`).
Then, each in its own process under /usr/bin/time -v:
- COLMAP: pycolmap extraction (one camera per folder, OPENCV_FISHEYE), apply_rig_config (each
  camera's intrinsics from the configuration), exhaustive matching, incremental mapping
  with the intrinsics and the rig fixed (ba_refine_sensor_from_rig False);
- ours: `colmap-ext reconstruct --rig_config` (frames registered whole, the rig held fixed).
Each model's rig consistency is measured against the configuration.

    COLMAP_EXT_DATA=/path/to/data python benchmarks/rig_baseline.py [--work_dir DIR] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np  # before pycolmap (zlib)
import pycolmap

from colmap_ext import rigs
from colmap_ext.colmap_mappers import colmap_incremental_options, fix_intrinsics_in_database
from colmap_ext.rig_consistency import config_rig_frames, rig_consistency

NUM_CAMERAS = 5
CAMCHAINS = ["calib_3_cam0-1-camchain-imucam.yaml", *(f"calib_3_cam{index}-camchain-imucam.yaml"
                                                      for index in range(2, NUM_CAMERAS))]


def link_images(source: Path, target: Path) -> list[str]:
    """Link hilti_rig's images/N.jpg as camC/POSE.jpg (C = N mod 5, POSE = N div 5)."""
    names = []
    for path in sorted(source.glob("*.jpg"), key=lambda p: int(p.stem)):
        number = int(path.stem)
        name = f"cam{number % NUM_CAMERAS}/{number // NUM_CAMERAS}.jpg"
        (target / name).parent.mkdir(parents=True, exist_ok=True)
        (target / name).unlink(missing_ok=True)
        (target / name).symlink_to(path.resolve())
        names.append(name)
    return names


def run_colmap(image_path: Path, rig_config: Path, output_path: Path, seed: int) -> None:
    """COLMAP's pipeline with the rig (run in a process of its own); writes times.json."""
    database_path = output_path / "database.db"
    configs = rigs.read_rig_config(rig_config)
    first = configs[0].cameras[0].camera
    times = {}
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions(camera_model=first.model.name,
                                         camera_params=",".join(map(str, first.params)))
    pycolmap.extract_features(database_path, image_path, camera_mode=pycolmap.CameraMode.PER_FOLDER,
                              reader_options=reader)
    times["features"] = time.perf_counter() - start
    with pycolmap.Database.open(str(database_path)) as db:
        pycolmap.apply_rig_config(configs, db)
    start = time.perf_counter()
    pycolmap.match_exhaustive(database_path)
    times["matching"] = time.perf_counter() - start
    camera_ids, _ = fix_intrinsics_in_database(database_path)
    options = colmap_incremental_options(camera_ids, seed)
    options.ba_refine_sensor_from_rig = False
    start = time.perf_counter()
    models = pycolmap.incremental_mapping(database_path, image_path, output_path / "sparse",
                                          options)
    times["mapper"] = time.perf_counter() - start
    (output_path / "times.json").write_text(json.dumps(times))
    print({index: model.num_reg_images() for index, model in models.items()})


def timed(command: list[str], log: Path) -> tuple[float, float]:
    """Run `command` under /usr/bin/time -v; its wall time (s) and peak memory (MiB)."""
    start = time.perf_counter()
    with log.open("w") as out:
        subprocess.run(["/usr/bin/time", "-v", *command], stdout=out, stderr=subprocess.STDOUT,
                       check=True)
    seconds = time.perf_counter() - start
    peak_kib = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", log.read_text())[1])
    return seconds, peak_kib / 1024


def summarize(name: str, sparse: Path, configs: list, names: list[str], seconds: float,
              peak_mib: float, mapper_seconds: float) -> dict:
    """Registered images, models and the largest model's rig consistency."""
    models = [pycolmap.Reconstruction(str(folder)) for folder in sorted(sparse.iterdir())
              if folder.is_dir()]
    models.sort(key=lambda model: -model.num_reg_images())
    consistency = rig_consistency(models[0], config_rig_frames(configs, names)) if models else None
    return {"pipeline": name, "num_images": len(names),
            "registered": [model.num_reg_images() for model in models],
            "time_s": round(seconds, 1), "mapper_s": round(mapper_seconds, 1),
            "peak_mib": round(peak_mib),
            "rig_consistency": consistency}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work_dir", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--colmap_only", nargs=3, metavar=("IMAGES", "RIG_JSON", "OUTPUT"),
                        help=argparse.SUPPRESS)  # the COLMAP process itself
    args = parser.parse_args()
    if args.colmap_only:
        images, rig_json, output = map(Path, args.colmap_only)
        run_colmap(images, rig_json, output, args.seed)
        return
    data = Path(os.environ["COLMAP_EXT_DATA"]) / "hilti_rig"
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="rig_baseline-"))
    images = work / "images"
    names = link_images(data / "images", images)
    rig_json = work / "rig_config.json"
    rigs.main([str(data / "calibration" / name) for name in CAMCHAINS], str(rig_json))
    configs = rigs.read_rig_config(rig_json)
    results = []
    colmap_out = work / "colmap"
    colmap_out.mkdir(parents=True, exist_ok=True)
    (colmap_out / "database.db").unlink(missing_ok=True)
    seconds, peak = timed([sys.executable, __file__, "--seed", str(args.seed), "--colmap_only",
                           str(images), str(rig_json), str(colmap_out)], work / "colmap.log")
    mapper_seconds = json.loads((colmap_out / "times.json").read_text())["mapper"]
    results.append(summarize("COLMAP incremental, rig fixed", colmap_out / "sparse", configs,
                             names, seconds, peak, mapper_seconds))
    ours_out = work / "ours"
    seconds, peak = timed([str(Path(sys.executable).with_name("colmap-ext")), "reconstruct",
                           "--image_path", str(images), "--workspace_path", str(ours_out),
                           "--rig_config", str(rig_json), "--seed", str(args.seed),
                           "--overwrite"], work / "ours.log")
    summary = json.loads((ours_out / "reconstruct_summary.json").read_text())
    results.append(summarize("colmap-ext reconstruct --rig_config", ours_out / "sparse",
                             configs, names, seconds, peak, summary["time_s"]["mapper"]))
    print(json.dumps(results, indent=1))
    print("| pipeline | registered (per model) | rig: rotation max deg | translation max m "
          "(scale) | total s | mapper s | peak MiB |\n|---|---|---|---|---|---|---|")
    for result in results:
        rig = result["rig_consistency"]
        cells = ("-", "-") if rig is None else (
            f"{rig['rotation_max_deg']:.2g}", f"{rig['translation_max']:.2g} ({rig['scale']:.3g})")
        print(f"| {result['pipeline']} | {'+'.join(map(str, result['registered']))} of "
              f"{result['num_images']} | {cells[0]} | {cells[1]} | {result['time_s']} | "
              f"{result['mapper_s']} | {result['peak_mib']} |")


if __name__ == "__main__":
    main()
