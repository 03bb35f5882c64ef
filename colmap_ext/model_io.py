"""Writing a command's result into its output folder safely, and COLMAP models the way
`colmap mapper` lays them out (OUTPUT/0, OUTPUT/1, ...).

Every command that writes builds its whole result in a temporary folder beside the
target (the same file system) and moves it into place at the end (`replacing`): an
interrupt, a full disk or an error at any moment leaves either the whole previous result
or the whole new one. `--overwrite` replaces only what the command itself writes,
recognised by name and content (`OutputLayout`); a lock file keeps a second run out of
the folder while one writes it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import mmap
import os
import re
import signal
import struct
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from colmap_ext.database import NUM_PARAMS
from colmap_ext.errors import UserError
from colmap_ext.temporary import OwnedTemporaryDirectory

OUTPUT_TYPES = ("BIN", "TXT")
# The lock file of an output folder being written, and the prefix of our temporary folders.
LOCK_NAME = ".colmap-ext.lock"
TEMPORARY_PREFIX = ".colmap-ext-"
# The files of a COLMAP model folder (pycolmap 4 writes rigs and frames; COLMAP's mapper,
# a project.ini).
MODEL_FILES = frozenset({f"{name}.{ext}" for ext in ("bin", "txt")
                         for name in ("cameras", "images", "points3D", "rigs", "frames")}
                        | {"project.ini"})


def is_model_folder(path: Path) -> bool:
    """A COLMAP model: cameras, images and points3D (.bin or .txt), and no other files."""
    if not path.is_dir() or path.is_symlink():
        return False
    names = {entry.name for entry in path.iterdir() if entry.is_file() and not entry.is_symlink()}
    complete = any({f"cameras.{e}", f"images.{e}", f"points3D.{e}"} <= names
                   for e in ("bin", "txt"))
    return complete and names <= MODEL_FILES and len(names) == len(list(path.iterdir()))


def holds_only(pattern: str) -> Callable[[Path], bool]:
    """A folder whose files, in it and below, all have names matching `pattern`."""
    def recognise(path: Path) -> bool:
        return path.is_dir() and not path.is_symlink() and all(
            entry.is_dir() or (entry.is_file() and re.fullmatch(pattern, entry.name))
            for entry in path.rglob("*"))
    return recognise


def is_file(path: Path) -> bool:
    return path.is_file() and not path.is_symlink()


@dataclass(frozen=True)
class OutputLayout:
    """What a command writes into its output folder: `entries`, names with a test that an
    existing entry of that name is the command's own; `numbered`, the test for numbered
    entries (model folders), of which --overwrite replaces only those the run writes again
    and those the earlier run recorded in its `summary` (JSON, "num_models"). Nothing else
    in the folder is touched."""

    result: str  # what the folder holds, for messages: "a model"
    entries: dict[str, Callable[[Path], bool]]
    numbered: Callable[[Path], bool] | None = None
    summary: str | None = None

    def recognise(self, path: Path) -> bool | None:
        """True: the command's own, replaced by --overwrite; False: the command's name but
        not its content; None: not the command's."""
        if self.numbered is not None and path.name.isdigit():
            return self.numbered(path)
        test = self.entries.get(path.name)
        return None if test is None else test(path)

    def is_output(self, path: Path) -> bool:
        """A folder holding this command's output and nothing else (e.g. a workspace's sparse/)."""
        return path.is_dir() and not path.is_symlink() and \
            all(self.recognise(entry) for entry in path.iterdir())


MAPPER_OUTPUT = OutputLayout("a model", {"mapper_summary.json": is_file}, numbered=is_model_folder,
                             summary="mapper_summary.json")


def _check_output_path(output_path: str | Path) -> Path:
    """The output folder, refused when empty or a file."""
    if not str(output_path).strip():
        raise UserError("the output path is empty")
    output_path = Path(output_path)
    if output_path.exists() and not output_path.is_dir():
        raise UserError(f"output path is a file, not a folder: {output_path}")
    return output_path


