"""`colmap-ext mapper` as a drop-in for `colmap mapper` and `pycolmap.incremental_mapping`:
the option table (mapper/flags.py) against COLMAP's options, project files, bad input, and
real COLMAP 3.8 clients on templeSparseRing (skipped without the `colmap` binary or the data)."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext.mapper import cli
from colmap_ext.errors import UserError
from colmap_ext.mapper.flags import (FLAGS, BY_NAME, PATH_ALIASES, get_field, mapper_options,
                                     pycolmap_options, read_project)
from colmap_ext.evaluate import evaluate
from colmap_ext.ground_truth import GroundTruth, read_ground_truth
from colmap_ext.mapper.options import MapperOptions, OptionError

CLI = [sys.executable, "-m", "colmap_ext", "mapper"]
TEMPLE_CAMERA = "1520.4,1525.9,302.32,246.87"
# pycolmap fields without an option of their own: arguments of the call (image_path,
# image_names), sets that COLMAP 4's command line reads from list files
# (Mapper.constant_rig_list_path, Mapper.constant_camera_list_path), and sub-option fields
# COLMAP copies from the pipeline's.
NOT_OPTIONS = {"image_path", "image_names", "constant_rigs", "constant_cameras"}


# COLMAP 4's `Mapper.*` options: OptionManager::AddMapperOptions in
# src/colmap/controllers/option_manager.cc (69 there), and the two bundle-adjustment
# backends COLMAP 4.1 added (IncrementalPipelineOptions.ba_local_backend, ba_global_backend).
COLMAP4_MAPPER_OPTIONS = [f"Mapper.{name}" for name in """
    min_num_matches ignore_watermarks multiple_models max_num_models max_model_overlap
    min_model_size init_image_id1 init_image_id2 init_num_trials
    structure_less_registration_fallback structure_less_registration_only extract_colors
    num_threads random_seed min_focal_length_ratio max_focal_length_ratio max_extra_param
    ba_refine_focal_length ba_refine_principal_point ba_refine_extra_params
    ba_refine_sensor_from_rig ba_local_function_tolerance ba_local_max_num_iterations
    ba_global_frames_ratio ba_global_points_ratio ba_global_frames_freq ba_global_points_freq
    ba_global_function_tolerance ba_global_max_num_iterations ba_global_max_refinements
    ba_global_max_refinement_change ba_local_max_refinements ba_local_max_refinement_change
    ba_use_gpu ba_gpu_index ba_min_num_residuals_for_cpu_multi_threading snapshot_path
    snapshot_frames_freq fix_existing_frames init_min_num_inliers init_max_error
    init_max_forward_motion init_min_tri_angle init_max_reg_trials abs_pose_max_error
    abs_pose_min_num_inliers abs_pose_min_inlier_ratio filter_max_reproj_error
    filter_min_tri_angle max_reg_trials ba_local_num_images ba_local_min_tri_angle
    ba_global_ignore_redundant_points3D ba_global_ignore_redundant_points3D_min_coverage_gain
    image_list_path constant_rig_list_path constant_camera_list_path max_runtime_seconds
    tri_max_transitivity tri_create_max_angle_error tri_continue_max_angle_error
    tri_merge_max_reproj_error tri_complete_max_reproj_error tri_complete_max_transitivity
    tri_re_max_angle_error tri_re_min_ratio tri_re_max_trials tri_min_angle
    tri_ignore_two_view_tracks ba_local_backend ba_global_backend""".split()]


def pycolmap_fields() -> list[str]:
    options = pycolmap.IncrementalPipelineOptions()
    top = [k for k in options.todict() if k not in ("mapper", "triangulation")]
    subs = [f"{name}.{k}" for name in ("mapper", "triangulation")
            for k in getattr(options, name).todict() if k not in top]
    return [k for k in top + subs if k not in NOT_OPTIONS]


def test_table_covers_every_pycolmap_option():
    covered = [flag.pycolmap for flag in FLAGS if flag.pycolmap]
    assert sorted(set(pycolmap_fields()) - set(covered)) == []
    assert len(covered) == len(set(covered))
    assert len(BY_NAME) == sum(len(flag.names) for flag in FLAGS), "a name used twice"
    defaults = MapperOptions()
    for flag in FLAGS:
        assert flag.help, flag.name
        if flag.field is not None:
            get_field(defaults, flag.field)  # an AttributeError names a field that is not there


def test_table_covers_colmap4s_mapper_options():
    """Every `Mapper.*` option of COLMAP 4 is accepted on the command line, as a COLMAP 4
    user types it (`--Mapper.random_seed 0`), and in a project file's [Mapper] section."""
    assert len(COLMAP4_MAPPER_OPTIONS) == len(set(COLMAP4_MAPPER_OPTIONS)) == 71
    assert sorted(set(COLMAP4_MAPPER_OPTIONS) - set(BY_NAME) - set(PATH_ALIASES)) == []
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    for name in COLMAP4_MAPPER_OPTIONS:
        parser.parse_args([f"--{name}", "1"])  # argparse exits on an unknown flag


