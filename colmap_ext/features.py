"""SIFT features with known intrinsics and the paper's adaptive detector threshold.

pycolmap imports every image with the given camera (model and parameters fixed by
the user). Chunks of images are then tasks of an executor (threads here, or Ray tasks):
each runs pycolmap's own extractor on a scratch database, so the rows are exactly what
COLMAP writes (keypoint format, masking, image reading), and, as in the paper, extracts
every image with fewer than `min_num_keypoints` keypoints again with half the SIFT
peak threshold, down to a floor. The features are written here as chunks complete.
Equirectangular panoramas may instead be extracted on their six cube faces, the
keypoints mapped back into the panorama (colmap_ext/panorama.py).

All input is checked before any work: a bad camera or an unreadable image is a
one-line `UserError`, not a COLMAP log line halfway through.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from colmap_ext.errors import UserError
from colmap_ext.executors import Executor, ImageSource, LocalExecutor, chunks, items_per_task
from colmap_ext.panorama import FACE_FORWARD_DOWN, CubeFaces, inside_mask, keypoint_scales
from colmap_ext.temporary import OwnedTemporaryDirectory

CAMERA_MODES = {"single": pycolmap.CameraMode.SINGLE, "per_folder": pycolmap.CameraMode.PER_FOLDER}
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp")
# The paper's rule: fewer keypoints than this and the detector runs again, more sensitive.
DEFAULT_MIN_NUM_KEYPOINTS = 500
DEFAULT_PEAK_THRESHOLD = pycolmap.SiftExtractionOptions().peak_threshold  # 0.02 / 3
# Floor of the halving (0.0033, 0.0017, then 0.00125): lower, SIFT mostly finds noise.
MIN_PEAK_THRESHOLD = 0.00125
# Images per extraction task, at most (fewer when that leaves some workers idle).
MAX_IMAGES_PER_TASK = 16
# Where SIFT runs on EQUIRECTANGULAR images: on the panorama itself (as COLMAP does) or on
# six cube faces rendered from it, the keypoints mapped back (panorama.py).
PANORAMA_FEATURES = ("equirectangular", "cube_faces")
DEFAULT_PANORAMA_FEATURES = "equirectangular"
# A focal length this many times the image's larger side sees under 0.06 degrees: a wrong
# parameter (a telephoto lens on a full-frame sensor is about 50).
MAX_FOCAL_LENGTH_RATIO = 1000
# COLMAP's SIFT keeps this many features per image, the largest; so do the cube faces together.
MAX_NUM_FEATURES = pycolmap.SiftExtractionOptions().max_num_features

Features = tuple[np.ndarray, pycolmap.FeatureDescriptors]
# extract(names, peak_threshold): the features of those images, by name.
Extractor = Callable[[list[str], float], dict[str, Features]]


@dataclass(frozen=True)
class CameraGroup:
    """Images that share one camera, its model and params; `label` says why, for messages."""

    label: str
    names: list[str]
    camera_model: str
    params: list[float]


@dataclass(frozen=True)
class FeatureSummary:
    """Keypoints per image name before and after the adaptive rule, and the threshold used."""

    initial_keypoints: dict[str, int]
    final_keypoints: dict[str, int]
    peak_thresholds: dict[str, float]
    seconds: float

    @property
    def reextracted(self) -> list[str]:
        """Images that needed a lower peak threshold."""
        return [name for name, value in self.peak_thresholds.items()
                if value < DEFAULT_PEAK_THRESHOLD]

    def keypoint_stats(self, final: bool = True) -> tuple[int, float, int]:
        """(min, median, max) keypoints per image."""
        counts = list((self.final_keypoints if final else self.initial_keypoints).values())
        return min(counts), statistics.median(counts), max(counts)

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "num_images": len(self.final_keypoints),
            "num_reextracted": len(self.reextracted),
            "keypoints_initial_min_median_max": self.keypoint_stats(final=False),
            "keypoints_final_min_median_max": self.keypoint_stats(final=True),
            "seconds": round(self.seconds, 3),
            "images": {name: {"initial": self.initial_keypoints[name],
                              "final": self.final_keypoints[name],
                              "peak_threshold": self.peak_thresholds[name]}
                       for name in self.final_keypoints},
        }


class _QuietLogs:
    """COLMAP's log level (one per process) raised while any thread is inside, and put
    back when the last one leaves: tasks in threads overlap."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.inside = 0
        self.previous = 0

    @contextlib.contextmanager
    def __call__(self) -> Iterator[None]:
        with self.lock:
            if not self.inside:
                self.previous = pycolmap.logging.minloglevel
                pycolmap.logging.minloglevel = max(self.previous,
                                                   int(pycolmap.logging.Level.WARNING))
            self.inside += 1
        try:
            yield
        finally:
            with self.lock:
                self.inside -= 1
                if not self.inside:
                    pycolmap.logging.minloglevel = self.previous