@contextlib.contextmanager
def replacing(output_path: str | Path, layout: OutputLayout, overwrite: bool) -> Iterator[Path]:
    """Yield an empty folder beside `output_path` to build the command's whole result in;
    when the block ends without an error, its entries replace the command's entries in
    `output_path` (with `overwrite`; without it, an earlier result is refused before any
    work). On an error or an interrupt nothing in `output_path` changes, and a folder
    created for the run is removed again."""
    output_path = _check_output_path(output_path)
    created = not output_path.exists()
    try:
        output_path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create output folder {output_path}: {exc.strerror}") from None
    try:
        with _locked(output_path):
            previous = _previous_result(output_path, layout, overwrite)
            num_recorded = _numbered_recorded(output_path, layout)
            try:  # and the leftovers of a killed run removed
                scratch = OwnedTemporaryDirectory(TEMPORARY_PREFIX, output_path)
            except OSError as exc:
                raise UserError(f"cannot write in {output_path}: {exc.strerror}") from None
            staging = Path(scratch.name)
            try:
                (staging / "new").mkdir()
                yield staging / "new"
            except BaseException:
                with _signals_deferred():  # a second Ctrl-C does not stop the clean-up
                    scratch.cleanup()
                raise
            with _signals_deferred():
                try:
                    _swap_in(staging / "new", output_path,
                             _replaced(previous, staging / "new", num_recorded), staging / "old")
                finally:
                    scratch.cleanup()
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                output_path.rmdir()  # only when empty
        raise


def moved(path: str | Path, new: Path, final: Path) -> Path:
    """Where `path` will be once `new`, the folder `replacing` yielded, is moved into
    `final`: for paths a command records or prints. A path outside `new` stays as it is."""
    path = Path(path)
    return final / path.relative_to(new) if path.is_relative_to(new) else path


def _previous_result(output_path: Path, layout: OutputLayout, overwrite: bool) -> list[Path]:
    """The command's entries already in `output_path`: refused without `overwrite`, and
    refused always when an entry of the command's name is not the command's."""
    previous = []
    for entry in sorted(output_path.iterdir()):
        if entry.name == LOCK_NAME or entry.name.startswith(TEMPORARY_PREFIX):
            continue
        ours = layout.recognise(entry)
        if ours is False:
            raise UserError(f"{entry} is not {layout.result} written by colmap-ext; it is left "
                            "alone and the run refused: move it away or choose another output path")
        if ours:
            previous.append(entry)
    if previous and not overwrite:
        raise UserError(f"{output_path} already holds {layout.result}; pass --overwrite to "
                        "replace it")
    return previous


def _numbered_recorded(output_path: Path, layout: OutputLayout) -> int:
    """How many numbered entries (0, 1, ...) the earlier run in `output_path` recorded as its
    own in its summary; 0 without a readable one (e.g. a model `colmap mapper` wrote)."""
    if layout.summary is None:
        return 0
    try:
        count = json.loads((output_path / layout.summary).read_text(encoding="utf-8"))["num_models"]
    except (OSError, ValueError, TypeError, KeyError):
        return 0
    return count if isinstance(count, int) else 0


def _replaced(previous: list[Path], new: Path, num_recorded: int) -> list[Path]:
    """The `previous` entries that the result in `new` replaces: every named one, and of
    the numbered ones (models) those it writes again or the earlier run recorded as its
    own (the first `num_recorded`)."""
    return [entry for entry in previous if not entry.name.isdigit()
            or int(entry.name) < num_recorded or (new / entry.name).exists()]


