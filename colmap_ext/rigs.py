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
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import yaml

from colmap_ext.errors import UserError
from colmap_ext.features import check_camera, check_camera_fits
from colmap_ext.geometry import QUATERNION_NORM_TOLERANCE
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
# A rig's cameras are closer than this to each other (in any unit a calibration uses).
MAX_RIG_TRANSLATION = 1e6
# A rig configuration or camchain file is a few kilobytes; a parser's time and memory grow
# with the file (a 16 MB camchain took 40 s and 1.2 GB to read).
MAX_CONFIG_BYTES = 2**20
# COLMAP's rig configuration nests 5 deep: rigs, a rig, its cameras, a camera, a pose.
RIG_CONFIG_NESTING = 5


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
    text = read_bounded_text(path, "camchain file")
    try:
        content = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(content, dict) or not content or not all(
            isinstance(entry, dict) for entry in content.values()):
        raise UserError(f"{path}: not a Kalibr camchain file (expected cam0:, cam1:, ...)")
    return content


def _colmap_camera(name: str, entry: dict) -> tuple[str, list[float]]:
    """The COLMAP model and params of one Kalibr camera entry: the intrinsics (positive
    focal lengths, the principal point inside the resolution) and the distortion
    coefficients, all finite."""
    if entry.get("camera_model") != "pinhole":
        raise UserError(f"{name}: camera_model {entry.get('camera_model')!r} is not supported "
                        "(only pinhole)")
    distortion = entry.get("distortion_model", "none")
    if not isinstance(distortion, str) or distortion not in KALIBR_DISTORTION_MODELS:
        raise UserError(f"{name}: distortion_model {distortion!r} is not supported; "
                        f"expected one of {', '.join(KALIBR_DISTORTION_MODELS)}")
    model, num_coefficients = KALIBR_DISTORTION_MODELS[distortion]
    intrinsics = _numbers(entry.get("intrinsics"), 4, f"{name}: intrinsics [fu, fv, pu, pv]")
    given = entry.get("distortion_coeffs", [])
    coefficients = _numbers(given, len(given) if isinstance(given, list) else -1,
                            f"{name}: distortion_coeffs")
    if len(coefficients) < num_coefficients or any(coefficients[num_coefficients:]):
        raise UserError(f"{name}: distortion_model {distortion} takes {num_coefficients} "
                        f"distortion_coeffs, got {coefficients}"
                        + (" (COLMAP's model would drop the others)"
                           if len(coefficients) > num_coefficients else ""))
    coefficients = coefficients[:num_coefficients]
    try:
        params = check_camera(model, intrinsics + coefficients)
        if "resolution" in entry:
            check_camera_fits(model, params, *_numbers(entry["resolution"], 2,
                                                       f"{name}: resolution"))
    except UserError as exc:
        raise UserError(f"{name}: {exc}") from None
    return model, params


def _rigid(name: str, key: str, matrix: list) -> pycolmap.Rigid3d:
    """A Kalibr 4x4 transform as a Rigid3d (it maps the second frame into the first)."""
    try:
        transform = np.array(matrix, dtype=float)
    except (TypeError, ValueError):
        transform = np.zeros(0)
    if transform.shape != (4, 4) or not np.isfinite(transform).all() or \
            not np.allclose(transform[3], [0, 0, 0, 1]):
        raise UserError(f"{name}: {key} is not a 4x4 rigid transform of finite numbers")
    if np.abs(transform[:3, 3]).max() > MAX_RIG_TRANSLATION:
        raise UserError(f"{name}: {key} moves by more than {MAX_RIG_TRANSLATION:g}")
    rotation = transform[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=_ROTATION_TOLERANCE) or \
            np.linalg.det(rotation) < 0:
        raise UserError(f"{name}: {key} does not hold a rotation")
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), transform[:3, 3])