def test_colmap4_names_of_our_options(tmp_path):
    assert mapper_options({"Mapper.random_seed": 0}).seed == 0
    project = tmp_path / "project.ini"
    project.write_text("[Mapper]\nimage_list_path=images.txt\nrandom_seed=3\n")
    values, paths = read_project(project)
    assert values == {"Mapper.random_seed": 3} and paths == {"image_list_path": "images.txt"}
    cameras = tmp_path / "cameras.txt"
    cameras.write_text("1\n\n3\n")
    options = mapper_options({"Mapper.constant_camera_list_path": str(cameras)})
    assert options.bundle_adjustment.constant_camera_ids == (1, 3)
    cameras.write_text("1\nfront\n")
    with pytest.raises(UserError, match="expected one camera id per line"):
        mapper_options({"Mapper.constant_camera_list_path": str(cameras)})
    with pytest.raises(UserError, match="cannot read camera list"):
        mapper_options({"Mapper.constant_camera_list_path": str(tmp_path / "missing.txt")})
    rigs = tmp_path / "rigs.txt"
    rigs.write_text("2\n")
    options = mapper_options({"Mapper.constant_rig_list_path": str(rigs),
                              "Mapper.ba_refine_sensor_from_rig": True})
    assert options.bundle_adjustment.constant_rig_ids == (2,)
    assert options.bundle_adjustment.refine_sensor_from_rig
    rigs.write_text("front\n")
    with pytest.raises(UserError, match="expected one rig id per line"):
        mapper_options({"Mapper.constant_rig_list_path": str(rigs)})


def test_pycolmap_options_set_our_fields_and_name_what_does_not_apply(caplog):
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 4
    options.multiple_models = False
    options.random_seed = 7
    options.mapper.abs_pose_max_error = 5.5
    options.ba_global_frames_ratio = 1.3
    options.triangulation.min_angle = 3.0
    with caplog.at_level(logging.WARNING):
        ours = pycolmap_options(options)
    assert (ours.min_model_size, ours.multiple_models, ours.seed) == (4, False, 7)
    assert ours.registration.abs_pose_max_error_px == 5.5
    assert ours.bundle_adjustment.global_images_ratio == 1.3
    assert ours.triangulation.min_tri_angle_deg == 3.0
    # pycolmap's -1 iterations: the solver's default, ours
    assert ours.bundle_adjustment.local_max_iterations == \
        MapperOptions().bundle_adjustment.local_max_iterations
    # pycolmap refines intrinsics and rigs by default: not applied, and said
    assert not ours.bundle_adjustment.refines_intrinsics
    assert not ours.bundle_adjustment.refine_sensor_from_rig
    named = sorted(re.search(r"--(\S+)", r.getMessage()).group(1) for r in caplog.records)
    assert named == ["Mapper.abs_pose_refine_extra_params", "Mapper.abs_pose_refine_focal_length",
                     "Mapper.ba_refine_extra_params", "Mapper.ba_refine_focal_length",
                     "Mapper.ba_refine_sensor_from_rig"]


