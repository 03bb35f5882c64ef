"""`colmap-ext compare`: every file written, the report's keys, intrinsics held fixed,
the user's database left byte for byte, and no silent overwriting."""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from colmap_ext import compare as compare_module
from colmap_ext.colmap_mappers import colmap_global_options, fix_intrinsics_in_database
from colmap_ext.compare import MAPPERS, compare
from colmap_ext.errors import UserError
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.synthetic import (ring_scene, scene_points, write_ground_truth, write_placeholder_images,
                                  write_synthetic_database)

MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")
MAPPER_KEYS = ("time_s", "num_registered", "num_images", "num_models", "num_points3D",
               "mean_track_length", "mean_reprojection_error")
# How far COLMAP's models may lie from ours on the synthetic ring: about 3x the worst of 24
# comparisons (ring seeds 3, 4, 5; compare seeds 0 to 7), both COLMAP mappers.
MAX_ROTATION_DISTANCE_DEG = 0.1  # worst 0.033 (incremental), 0.028 (global)
MAX_CENTRE_DISTANCE = 0.0025  # worst 0.00082 (incremental), 0.00066 (global), camera spreads
# errors.png: 12 x 5 inches at 120 dpi; matplotlib's first three colours, C0 to C2.
FIGURE_SIZE = (1440, 600)
MAPPER_COLOURS = ((0x1F, 0x77, 0xB4), (0xFF, 0x7F, 0x0E), (0x2C, 0xA0, 0x2C))
MIN_PIXELS_PER_MAPPER = 1000  # measured 2555 to 4792 pixels of exactly its colour


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
    write_placeholder_images(folder / "images", scene.image_names)
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


@pytest.fixture(scope="module")
def compared_all(synthetic, tmp_path_factory, record_figures):
    """compare with its default mapper list (all three), and the figures it drew."""
    folder, _ = synthetic
    output = tmp_path_factory.mktemp("cmp_all") / "CMP"
    with record_figures() as figures:
        report = compare(folder / "database.db", folder / "images", output,
                         ground_truth=folder / "gt", seed=0, progress=False)
    return output, report, figures


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
    auc = report["mappers"]["ours"]["AUC_percent"]
    assert "AUC@0.5/1/5/10 deg [%]" in markdown and " / ".join(f"{v:.2f}" for v in auc.values()) in ours_row


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


def test_default_runs_every_mapper_including_global(compared_all, synthetic):
    """Without --mappers, COLMAP's global mapper runs too: all images, intrinsics held fixed."""
    output, report, _ = compared_all
    _, scene = synthetic
    assert list(report["mappers"]) == list(MAPPERS) == ["ours", "colmap_incremental", "colmap_global"]
    for name, entry in report["mappers"].items():
        assert "error" not in entry, entry.get("error")
        assert entry["num_registered"] == entry["num_images"] == scene.num_images, name
        assert entry["R_err_max_deg"] < 0.2, name
        for file in MODEL_FILES:
            assert (output / name / "0" / file).is_file(), f"{name}/0/{file} missing"
        for camera in pycolmap.Reconstruction(output / name / "0").cameras.values():
            np.testing.assert_array_equal(camera.params, scene.camera.params)
    assert "| colmap_global " in (output / "report.md").read_text()


def test_colmap_global_keeps_tracks_longer_than_100_views(tmp_path):
    """COLMAP's generator at 110 images, every point seen by every image: with GLOMAP's
    default cap of 100 views a track, COLMAP's global mapper finds no track and no model;
    as compare and the benchmarks set it up, it registers every image."""
    pycolmap.set_random_seed(0)
    options = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_cameras_per_rig=1,
                                               num_frames_per_rig=110, num_points3D=60)
    with pycolmap.Database.open(tmp_path / "database.db") as database:
        pycolmap.synthesize_dataset(options, database)
    _, num_images = fix_intrinsics_in_database(tmp_path / "database.db")
    reconstructions = pycolmap.global_mapping(tmp_path / "database.db", tmp_path, tmp_path / "out",
                                              colmap_global_options(0, num_images))
    assert [r.num_reg_images() for r in reconstructions.values()] == [110]


