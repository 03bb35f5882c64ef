"""Read a COLMAP database into memory without ever writing the user's file.

pycolmap opens a database read-write and upgrades its schema in place, so we read
from a private copy in a temporary folder (`copy_database`, through SQLite) and leave the
original byte for byte. The descriptors, most of a database's size, stay in that copy and
are read per image when the mapper asks for them (`DescriptorReader`).
"""

from __future__ import annotations

import shutil
import sqlite3
import threading
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.errors import UserError
from colmap_ext.geometry import QUATERNION_NORM_TOLERANCE
from colmap_ext.temporary import OwnedTemporaryDirectory


# How far outside its image a keypoint may be (pixels): a simulated one's noise puts it a
# little outside; far outside, the keypoints are not of the camera's image.
KEYPOINT_MARGIN_PX = 16
# Descriptors kept in memory after reading, the most recently used images' first.
DESCRIPTOR_CACHE_BYTES = 32 * 2**20


@dataclass
class ImageFeatures:
    image_id: int
    name: str
    camera_id: int
    keypoints: np.ndarray  # (n, 2) pixel coordinates, COLMAP's convention (centre of top-left pixel at 0.5)
    frame_id: int | None = None  # None in a database without frames (COLMAP 3.x)


class DescriptorReader(Mapping[int, np.ndarray]):
    """Each image's SIFT descriptors, (n, 128) uint8, read from the private copy of the
    database when asked; the most recently used are kept up to `max_bytes`. The copy's
    folder is removed with the reader. Safe to use from several threads."""

    def __init__(self, folder: OwnedTemporaryDirectory, copy: Path, image_ids: list[int],
                 max_bytes: int = DESCRIPTOR_CACHE_BYTES) -> None:
        self._folder = folder
        # Read only: pycolmap folds the write-ahead log into the file when it closes the
        # database, and nobody writes the copy after. Immutable, so SQLite writes nothing
        # beside it (no shared-memory file, which a full disk would refuse) and takes no locks.
        self._connection = sqlite3.connect(f"{copy.as_uri()}?immutable=1", uri=True,
                                           check_same_thread=False)
        self._image_ids = dict.fromkeys(image_ids)  # ordered, and quick to look up
        self._max_bytes = max_bytes
        self._kept: OrderedDict[int, np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def __getitem__(self, image_id: int) -> np.ndarray:
        with self._lock:
            if image_id in self._kept:
                self._kept.move_to_end(image_id)
                return self._kept[image_id]
            if image_id not in self._image_ids:
                raise KeyError(image_id)
            row = self._connection.execute(
                "SELECT rows, cols, data FROM descriptors WHERE image_id = ?", (image_id,)).fetchone()
            descriptors = np.zeros((0, 128), np.uint8) if row is None or not row[0] else \
                np.frombuffer(row[2], np.uint8).reshape(row[0], row[1])
            self._kept[image_id] = descriptors
            self._bytes += descriptors.nbytes
            while self._bytes > self._max_bytes and len(self._kept) > 1:
                self._bytes -= self._kept.popitem(last=False)[1].nbytes
            return descriptors

    def release(self) -> None:
        """Give up the descriptors kept (they are read again when asked)."""
        with self._lock:
            self._kept.clear()
            self._bytes = 0

    def shapes(self) -> dict[int, tuple[int, int, int]]:
        """image id -> (rows, columns, bytes) of each stored descriptor array."""
        with self._lock:
            return {image_id: (rows, cols, size) for image_id, rows, cols, size in
                    self._connection.execute(
                        "SELECT image_id, rows, cols, length(data) FROM descriptors")}

    def __iter__(self) -> Iterator[int]:
        return iter(self._image_ids)

    def __len__(self) -> int:
        return len(self._image_ids)

    def __reduce__(self):
        """Pickled (for a worker process) as the plain dict of every image's descriptors."""
        return dict, (dict(self.items()),)


@dataclass(frozen=True)
class RigCalibration:
    """A rig of COLMAP 4's database: its reference camera, and the pose of each other
    camera in the rig (plain data, to send to worker processes)."""

    ref_camera_id: int
    cams_from_rig: dict[int, pycolmap.Rigid3d]  # non-reference camera id -> sensor_from_rig

    def rig(self, rig_id: int) -> pycolmap.Rig:
        rig = pycolmap.Rig()
        rig.rig_id = rig_id
        rig.add_ref_sensor(_camera_sensor(self.ref_camera_id))
        for camera_id, cam_from_rig in self.cams_from_rig.items():
            rig.add_sensor(_camera_sensor(camera_id), cam_from_rig)
        return rig

    @property
    def camera_ids(self) -> list[int]:
        return [self.ref_camera_id, *self.cams_from_rig]


@dataclass(frozen=True)
class FrameImages:
    """A frame of COLMAP 4's database: its rig and its images."""

    rig_id: int
    image_ids: tuple[int, ...]


def _camera_sensor(camera_id: int) -> pycolmap.sensor_t:
    return pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id)


