"""Setting up a camera rig: Kalibr's camchain YAML to COLMAP's rig configuration, and the
configuration applied to a database (`colmap-ext rig_config_from_kalibr`, `reconstruct
--rig_config`).

COLMAP's rig configuration (`colmap rig_configurator`, `pycolmap.read_rig_config`) is a JSON
list of rigs, each a list of cameras: `image_prefix`, then either `ref_sensor: true` (the
camera whose frame is the rig's) or `cam_from_rig_rotation` [w, x, y, z] and
`cam_from_rig_translation`, and optionally `camera_model_name` and `camera_params`. A frame
is the set of images with the same name under each camera's prefix (`cam0/0001.jpg`,
`cam1/0001.jpg`, ...).

Kalibr's camchain files give per camera `camera_model`, `intrinsics` [fu, fv, pu, pv],
`distortion_model` and `distortion_coeffs`, `resolution`, and its place: `T_cam_imu` (IMU
frame to camera frame, in camchain-imucam files) or `T_cn_cnm1` (previous camera to this
one). Several files describe one rig through the IMU they share, so each then needs
`T_cam_imu`; a file without it is one chain from its first camera. COLMAP needs a camera as
the rig's reference, so the rig frame written is the first camera's.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import yaml

from colmap_ext.errors import UserError
from colmap_ext.model_io import write_json

# Kalibr distortion model (with camera_model pinhole) -> COLMAP camera model; the COLMAP
# parameters are the intrinsics followed by the distortion coefficients in Kalibr's order.
KALIBR_DISTORTION_MODELS = {
    "none": ("PINHOLE", 0),
    "radtan": ("OPENCV", 4),  # k1, k2, p1, p2
    "equidistant": ("OPENCV_FISHEYE", 4),  # Kannala-Brandt k1..k4
}

# A pose read from text is a rotation to about 1e-9; far beyond that it is not one.
_ROTATION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig: its COLMAP model and params, and where it sits on the rig."""

    name: str  # "<file>:<camera>", for messages
    model: str
    params: list[float]
    cam_from_rig: pycolmap.Rigid3d


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Define the options of `colmap-ext rig_config_from_kalibr`."""
    parser.add_argument("--camchain", nargs="+", required=True,
                        help="Kalibr camchain YAML files of one rig (several: linked by "
                             "their T_cam_imu, i.e. camchain-imucam files)")
    parser.add_argument("--image_prefix", nargs="+", default=None,
                        help="each camera's image prefix, in file and camera order "
                             "(default: cam0/, cam1/, ...)")
    parser.add_argument("--output_path", required=True,
                        help="the rig configuration JSON to write (COLMAP's format)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing file at --output_path")


def main(camchain: list[str], output_path: str, image_prefix: list[str] | None = None,
         overwrite: bool = False) -> list[dict]:
    """Write the rig configuration of the Kalibr files `camchain` to `output_path` (in one
    step: a temporary file renamed into place); an existing file only with `overwrite`."""
    if Path(output_path).is_dir() or (Path(output_path).exists() and not overwrite):
        raise UserError(f"{output_path} exists; pass --overwrite to replace it"
                        if not Path(output_path).is_dir() else
                        f"output path is a folder, not a file: {output_path}")
    cameras = read_kalibr_rig([Path(path) for path in camchain])
    prefixes = image_prefix or [f"cam{index}/" for index in range(len(cameras))]
    config = rig_config(cameras, prefixes)
    write_json(config, output_path)
    print(f"Rig configuration of {len(cameras)} cameras: {output_path}")
    return config


def read_kalibr_rig(paths: list[Path]) -> list[RigCamera]:
    """The cameras of the Kalibr camchain files `paths`, in file and camera order, with
    `cam_from_rig` in the first camera's frame."""
    if not paths:
        raise UserError("no camchain file given")
    cameras: list[tuple[str, str, list[float], pycolmap.Rigid3d]] = []
    for path in paths:
        entries = _read_yaml(path)
        has_imu = [("T_cam_imu" in entry) for entry in entries.values()]
        if len(paths) > 1 and not all(has_imu):
            raise UserError(f"{path}: every camera needs T_cam_imu when several camchain "
                            "files describe one rig (they are linked through the IMU)")
        if any(has_imu) and not all(has_imu):
            raise UserError(f"{path}: T_cam_imu on some cameras only")
        previous: pycolmap.Rigid3d | None = None
        for camera_name, entry in entries.items():
            name = f"{path}:{camera_name}"
            model, params = _colmap_camera(name, entry)
            if all(has_imu):
                cam_from_base = _rigid(name, "T_cam_imu", entry["T_cam_imu"])
            elif previous is None:
                cam_from_base = pycolmap.Rigid3d()
            elif "T_cn_cnm1" in entry:
                cam_from_base = _rigid(name, "T_cn_cnm1", entry["T_cn_cnm1"]) * previous
            else:
                raise UserError(f"{name}: neither T_cam_imu nor T_cn_cnm1 places it on the rig")
            cameras.append((name, model, params, cam_from_base))
            previous = cam_from_base
    base_from_ref = cameras[0][3].inverse()
    return [RigCamera(name, model, params, cam_from_base * base_from_ref)
            for name, model, params, cam_from_base in cameras]


def _read_yaml(path: Path) -> dict[str, dict]:
    """The camera entries (cam0, cam1, ...) of one camchain file, in file order."""
    try:
        content = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(content, dict) or not content or not all(
            isinstance(entry, dict) for entry in content.values()):
        raise UserError(f"{path}: not a Kalibr camchain file (expected cam0:, cam1:, ...)")
    return content


