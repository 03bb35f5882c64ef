"""Read a COLMAP database into memory without ever writing the user's file.

pycolmap opens a database read-write and upgrades its schema in place, so we read
from a private copy in a temporary folder and leave the original byte for byte.
"""

from __future__ import annotations

import shutil
import sqlite3
import tempfile
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.errors import UserError


@dataclass
class ImageFeatures:
    image_id: int
    name: str
    camera_id: int
    keypoints: np.ndarray  # (n, 2) pixel coordinates, COLMAP's convention (centre of top-left pixel at 0.5)
    descriptors: np.ndarray  # (n, 128) uint8


@dataclass
class DatabaseContents:
    cameras: dict[int, pycolmap.Camera]
    images: dict[int, ImageFeatures]
    # (image_id1, image_id2) with id1 < id2 -> (m, 2) keypoint indices into image1, image2
    verified_matches: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    raw_matches: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)


def check_database_file(path: Path) -> None:
    """A readable SQLite file, checked from its header without opening it as a database."""
    if path.is_dir():
        raise UserError(f"database path is a folder, not a file: {path}")
    if not path.is_file():
        raise UserError(f"database not found: {path}")
    try:
        with open(path, "rb") as f:
            header = f.read(16)
    except OSError as exc:
        raise UserError(f"cannot read database {path}: {exc.strerror}") from None
    if header != b"SQLite format 3\x00":
        raise UserError(f"not an SQLite database: {path}")


def copy_database(path: Path, copy: Path) -> None:
    """Copy the file and its write-ahead log, if any (changes not yet folded into the file).

    Even a read-only SQLite connection leaves `-wal`/`-shm` files beside a WAL-mode
    database (as COLMAP writes them), so the user's file is only ever read as bytes."""
    try:
        shutil.copyfile(path, copy)
        wal = path.with_name(f"{path.name}-wal")
        if wal.is_file():
            shutil.copyfile(wal, copy.with_name(f"{copy.name}-wal"))
    except OSError as exc:
        raise UserError(f"cannot copy database {path} to a temporary folder: "
                        f"{exc.strerror or exc}") from None


# COLMAP's camera model ids -> number of parameters.
_NUM_PARAMS = {int(model_id): len(pycolmap.Camera.create_from_model_id(0, model_id, 1.0, 1, 1).params)
               for name, model_id in pycolmap.CameraModelId.__members__.items() if name != "INVALID"}


def _check_tables(copy: Path, path: Path) -> None:
    """The COLMAP tables are there and every camera is one pycolmap can read."""
    try:
        with closing(sqlite3.connect(copy)) as conn:
            tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            cameras = conn.execute("SELECT camera_id, model, params FROM cameras").fetchall() \
                if "cameras" in tables else []
    except sqlite3.Error as exc:
        raise UserError(f"cannot read database {path}: {exc}") from None
    missing = {"cameras", "images", "keypoints", "descriptors", "matches"} - tables
    if missing:
        raise UserError(f"not a COLMAP database (no table {', '.join(sorted(missing))}): {path}")
    for camera_id, model_id, params in cameras:
        if model_id not in _NUM_PARAMS:
            raise UserError(f"camera {camera_id} in {path} has model id {model_id}, which is no "
                            "COLMAP camera model")
        num_params = len(params or b"") / 8
        if num_params != _NUM_PARAMS[model_id]:
            raise UserError(f"camera {camera_id} in {path} has {num_params:g} params; its model "
                            f"{pycolmap.CameraModelId(model_id).name} takes {_NUM_PARAMS[model_id]}")


def read_database(path: str | Path) -> DatabaseContents:
    """Cameras, images with keypoints and descriptors, and matches, from a copy of `path`."""
    path = Path(path)
    check_database_file(path)
    with tempfile.TemporaryDirectory(prefix="colmap-ext-db-") as tmp:
        copy = Path(tmp) / "database.db"
        copy_database(path, copy)
        _check_tables(copy, path)
        try:
            db = pycolmap.Database.open(copy)
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad schemas
            raise UserError(f"cannot open database {path}: {exc}") from None
        try:
            return _read_open_database(db, path)
        finally:
            db.close()