PROJECT = """\
log_to_stderr=false
random_seed=3
database_path=/data/db.db
image_path=
[ImageReader]
camera_model=PINHOLE
[Mapper]
min_model_size=5
ba_global_images_ratio=1.2
ba_refine_focal_length=false
init_min_tri_angle=8
[PatchMatchStereo]
max_image_size=-1
"""


def test_project_file_values_and_command_line_wins(tmp_path, monkeypatch):
    project = tmp_path / "project.ini"
    project.write_text(PROJECT)
    values, paths = read_project(project)
    assert paths == {"database_path": "/data/db.db"}  # empty values are unset
    assert values == {"random_seed": 3, "log_to_stderr": False, "Mapper.min_model_size": 5,
                      "Mapper.ba_global_images_ratio": 1.2,
                      "Mapper.ba_refine_focal_length": False, "Mapper.init_min_tri_angle": 8.0}
    seen = {}

    def fake_run(database_path, image_path, output_path, options, **kwargs):
        seen.update(database=database_path, options=options)
        raise KeyboardInterrupt  # stop before the summary is read

    monkeypatch.setattr(cli, "run", fake_run)
    with pytest.raises(KeyboardInterrupt):
        cli.main(image_path="images", output_path="out", project_path=str(project),
                 seed=1, **{"Mapper.min_model_size": 7, "Mapper.init_min_tri_angle": None})
    options = seen["options"]
    assert seen["database"] == "/data/db.db"
    assert (options.seed, options.min_model_size) == (1, 7)  # given: they win
    assert options.initialization.min_tri_angle_deg == 8.0
    assert options.bundle_adjustment.global_images_ratio == 1.2


