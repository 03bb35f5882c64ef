"""Writing COLMAP models the way `colmap mapper` lays them out (OUTPUT/0, OUTPUT/1, ...),
atomically: models are written to a temporary folder beside the target and renamed
into place, so an interrupted run never leaves a half-written model where one stood."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pycolmap

from colmap_ext.errors import UserError

OUTPUT_TYPES = ("BIN", "TXT")


def check_output_path(output_path: str | Path, overwrite: bool) -> Path:
    """Refuse a file in the way, or an existing model without `overwrite`."""
    output_path = Path(output_path)
    if output_path.exists() and not output_path.is_dir():
        raise UserError(f"output path is a file, not a folder: {output_path}")
    if (output_path / "0").exists() and not overwrite:
        raise UserError(f"{output_path / '0'} already holds a model; pass --overwrite to replace it")
    try:
        output_path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create output folder {output_path}: {exc.strerror}") from None
    try:  # before any work; os.access says yes to root even where no one may write
        os.rmdir(tempfile.mkdtemp(prefix=".colmap-ext-", dir=output_path))
    except OSError as exc:
        raise UserError(f"cannot write in {output_path}: {exc.strerror}") from None
    return output_path


@contextlib.contextmanager
def output_folder(output_path: str | Path, overwrite: bool) -> Iterator[Path]:
    """check_output_path, and a folder it had to create removed again if the work inside
    fails before writing anything to it."""
    existed = Path(output_path).exists()
    output_path = check_output_path(output_path, overwrite)
    try:
        yield output_path
    except BaseException:
        if not existed:
            with contextlib.suppress(OSError):
                output_path.rmdir()  # only when empty
        raise


def read_model(path: str | Path) -> pycolmap.Reconstruction:
    """A COLMAP model folder (BIN or TXT), e.g. one to continue; a UserError if it is
    missing or cannot be read."""
    path = Path(path)
    found = {f.name for f in path.iterdir()} if path.is_dir() else set()
    if not any({f"cameras.{e}", f"images.{e}", f"points3D.{e}"} <= found for e in ("bin", "txt")):
        raise UserError(f"no COLMAP model in {path}: expected cameras, images and points3D "
                        f"(.bin or .txt)")
    try:
        return pycolmap.Reconstruction(path)
    except Exception as exc:  # pycolmap: ValueError, IndexError, RuntimeError on bad files
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise UserError(f"cannot read the model in {path}: {reason}") from None


def write_models(reconstructions: list[pycolmap.Reconstruction], output_path: str | Path,
                 output_type: str = "BIN") -> None:
    """Write models as output_path/0, 1, ... replacing any numbered models there."""
    output_path = Path(output_path)
    if output_type.upper() not in OUTPUT_TYPES:
        raise UserError(f"--output_type must be BIN or TXT, got {output_type}")
    try:
        staging = Path(tempfile.mkdtemp(prefix=".colmap-ext-", dir=output_path))
    except OSError as exc:
        raise UserError(f"cannot write in {output_path}: {exc.strerror}") from None
    try:
        new = staging / "new"
        for index, reconstruction in enumerate(reconstructions):
            folder = new / str(index)
            folder.mkdir(parents=True)
            if output_type.upper() == "TXT":
                reconstruction.write_text(folder)
            else:
                reconstruction.write_binary(folder)
            _check_written(reconstruction, folder)
        _swap_in(new, output_path, staging / "old")
    except (OSError, ValueError, RuntimeError) as exc:  # pycolmap: ValueError on a failed open
        raise UserError(f"could not write the model to {output_path}: "
                        f"{getattr(exc, 'strerror', None) or exc}; the previous model is unchanged") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _check_written(reconstruction: pycolmap.Reconstruction, folder: Path) -> None:
    """pycolmap does not check its writes: a full disk leaves truncated files and no error.
    Read the model back before it replaces anything."""
    def counts(model: pycolmap.Reconstruction) -> tuple[int, ...]:
        return (model.num_cameras(), model.num_images(), model.num_reg_images(),
                model.num_points3D())

    try:
        complete = counts(pycolmap.Reconstruction(folder)) == counts(reconstruction)
    except Exception:  # ValueError, IndexError... on a truncated file
        complete = False
    if not complete:
        raise OSError(f"the model written to {folder.name} reads back incomplete (is the disk full?)")


def _swap_in(new: Path, output_path: Path, old: Path) -> None:
    """Move the numbered models in `new` into `output_path`, the previous ones out to
    `old`; on failure, put everything back as it was."""
    old.mkdir()
    moved_out: list[Path] = []
    moved_in: list[Path] = []
    try:
        for previous in sorted(p for p in output_path.iterdir() if p.is_dir() and p.name.isdigit()):
            previous.rename(old / previous.name)
            moved_out.append(previous)
        for folder in sorted(new.iterdir(), key=lambda p: int(p.name)):
            folder.rename(output_path / folder.name)
            moved_in.append(output_path / folder.name)
    except BaseException:  # OSError, or Ctrl-C between two renames
        for folder in moved_in:
            shutil.rmtree(folder, ignore_errors=True)
        for previous in moved_out:
            (old / previous.name).rename(previous)
        raise


def write_json(data: dict, path: str | Path) -> None:
    """Write JSON through a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise UserError(f"could not write {path}: {exc.strerror or exc}") from None