def rig_config(cameras: list[RigCamera], image_prefixes: list[str]) -> list[dict]:
    """COLMAP's rig configuration (one rig) of `cameras`, the first as the reference."""
    if len(image_prefixes) != len(cameras):
        raise UserError(f"{len(image_prefixes)} image prefixes for {len(cameras)} cameras")
    _check_prefixes(image_prefixes, "--image_prefix")
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
    """COLMAP's rig configuration at `path`, every value checked (`parse_rig_config`); read
    here, not by pycolmap, whose reader takes a wrong value for another (a 3-number rotation
    for the identity, a string for a zero quaternion) and overflows its stack on deep nesting."""
    text = read_bounded_text(Path(path), "rig configuration")
    if (depth := json_nesting_depth(text)) > RIG_CONFIG_NESTING:
        raise UserError(f"{path}: not a COLMAP rig configuration (nested {depth} levels deep; "
                        f"it nests {RIG_CONFIG_NESTING})")
    try:
        content = json.loads(text, parse_constant=_refuse_constant,
                             object_pairs_hook=_refuse_duplicate_keys)
    except ValueError as exc:  # json.JSONDecodeError too
        raise UserError(f"{path}: not JSON ({exc})") from None
    return parse_rig_config(content, str(path))


def read_bounded_text(path: Path, what: str) -> str:
    """The UTF-8 text of a small input file; a UserError if it is missing, larger than
    MAX_CONFIG_BYTES (a parser's time and memory grow with it) or not UTF-8 text."""
    if path.is_dir():
        raise UserError(f"{what} is a folder, not a file: {path}")
    if not path.is_file():
        raise UserError(f"cannot read {what} {path}: no such file")
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise UserError(f"{path}: larger than {MAX_CONFIG_BYTES // 2**20} MiB; a {what} "
                        "is a few kilobytes")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    if "\x00" in text:
        raise UserError(f"{path}: not text (it holds NUL bytes)")
    return text


def json_nesting_depth(text: str) -> int:
    """How deep the arrays and objects of JSON `text` nest (strings skipped), found without
    parsing it."""
    depth = deepest = 0
    for token in re.finditer(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', text):
        bracket = token.group()
        if bracket in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif bracket in "]}":
            depth -= 1
    return deepest


def _refuse_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number COLMAP reads")


def _refuse_duplicate_keys(pairs: list[tuple[str, object]]) -> dict:
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"key {next(k for k in keys if keys.count(k) > 1)!r} given twice")
    return dict(pairs)


def parse_rig_config(content: object, where: str) -> list[pycolmap.RigConfig]:
    """COLMAP's rig configuration from its parsed JSON `content`: a list of rigs, each
    {"cameras": [...]} with one reference camera; each other camera placed by a unit
    quaternion [w, x, y, z] and a translation of 3 numbers; intrinsics, where given, a
    COLMAP model name and its number of finite params (checked against the images by
    `check_rig_images`); image prefixes neither repeated nor one within another."""
    if not isinstance(content, list) or not content:
        raise UserError(f"{where}: not a COLMAP rig configuration (expected a list of rigs, "
                        'each {"cameras": [...]})')
    configs = []
    for index, rig in enumerate(content):
        rig_where = f"{where}: rig {index}"
        if not isinstance(rig, dict) or set(rig) != {"cameras"} or \
                not isinstance(rig["cameras"], list) or not rig["cameras"]:
            raise UserError(f'{rig_where}: expected {{"cameras": [...]}} with one camera or more')
        cameras = [_config_camera(camera, f"{rig_where}, camera {position}")
                   for position, camera in enumerate(rig["cameras"])]
        num_refs = sum(camera.ref_sensor for camera in cameras)
        if num_refs != 1:
            raise UserError(f'{rig_where}: {num_refs} cameras have "ref_sensor": true; a rig '
                            "has one reference camera")
        configs.append(pycolmap.RigConfig(cameras=cameras))
    _check_prefixes([camera.image_prefix for config in configs for camera in config.cameras],
                    where)
    return configs


_CAMERA_KEYS = ("image_prefix", "ref_sensor", "cam_from_rig_rotation",
                "cam_from_rig_translation", "camera_model_name", "camera_params")