@dataclass
class DatabaseContents:
    cameras: dict[int, pycolmap.Camera]
    images: dict[int, ImageFeatures]
    descriptors: Mapping[int, np.ndarray]  # image_id -> (n, 128) uint8, one per keypoint
    # (image_id1, image_id2) with id1 < id2 -> (m, 2) keypoint indices into image1, image2
    verified_matches: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    raw_matches: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    # COLMAP 4's rigs and frames; empty for a COLMAP 3.x database, whose images are each
    # a frame of their own (see mapper/model.py's database_reconstruction).
    rigs: dict[int, RigCalibration] = field(default_factory=dict)
    frames: dict[int, FrameImages] = field(default_factory=dict)


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


# Seconds to wait for another process's write transaction on the database to end.
BUSY_TIMEOUT_S = 5


def copy_database(path: Path, copy: Path) -> None:
    """Copy what `path` holds committed into the new file `copy`, creating no file beside
    `path` and writing none.

    A database with a rollback journal is copied by SQLite's backup API on a read-only
    connection, inside a read transaction: SQLite's locks keep out the pages of a
    transaction another process has not committed (waiting up to BUSY_TIMEOUT_S for it to
    end). Two kinds SQLite cannot read so without writing beside them are copied as files
    instead, and SQLite recovers the copy when it first opens it: a WAL database (as COLMAP
    leaves them; even a read-only connection creates `-wal`/`-shm` files), its log's
    uncommitted frames left out, and one with a hot journal (its writer died mid-transaction),
    rolled back."""
    if _is_wal_database(path):
        _copy_files(path, copy, "-wal")
        return
    try:
        source = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True,
                                 timeout=BUSY_TIMEOUT_S)
    except sqlite3.Error as exc:
        raise UserError(f"cannot read database {path}: {exc}") from None
    try:
        with closing(source), closing(sqlite3.connect(copy)) as target:
            source.execute("BEGIN")
            source.execute("SELECT count(*) FROM sqlite_master")  # takes the read lock
            source.backup(target)
    except sqlite3.Error as exc:
        copy.unlink(missing_ok=True)
        if getattr(exc, "sqlite_errorname", None) == "SQLITE_READONLY_ROLLBACK":
            _copy_files(path, copy, "-journal")
        elif getattr(exc, "sqlite_errorname", None) == "SQLITE_BUSY":
            raise UserError(f"database {path} is being written by another process (still "
                            f"locked after {BUSY_TIMEOUT_S} s); run again once it is "
                            "done") from None
        else:
            raise UserError(f"cannot read database {path}: {exc}") from None


def _is_wal_database(path: Path) -> bool:
    """SQLite's header: file format versions 2 (bytes 18, 19) mean WAL mode."""
    try:
        with open(path, "rb") as f:
            header = f.read(20)
    except OSError as exc:
        raise UserError(f"cannot read database {path}: {exc.strerror}") from None
    return header[18:20] == b"\x02\x02"


def _copy_files(path: Path, copy: Path, journal_suffix: str) -> None:
    """Copy the database file and its journal or log (`journal_suffix`), if any, as bytes."""
    try:
        shutil.copyfile(path, copy)
        journal = path.with_name(f"{path.name}{journal_suffix}")
        if journal.is_file():
            shutil.copyfile(journal, copy.with_name(f"{copy.name}{journal_suffix}"))
    except OSError as exc:
        raise UserError(f"cannot copy database {path} to a temporary folder: "
                        f"{exc.strerror or exc}") from None


