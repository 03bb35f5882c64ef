"""Ground-truth camera poses and intrinsics from the formats the evaluation meets.

Every reader returns a `GroundTruth`: poses as COLMAP's `cam_from_world` (x_cam = R X + t)
keyed by image name, in the set's own order (file order for Middlebury, sorted names
otherwise), because the evaluation measures everything relative to the first image.

- Middlebury `*_par.txt`: first line N, then `name k11..k33 r11..r33 t1 t2 t3`, P = K[R|t].
- Strecha: a folder of `<image name>.camera` files: K (3 rows), a row of zeros, R
  (world-from-camera, 3 rows), the centre C, then `width height`.
- COLMAP: a model folder (`cameras`, `images`, ... as .bin or .txt).

Bad input raises `UserError` with a one-line message naming the file and line.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from colmap_ext.errors import UserError
from colmap_ext.geometry import nearest_rotation
from colmap_ext.model_io import read_model

FORMATS = ("middlebury", "strecha", "colmap")

# Rows of text rotations are orthonormal to ~1e-6; far beyond that the file is not a rotation.
_ROTATION_TOLERANCE = 1e-3
# Poses and intrinsics in any unit stay far below this; beyond it, their squares overflow.
_MAX_MAGNITUDE = 1e12


@dataclass(frozen=True)
class GroundTruth:
    """Poses (cam_from_world, in the set's order) and the intrinsics of each image."""

    poses: dict[str, pycolmap.Rigid3d]
    cameras: dict[str, pycolmap.Camera]


def read_ground_truth(path: str | os.PathLike, format: str | None = None) -> GroundTruth:
    """Read a ground truth, detecting its format from `path` unless `format` names one."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"ground truth not found: {path}")
    if format is None:
        format = detect_format(path)
    if format == "middlebury":
        return read_middlebury(_middlebury_file(path))
    if format == "strecha":
        return read_strecha(path)
    if format == "colmap":
        return read_colmap(path)
    raise UserError(f"unknown ground-truth format {format!r}; expected one of {', '.join(FORMATS)}")


def detect_format(path: Path) -> str:
    """Name the format of an existing `path`: any file is read as Middlebury, folders by content."""
    if path.is_file():
        return "middlebury"
    if any(path.glob("*.camera")):
        return "strecha"
    if (path / "cameras.bin").is_file() or (path / "cameras.txt").is_file():
        return "colmap"
    if len(list(path.glob("*_par.txt"))) == 1:
        return "middlebury"
    raise UserError(
        f"{path}: no ground truth recognised (expected a *_par.txt file, *.camera files "
        "or a COLMAP model with cameras.bin/.txt)"
    )


def _middlebury_file(path: Path) -> Path:
    """The `*_par.txt` file itself, or the only one inside the folder `path`."""
    if path.is_file():
        return path
    candidates = sorted(path.glob("*_par.txt"))
    if len(candidates) != 1:
        raise UserError(f"{path}: expected exactly one *_par.txt file, found {len(candidates)}")
    return candidates[0]


def read_middlebury(path: str | os.PathLike) -> GroundTruth:
    """Read a Middlebury `*_par.txt`; image sizes come from the images beside it, if present."""
    path = Path(path)
    lines = _read_lines(path)
    if not lines:
        raise UserError(f"{path}: empty file; expected the number of images on line 1")
    first_number, first_text = lines[0]
    try:
        count = int(first_text)
    except ValueError:
        raise UserError(
            f"{path}:{first_number}: expected the number of images, got {first_text!r}"
        ) from None
    entries = lines[1:]
    if len(entries) != count:
        raise UserError(f"{path}: line {first_number} announces {count} images, found {len(entries)}")
    poses: dict[str, pycolmap.Rigid3d] = {}
    cameras: dict[str, pycolmap.Camera] = {}
    for number, text in entries:
        name, *fields = text.split()
        values = _parse_numbers(fields, 21, path, number, "name k11..k33 r11..r33 t1 t2 t3")
        if name in poses:
            raise UserError(f"{path}:{number}: image {name!r} appears twice")
        K, R, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:]
        poses[name] = pycolmap.Rigid3d(_rotation(R, path, number), t)
        cameras[name] = _pinhole_camera(K, _image_size(path.parent / name), path, number)
    return GroundTruth(poses, cameras)


def read_strecha(folder: str | os.PathLike) -> GroundTruth:
    """Read every `<image name>.camera` file of a Strecha-style folder."""
    folder = Path(folder)
    files = sorted(folder.glob("*.camera")) if folder.is_dir() else []
    if not files:
        raise UserError(f"{folder}: no *.camera files")
    poses: dict[str, pycolmap.Rigid3d] = {}
    cameras: dict[str, pycolmap.Camera] = {}
    for file in files:
        name = file.name.removesuffix(".camera")
        poses[name], cameras[name] = _read_strecha_camera(file)
    return GroundTruth(poses, cameras)


# What each line of a Strecha .camera file holds, top to bottom: (numbers on it, description).
_STRECHA_LINES = 3 * [(3, "a row of K")] + [(3, "the distortion row, zeros")] + \
    3 * [(3, "a row of R")] + [(3, "the camera centre"), (2, "width height")]


def _read_strecha_camera(path: Path) -> tuple[pycolmap.Rigid3d, pycolmap.Camera]:
    """One Strecha camera: cam_from_world = (R^T, -R^T C) and its pinhole intrinsics."""
    lines = _read_lines(path)
    if len(lines) != len(_STRECHA_LINES):
        raise UserError(f"{path}: expected {len(_STRECHA_LINES)} non-empty lines "
                        f"(K, zeros, R, C, size), found {len(lines)}")
    values = [_parse_numbers(text.split(), count, path, number, what)
              for (number, text), (count, what) in zip(lines, _STRECHA_LINES)]
    numbers = [number for number, _ in lines]
    if np.any(values[3]):
        raise UserError(f"{path}:{numbers[3]}: non-zero distortion is not supported; "
                        "undistort the images first")
    R = _rotation(np.array(values[4:7]), path, numbers[4]).matrix()
    width, height = values[8]
    if width != round(width) or height != round(height) or width <= 0 or height <= 0:
        raise UserError(f"{path}:{numbers[8]}: width and height must be positive integers")
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R.T), -R.T @ values[7])
    camera = _pinhole_camera(np.array(values[0:3]), (int(width), int(height)), path, numbers[0])
    return pose, camera


def read_colmap(folder: str | os.PathLike) -> GroundTruth:
    """Read the posed images of a COLMAP model folder, sorted by name."""
    folder = Path(folder)
    model = read_model(folder)
    images = sorted((image for image in model.images.values() if image.has_pose),
                    key=lambda image: image.name)
    if not images:
        raise UserError(f"{folder}: the COLMAP model has no posed images")
    # Copies: `image.camera` points into `model`, which is freed on return.
    return GroundTruth(
        poses={image.name: copy.copy(image.cam_from_world()) for image in images},
        cameras={image.name: copy.copy(image.camera) for image in images},
    )


def to_reconstruction(ground_truth: GroundTruth) -> pycolmap.Reconstruction:
    """A COLMAP model holding the ground-truth poses and intrinsics, without points.

    Images sharing intrinsics share a camera, as `colmap point_triangulator` and the
    evaluation of a perfect model expect.
    """
    reconstruction = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, (name, pose) in enumerate(ground_truth.poses.items(), start=1):
        camera = ground_truth.cameras[name]
        key = (camera.model_name, camera.width, camera.height, tuple(camera.params))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(
                camera_id=camera_ids[key], model=camera.model_name, width=camera.width,
                height=camera.height, params=camera.params))
        image = pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pose)
    return reconstruction


def _rotation(matrix: np.ndarray, path: Path, line: int) -> pycolmap.Rotation3d:
    """Project a read matrix onto SO(3), refusing one that is no rotation at all."""
    orthonormal = np.abs(matrix.T @ matrix - np.eye(3)).max() < _ROTATION_TOLERANCE
    if not orthonormal or np.linalg.det(matrix) <= 0:
        raise UserError(f"{path}:{line}: the rotation matrix is not a rotation "
                        "(not orthonormal with determinant +1)")
    return pycolmap.Rotation3d(nearest_rotation(matrix))


def _pinhole_camera(K: np.ndarray, size: tuple[int, int], path: Path, line: int) -> pycolmap.Camera:
    """A PINHOLE camera from K, which must be [[fx 0 cx] [0 fy cy] [0 0 1]] (COLMAP has no skew)."""
    pinhole_zeros = K[[0, 1, 2, 2], [1, 0, 0, 1]]
    if np.any(pinhole_zeros) or K[2, 2] != 1 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{path}:{line}: K must be [[fx 0 cx] [0 fy cy] [0 0 1]] with fx, fy > 0")
    width, height = size
    return pycolmap.Camera(model="PINHOLE", width=width, height=height,
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) read from the image header, or (0, 0) when the image is not there."""
    try:
        with Image.open(path) as image:
            return image.size
    except OSError:  # missing, unreadable or not an image
        return 0, 0


def _read_lines(path: Path) -> list[tuple[int, str]]:
    """Non-empty lines of a text file as (1-based line number, stripped text)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read ({exc})") from None
    return [(number, line.strip()) for number, line in enumerate(text.splitlines(), start=1)
            if line.strip()]


def _parse_numbers(fields: list[str], expected: int, path: Path, line: int, what: str) -> np.ndarray:
    """`expected` finite floats from `fields`, or a UserError naming the file and line."""
    if len(fields) != expected:
        raise UserError(f"{path}:{line}: expected {expected} numbers ({what}), found {len(fields)}")
    try:
        values = np.array([float(field) for field in fields])
    except ValueError:
        raise UserError(f"{path}:{line}: not a number in {' '.join(fields)!r} ({what})") from None
    if not np.all(np.isfinite(values)):
        raise UserError(f"{path}:{line}: non-finite number ({what})")
    if np.abs(values).max() > _MAX_MAGNITUDE:
        raise UserError(f"{path}:{line}: a number beyond {_MAX_MAGNITUDE:g} ({what})")
    return values
