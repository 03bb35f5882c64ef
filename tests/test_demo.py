"""`colmap-ext demo`: the whole pipeline on the project's rendered ring, run as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from colmap_ext import evaluate
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.model_io import read_model


def test_demo_runs_to_completion(tmp_path: Path, record_figures, assert_scene_shows) -> None:
    """`colmap-ext demo` renders 24 views, reconstructs and evaluates them: it exits 0,
    every view is registered in one model with accurate poses, and the report and its
    plots are written; the scene plot draws the aligned model over the ground truth."""
    root = tmp_path / "demo"
    result = subprocess.run([sys.executable, "-m", "colmap_ext", "demo", "--output_path",
                             str(root)], capture_output=True, text=True, timeout=1200)
    assert result.returncode == 0, result.stderr
    assert f"report: {root / 'report.json'}" in result.stdout
    assert [path.name for path in (root / "workspace" / "sparse").iterdir() if path.is_dir()] \
        == ["0"]
    report = json.loads((root / "report.json").read_text())
    assert report["num_gt_images"] == 24 and report["num_registered"] == 24
    # Measured over seeds 0-2: R_err max 0.016-0.022 deg, C_err max 0.0017.
    assert report["R_err_max_deg"] < 0.07
    assert report["C_err_max"] < 0.005
    assert (root / "errors.png").stat().st_size > 0
    assert f"{root / 'errors_scene.png'}" in result.stdout

    # The demo's scene figure, drawn again here (pixel for pixel) where its artists can be read.
    model_path, truth_path = root / "workspace" / "sparse" / "0", root / "ground_truth"
    with record_figures() as figures:
        again = evaluate.main(model_path, truth_path, plot=tmp_path / "errors.png")
    [_, (scene, _)] = figures
    with Image.open(root / "errors_scene.png") as drawn, \
            Image.open(tmp_path / "errors_scene.png") as redrawn:
        assert drawn.format == "PNG"
        np.testing.assert_array_equal(np.asarray(drawn), np.asarray(redrawn))
    truth = read_ground_truth(truth_path)
    cameras, points = evaluate.aligned_to_ground_truth(read_model(model_path), truth)
    data = assert_scene_shows(scene, truth.poses, cameras, points, again)
    assert len(data["estimated directions"]) == 24 and len(data["unregistered"]) == 0
    assert len(data["points"]) > 1000
    assert data["named"] == []  # accurate poses: no camera visibly off its ground truth