def run_cli(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("body, message", [
    ("[Mapper]\nmin_model_size=5\nfoo_bar=1\n", "line 3: unrecognised option 'Mapper.foo_bar'"),
    ("unknown_top=1\n", "line 1: unrecognised option 'unknown_top'"),
    ("[Mapper]\nmin_model_size=ten\n", "line 2: invalid value 'ten' for option "
                                       "'Mapper.min_model_size'"),
    ("[Mapper]\nmultiple_models=maybe\n", "line 2: invalid value 'maybe' for option "
                                          "'Mapper.multiple_models'"),
])
def test_bad_project_file_is_one_line_and_writes_nothing(tmp_path, body, message):
    project = tmp_path / "project.ini"
    project.write_text(body)
    result = run_cli("--project_path", project, "--database_path", tmp_path / "db.db",
                     "--image_path", tmp_path, "--output_path", tmp_path / "out")
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [f"colmap-ext: error: {project}, {message}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["project.ini"]


def test_unknown_flag_is_refused_and_help_lists_every_option_with_its_default(tmp_path):
    result = run_cli("--database_path", "db", "--image_path", ".", "--output_path",
                     tmp_path / "out", "--Mapper.no_such_option", "1")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "colmap-ext mapper: error: unrecognized arguments: --Mapper.no_such_option 1 "
        "(see 'colmap-ext mapper -h')"]
    assert not (tmp_path / "out").exists()
    help_text = " ".join(run_cli("-h").stdout.split())
    for flag in FLAGS:
        for name in flag.names:
            assert f"--{name} VALUE" in help_text, name
    assert help_text.count("(default: ") == len(FLAGS)


# ---------------------------------------------------------------- COLMAP 3.8 as the client


def colmap(*args: str | Path) -> str:
    result = subprocess.run(["colmap", *map(str, args)], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout + result.stderr


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def colmap_database(real_data, tmp_path_factory) -> tuple[Path, Path]:
    """templeSparseRing's database as COLMAP 3.8's extractor and exhaustive matcher write it."""
    if shutil.which("colmap") is None:
        pytest.skip("the `colmap` binary is not installed (`make test` installs Debian's "
                    "colmap): the real-client tests are skipped")
    images = real_data / "templeSparseRing"
    database = tmp_path_factory.mktemp("colmap38") / "database.db"
    colmap("feature_extractor", "--database_path", database, "--image_path", images,
           "--ImageReader.camera_model", "PINHOLE", "--ImageReader.single_camera", "1",
           "--ImageReader.camera_params", TEMPLE_CAMERA, "--SiftExtraction.use_gpu", "0",
           # One thread: image ids in name order (threads number them as they finish).
           "--SiftExtraction.num_threads", "1")
    colmap("exhaustive_matcher", "--database_path", database, "--SiftMatching.use_gpu", "0")
    return database, images


def colmap_mapper_defaults() -> list[str]:
    """Every flag of `colmap mapper -h` that has a default, at it; refinement flags 0."""
    text = subprocess.run(["colmap", "mapper", "-h"], capture_output=True, text=True).stdout
    args = []
    for name, default in re.findall(r"^\s+--(\S+) arg \(=([^)]*)\)", text, re.M):
        args += [f"--{name}", "0" if name.startswith("Mapper.ba_refine_") else default]
    assert len(args) > 2 * 60, text
    return args


def check_model(output: Path, summary_line: str, tmp_path: Path) -> int:
    """COLMAP 3.8's tools read OUTPUT/0 and count the registered images we reported."""
    registered = int(re.search(r"Registered (\d+) images", summary_line).group(1))
    analysis = colmap("model_analyzer", "--path", output / "0")
    assert f"Registered images: {registered}" in analysis, analysis
    (tmp_path / "txt").mkdir()
    colmap("model_converter", "--input_path", output / "0", "--output_path", tmp_path / "txt",
           "--output_type", "TXT")
    assert f"Number of images: {registered}," in (tmp_path / "txt" / "images.txt").read_text()
    return registered


@pytest.fixture(scope="module")
def cli_run(colmap_database, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    database, images = colmap_database
    output = tmp_path_factory.mktemp("cli") / "sparse"
    before = sha256(database)
    result = run_cli("--database_path", database, "--image_path", images, "--output_path",
                     output, *colmap_mapper_defaults())
    assert result.returncode == 0, result.stderr
    assert sha256(database) == before, "the user's database was written"
    return output, result


def test_colmap_client_every_flag_at_its_default(cli_run, tmp_path):
    output, result = cli_run
    # Measured on 60 COLMAP 3.8 databases: 16/16 on each (57 of 60 before
    # registration.pose_max_error_px: an image posed 26 deg off kept two others out)
    assert check_model(output, result.stdout, tmp_path) == 16


def test_colmap_client_project_file(colmap_database, tmp_path):
    """The .ini `colmap project_generator` writes, paths filled in as a user does; its
    other sections configure other commands. (COLMAP 3.8's own mapper refuses this file.)"""
    database, images = colmap_database
    project = tmp_path / "project.ini"
    colmap("project_generator", "--output_path", project)
    text = project.read_text()
    text = text.replace("database_path=\n", f"database_path={database}\n", 1)
    project.write_text(text.replace("image_path=\n", f"image_path={images}\n", 1))
    before = sha256(database)
    result = run_cli("--project_path", project, "--output_path", tmp_path / "sparse")
    assert result.returncode == 0, result.stderr
    assert sha256(database) == before
    # 16/16 on most COLMAP 3.8 databases (whose RANSAC draws differ on every run, one
    # matching thread too), with the intrinsics refined as the file asks: 60 of 60
    # measured since registration.pose_max_error_px (12 of 15 before it, two 13)
    assert check_model(tmp_path / "sparse", result.stdout, tmp_path) >= 13
    # ba_refine_focal_length=true and ba_refine_extra_params=true there, as COLMAP's
    # defaults: applied, as a user who asks for them, and said once
    assert result.stderr.count("refining the focal length and extra params in global "
                               "bundle adjustment, as asked") == 1


def test_pycolmap_options_give_the_cli_model(colmap_database, cli_run, tmp_path):
    """pycolmap's options at the values the CLI test passes (COLMAP's defaults, no
    refinement, seed 0): the same model, byte for byte."""
    from colmap_ext import incremental_mapping

    database, images = colmap_database
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.random_seed = 0
    reconstructions = incremental_mapping(database, images, tmp_path, options)
    assert sorted(reconstructions) == [0]
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (tmp_path / "0" / name).read_bytes() == (cli_run[0] / "0" / name).read_bytes()


def test_colmap_client_continues_a_model(colmap_database, cli_run, real_data, tmp_path):
    """Six images with --image_list_path, the rest through --input_path: one model of all
    16, within 0.05 deg of the single run, the input model's files unchanged. The six are
    neighbouring views of the lower ring (templeSR_ang.txt: images 6-11 at longitudes 65 to
    180 deg), which map as one model; images 1-8 fall apart into two models of 3 (gaps of
    54 and 122 deg between 2 and 3 and 5 and 6). Measured on 60 COLMAP 3.8 databases
    (COLMAP matches differently on each run): 16/16 on 59 (R_err max 0.183-0.190 deg on 8
    measured earlier). On the 60th, image 4 registers 24 deg off through 18 verified matches
    whose only registered image is 5 (a pose their epipolar lines cannot tell from the
    true one), keeps 3 and 14 out, and goes at the end: 13 images, R_err max 0.22 deg, a
    product gap. With images 1 and 2 added to the six, one of 8 left images 3, 4 and 14
    out (docs/experiments/continued-models.md)."""
    database, images = colmap_database
    names = sorted(p.name for p in images.glob("*.png"))
    half_ring = [names[k - 1] for k in (6, 7, 8, 9, 10, 11)]
    (tmp_path / "half.txt").write_text("\n".join(half_ring) + "\n")
    half, full = tmp_path / "half", tmp_path / "full"
    result = run_cli("--database_path", database, "--image_path", images, "--output_path", half,
                     "--image_list_path", tmp_path / "half.txt", "--seed", "0")
    assert result.returncode == 0, result.stderr
    assert pycolmap.Reconstruction(half / "0").num_reg_images() == 6
    before = folder_digest(half / "0")
    result = run_cli("--database_path", database, "--image_path", images, "--output_path", full,
                     "--input_path", half / "0", "--seed", "0")
    assert result.returncode == 0, result.stderr
    assert folder_digest(half / "0") == before, "the input model was written"
    assert check_model(full, result.stdout, tmp_path) >= 13
    truth = read_ground_truth(next((real_data / "templeSparseRing").glob("*_par.txt")))
    continued = evaluate(pycolmap.Reconstruction(full / "0"), truth)["R_err_max_deg"]
    single = evaluate(pycolmap.Reconstruction(cli_run[0] / "0"), truth)["R_err_max_deg"]
    assert continued < single + 0.05, (continued, single)


# ---------------------------------------------------------------- continuing a model


def folder_digest(folder: Path) -> dict[str, str]:
    return {p.name: sha256(p) for p in sorted(folder.iterdir())}


def map_ring(folder: Path, output: Path, *args: str | Path) -> subprocess.CompletedProcess:
    result = run_cli("--database_path", folder / "database.db", "--image_path",
                     folder / "images", "--output_path", output, "--seed", "0", *args)
    assert result.returncode == 0, result.stderr
    return result


@pytest.fixture(scope="module")
def half_ring(synthetic_ring, tmp_path_factory) -> Path:
    """The first 6 images of the ring mapped alone: the model to continue."""
    folder, scene = synthetic_ring
    root = tmp_path_factory.mktemp("half_ring")
    (root / "half.txt").write_text("\n".join(scene.image_names[:6]) + "\n")
    map_ring(folder, root / "sparse", "--image_list_path", root / "half.txt")
    assert pycolmap.Reconstruction(root / "sparse" / "0").num_reg_images() == 6
    return root / "sparse" / "0"


def ring_errors(model: Path, scene) -> dict:
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    return evaluate(pycolmap.Reconstruction(model), truth)


@pytest.mark.parametrize("fix", [False, True])
def test_input_path_registers_the_other_images_into_the_model(synthetic_ring, half_ring,
                                                              tmp_path, fix):
    """The rest of the ring joins the given model (BIN, or TXT as model_converter writes
    it): all 12 images in one model, as accurate as a single run; with
    fix_existing_images, the given poses are kept (to rounding: pycolmap's adjustment
    normalises every frame's quaternion, constant ones too, measured 3e-16). The input
    model and the database are not written."""
    folder, scene = synthetic_ring
    given_model = half_ring
    if fix:  # the same model as TXT
        given_model = tmp_path / "half_txt"
        given_model.mkdir()
        pycolmap.Reconstruction(half_ring).write_text(given_model)
    before = folder_digest(given_model), sha256(folder / "database.db")
    map_ring(folder, tmp_path / "full", "--input_path", given_model,
             "--Mapper.fix_existing_images", str(int(fix)))
    assert (folder_digest(given_model), sha256(folder / "database.db")) == before
    assert sorted(p.name for p in (tmp_path / "full").iterdir()) == ["0", "mapper_summary.json"]
    continued = ring_errors(tmp_path / "full" / "0", scene)
    assert continued["num_registered"] == 12
    map_ring(folder, tmp_path / "single")
    single = ring_errors(tmp_path / "single" / "0", scene)
    assert continued["R_err_max_deg"] < single["R_err_max_deg"] + 0.05
    given = pycolmap.Reconstruction(given_model)
    result = pycolmap.Reconstruction(tmp_path / "full" / "0")
    by_name = {image.name: image for image in result.images.values()}
    moved = max(np.abs(by_name[image.name].cam_from_world().matrix()
                       - image.cam_from_world().matrix()).max()
                for image in given.images.values())
    if fix:
        assert moved < 1e-12
    else:
        assert 0.0 < moved < 0.05  # refined by the adjustments, not replaced


def _corrupt(model: Path, root: Path) -> Path:
    copy = root / "corrupt"
    shutil.copytree(model, copy)
    data = (copy / "images.bin").read_bytes()
    (copy / "images.bin").write_bytes(data[:len(data) // 2])
    return copy


def _renamed(model: Path, root: Path) -> Path:
    reconstruction = pycolmap.Reconstruction(model)
    image = reconstruction.images[min(reconstruction.reg_image_ids())]
    image.name = "not_in_the_database.png"
    reconstruction.write_text(root)
    return root


def _other_keypoints(model: Path, root: Path) -> Path:
    reconstruction = pycolmap.Reconstruction(model)
    image = reconstruction.images[min(reconstruction.reg_image_ids())]
    image.points2D[int(np.flatnonzero([p.has_point3D() for p in image.points2D])[0])].xy += 5
    reconstruction.write_binary(root)
    return root


@pytest.mark.parametrize("make_input, message", [
    (lambda model, root: root / "missing", "no COLMAP model in {input}: expected cameras, "
                                           "images and points3D (.bin or .txt)"),
    (_corrupt, "cannot read the model in {input}: "),
    (_renamed, "1 images of the input model are not in the database: not_in_the_database.png"),
    (_other_keypoints, "image ring0000.png of the input model has other keypoints than the "
                       "database's: the model was made from another database"),
    (lambda model, root: root.parent / "out" / "0", "--input_path {input} is a model of "
                                                     "--output_path, which the result would "
                                                     "replace"),
], ids=["missing", "corrupt", "not_in_database", "other_database", "inside_output"])
def test_bad_input_model_is_one_line_and_writes_nothing(synthetic_ring, half_ring, tmp_path,
                                                        make_input, message):
    folder, _ = synthetic_ring
    (tmp_path / "input").mkdir()
    input_path = make_input(half_ring, tmp_path / "input")
    if input_path.parent.name == "out":  # the model the output would replace
        shutil.copytree(half_ring, input_path)
    watched = {p: sha256(p) for p in tmp_path.rglob("*") if p.is_file()}
    result = run_cli("--database_path", folder / "database.db", "--image_path",
                     folder / "images", "--output_path", tmp_path / "out", "--input_path",
                     input_path, "--overwrite")
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "colmap-ext: error: " + message.format(input=input_path.resolve()
                                               if "output" in message else input_path)), lines
    assert {p: sha256(p) for p in tmp_path.rglob("*") if p.is_file()} == watched
    if input_path.parent.name != "out":
        assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- options that act


def test_refining_the_focal_length_on_request(synthetic_ring, tmp_path):
    """A database whose focal length is 1.5 % off: held constant by default (the camera is
    written as given), refined towards the truth with --Mapper.ba_refine_focal_length 1."""
    folder, scene = synthetic_ring
    shutil.copytree(folder, tmp_path / "ring")
    true_focal = scene.camera.params[:2]  # OPENCV: fx, fy, cx, cy, k1, k2, p1, p2
    with pycolmap.Database.open(tmp_path / "ring" / "database.db") as db:
        camera = db.read_all_cameras()[0]
        camera.params = [*(true_focal * 1.015), *camera.params[2:]]
        db.update_camera(camera)
    given = camera.params.copy()
    map_ring(tmp_path / "ring", tmp_path / "constant")
    constant = pycolmap.Reconstruction(tmp_path / "constant" / "0").cameras[1]
    assert np.array_equal(constant.params, given)
    result = map_ring(tmp_path / "ring", tmp_path / "refined",
                      "--Mapper.ba_refine_focal_length", "1")
    assert "refining the focal length" in result.stderr
    refined = pycolmap.Reconstruction(tmp_path / "refined" / "0").cameras[1]
    assert np.all(np.abs(refined.params[:2] - true_focal) < 0.1 * np.abs(given[:2] - true_focal))
    assert np.array_equal(refined.params[2:], given[2:])  # only what was asked for
    errors = ring_errors(tmp_path / "refined" / "0", scene)
    assert errors["num_registered"] == 12 and errors["R_err_max_deg"] < 0.2
    # A camera in --Mapper.constant_camera_list_path stays as given (COLMAP 4's option).
    (tmp_path / "constant_cameras.txt").write_text("1\n")
    map_ring(tmp_path / "ring", tmp_path / "listed", "--Mapper.ba_refine_focal_length", "1",
             "--Mapper.constant_camera_list_path", tmp_path / "constant_cameras.txt")
    listed = pycolmap.Reconstruction(tmp_path / "listed" / "0").cameras[1]
    assert np.array_equal(listed.params, given)


def test_snapshots_every_n_registered_images(synthetic_ring, tmp_path):
    folder, _ = synthetic_ring
    map_ring(folder, tmp_path / "out", "--Mapper.snapshot_path", tmp_path / "snapshots",
             "--Mapper.snapshot_frames_freq", "4")
    snapshots = sorted((tmp_path / "snapshots").iterdir())
    assert [pycolmap.Reconstruction(s).num_reg_images() for s in snapshots] == [4, 8, 12]


def test_every_option_of_every_component_is_checked():
    """check() refuses a value out of range for each field that has one, naming the field."""
    options = MapperOptions()
    for component_name, component in options.components().items():
        for field in dataclasses.fields(component):
            value = getattr(component, field.name)
            if isinstance(value, bool):
                continue
            bad = "no such choice" if isinstance(value, str) else -10**6
            broken = copy.deepcopy(options)
            setattr(getattr(broken, component_name), field.name, bad)
            with pytest.raises(OptionError, match=rf"^{type(component).__name__}\.{field.name} "
                                                  r"must be .*, got "):
                broken.check()


def test_option_out_of_range_names_the_flag_given(tmp_path):
    result = run_cli("--database_path", tmp_path / "db.db", "--image_path", tmp_path,
                     "--output_path", tmp_path / "out", "--Mapper.min_num_matches", "2")
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        "colmap-ext: error: --Mapper.min_num_matches 2: TwoViewOptions.min_num_inliers must "
        "be >= 5, got 2"]
    assert not (tmp_path / "out").exists()