@contextlib.contextmanager
def _locked(output_path: Path) -> Iterator[None]:
    """Hold the output folder's lock file: another run that tries is refused with the
    holder's pid. The kernel releases the lock when its process ends, however it ends, so a
    lock file left by a killed run is taken over."""
    path = output_path / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise UserError(f"cannot write in {output_path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            if exc.errno not in (errno.EAGAIN, errno.EACCES):
                raise UserError(f"cannot lock {path}: {exc.strerror}") from None
            raise UserError(f"{output_path} is being written by another colmap-ext run "
                            f"(pid {holder})") from None
        try:  # the holder before us may have removed the file we opened
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while locked: a waiting run then opens a new file
        os.close(fd)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block is done (only the main thread sets handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    deferred = [signum for signum, handler in previous.items()
                if handler not in (None, signal.SIG_IGN)]
    for signum in deferred:
        signal.signal(signum, lambda number, frame: received.append(number))
    try:
        yield
    finally:
        for signum in deferred:
            signal.signal(signum, previous[signum])
        for signum in received[:1]:
            signal.raise_signal(signum)


def _swap_in(new: Path, output_path: Path, previous: list[Path], old: Path) -> None:
    """Move the `previous` entries out to `old`, and the entries of `new` into
    `output_path`; on failure, put everything back as it was."""
    old.mkdir()
    moved_out: list[Path] = []
    moved_in: list[Path] = []
    try:
        for entry in previous:
            entry.rename(old / entry.name)
            moved_out.append(entry)
        for entry in sorted(new.iterdir()):
            entry.rename(output_path / entry.name)
            moved_in.append(output_path / entry.name)
    except OSError as exc:
        for entry in moved_in:
            entry.rename(new / entry.name)
        for entry in moved_out:
            (old / entry.name).rename(entry)
        raise UserError(f"could not move the result into {output_path}: {exc.strerror or exc}; "
                        "the previous result is unchanged") from None


def read_model(path: str | Path) -> pycolmap.Reconstruction:
    """A COLMAP model folder (BIN or TXT); a one-line UserError if it is missing or cannot
    be read."""
    path = Path(path)
    found = {f.name for f in path.iterdir()} if path.is_dir() else set()
    if not any({f"cameras.{e}", f"images.{e}", f"points3D.{e}"} <= found for e in ("bin", "txt")):
        kind = "not a readable COLMAP model" if path.is_dir() else "model not found"
        raise UserError(f"no COLMAP model in {path}: expected cameras, images and points3D "
                        f"(.bin or .txt) ({kind})")
    try:
        check_binary_model(path)
    except OSError as exc:
        raise UserError(f"cannot read the model in {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise UserError(f"cannot read the model in {path}: {exc} (not a readable COLMAP "
                        "model)") from None
    try:
        return pycolmap.Reconstruction(path)
    except Exception as exc:  # pycolmap: ValueError, IndexError, RuntimeError on bad files
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"cannot read the model in {path}: {reason} (not a readable COLMAP "
                        "model)") from None


def write_models(reconstructions: list[pycolmap.Reconstruction], output_path: str | Path,
                 output_type: str = "BIN") -> None:
    """Write models as output_path/0, 1, ... into a new folder (`replacing`'s)."""
    output_path = Path(output_path)
    if output_type.upper() not in OUTPUT_TYPES:
        raise UserError(f"--output_type must be BIN or TXT, got {output_type}")
    try:
        for index, reconstruction in enumerate(reconstructions):
            folder = output_path / str(index)
            folder.mkdir(parents=True)
            if output_type.upper() == "TXT":
                reconstruction.write_text(folder)
            else:
                reconstruction.write_binary(folder)
            _check_written(reconstruction, folder)
    except (OSError, ValueError, RuntimeError) as exc:  # pycolmap: ValueError on a failed open
        raise UserError(f"could not write the model to {output_path}: "
                        f"{getattr(exc, 'strerror', None) or exc}; the previous model is unchanged") from None


def _check_written(reconstruction: pycolmap.Reconstruction, folder: Path) -> None:
    """pycolmap does not check its writes: a full disk leaves truncated files and no error.
    Read the model back before it replaces anything."""
    def counts(model: pycolmap.Reconstruction) -> tuple[int, ...]:
        return (model.num_cameras(), model.num_images(), model.num_reg_images(),
                model.num_points3D())

    try:
        check_binary_model(folder)
        complete = counts(pycolmap.Reconstruction(folder)) == counts(reconstruction)
    except Exception:  # ValueError, IndexError... on a truncated file
        complete = False
    if not complete:
        raise OSError(f"the model written to {folder.name} reads back incomplete (is the disk full?)")


class _BinaryReader:
    """Reads a COLMAP binary model file front to back, every count checked against the bytes
    left, so that a truncated or garbage file is a ValueError naming it."""

    def __init__(self, path: Path, data: bytes | mmap.mmap) -> None:
        self.path, self.data, self.offset = path, data, 0

    def skip(self, size: int) -> None:
        if self.offset + size > len(self.data):
            raise ValueError(f"{self.path.name} is truncated: it ends at byte {len(self.data)}, "
                             f"inside the record at byte {self.offset}")
        self.offset += size

    def number(self, layout: struct.Struct) -> int:
        start = self.offset
        self.skip(layout.size)
        return layout.unpack_from(self.data, start)[0]

    def count(self, layout: struct.Struct, record_size: int, what: str) -> int:
        """A count of records of at least `record_size` bytes each that must fit in the file."""
        count = self.number(layout)
        if count * record_size > len(self.data) - self.offset:
            raise ValueError(f"{self.path.name} is truncated or corrupt: it announces {count} "
                             f"{what}, more than its {len(self.data) - self.offset} remaining "
                             "bytes hold")
        return count

    def name(self) -> None:
        end = self.data.find(b"\0", self.offset)
        self.skip(len(self.data) - self.offset + 1 if end < 0 else end + 1 - self.offset)


_INT32, _UINT32, _UINT64 = struct.Struct("<i"), struct.Struct("<I"), struct.Struct("<Q")
_UINT8 = struct.Struct("<B")
_POSE_BYTES = 7 * 8  # quaternion w, x, y, z and translation x, y, z, doubles


def check_binary_model(folder: Path) -> None:
    """Walk the binary files of the model in `folder` (COLMAP's layout, as pycolmap 4 reads
    it) and raise a ValueError naming the first that does not hold what its counts say:
    pycolmap reserves memory by a count read from past the end of a truncated file and then
    allocates without bound, and it ends in `unordered_map::at` on an image without a frame.
    A text model, or no binary one: nothing to check."""
    names = ("cameras", "images", "points3D", "rigs", "frames")
    files = {name: folder / f"{name}.bin" for name in names}
    if not all(files[name].is_file() for name in names[:3]):
        return
    readers = {}
    with contextlib.ExitStack() as stack:
        for name, path in files.items():
            if path.is_file():
                handle = stack.enter_context(open(path, "rb"))
                size = os.fstat(handle.fileno()).st_size
                readers[name] = _BinaryReader(path, stack.enter_context(
                    mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)) if size else b"")
        frame_images = _check_rigs_and_frames(readers.get("rigs"), readers.get("frames"))
        _check_cameras(readers["cameras"])
        _check_images(readers["images"], frame_images)
        _check_points(readers["points3D"])


def _check_rigs_and_frames(rigs: _BinaryReader | None,
                           frames: _BinaryReader | None) -> set[int] | None:
    """The image ids the frames hold; None for a model without rigs and frames (COLMAP 3)."""
    num_rigs = 0 if rigs is None else rigs.count(_UINT64, 8, "rigs")
    for _ in range(num_rigs):
        rigs.skip(4)  # rig id
        num_sensors = rigs.count(_UINT32, 8, "sensors")
        rigs.skip(8 if num_sensors else 0)  # the reference sensor: type, id
        for _ in range(max(num_sensors - 1, 0)):
            rigs.skip(8)  # type, id
            rigs.skip(_POSE_BYTES if rigs.number(_UINT8) else 0)
    num_frames = 0 if frames is None else frames.count(_UINT64, 68, "frames")
    if num_rigs == 0 and num_frames == 0:
        return None
    camera = int(pycolmap.SensorType.CAMERA.value)
    image_ids = set()
    for _ in range(num_frames):
        frames.skip(8 + _POSE_BYTES)  # frame id, rig id, rig_from_world
        for _ in range(frames.count(_UINT32, 16, "images of a frame")):
            sensor_type = frames.number(_INT32)
            frames.skip(4)  # sensor id
            data_id = frames.number(_UINT64)
            if sensor_type == camera:
                image_ids.add(data_id)
    return image_ids


def _check_cameras(cameras: _BinaryReader) -> None:
    for _ in range(cameras.count(_UINT64, 24, "cameras")):
        camera_id, model_id = cameras.number(_UINT32), cameras.number(_INT32)
        if model_id not in NUM_PARAMS:
            raise ValueError(f"{cameras.path.name}: camera {camera_id} has model id {model_id}, "
                             "which is no COLMAP camera model")
        cameras.skip(16 + 8 * NUM_PARAMS[model_id])  # width, height, params


def _check_images(images: _BinaryReader, frame_images: set[int] | None) -> None:
    for _ in range(images.count(_UINT64, 73, "images")):
        image_id = images.number(_UINT32)
        if frame_images is not None and image_id not in frame_images:
            raise ValueError(f"{images.path.name} is corrupt: its image {image_id} is in no "
                             "frame of frames.bin")
        images.skip(_POSE_BYTES + 4)  # cam_from_world, camera id
        images.name()
        images.skip(24 * images.count(_UINT64, 24, "keypoints of an image"))


def _check_points(points: _BinaryReader) -> None:
    for _ in range(points.count(_UINT64, 51, "points")):
        points.skip(43)  # id, xyz, colour, error
        points.skip(8 * points.count(_UINT64, 8, "observations of a point"))


def check_output_file(path: str | Path, inputs: list[Path], overwrite: bool) -> None:
    """An output file of a command that writes single files: refused when it is a folder or
    one of the run's `inputs` (or inside one), and when it exists without `overwrite`."""
    path = Path(path)
    if any(path.resolve().is_relative_to(source.resolve()) for source in inputs):
        raise UserError(f"{path} is an input of this run; choose another output file")
    if path.is_dir():
        raise UserError(f"output path is a folder, not a file: {path}")
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise UserError(f"{path} exists; pass --overwrite to replace it")


def write_json(data: dict | list, path: str | Path) -> None:
    """Write JSON through a temporary file and a rename, so no reader sees half of it."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
        os.replace(temporary, path)
    except OSError as exc:
        with contextlib.suppress(OSError):  # e.g. the folder is a file: no temporary to remove
            temporary.unlink(missing_ok=True)
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