# Silence COLMAP's per-image INFO lines while our progress bars report; warnings stay.
quiet_colmap_logs = _QuietLogs()


def check_camera(camera_model: str, camera_params: str | Sequence[float]) -> list[float]:
    """The parameters as floats, checked against the COLMAP camera model."""
    models = [name for name in pycolmap.CameraModelId.__members__ if name != "INVALID"]
    if camera_model not in models:
        raise UserError(f"unknown camera model {camera_model!r}; COLMAP's models are "
                        f"{', '.join(models)}")
    if isinstance(camera_params, str):
        fields = [field.strip() for field in camera_params.replace(" ", ",").split(",")]
        fields = [field for field in fields if field]
    else:
        fields = list(camera_params)
    try:
        params = [float(value) for value in fields]
    except (TypeError, ValueError):
        raise UserError(f"camera params must be numbers separated by commas, "
                        f"got {camera_params!r}") from None
    camera = pycolmap.Camera.create_from_model_name(0, camera_model, 1.0, 1, 1)
    if len(params) != len(camera.params):
        raise UserError(f"camera model {camera_model} takes {len(camera.params)} params "
                        f"({camera.params_info}), got {len(params)}")
    if not all(math.isfinite(value) for value in params):
        raise UserError(f"camera params must be finite, got {params}")
    if any(params[i] <= 0 for i in camera.focal_length_idxs()):
        raise UserError(f"focal lengths must be positive ({camera.params_info}), got {params}")
    if not camera.focal_length_idxs() and any(value <= 0 for value in params):
        # EQUIRECTANGULAR: the panorama's width and height
        raise UserError(f"camera params must be positive ({camera.params_info}), got {params}")
    return params