def _config_camera(entry: object, where: str) -> pycolmap.RigConfigCamera:
    """One camera of a rig configuration, each value checked."""
    if not isinstance(entry, dict):
        raise UserError(f"{where}: expected an object with {', '.join(_CAMERA_KEYS)}")
    unknown = [key for key in entry if key not in _CAMERA_KEYS]
    if unknown:
        raise UserError(f"{where}: unknown key {unknown[0]!r}; a camera has "
                        f"{', '.join(_CAMERA_KEYS)}")
    prefix = entry.get("image_prefix")
    if not isinstance(prefix, str):
        raise UserError(f"{where}: image_prefix must be a string, got {prefix!r}")
    where = f"{where} ({prefix!r})"
    ref_sensor = entry.get("ref_sensor", False)
    if not isinstance(ref_sensor, bool):
        raise UserError(f"{where}: ref_sensor must be true or false, got {ref_sensor!r}")
    camera = pycolmap.RigConfigCamera(image_prefix=prefix, ref_sensor=ref_sensor)
    posed = [key for key in ("cam_from_rig_rotation", "cam_from_rig_translation") if key in entry]
    if ref_sensor and posed:
        raise UserError(f"{where}: the reference camera's frame is the rig's; it takes no "
                        f"{posed[0]}")
    if not ref_sensor:
        if len(posed) != 2:
            raise UserError(f'{where}: "ref_sensor": false needs cam_from_rig_rotation and '
                            "cam_from_rig_translation (its place on the rig)")
        rotation = np.array(_numbers(entry["cam_from_rig_rotation"], 4,
                                     f"{where}: cam_from_rig_rotation [w, x, y, z]"))
        norm = np.linalg.norm(rotation)
        if abs(norm - 1) > QUATERNION_NORM_TOLERANCE:
            raise UserError(f"{where}: cam_from_rig_rotation {rotation.tolist()} is not a unit "
                            f"quaternion (norm {norm:g})")
        translation = _numbers(entry["cam_from_rig_translation"], 3,
                               f"{where}: cam_from_rig_translation")
        if max(abs(value) for value in translation) > MAX_RIG_TRANSLATION:
            raise UserError(f"{where}: cam_from_rig_translation {translation} is beyond "
                            f"{MAX_RIG_TRANSLATION:g}")
        w, x, y, z = rotation / norm
        camera.cam_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])),
                                               translation)
    given = [key for key in ("camera_model_name", "camera_params") if key in entry]
    if len(given) == 1:
        raise UserError(f"{where}: give camera_model_name and camera_params together")
    if given:
        model = entry["camera_model_name"]
        if not isinstance(model, str):
            raise UserError(f"{where}: camera_model_name must be a string, got {model!r}")
        params = entry["camera_params"]
        _numbers(params, len(params) if isinstance(params, list) else -1,
                 f"{where}: camera_params")
        try:
            params = check_camera(model, params)
        except UserError as exc:
            raise UserError(f"{where}: {exc}") from None
        camera.camera = pycolmap.Camera.create_from_model_name(0, model, 1.0, 0, 0)
        camera.camera.params = params
    return camera


def _numbers(value: object, count: int, what: str) -> list[float]:
    """`value` as `count` finite numbers (JSON or YAML numbers, not strings or booleans)."""
    if not isinstance(value, list) or len(value) != count or not all(
            isinstance(item, (int, float)) and not isinstance(item, bool) for item in value):
        raise UserError(f"{what} must be a list of {count if count >= 0 else 'some'} "
                        f"numbers, got {value!r}")
    if not all(math.isfinite(item) for item in value):
        raise UserError(f"{what} must be finite, got {value!r}")
    return [float(item) for item in value]


def _check_prefixes(prefixes: list[str], where: str) -> None:
    """Each image belongs to one camera: no prefix repeated or the start of another (the
    empty prefix, which holds every image, only for a rig of one camera)."""
    for index, prefix in enumerate(prefixes):
        for other in prefixes[index + 1:]:
            if other.startswith(prefix) or prefix.startswith(other):
                same = "is given twice" if other == prefix else f"and {other!r} overlap"
                raise UserError(f"{where}: image prefix {prefix!r} {same}; each image must "
                                "be under one camera's prefix")


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
    """Write the rigs and frames of `configs` into a database whose images under each
    camera's prefix share a camera of their own (as `extract_features` with `rig_cameras`
    imports them), replacing the trivial ones the import wrote. Rigs of one camera each are
    those trivial ones already (and COLMAP's apply_rig_config refuses the empty prefix)."""
    if all(len(config.cameras) == 1 for config in configs):
        return
    with pycolmap.Database.open(str(database_path)) as db:
        db.clear_frames()
        db.clear_rigs()
        pycolmap.apply_rig_config(configs, db)
