"""Every central camera model end to end, on databases from COLMAP's own generator
(`pycolmap.synthesize_dataset`), without image files: `colmap-ext mapper` runs in a
subprocess, so that a crash inside pycolmap fails the test instead of ending pytest."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import GroundTruth
from colmap_ext.synthetic.pycolmap_generator import write_pycolmap_dataset


def run_mapper(folder: Path, *flags: str) -> subprocess.CompletedProcess:
    (folder / "images").mkdir(exist_ok=True)
    return subprocess.run(
        [sys.executable, "-m", "colmap_ext", "mapper", "--database_path",
         str(folder / "database.db"), "--image_path", str(folder / "images"),
         "--output_path", str(folder / "sparse"), "--seed", "0", *flags],
        capture_output=True, text=True, timeout=600)


def ground_truth(truth: pycolmap.Reconstruction) -> GroundTruth:
    images = sorted(truth.images.values(), key=lambda image: image.name)
    return GroundTruth(poses={image.name: copy.copy(image.cam_from_world()) for image in images},
                       cameras={image.name: copy.copy(image.camera) for image in images})


def test_equirectangular_database_maps_without_image_files(tmp_path):
    """Regression: pycolmap's focal-length accessors crashed the mapper (SIGSEGV) on a
    camera model without a focal length. The image files are absent: the model is made,
    its colours skipped with one warning."""
    truth = write_pycolmap_dataset(tmp_path / "database.db", "EQUIRECTANGULAR", seed=0,
                                   num_images=10)
    result = run_mapper(tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    warnings = [line for line in result.stderr.splitlines() if "not under" in line]
    assert len(warnings) == 1 and "colours not extracted" in warnings[0]
    report = evaluate(pycolmap.Reconstruction(tmp_path / "sparse" / "0"), ground_truth(truth))
    assert report["num_registered"] == 10
    assert report["R_err_max_deg"] < 1.0
