"""`colmap-ext mapper` as a drop-in for `colmap mapper` and `pycolmap.incremental_mapping`:
the option table (mapper/flags.py) against COLMAP's options, project files, bad input, and
real COLMAP 3.8 clients on templeSparseRing (skipped without the `colmap` binary or the data)."""

from __future__ import annotations

import hashlib
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pycolmap
import pytest

from colmap_ext.mapper import cli
from colmap_ext.mapper.flags import FLAGS, BY_NAME, get_field, pycolmap_options, read_project
from colmap_ext.mapper.options import MapperOptions

CLI = [sys.executable, "-m", "colmap_ext", "mapper"]
TEMPLE_CAMERA = "1520.4,1525.9,302.32,246.87"
# pycolmap fields without an option of their own: arguments of the call (image_path,
# image_names), sets with no command-line form (intrinsics are constant here anyway), and
# sub-option fields COLMAP copies from the pipeline's.
NOT_OPTIONS = {"image_path", "image_names", "constant_rigs", "constant_cameras"}


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
    # pycolmap refines intrinsics by default: not applied, and said
    assert not ours.bundle_adjustment.refines_intrinsics
    named = sorted(re.search(r"--(\S+)", r.getMessage()).group(1) for r in caplog.records)
    assert named == ["Mapper.abs_pose_refine_extra_params", "Mapper.abs_pose_refine_focal_length",
                     "Mapper.ba_refine_extra_params", "Mapper.ba_refine_focal_length"]


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
    assert result.returncode != 0
    assert "unrecognized arguments: --Mapper.no_such_option 1" in result.stderr
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
           "--ImageReader.camera_params", TEMPLE_CAMERA, "--SiftExtraction.use_gpu", "0")
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
    assert check_model(output, result.stdout, tmp_path) == 16  # measured: 16/16


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
    assert check_model(tmp_path / "sparse", result.stdout, tmp_path) == 16
    # ba_refine_focal_length=true there: named, with the reason, once
    assert result.stderr.count("--Mapper.ba_refine_focal_length 1: not applicable") == 1


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