def list_images(image_path: str | os.PathLike,
                image_names: Sequence[str] | None = None) -> list[str]:
    """Image names relative to `image_path` (with '/'), sorted; all image files below it
    unless `image_names` picks some."""
    root = Path(image_path)
    if not root.is_dir():
        raise UserError(f"image folder not found: {root}")
    if image_names is not None:
        missing = [name for name in image_names if not (root / name).is_file()]
        if missing:
            raise UserError(f"image not found: {root / missing[0]}"
                            + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        names = list(image_names)
    else:
        names = [path.relative_to(root).as_posix() for path in root.rglob("*")
                 if path.is_file() and path.suffix.lower() in IMAGE_EXTENSIONS]
    if not names:
        raise UserError(f"no images in {root} (looked for {', '.join(IMAGE_EXTENSIONS)})")
    if len(set(names)) != len(names):
        raise UserError("image_names lists an image twice")
    return sorted(names)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image decoded in full, so a truncated file fails here."""
    if path.stat().st_size == 0:
        raise UserError(f"image file is empty (0 bytes): {path}")
    try:
        with Image.open(path) as image:
            image.load()
            return image.size
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise UserError(f"cannot read image {path}: {exc}") from None


def read_sizes(folder: Path, names: Sequence[str], suffix: str = "") -> dict[str, tuple[int, int]]:
    """(width, height) of every `folder/<name><suffix>`, decoded in parallel threads."""
    paths = [folder / f"{name}{suffix}" for name in names]
    for path in paths:
        if not path.is_file():
            raise UserError(f"file not found: {path}")
    with ThreadPoolExecutor(min(8, os.cpu_count() or 1)) as pool:
        return dict(zip(names, pool.map(image_size, paths)))


def check_images(image_path: str | os.PathLike, names: Sequence[str],
                 options: FeatureOptions) -> dict[str, tuple[int, int]]:
    """Check that every image reads, that the images sharing a camera share a size its
    parameters fit (`check_camera_fits`), and that every image has a mask of its size."""
    if options.camera_mode not in CAMERA_MODES:
        raise UserError(f"unknown camera mode {options.camera_mode!r}; choose one of "
                        f"{', '.join(CAMERA_MODES)}")
    sizes = read_sizes(Path(image_path), names)
    for group in options.camera_groups(names):
        odd = [name for name in group.names if sizes[name] != sizes[group.names[0]]]
        if odd:
            (w0, h0), (w1, h1) = sizes[group.names[0]], sizes[odd[0]]
            raise UserError(f"images sharing one camera must have one size: {group.names[0]} "
                            f"is {w0}x{h0}, {odd[0]} is {w1}x{h1} ({group.label})")
        check_camera_fits(group.camera_model, group.params, *sizes[group.names[0]])
    if options.mask_path is not None:
        check_masks(Path(options.mask_path), sizes)
    return sizes


def check_camera_fits(camera_model: str, params: Sequence[float], width: int,
                      height: int) -> None:
    """The parameters describe a camera of `width` x `height` pixels: its principal point
    inside, its focal lengths below MAX_FOCAL_LENGTH_RATIO times the larger side (the size
    itself, for a camera without them, such as EQUIRECTANGULAR)."""
    camera = pycolmap.Camera.create_from_model_name(0, camera_model, 1.0, 1, 1)
    shown = f"camera params {','.join(f'{p:g}' for p in params)} ({camera.params_info})"
    principal_point = [params[i] for i in camera.principal_point_idxs()]
    if not principal_point and [width, height] != list(params):  # EQUIRECTANGULAR
        raise UserError(f"{shown} are not the images' size {width:g}x{height:g}")
    if principal_point and not (0 <= principal_point[0] <= width and
                                0 <= principal_point[1] <= height):
        raise UserError(f"principal point ({principal_point[0]:g}, {principal_point[1]:g}) "
                        f"is outside the {width:g}x{height:g} images: are the camera params "
                        "for another image size?")
    if any(params[i] > MAX_FOCAL_LENGTH_RATIO * max(width, height)
           for i in camera.focal_length_idxs()):
        raise UserError(f"{shown}: a focal length over {MAX_FOCAL_LENGTH_RATIO} times the "
                        f"{width:g}x{height:g} images' size is no lens's")


def check_masks(mask_path: Path, sizes: dict[str, tuple[int, int]]) -> None:
    """Every image needs `MASK_PATH/<image name>.png` of its own size (COLMAP's layout)."""
    if not mask_path.is_dir():
        raise UserError(f"mask folder not found: {mask_path}")
    mask_sizes = read_sizes(mask_path, list(sizes), suffix=".png")
    for name, size in mask_sizes.items():
        if size != sizes[name]:
            raise UserError(f"mask {mask_path / (name + '.png')} is {size[0]}x{size[1]}, "
                            f"its image is {sizes[name][0]}x{sizes[name][1]}")


def posix_parent(name: str) -> str:
    """The folder part of an image name ('' at the top level)."""
    return name.rpartition("/")[0]


@dataclass
class FeatureOptions:
    """Feature extraction (extract_features): the known camera, masks, and the adaptive
    detector threshold."""

    # A COLMAP camera model with a focal length, e.g. PINHOLE, OPENCV.
    camera_model: str
    # Its parameters in COLMAP's order: numbers, or a string "fx,fy,cx,cy".
    camera_params: str | Sequence[float]
    # One of CAMERA_MODES: one camera for all images, or one per sub-folder.
    camera_mode: str = "single"
    # COLMAP masks: MASK_PATH/<image name>.png, 0 = ignore.
    mask_path: str | os.PathLike | None = None
    # Images with fewer keypoints are extracted again with a lower SIFT peak threshold.
    min_num_keypoints: int = DEFAULT_MIN_NUM_KEYPOINTS
    # COLMAP's DSP-SIFT descriptors.
    domain_size_pooling: bool = False
    # EQUIRECTANGULAR cameras: one of PANORAMA_FEATURES (other cameras: not used).
    panorama_features: str = DEFAULT_PANORAMA_FEATURES
    # A rig configuration's cameras, image prefix -> (model, params): the images under each
    # prefix share its camera instead (camera_model and camera_params are then the first's).
    rig_cameras: dict[str, tuple[str, list[float]]] | None = None

    def check(self) -> None:
        """The camera, the keypoint minimum and the panorama features (the images:
        check_images)."""
        self.params()
        minimum = self.min_num_keypoints
        if isinstance(minimum, bool) or not isinstance(minimum, int) or minimum < 0:
            raise UserError(f"min_num_keypoints must be a non-negative integer, got {minimum!r}")
        if self.panorama_features not in PANORAMA_FEATURES:
            raise UserError(f"unknown panorama features {self.panorama_features!r}; choose one "
                            f"of {', '.join(PANORAMA_FEATURES)}")
        if self.rig_cameras is not None:
            for model, params in self.rig_cameras.values():
                check_camera(model, params)
            if self.uses_cube_faces() and len({(model, tuple(params)) for model, params
                                               in self.rig_cameras.values()}) > 1:
                raise UserError("panorama features on cube faces need the rig's cameras to be "
                                "EQUIRECTANGULAR of one size")

    def camera_groups(self, names: Sequence[str]) -> list[CameraGroup]:
        """The images (of `names`) that share one camera, with its model and params: all
        of them (camera mode single), those of each folder (per_folder), or those under
        each rig camera's image prefix (`rig_cameras`)."""
        if self.rig_cameras is not None:
            groups = [CameraGroup(f"image prefix {prefix!r}",
                                  [name for name in names if name.startswith(prefix)],
                                  model, list(params))
                      for prefix, (model, params) in self.rig_cameras.items()]
            return [group for group in groups if group.names]
        folders: dict[str, list[str]] = {}
        for name in names:
            folder = posix_parent(name) if self.camera_mode == "per_folder" else ""
            folders.setdefault(folder, []).append(name)
        label = f"camera mode {self.camera_mode}"
        return [CameraGroup(label if self.camera_mode == "single" else f"{label}, folder "
                            f"{folder!r}", members, self.camera_model, self.params())
                for folder, members in folders.items()]

    def uses_cube_faces(self) -> bool:
        """SIFT on the cube faces of EQUIRECTANGULAR panoramas (panorama.py)."""
        return self.camera_model == "EQUIRECTANGULAR" and self.panorama_features == "cube_faces"

    def params(self) -> list[float]:
        """The camera parameters as floats, checked against the camera model."""
        return check_camera(self.camera_model, self.camera_params)

    def reader_options(self, mask_path: str | os.PathLike | None,
                       camera: tuple[str, Sequence[float]] | None = None,
                       ) -> pycolmap.ImageReaderOptions:
        """pycolmap's reader with the camera fixed (`camera`: model and params, else the
        options' own) and the masks in `mask_path`."""
        model, params = camera or (self.camera_model, self.params())
        reader = pycolmap.ImageReaderOptions(
            camera_model=model, camera_params=",".join(repr(float(p)) for p in params))
        if mask_path is not None:
            reader.mask_path = Path(mask_path)
        return reader

    def extractor(self, image_path: str | os.PathLike, mask_path: str | os.PathLike | None,
                  num_threads: int) -> Extractor:
        """SIFT of the images in `image_path` with the masks in `mask_path`: pycolmap's
        extractor on the images, or on the cube faces of EQUIRECTANGULAR panoramas."""
        if self.uses_cube_faces():
            width, height = (int(value) for value in self.params())
            return partial(extract_cube_faces_to_memory, image_path, mask_path,
                           CubeFaces.of_panorama(width, height),
                           domain_size_pooling=self.domain_size_pooling,
                           num_threads=num_threads)
        return partial(extract_to_memory, image_path, self.reader_options(mask_path),
                       domain_size_pooling=self.domain_size_pooling, num_threads=num_threads)


def extract_features(database_path: str | os.PathLike, image_path: str | os.PathLike,
                     options: FeatureOptions, *, image_names: Sequence[str] | None = None,
                     executor: Executor | None = None, progress: bool = True) -> FeatureSummary:
    """Extract SIFT features of every image (or of `image_names`) into a new database,
    with the adaptive rule; chunks of images are tasks of `executor` (default: this
    machine's threads), written here as they complete."""
    start = time.perf_counter()
    options.check()
    names = list_images(image_path, image_names)
    check_images(image_path, names, options)
    check_new_database(Path(database_path))
    with quiet_colmap_logs():
        # Importing first gives image ids in name order, and the cameras.
        pycolmap.Database.open(database_path).close()
        if options.rig_cameras is None:
            pycolmap.import_images(database_path, image_path,
                                   camera_mode=CAMERA_MODES[options.camera_mode],
                                   image_names=names,
                                   options=options.reader_options(options.mask_path))
        else:  # a camera per prefix; prefix order is name order, as no prefix holds another
            for group in sorted(options.camera_groups(names), key=lambda group: group.names):
                pycolmap.import_images(database_path, image_path,
                                       camera_mode=pycolmap.CameraMode.SINGLE,
                                       image_names=group.names,
                                       options=options.reader_options(
                                           options.mask_path, (group.camera_model, group.params)))
    executor = executor or LocalExecutor()
    groups = chunks(names, items_per_task(len(names), MAX_IMAGES_PER_TASK, executor.num_workers))
    sources = executor.image_sources(str(image_path), None if options.mask_path is None
                                     else str(options.mask_path), groups)
    initial: dict[str, int] = {}
    thresholds: dict[str, float] = {}
    final: dict[str, int] = {}
    with pycolmap.Database.open(database_path) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        for chunk in executor.map(extract_chunk, ((source, list(group), options,
                                                   executor.threads_per_task)
                                                  for source, group in zip(sources, groups)),
                                  len(groups), desc="extract", progress=progress):
            with pycolmap.DatabaseTransaction(db):
                for name, (keypoints, descriptors) in chunk.features.items():
                    db.write_keypoints(ids[name], keypoints)
                    db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(
                        pycolmap.FeatureExtractorType.SIFT, descriptors))
                    final[name] = len(keypoints)
            initial.update(chunk.initial_keypoints)
            thresholds.update(chunk.peak_thresholds)
    in_name_order = [{name: counts[name] for name in names}
                     for counts in (initial, final, thresholds)]
    return FeatureSummary(*in_name_order, time.perf_counter() - start)


@dataclass(frozen=True)
class ExtractedChunk:
    """What one extraction task found: per image name its final keypoints (n, 6) float32
    and descriptors (n, 128) uint8, its keypoint count at the default threshold, and the
    peak threshold of the final features."""

    features: dict[str, tuple[np.ndarray, np.ndarray]]
    initial_keypoints: dict[str, int]
    peak_thresholds: dict[str, float]


def extract_chunk(source: ImageSource, names: list[str], options: FeatureOptions,
                  num_threads: int) -> ExtractedChunk:
    """The task: SIFT of `names` at COLMAP's peak threshold, then the adaptive rule, in
    `num_threads` threads. `source`: where this process reads the images (an
    executor's image_sources)."""
    with source.local() as (image_path, mask_path):
        extract = options.extractor(image_path, mask_path, num_threads)
        found = extract(names, DEFAULT_PEAK_THRESHOLD)
        initial = {name: len(found[name][0]) for name in names}
        thresholds = dict.fromkeys(names, DEFAULT_PEAK_THRESHOLD)
        low = [name for name in names if initial[name] < options.min_num_keypoints]
        if low:
            found.update(reextract(extract, low, options.min_num_keypoints, thresholds))
    features = {name: (np.asarray(keypoints, np.float32), np.asarray(descriptors.data, np.uint8))
                for name, (keypoints, descriptors) in found.items()}
    return ExtractedChunk(features, initial, thresholds)


def extraction_options(peak_threshold: float, domain_size_pooling: bool,
                       num_threads: int) -> pycolmap.FeatureExtractionOptions:
    """CPU SIFT in the task's threads (said explicitly, which also spares COLMAP's
    memory warning)."""
    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = num_threads
    options.sift.domain_size_pooling = domain_size_pooling
    options.sift.peak_threshold = peak_threshold
    return options


def check_new_database(database_path: Path) -> None:
    """Features go into a database without images: mixing runs would mix thresholds."""
    if not database_path.parent.is_dir():
        raise UserError(f"folder of the database not found: {database_path.parent}")
    if database_path.exists():
        db = pycolmap.Database.open(database_path)
        try:
            num_images = db.num_images()
        finally:
            db.close()
        if num_images:
            raise UserError(f"database {database_path} already holds {num_images} images; "
                            "extract into a new database")


def reextract(extract: Extractor, names: list[str], min_num_keypoints: int,
              thresholds: dict[str, float]) -> dict[str, Features]:
    """Halve the peak threshold of the images still short of keypoints until each has
    enough or the floor is reached; updates `thresholds`, returns the last features."""
    features: dict[str, Features] = {}
    pending = list(names)
    threshold = DEFAULT_PEAK_THRESHOLD
    while pending and threshold > MIN_PEAK_THRESHOLD:
        threshold = max(threshold / 2, MIN_PEAK_THRESHOLD)
        features.update(extract(pending, threshold))
        thresholds.update(dict.fromkeys(pending, threshold))
        pending = [name for name in pending if len(features[name][0]) < min_num_keypoints]
    return features


def extract_to_memory(image_path: str | os.PathLike, reader: pycolmap.ImageReaderOptions,
                      names: list[str], peak_threshold: float, *,
                      domain_size_pooling: bool, num_threads: int) -> dict[str, Features]:
    """Keypoints and descriptors of `names` from pycolmap's extractor on a scratch
    database (one camera per image there: only the features are kept)."""
    with OwnedTemporaryDirectory("colmap-ext-sift-") as scratch:
        database_path = Path(scratch) / "database.db"
        with quiet_colmap_logs():
            pycolmap.extract_features(database_path, image_path, image_names=names,
                                      camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                      reader_options=reader,
                                      extraction_options=extraction_options(
                                          peak_threshold, domain_size_pooling, num_threads),
                                      device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database_path) as db:
            ids = {image.name: image.image_id for image in db.read_all_images()}
            missing = [name for name in names if name not in ids]
            if missing:
                again = "" if peak_threshold == DEFAULT_PEAK_THRESHOLD \
                    else f" again (peak threshold {peak_threshold:g})"
                raise UserError(f"COLMAP could not extract features from {missing[0]}{again}"
                                + (f" (and {len(missing) - 1} more)" if len(missing) > 1
                                   else ""))
            return {name: (db.read_keypoints(ids[name]), db.read_descriptors(ids[name]))
                    for name in names}


def extract_cube_faces_to_memory(image_path: str | os.PathLike,
                                 mask_path: str | os.PathLike | None, faces: CubeFaces,
                                 names: list[str], peak_threshold: float, *,
                                 domain_size_pooling: bool,
                                 num_threads: int) -> dict[str, Features]:
    """Keypoints (in panorama pixels) and descriptors of the panoramas `names`, from
    pycolmap's extractor on their cube faces: each face's own keypoints (panorama.py), not
    under the panorama's mask, and of them the MAX_NUM_FEATURES largest detections, as
    COLMAP keeps on one image."""
    face_names = {name: [f"{index}_{face}.png" for face in range(len(FACE_FORWARD_DOWN))]
                  for index, name in enumerate(names)}
    with OwnedTemporaryDirectory("colmap-ext-cube-faces-") as scratch:
        for name in names:
            panorama = read_grey(Path(image_path) / name)
            for face_name, image in zip(face_names[name], faces.render(panorama)):
                if not cv2.imwrite(str(Path(scratch) / face_name), image,
                                   [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise UserError(f"cannot write a cube face of {name} into {scratch}")
        reader = pycolmap.ImageReaderOptions(
            camera_model="SIMPLE_PINHOLE",
            camera_params=",".join(repr(p) for p in (faces.focal, faces.size / 2, faces.size / 2)))
        # One extractor per face: pycolmap 4.2.1's CPU SIFT reuses its filter across images
        # of one size, and a face then loses keypoints after a face with few (a blob
        # found alone, missed after a near-empty face).
        found: dict[str, Features] = {}
        for face_name in (face_name for of_one in face_names.values() for face_name in of_one):
            found.update(extract_to_memory(scratch, reader, [face_name], peak_threshold,
                                           domain_size_pooling=domain_size_pooling,
                                           num_threads=num_threads))
    features: dict[str, Features] = {}
    for name in names:
        keypoints, descriptors = [], []
        for face, face_name in enumerate(face_names[name]):
            face_keypoints, face_descriptors = found[face_name]
            mapped, owned = faces.to_panorama(face, face_keypoints)
            keypoints.append(mapped[owned])
            descriptors.append(np.asarray(face_descriptors.data, np.uint8)[owned])
        all_keypoints, all_descriptors = np.concatenate(keypoints), np.concatenate(descriptors)
        if mask_path is not None:
            kept = inside_mask(read_grey(Path(mask_path) / f"{name}.png"), all_keypoints[:, :2])
            all_keypoints, all_descriptors = all_keypoints[kept], all_descriptors[kept]
        largest = largest_detections(all_keypoints, MAX_NUM_FEATURES)
        features[name] = (all_keypoints[largest], pycolmap.FeatureDescriptors(
            pycolmap.FeatureExtractorType.SIFT, all_descriptors[largest]))
    return features


def largest_detections(keypoints: np.ndarray, max_num_features: int) -> np.ndarray:
    """Which keypoints (n, 6) belong to the `max_num_features` largest detections, as COLMAP
    counts them: the keypoints of one place (its orientations) are one detection."""
    _, detection = np.unique(keypoints[:, :2], axis=0, return_inverse=True)
    detection = detection.reshape(-1)
    scales = np.zeros(detection.max(initial=-1) + 1)
    np.maximum.at(scales, detection, keypoint_scales(keypoints))
    return np.isin(detection, np.argsort(-scales, kind="stable")[:max_num_features])


def read_grey(path: Path) -> np.ndarray:
    """An 8-bit grey image as COLMAP reads it (EXIF orientation not applied)."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise UserError(f"cannot read image {path}")
    return image