def _colmap_camera(name: str, entry: dict) -> tuple[str, list[float]]:
    """The COLMAP model and params of one Kalibr camera entry."""
    if entry.get("camera_model") != "pinhole":
        raise UserError(f"{name}: camera_model {entry.get('camera_model')!r} is not supported "
                        "(only pinhole)")
    distortion = entry.get("distortion_model", "none")
    if distortion not in KALIBR_DISTORTION_MODELS:
        raise UserError(f"{name}: distortion_model {distortion!r} is not supported; "
                        f"expected one of {', '.join(KALIBR_DISTORTION_MODELS)}")
    model, num_coefficients = KALIBR_DISTORTION_MODELS[distortion]
    intrinsics = list(entry.get("intrinsics") or [])
    coefficients = list(entry.get("distortion_coeffs") or [])[:num_coefficients] \
        if num_coefficients else []
    if len(intrinsics) != 4 or len(coefficients) != num_coefficients:
        raise UserError(f"{name}: expected 4 intrinsics and {num_coefficients} distortion "
                        f"coefficients ({distortion}), got {len(intrinsics)} and "
                        f"{len(entry.get('distortion_coeffs') or [])}")
    return model, [float(value) for value in intrinsics + coefficients]


def _rigid(name: str, key: str, matrix: list) -> pycolmap.Rigid3d:
    """A Kalibr 4x4 transform as a Rigid3d (it maps the second frame into the first)."""
    try:
        transform = np.array(matrix, dtype=float)
    except (TypeError, ValueError):
        transform = np.zeros(0)
    if transform.shape != (4, 4) or not np.allclose(transform[3], [0, 0, 0, 1]):
        raise UserError(f"{name}: {key} is not a 4x4 rigid transform")
    rotation = transform[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=_ROTATION_TOLERANCE) or \
            np.linalg.det(rotation) < 0:
        raise UserError(f"{name}: {key} does not hold a rotation")
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), transform[:3, 3])


def rig_config(cameras: list[RigCamera], image_prefixes: list[str]) -> list[dict]:
    """COLMAP's rig configuration (one rig) of `cameras`, the first as the reference."""
    if len(image_prefixes) != len(cameras):
        raise UserError(f"{len(image_prefixes)} image prefixes for {len(cameras)} cameras")
    if len(set(image_prefixes)) != len(image_prefixes):
        raise UserError("the image prefixes must differ")
    entries = []
    for index, (camera, prefix) in enumerate(zip(cameras, image_prefixes)):
        entry: dict = {"image_prefix": prefix}
        if index == 0:
            entry["ref_sensor"] = True
        else:
            x, y, z, w = camera.cam_from_rig.rotation.quat
            entry["cam_from_rig_rotation"] = [float(w), float(x), float(y), float(z)]
            entry["cam_from_rig_translation"] = [float(v) for v in camera.cam_from_rig.translation]
        entry["camera_model_name"] = camera.model
        entry["camera_params"] = camera.params
        entries.append(entry)
    return [{"cameras": entries}]


def read_rig_config(path: str | os.PathLike) -> list[pycolmap.RigConfig]:
    """COLMAP's rig configuration at `path`, as pycolmap reads it; a UserError if it cannot."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"rig configuration not found: {path}")
    try:
        return pycolmap.read_rig_config(str(path))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with COLMAP's check
        message = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"{path}: not a COLMAP rig configuration ({message})") from None


def check_rig_images(configs: list[pycolmap.RigConfig], names: list[str]) -> None:
    """Every image under exactly one camera's prefix, and every camera with images: what
    `apply_rig_config` needs to make one camera per prefix."""
    prefixes = [camera.image_prefix for config in configs for camera in config.cameras]
    for name in names:
        owners = [prefix for prefix in prefixes if name.startswith(prefix)]
        if len(owners) != 1:
            raise UserError(f"image {name} is under {len(owners)} of the rig configuration's "
                            f"image prefixes ({', '.join(prefixes)}); it must be under one")
    empty = [prefix for prefix in prefixes if not any(name.startswith(prefix) for name in names)]
    if empty:
        raise UserError(f"no image under the rig configuration's image prefix {empty[0]!r}")


def apply_rig_config(database_path: str | os.PathLike,
                     configs: list[pycolmap.RigConfig]) -> None:
    """Give each rig camera's images a camera of their own, then write the rigs and frames
    (`pycolmap.apply_rig_config`, which also sets each camera's model and params from the
    configuration). COLMAP needs the first step done at extraction (one camera per folder);
    here any prefix works."""
    with pycolmap.Database.open(str(database_path)) as db:
        db.clear_frames()  # they name each image's camera; apply_rig_config rewrites them
        db.clear_rigs()
        images = db.read_all_images()
        claimed: set[int] = set()
        for config in configs:
            for camera in config.cameras:
                group = [image for image in images if image.name.startswith(camera.image_prefix)]
                camera_id = group[0].camera_id
                if camera_id in claimed or any(image.camera_id != camera_id for image in group):
                    camera_id = db.write_camera(db.read_camera(camera_id))
                claimed.add(camera_id)
                for image in group:
                    if image.camera_id != camera_id:
                        image.camera_id = camera_id
                        db.update_image(image)
        pycolmap.apply_rig_config(configs, db)