def _read_open_database(db: pycolmap.Database, path: Path) -> DatabaseContents:
    cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
    images: dict[int, ImageFeatures] = {}
    for image in db.read_all_images():
        if image.camera_id not in cameras:
            raise UserError(f"image {image.name} refers to camera {image.camera_id}, "
                            f"which is not in the database {path}")
        keypoints = db.read_keypoints(image.image_id) if db.exists_keypoints(image.image_id) \
            else np.zeros((0, 2), np.float32)
        descriptors = db.read_descriptors(image.image_id).data \
            if db.exists_descriptors(image.image_id) else np.zeros((0, 128), np.uint8)
        images[image.image_id] = ImageFeatures(
            image.image_id, image.name, image.camera_id,
            np.asarray(keypoints[:, :2], dtype=np.float64),
            np.asarray(descriptors, dtype=np.uint8))
    if not images:
        raise UserError(f"the database has no images: {path}")
    for camera in cameras.values():
        if len(camera.params) == 0 or not np.isfinite(camera.params).all() or \
                camera.width <= 0 or camera.height <= 0:
            raise UserError(f"camera {camera.camera_id} in {path} has no valid parameters "
                            f"(model {camera.model.name}, params {list(camera.params)})")
    if sum(len(image.keypoints) for image in images.values()) == 0:
        raise UserError(f"the database has no keypoints: {path} (run feature extraction first)")

    contents = DatabaseContents(cameras, images)
    # Keypoint indices as int32, each pair's read arrays released once converted: on
    # long turntables (every pair matched) the matches are most of the memory.
    pair_ids, geometries = db.read_two_view_geometries()
    for k, pair_id in enumerate(pair_ids):
        geometry, geometries[k] = geometries[k], None
        matches = np.asarray(geometry.inlier_matches, dtype=np.int32).reshape(-1, 2)
        if len(matches) and geometry.config not in _FAILED_CONFIGS:
            key, ordered = _ordered(pair_id, matches)
            contents.verified_matches[key] = ordered
    pair_ids, matches_list = db.read_all_matches()
    for k, pair_id in enumerate(pair_ids):
        matches, matches_list[k] = matches_list[k], None
        if len(matches):
            key, ordered = _ordered(pair_id, np.asarray(matches, dtype=np.int32))
            contents.raw_matches[key] = ordered
    if not contents.verified_matches and not contents.raw_matches:
        raise UserError(f"the database has no matches: {path} (run feature matching first)")
    _check_match_indices(contents, path)
    return contents


_FAILED_CONFIGS = (pycolmap.TwoViewGeometryConfiguration.UNDEFINED,
                   pycolmap.TwoViewGeometryConfiguration.DEGENERATE,
                   pycolmap.TwoViewGeometryConfiguration.WATERMARK,
                   pycolmap.TwoViewGeometryConfiguration.MULTIPLE)


def _ordered(pair_id: int, matches: np.ndarray) -> tuple[tuple[int, int], np.ndarray]:
    """Pairs keyed with the smaller image id first (COLMAP's pair ids already are)."""
    id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
    if id1 > id2:
        return (id2, id1), matches[:, ::-1].copy()
    return (id1, id2), matches


def _check_match_indices(contents: DatabaseContents, path: Path) -> None:
    for matches_by_pair in (contents.verified_matches, contents.raw_matches):
        for (id1, id2), matches in list(matches_by_pair.items()):
            if id1 not in contents.images or id2 not in contents.images:
                raise UserError(f"matches refer to an image that is not in {path}: {id1}, {id2}")
            n1, n2 = len(contents.images[id1].keypoints), len(contents.images[id2].keypoints)
            if len(matches) and (matches[:, 0].max() >= n1 or matches[:, 1].max() >= n2):
                raise UserError(f"matches between images {id1} and {id2} refer to keypoints "
                                f"that do not exist in {path}")