@pytest.mark.parametrize("run", ["compared", "compared_all"])
def test_model_distances_are_small_on_synthetic_data(run, request, synthetic):
    """COLMAP's models of the ring (0.5 px noise) lie within a few hundredths of a degree
    and a thousandth of the camera spread of ours."""
    _, report, _ = request.getfixturevalue(run)
    _, scene = synthetic
    distance = report["model_comparison"]
    assert distance["reference"] == "ours"
    assert set(distance["mappers"]) == set(report["mappers"]) - {"ours"}
    for name, entry in distance["mappers"].items():
        assert entry["num_common_images"] == scene.num_images, name
        assert entry["rotation_error_median_deg"] <= entry["rotation_error_max_deg"] \
            < MAX_ROTATION_DISTANCE_DEG, name
        assert entry["centre_error_median"] <= entry["centre_error_max"] < MAX_CENTRE_DISTANCE, name


def test_errors_png_draws_every_mappers_errors(compared_all, assert_figure_shows):
    """errors.png is the figure of the report's per-image errors, one colour per mapper."""
    output, report, figures = compared_all
    [(figure, path)] = figures
    assert path.name == "errors.png"  # drawn beside CMP, then moved in with the report
    assert_figure_shows(figure, report["mappers"])
    with Image.open(output / "errors.png") as image:
        assert image.size == FIGURE_SIZE
        pixels = np.asarray(image.convert("RGB")).reshape(-1, 3)
    for colour in MAPPER_COLOURS:  # each mapper's lines and markers are on the image
        assert np.count_nonzero((pixels == colour).all(axis=1)) > MIN_PIXELS_PER_MAPPER, colour


def test_failing_mapper_is_reported_and_the_others_still_run(synthetic, tmp_path, monkeypatch,
                                                              record_figures, assert_figure_shows):
    """A mapper that raises gets a failed row and no model (an earlier one is removed);
    the others run, are compared and plotted without it."""
    folder, scene = synthetic

    def explode(*args, **kwargs):
        raise RuntimeError("solver exploded\nsecond line of the message")

    monkeypatch.setattr(pycolmap, "incremental_mapping", explode)  # COLMAP's mapper fails
    output = tmp_path / "CMP"
    (output / "colmap_incremental" / "0").mkdir(parents=True)  # from an earlier comparison
    pycolmap.Reconstruction().write(output / "colmap_incremental" / "0")
    with record_figures() as figures:
        report = compare(folder / "database.db", folder / "images", output,
                         ground_truth=folder / "gt", seed=0, progress=False, overwrite=True)
    failed = report["mappers"]["colmap_incremental"]
    assert failed["error"] == "RuntimeError: solver exploded"
    assert (failed["num_registered"], failed["num_models"], failed["num_points3D"]) == (0, 0, 0)
    assert failed["models"] == [] and "R_err_max_deg" not in failed
    assert not (output / "colmap_incremental" / "0").exists()
    for name in ("ours", "colmap_global"):
        assert report["mappers"][name]["num_registered"] == scene.num_images
    assert set(report["model_comparison"]["mappers"]) == {"colmap_global"}

    markdown = (output / "report.md").read_text()
    row = next(line for line in markdown.splitlines() if line.startswith("| colmap_incremental "))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[:6] == ["colmap_incremental", "failed: RuntimeError: solver exploded", "0", "0",
                         "–", "–"]
    assert cells[7:] == ["–"] * 5  # no pose errors, no AUC
    assert "time / COLMAP incremental" not in markdown  # no ratio to a failed mapper's time
    [(figure, _)] = figures
    assert_figure_shows(figure, {name: report["mappers"][name] for name in ("ours", "colmap_global")})
