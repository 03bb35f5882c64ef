"""Ground-truth readers: known poses through each format, and one-line errors for bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from colmap_ext.errors import UserError
from colmap_ext.geometry import nearest_rotation
from colmap_ext.ground_truth import GroundTruth, read_ground_truth, to_reconstruction

K = np.array([[1520.4, 0.0, 302.32], [0.0, 1525.9, 246.87], [0.0, 0.0, 1.0]])


def rotation(axis_angle: list[float]) -> np.ndarray:
    """Rotation matrix from an axis-angle vector (radians)."""
    return pycolmap.Rotation3d(np.array(axis_angle, dtype=float)).matrix()


# name -> (R, t) of cam_from_world, hand-made.
POSES = {
    "img0.png": (rotation([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])),
    "img1.png": (rotation([0.1, -0.4, 0.05]), np.array([0.3, -0.1, 0.9])),
    "img2.png": (rotation([-0.2, 0.8, 0.3]), np.array([-0.5, 0.2, 1.1])),
}


def middlebury_line(name: str, R: np.ndarray, t: np.ndarray) -> str:
    """One `*_par.txt` line, numbers rounded to 6 decimals as in the real files."""
    return " ".join([name, *(f"{v:.6f}" for v in [*K.ravel(), *R.ravel(), *t])])


def write_middlebury(path: Path, poses: dict = POSES) -> Path:
    lines = [str(len(poses))] + [middlebury_line(name, R, t) for name, (R, t) in poses.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def strecha_text(R_cw: np.ndarray, t: np.ndarray, size: str = "3072 2048") -> str:
    """A Strecha .camera file for cam_from_world (R_cw, t): it stores R = R_cw^T and C = -R_cw^T t."""
    rows = [*K, np.zeros(3), *R_cw.T, -R_cw.T @ t]
    return "\n".join(" ".join(f"{v:.9g}" for v in row) for row in rows) + f"\n{size}\n"


def write_strecha(folder: Path, poses: dict = POSES) -> Path:
    folder.mkdir(exist_ok=True)
    for name, (R, t) in poses.items():
        (folder / f"{name}.camera").write_text(strecha_text(R, t))
    return folder


def assert_poses(ground_truth: GroundTruth, poses: dict, atol: float) -> None:
    assert list(ground_truth.poses) == list(poses)
    for name, (R, t) in poses.items():
        pose = ground_truth.poses[name]
        np.testing.assert_allclose(pose.rotation.matrix(), R, atol=atol)
        np.testing.assert_allclose(pose.translation, t, atol=atol)


def assert_one_line_error(excinfo: pytest.ExceptionInfo, *parts: str) -> None:
    message = str(excinfo.value)
    assert "\n" not in message
    for part in parts:
        assert part in message, message


# --- Middlebury ---------------------------------------------------------------------------


def test_middlebury_known_poses_and_intrinsics(tmp_path: Path) -> None:
    gt = read_ground_truth(write_middlebury(tmp_path / "set_par.txt"))
    assert_poses(gt, POSES, atol=2e-6)
    camera = gt.cameras["img1.png"]
    assert camera.model_name == "PINHOLE"
    np.testing.assert_allclose(camera.params, [1520.4, 1525.9, 302.32, 246.87])
    assert (camera.width, camera.height) == (0, 0)  # no image beside the file


def test_middlebury_rotations_are_projected_onto_so3(tmp_path: Path) -> None:
    gt = read_ground_truth(write_middlebury(tmp_path / "set_par.txt"))
    for pose in gt.poses.values():
        R = pose.rotation.matrix()
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)


def test_middlebury_image_size_from_image_beside_file(tmp_path: Path) -> None:
    Image.new("RGB", (64, 48)).save(tmp_path / "img0.png")
    gt = read_ground_truth(write_middlebury(tmp_path / "set_par.txt"))
    assert (gt.cameras["img0.png"].width, gt.cameras["img0.png"].height) == (64, 48)
    assert gt.cameras["img1.png"].width == 0


def test_middlebury_detected_for_any_text_file_and_folder_with_one_par_file(tmp_path: Path) -> None:
    assert_poses(read_ground_truth(write_middlebury(tmp_path / "poses.txt")), POSES, atol=2e-6)
    folder = tmp_path / "set"
    folder.mkdir()
    write_middlebury(folder / "set_par.txt")
    assert_poses(read_ground_truth(folder), POSES, atol=2e-6)
    assert_poses(read_ground_truth(folder, format="middlebury"), POSES, atol=2e-6)


def test_middlebury_keeps_file_order(tmp_path: Path) -> None:
    reordered = {name: POSES[name] for name in ["img2.png", "img0.png", "img1.png"]}
    gt = read_ground_truth(write_middlebury(tmp_path / "set_par.txt", reordered))
    assert list(gt.poses) == ["img2.png", "img0.png", "img1.png"]


def test_middlebury_tolerates_blank_lines_and_crlf(tmp_path: Path) -> None:
    path = write_middlebury(tmp_path / "set_par.txt")
    path.write_text(path.read_text().replace("\n", "\r\n\r\n"))
    assert_poses(read_ground_truth(path), POSES, atol=2e-6)


GOOD = middlebury_line("a.png", *POSES["img1.png"])
BAD_ROTATION = middlebury_line("a.png", 2 * POSES["img1.png"][0], POSES["img1.png"][1])
MIRROR = middlebury_line("a.png", -POSES["img1.png"][0], POSES["img1.png"][1])
SKEWED = GOOD.replace("a.png 1520.400000 0.000000", "a.png 1520.400000 3.000000")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty file"),
        ("sixteen\n" + GOOD, ":1: expected the number of images"),
        ("2\n" + GOOD, "announces 2 images, found 1"),
        ("1\n" + GOOD + " 7.0", ":2: expected 21 numbers"),
        ("1\n" + GOOD.rsplit(" ", 1)[0], ":2: expected 21 numbers"),
        ("1\n" + GOOD.replace("0.000000", "zero", 1), ":2: not a number"),
        ("1\n" + GOOD.replace("0.000000", "nan", 1), ":2: non-finite"),
        ("1\n" + BAD_ROTATION, ":2: the rotation matrix is not a rotation"),
        ("1\n" + MIRROR, ":2: the rotation matrix is not a rotation"),
        ("1\n" + SKEWED, ":2: K must be"),
        ("2\n" + GOOD + "\n" + GOOD, ":3: image 'a.png' appears twice"),
    ],
)
def test_middlebury_malformed(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "bad_par.txt"
    path.write_text(text)
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(path)
    assert_one_line_error(excinfo, str(path), expected)


def test_middlebury_binary_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "image_par.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(path)
    assert_one_line_error(excinfo, str(path), "cannot read")


# --- Strecha ------------------------------------------------------------------------------


def test_strecha_known_poses_and_intrinsics(tmp_path: Path) -> None:
    gt = read_ground_truth(write_strecha(tmp_path / "fountain"))
    assert_poses(gt, POSES, atol=1e-8)
    camera = gt.cameras["img2.png"]
    assert (camera.model_name, camera.width, camera.height) == ("PINHOLE", 3072, 2048)
    np.testing.assert_allclose(camera.params, [1520.4, 1525.9, 302.32, 246.87])


def test_strecha_centre_is_read_as_world_position(tmp_path: Path) -> None:
    """A camera at C = (1, 2, 3) with axes aligned to the world has t = -C."""
    folder = tmp_path / "set"
    folder.mkdir()
    (folder / "0000.png.camera").write_text(
        "100 0 50\n0 100 40\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 2 3\n100 80\n"
    )
    pose = read_ground_truth(folder, format="strecha").poses["0000.png"]
    np.testing.assert_allclose(pose.translation, [-1, -2, -3])
    np.testing.assert_allclose(pose.inverse().translation, [1, 2, 3])


def test_strecha_sorted_by_name(tmp_path: Path) -> None:
    poses = {name: POSES["img0.png"] for name in ["b.png", "a.png", "c.png"]}
    assert list(read_ground_truth(write_strecha(tmp_path / "set", poses)).poses) == [
        "a.png", "b.png", "c.png"
    ]


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (lambda lines: lines[:-1], "expected 9 non-empty lines"),
        (lambda lines: lines[:4] + ["1 0"] + lines[5:], ":5: expected 3 numbers (a row of R)"),
        (lambda lines: lines[:3] + ["0.1 0 0"] + lines[4:], ":4: non-zero distortion"),
        (lambda lines: lines[:7] + ["1 2 x"] + lines[8:], ":8: not a number"),
        (lambda lines: lines[:8] + ["3072.5 2048"], ":9: width and height"),
        (lambda lines: lines[:4] + ["2 0 0", "0 2 0", "0 0 2"] + lines[7:], ":5: the rotation matrix"),
    ],
)
def test_strecha_malformed(tmp_path: Path, edit, expected: str) -> None:
    folder = write_strecha(tmp_path / "set")
    path = folder / "img1.png.camera"
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(folder)
    assert_one_line_error(excinfo, str(path), expected)


def test_strecha_forced_on_folder_without_camera_files(tmp_path: Path) -> None:
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(tmp_path, format="strecha")
    assert_one_line_error(excinfo, str(tmp_path), "no *.camera files")


# --- COLMAP -------------------------------------------------------------------------------


def ground_truth_from(poses: dict) -> GroundTruth:
    camera = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[1500, 1500, 320, 240])
    return GroundTruth(
        poses={name: pycolmap.Rigid3d(pycolmap.Rotation3d(R), t) for name, (R, t) in poses.items()},
        cameras={name: camera for name in poses},
    )


@pytest.mark.parametrize("write", ["write_binary", "write_text"])
def test_colmap_model_round_trip(tmp_path: Path, write: str) -> None:
    getattr(to_reconstruction(ground_truth_from(POSES)), write)(str(tmp_path))
    gt = read_ground_truth(tmp_path)
    assert_poses(gt, POSES, atol=1e-12)
    assert gt.cameras["img0.png"].width == 640
    assert_poses(read_ground_truth(tmp_path, format="colmap"), POSES, atol=1e-12)


def test_colmap_model_sorted_by_name_and_skips_unposed_images(tmp_path: Path) -> None:
    reconstruction = to_reconstruction(ground_truth_from({n: POSES[n] for n in ["img2.png", "img0.png"]}))
    reconstruction.add_image_with_trivial_frame(pycolmap.Image(name="unposed.png", camera_id=1, image_id=9))
    reconstruction.write(str(tmp_path))
    assert list(read_ground_truth(tmp_path).poses) == ["img0.png", "img2.png"]


def test_colmap_forced_on_folder_without_model(tmp_path: Path) -> None:
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(tmp_path, format="colmap")
    assert_one_line_error(excinfo, str(tmp_path), "not a readable COLMAP model")


def test_to_reconstruction_shares_identical_cameras() -> None:
    reconstruction = to_reconstruction(ground_truth_from(POSES))
    assert reconstruction.num_cameras() == 1
    assert reconstruction.num_reg_images() == 3


# --- detection and missing input ----------------------------------------------------------


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(tmp_path / "nothing_par.txt")
    assert_one_line_error(excinfo, "ground truth not found", "nothing_par.txt")


def test_unrecognised_folder(tmp_path: Path) -> None:
    (tmp_path / "notes.md").write_text("hello")
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(tmp_path)
    assert_one_line_error(excinfo, str(tmp_path), "no ground truth recognised")


def test_unknown_format(tmp_path: Path) -> None:
    path = write_middlebury(tmp_path / "set_par.txt")
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(path, format="bundler")
    assert_one_line_error(excinfo, "unknown ground-truth format 'bundler'")


def test_middlebury_forced_on_folder_with_two_par_files(tmp_path: Path) -> None:
    write_middlebury(tmp_path / "a_par.txt")
    write_middlebury(tmp_path / "b_par.txt")
    with pytest.raises(UserError) as excinfo:
        read_ground_truth(tmp_path, format="middlebury")
    assert_one_line_error(excinfo, "exactly one *_par.txt", "found 2")


# --- SO(3) projection ---------------------------------------------------------------------


@settings(max_examples=50, deadline=None)
@given(
    axis_angle=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    noise=st.lists(st.floats(-1e-6, 1e-6), min_size=9, max_size=9),
)
def test_projection_of_rounded_rotation_is_the_nearby_rotation(axis_angle, noise) -> None:
    R = rotation(axis_angle)
    projected = nearest_rotation(R + np.reshape(noise, (3, 3)))
    np.testing.assert_allclose(projected.T @ projected, np.eye(3), atol=1e-14)
    assert np.linalg.det(projected) == pytest.approx(1.0)
    np.testing.assert_allclose(projected, R, atol=1e-5)
