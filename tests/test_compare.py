"""`colmap-ext compare`: every file written, the report's keys, intrinsics held fixed,
the user's database left byte for byte, and no silent overwriting."""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext import compare as compare_module
from colmap_ext.compare import compare
from colmap_ext.errors import UserError
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.synthetic import ring_scene, scene_points, write_ground_truth, write_synthetic_database

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")
MAPPER_KEYS = ("time_s", "num_registered", "num_images", "num_models", "num_points3D",
               "mean_track_length", "mean_reprojection_error")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A 10-view ring database with verified geometries (COLMAP's mappers need them),
    placeholder images (our mapper reads point colours) and the true poses."""
    folder = tmp_path_factory.mktemp("compare")
    scene = ring_scene(num_images=10, seed=3)
    write_synthetic_database(folder / "database.db", scene, scene_points(scene, 1500, seed=3),
                             noise_px=0.5, outlier_ratio=0.2, seed=3, two_view_geometries=True)
    (folder / "images").mkdir()
    for name in scene.image_names:
        cv2.imwrite(str(folder / "images" / name), np.zeros((8, 8), np.uint8))
    write_ground_truth(scene, folder / "gt")
    return folder, scene


@pytest.fixture(scope="module")
def compared(synthetic, tmp_path_factory):
    folder, _ = synthetic
    before = (sha256(folder / "database.db"), sorted(p.name for p in folder.iterdir()))
    output = tmp_path_factory.mktemp("cmp") / "CMP"
    report = compare(folder / "database.db", folder / "images", output,
                     ground_truth=folder / "gt", mappers="ours,colmap_incremental", seed=0,
                     progress=False)
    return output, report, before


def test_writes_every_file(compared):
    output, _, _ = compared
    for mapper in ("ours", "colmap_incremental"):
        for name in MODEL_FILES:
            assert (output / mapper / "0" / name).is_file(), f"{mapper}/0/{name} missing"
    for name in ("report.json", "report.md", "errors.png"):
        assert (output / name).is_file()
    assert not (output / "colmap_global").exists()
    assert not [p for p in output.iterdir() if p.name.startswith(".")], "temporary files left"
    markdown = (output / "report.md").read_text()
    assert "| ours " in markdown and "| colmap_incremental " in markdown
    # Our time as a ratio to COLMAP incremental's, the measure users compare mappers by.
    report = json.loads((output / "report.json").read_text())
    ratio = report["mappers"]["ours"]["time_s"] / report["mappers"]["colmap_incremental"]["time_s"]
    ours_row = next(line for line in markdown.splitlines() if line.startswith("| ours "))
    assert "time / COLMAP incremental" in markdown and f" {ratio:.2f}x " in ours_row
    assert "compare_reconstructions" in markdown


def test_report_has_the_keys(compared, synthetic):
    output, report, _ = compared
    folder, scene = synthetic
    assert json.loads((output / "report.json").read_text()) == report
    evaluate_keys = set(evaluate(pycolmap.Reconstruction(output / "ours" / "0"),
                                 read_ground_truth(folder / "gt")))
    assert set(report["mappers"]) == {"ours", "colmap_incremental"}
    for name, entry in report["mappers"].items():
        assert "error" not in entry, entry.get("error")
        assert set(MAPPER_KEYS) <= set(entry), name
        assert evaluate_keys <= set(entry), name
        assert entry["num_images"] == scene.num_images
        assert entry["num_registered"] == scene.num_images
        assert entry["R_err_max_deg"] < 0.2
    distance = report["model_comparison"]
    assert distance["reference"] == "ours"
    assert distance["mappers"]["colmap_incremental"]["num_common_images"] == scene.num_images


def test_intrinsics_stay_fixed_and_database_unchanged(compared, synthetic):
    output, _, before = compared
    folder, scene = synthetic
    assert sha256(folder / "database.db") == before[0], "the user's database was modified"
    assert sorted(p.name for p in folder.iterdir()) == before[1], "files appeared beside it"
    for mapper in ("ours", "colmap_incremental"):
        model = pycolmap.Reconstruction(output / mapper / "0")
        for camera in model.cameras.values():
            np.testing.assert_array_equal(camera.params, scene.camera.params)


def test_refuses_without_overwrite_then_replaces(compared, synthetic):
    output, _, _ = compared
    folder, _ = synthetic
    written = sha256(output / "report.json")
    args = ["--database_path", str(folder / "database.db"), "--image_path",
            str(folder / "images"), "--output_path", str(output), "--mappers",
            "colmap_incremental", "--seed", "1"]
    parser = argparse.ArgumentParser()
    compare_module.add_arguments(parser)
    with pytest.raises(UserError, match="pass --overwrite"):
        compare_module.main(**vars(parser.parse_args(args)))
    assert sha256(output / "report.json") == written

    report = compare_module.main(**vars(parser.parse_args([*args, "--overwrite"])))
    assert list(report["mappers"]) == ["colmap_incremental"]
    assert report["seed"] == 1
    assert not (output / "errors.png").exists(), "a stale figure was left behind"
    assert json.loads((output / "report.json").read_text())["seed"] == 1


@pytest.mark.parametrize("mappers, message", [("ours,nope", "unknown mapper 'nope'"),
                                              ("ours,ours", "names a mapper twice"),
                                              (",", "--mappers is empty")])
def test_bad_mapper_list(synthetic, tmp_path, mappers, message):
    folder, _ = synthetic
    with pytest.raises(UserError, match=message):
        compare(folder / "database.db", folder / "images", tmp_path / "cmp", mappers=mappers)
    assert not (tmp_path / "cmp").exists()


def test_ground_truth_of_other_images_is_refused_before_any_work(synthetic, tmp_path):
    folder, _ = synthetic
    other = ring_scene(num_images=4, seed=1)
    other.image_names[:] = [f"other{i}.png" for i in range(4)]
    write_ground_truth(other, tmp_path / "gt")
    with pytest.raises(UserError, match="ground-truth images are in the database"):
        compare(folder / "database.db", folder / "images", tmp_path / "cmp",
                ground_truth=tmp_path / "gt")
    assert not (tmp_path / "cmp").exists()