_MODELS = {int(model_id): pycolmap.Camera.create_from_model_id(0, model_id, 1.0, 1, 1)
           for name, model_id in pycolmap.CameraModelId.__members__.items() if name != "INVALID"}
# COLMAP's camera model ids -> number of parameters, and the focal lengths' indices.
NUM_PARAMS = {model_id: len(camera.params) for model_id, camera in _MODELS.items()}
_FOCAL_LENGTH_IDXS = {model_id: camera.focal_length_idxs() for model_id, camera in _MODELS.items()}
# Bytes of the two-view geometry blobs that hold one fixed-size array each (doubles):
# F, E, H 3x3, qvec 4, tvec 3. Empty or NULL: not estimated.
_GEOMETRY_BLOB_BYTES = {"F": 72, "E": 72, "H": 72, "qvec": 32, "tvec": 24}
# Columns a keypoints row may have: x, y; x, y, scale, orientation; x, y and an affine shape.
_KEYPOINT_COLUMNS = (2, 4, 6)


def colmap_tables(conn: sqlite3.Connection, path: Path) -> set[str]:
    """The tables of the open database `conn` (a copy of `path`); a UserError unless
    COLMAP's are among them."""
    tables = {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    missing = {"cameras", "images", "keypoints", "descriptors", "matches"} - tables
    if missing:
        raise UserError(f"not a COLMAP database (no table {', '.join(sorted(missing))}): {path}")
    return tables


def _check_tables(copy: Path, path: Path) -> None:
    """The COLMAP tables are there, every camera is one pycolmap can read, and every
    keypoint and match blob holds what its rows and columns say (read as raw bytes before
    pycolmap, which would read past a short blob or reinterpret a long one)."""
    try:
        with closing(sqlite3.connect(copy)) as conn:
            tables = colmap_tables(conn, path)
            for row in conn.execute("SELECT camera_id, model, width, height, params FROM cameras"):
                _check_camera(*row, path)
            _check_blobs(conn, path, "two_view_geometries" in tables)
            if "rig_sensors" in tables:
                _check_sensors_from_rig(conn, path)
    except sqlite3.Error as exc:
        raise UserError(f"cannot read database {path}: {exc}") from None


def _check_camera(camera_id: int, model_id: int, width: int, height: int, params: bytes | None,
                  path: Path) -> None:
    if model_id not in NUM_PARAMS:
        raise UserError(f"camera {camera_id} in {path} has model id {model_id}, which is no "
                        "COLMAP camera model")
    num_params = len(params or b"") / 8
    if num_params != NUM_PARAMS[model_id]:
        raise UserError(f"camera {camera_id} in {path} has {num_params:g} params; its model "
                        f"{pycolmap.CameraModelId(model_id).name} takes {NUM_PARAMS[model_id]}")
    values = np.frombuffer(params, np.float64)
    if not np.isfinite(values).all():
        raise UserError(f"camera {camera_id} in {path} has no valid parameters "
                        f"(model {pycolmap.CameraModelId(model_id).name}, params {list(values)})")
    if not (isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0):
        raise UserError(f"camera {camera_id} in {path} has an image size of {width} x {height}; "
                        "expected positive integers")
    focal_lengths = values[_FOCAL_LENGTH_IDXS[model_id]]
    if (focal_lengths <= 0).any():
        raise UserError(f"camera {camera_id} in {path} has focal length "
                        f"{', '.join(f'{f:g}' for f in focal_lengths)}; expected a positive one")
    if not len(focal_lengths) and list(values) != [width, height]:  # EQUIRECTANGULAR
        raise UserError(f"camera {camera_id} in {path} is {width} x {height} with params "
                        f"{', '.join(f'{v:g}' for v in values)}; its model "
                        f"{pycolmap.CameraModelId(model_id).name} takes the image size")


def _check_sensors_from_rig(conn: sqlite3.Connection, path: Path) -> None:
    """Every camera's place on its rig (7 doubles: a unit quaternion, a translation), read
    as raw bytes: pycolmap takes NULL for no pose, and a zero quaternion as one."""
    for rig_id, sensor_id, pose in conn.execute(
            "SELECT rig_id, sensor_id, sensor_from_rig FROM rig_sensors WHERE sensor_type = ?",
            (int(pycolmap.SensorType.CAMERA),)):
        values = np.frombuffer(pose, np.float64) if isinstance(pose, bytes) and \
            len(pose) == 7 * 8 else None
        if values is None or not np.isfinite(values).all() or \
                abs(np.linalg.norm(values[:4]) - 1) > QUATERNION_NORM_TOLERANCE:
            shown = "NULL" if pose is None else "not a pose" if values is None else \
                f"[{', '.join(f'{v:g}' for v in values)}]"
            raise UserError(f"rig {rig_id} in {path}: camera {sensor_id}'s sensor_from_rig is "
                            f"{shown}; expected a unit quaternion and a translation (run "
                            "colmap rig_configurator again)")


def _check_blobs(conn: sqlite3.Connection, path: Path, has_geometries: bool) -> None:
    """Keypoints: rows x (2, 4 or 6) float32; matches and verified matches: rows x 2
    uint32; the two-view geometry's matrices: empty or their size."""
    for image_id, name, rows, cols, size in conn.execute(
            "SELECT keypoints.image_id, images.name, keypoints.rows, keypoints.cols, "
            "length(keypoints.data) FROM keypoints LEFT JOIN images USING (image_id)"):
        if rows and (cols not in _KEYPOINT_COLUMNS or size != rows * cols * 4):
            raise UserError(f"the keypoints of image {name or image_id} in {path} hold {size} "
                            f"bytes for {rows} x {cols}; expected {rows} rows of 2, 4 or 6 "
                            "4-byte numbers")
    geometry_columns = ", " + ", ".join(f"length({c})" for c in _GEOMETRY_BLOB_BYTES)
    for table in ("matches", "two_view_geometries") if has_geometries else ("matches",):
        extra = geometry_columns if table == "two_view_geometries" else ""
        for pair_id, rows, cols, size, *blobs in conn.execute(
                f"SELECT pair_id, rows, cols, length(data){extra} FROM {table}"):
            pair = "images {} and {}".format(*pycolmap.pair_id_to_image_pair(pair_id))
            if rows and (cols != 2 or size != rows * 8):
                raise UserError(f"{table} of {pair} in {path} hold {size} bytes for {rows} x "
                                f"{cols}; expected {rows} rows of 2 keypoint indices "
                                "(4 bytes each)")
            for (blob, expected), length in zip(_GEOMETRY_BLOB_BYTES.items(), blobs):
                if length and length != expected:
                    raise UserError(f"two_view_geometries of {pair} in {path}: {blob} holds "
                                    f"{length} bytes; expected {expected}")


def read_database(path: str | Path) -> DatabaseContents:
    """Cameras, images with keypoints, and matches, from a copy of `path`; the
    descriptors are read from that copy when asked for (DescriptorReader)."""
    path = Path(path)
    check_database_file(path)
    folder = OwnedTemporaryDirectory("colmap-ext-db-")
    try:
        copy = Path(folder.name) / "database.db"
        copy_database(path, copy)
        _check_tables(copy, path)
        try:
            db = pycolmap.Database.open(copy)
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad schemas
            raise UserError(f"cannot open database {path}: {exc}") from None
        try:
            contents = _read_open_database(db, path)
        finally:
            db.close()
        contents.descriptors = DescriptorReader(folder, copy, list(contents.images))
        _check_descriptors(contents, path)
        return contents
    except BaseException:
        folder.cleanup()
        raise


def _read_open_database(db: pycolmap.Database, path: Path) -> DatabaseContents:
    cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
    images: dict[int, ImageFeatures] = {}
    for image in db.read_all_images():
        if image.camera_id not in cameras:
            raise UserError(f"image {image.name} refers to camera {image.camera_id}, "
                            f"which is not in the database {path}")
        keypoints = db.read_keypoints(image.image_id) if db.exists_keypoints(image.image_id) \
            else np.zeros((0, 2), np.float32)
        images[image.image_id] = ImageFeatures(
            image.image_id, image.name, image.camera_id,
            np.asarray(keypoints[:, :2], dtype=np.float64),
            image.frame_id if image.has_frame_id() else None)
    if not images:
        raise UserError(f"the database has no images: {path}")
    for image in images.values():
        if not np.isfinite(image.keypoints).all():
            raise UserError(f"the keypoints of image {image.name} in {path} are not all finite "
                            "numbers (NaN or infinity)")
        camera = cameras[image.camera_id]
        outside = np.any((image.keypoints < -KEYPOINT_MARGIN_PX) |
                         (image.keypoints > [camera.width + KEYPOINT_MARGIN_PX,
                                             camera.height + KEYPOINT_MARGIN_PX]), axis=1)
        if outside.any():
            x, y = image.keypoints[outside][0]
            raise UserError(f"{outside.sum()} keypoints of image {image.name} in {path} are "
                            f"outside its camera's {camera.width} x {camera.height} image, "
                            f"e.g. ({x:g}, {y:g})")
    if sum(len(image.keypoints) for image in images.values()) == 0:
        raise UserError(f"the database has no keypoints: {path} (run feature extraction first)")

    contents = DatabaseContents(cameras, images, {})
    _read_rigs_and_frames(db, contents, path)
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


def _read_rigs_and_frames(db: pycolmap.Database, contents: DatabaseContents, path: Path) -> None:
    """The database's rigs and frames, where every image belongs to a frame whose rig
    holds its camera; none where no image has a frame (a COLMAP 3.x database)."""
    if all(image.frame_id is None for image in contents.images.values()):
        return
    for rig in db.read_all_rigs():
        cameras = [sensor for sensor in rig.non_ref_sensors
                   if sensor.type == pycolmap.SensorType.CAMERA]
        contents.rigs[rig.rig_id] = RigCalibration(
            rig.ref_sensor_id.id, {sensor.id: rig.sensor_from_rig(sensor) for sensor in cameras})
    for frame in db.read_all_frames():
        contents.frames[frame.frame_id] = FrameImages(
            frame.rig_id, tuple(data_id.id for data_id in frame.image_ids))
    for image in contents.images.values():
        frame = contents.frames.get(image.frame_id)
        rig = contents.rigs.get(frame.rig_id) if frame is not None else None
        if rig is None or image.camera_id not in rig.camera_ids or \
                image.image_id not in frame.image_ids:
            raise UserError(f"image {image.name} in {path} has no frame whose rig holds its "
                            f"camera {image.camera_id}: run colmap rig_configurator again")
    for frame_id, frame in contents.frames.items():
        by_camera: dict[int, str] = {}
        for image in (contents.images[i] for i in frame.image_ids if i in contents.images):
            first = by_camera.setdefault(image.camera_id, image.name)
            if first != image.name:
                raise UserError(f"frame {frame_id} in {path} holds images {first} and "
                                f"{image.name} of one camera ({image.camera_id}); a frame "
                                "holds one image per camera: run colmap rig_configurator again")


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
            # int32 from COLMAP's uint32: an index of 2^31 or more reads as negative
            if len(matches) and (matches.min() < 0 or matches[:, 0].max() >= n1
                                 or matches[:, 1].max() >= n2):
                raise UserError(f"matches between images {id1} and {id2} refer to keypoints "
                                f"that do not exist in {path}")


def _check_descriptors(contents: DatabaseContents, path: Path) -> None:
    """Every image's descriptors are uint8 SIFT, one per keypoint."""
    shapes = contents.descriptors.shapes()
    for image_id, image in contents.images.items():
        rows, cols, size = shapes.get(image_id, (0, 128, 0))
        if rows != len(image.keypoints) or (rows and (cols != 128 or size != rows * cols)):
            raise UserError(f"image {image.name} in {path} has {rows} descriptors of {cols} "
                            f"values for {len(image.keypoints)} keypoints; expected one SIFT "
                            "descriptor (128 values) per keypoint")
