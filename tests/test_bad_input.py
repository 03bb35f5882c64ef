"""Bad input through the real command line: every case runs `python -m colmap_ext` in a
subprocess and checks the exit code, one clear line on stderr, no traceback, and that
every input (and any previous model) is byte for byte what it was, with no stray files
(e.g. SQLite `-wal`/`-shm` files beside a database) and no temporary folders left.

An interrupted run (exit 130 or 143: `interrupted(marker, signal)` sends the signal once a
stage has begun) may print the stage's own log lines first; its last line is the one
message, and no stack dump follows. Inputs and the previous result stay byte for byte.

To add a case, write a builder under `@case(...)`: it makes the inputs in `env.inputs`
(hashed before and after the run) and returns the command's arguments.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pytest

CLI = [sys.executable, "-m", "colmap_ext"]
NOBODY = 65534
IS_ROOT = os.geteuid() == 0
# tqdm's bars: "registered:  50%|#####     | 3/6 [00:01<00:01, ...]", "pairs: 0pair [00:00, ...]"
PROGRESS_LINE = re.compile(r"\d+%\||\[\d+:\d\d[<,\]]")
TEMP_PREFIXES = (".colmap-ext-", "colmap-ext-")
INTERRUPTED_CODES = (128 + signal.SIGINT, 128 + signal.SIGTERM)
RING_PARAMS = [300.0, 300.0, 160.0, 120.0]  # PINHOLE, the rendered ring's camera


# ---------------------------------------------------------------- shared inputs


def write_png(path: Path, size: tuple[int, int] = (8, 8)) -> None:
    """The mapper reads point colours from the images. (Any PNG writer aborts in zlib's
    deflateEnd if pycolmap was loaded before zlib; pytest loads zlib first.)"""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.zeros(size[::-1], np.uint8))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Assets:
    """Inputs built once per session; cases copy what they use into their own folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        # HOME and MPLCONFIGDIR of the runs: matplotlib's font cache is built once, here.
        self.home = root / "home"
        self.home.mkdir()
        self.scenes: dict = {}

    def _synthetic(self, name: str, num_images: int, num_points: int) -> tuple[Path, Path, list[str]]:
        from colmap_ext.synthetic.database import scene_points, write_synthetic_database
        from colmap_ext.synthetic.scene import ring_scene

        folder = self.root / name
        scene = ring_scene(num_images=num_images, seed=3)
        folder.mkdir()
        write_synthetic_database(folder / "database.db", scene,
                                 scene_points(scene, num_points, seed=3), noise_px=0.5,
                                 outlier_ratio=0.2, seed=3)
        for image_name in scene.image_names:
            write_png(folder / "images" / image_name)
        self.scenes[name] = scene
        return folder / "database.db", folder / "images", scene.image_names

    @cached_property
    def small(self) -> tuple[Path, Path, list[str]]:
        """6 views, 500 points: maps in under a second."""
        return self._synthetic("small", 6, 500)

    @cached_property
    def big(self) -> tuple[Path, Path, list[str]]:
        """36 views, 4000 points: maps in about 3 s, time to press Ctrl-C."""
        return self._synthetic("big", 36, 4000)

    @cached_property
    def model(self) -> Path:
        """OUT/ of a mapper run on `small`: OUT/0 and OUT/mapper_summary.json."""
        from colmap_ext.mapper import MapperOptions, run

        database, images, _ = self.small
        out = self.root / "model"
        run(database, images, out, MapperOptions(seed=0), progress=False)
        return out

    @cached_property
    def ground_truth(self) -> Path:
        """Middlebury *_par.txt of the small scene."""
        from colmap_ext.synthetic.render import write_par_file

        self.small  # noqa: B018 (makes the scene)
        path = self.root / "small_par.txt"
        write_par_file(self.scenes["small"], path)
        return path

    @cached_property
    def ring(self) -> tuple[Path, Path]:
        """10 rendered 320x240 views of the ring scene (`reconstruct` takes about 6 s) and
        their ground truth (Middlebury *_par.txt)."""
        import pycolmap

        from colmap_ext.synthetic.render import render_images, write_par_file
        from colmap_ext.synthetic.scene import ring_scene

        camera = pycolmap.Camera(camera_id=1, model="PINHOLE", width=320, height=240,
                                 params=RING_PARAMS)
        scene = ring_scene(num_images=10, seed=0, camera=camera)
        render_images(scene, self.root / "ring", supersample=1)
        write_par_file(scene, self.root / "ring_par.txt")
        return self.root / "ring", self.root / "ring_par.txt"

    @cached_property
    def workspace(self) -> Path:
        """WS/ of `reconstruct` on `ring`: database.db, sparse/0 ..., reconstruct_summary.json."""
        from colmap_ext.reconstruct import main

        main(self.ring[0], self.root / "workspace", "PINHOLE", ",".join(map(str, RING_PARAMS)), seed=0)
        return self.root / "workspace"

    @cached_property
    def rig_database(self) -> Path:
        """COLMAP's generator: one rig of 2 cameras 0.1 apart (the first the reference),
        4 frames, 0.5 px noise."""
        from colmap_ext.synthetic.pycolmap_generator import write_pycolmap_dataset

        path = self.root / "rig" / "database.db"
        path.parent.mkdir()
        write_pycolmap_dataset(path, None, 0, 8, 0.5, 300, 2, num_rigs=1, rig_baseline=0.1)
        return path

    @cached_property
    def colmap38(self) -> tuple[Path, Path, str]:
        """A database written by COLMAP 3.8 (Debian's `colmap`), or by hand in its schema."""
        folder = self.root / "colmap38"
        folder.mkdir()
        version = shutil.which("colmap") and subprocess.run(
            ["colmap", "-h"], capture_output=True, text=True).stdout
        if version and "COLMAP 3.8" in version:
            return (*make_colmap38_database(folder), "written by COLMAP 3.8 (colmap feature_extractor)")
        database, images, _ = self.small
        shutil.copytree(images, folder / "images")
        make_38_schema_database(database, folder / "database.db")
        return folder / "database.db", folder / "images", "hand-built in COLMAP 3.8's schema"


def make_colmap38_database(folder: Path) -> tuple[Path, Path]:
    """3 rendered 320x240 views, `colmap feature_extractor` + `exhaustive_matcher` (3.8)."""
    import pycolmap

    from colmap_ext.synthetic.render import render_images
    from colmap_ext.synthetic.scene import Scene, ring_scene

    camera = pycolmap.Camera(camera_id=1, model="PINHOLE", width=320, height=240,
                             params=[300.0, 300.0, 160.0, 120.0])
    ring = ring_scene(num_images=36, seed=3, camera=camera)
    scene = Scene(ring.camera, ring.cams_from_world[:3], ring.image_names[:3], ring.quads)
    render_images(scene, folder / "images", seed=0, supersample=1)
    database = folder / "database.db"
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    for command in (["feature_extractor", "--image_path", str(folder / "images"),
                     "--ImageReader.camera_model", "PINHOLE", "--ImageReader.single_camera", "1",
                     "--ImageReader.camera_params", "300,300,160,120",
                     "--SiftExtraction.use_gpu", "0"],
                    ["exhaustive_matcher", "--SiftMatching.use_gpu", "0"]):
        subprocess.run(["colmap", *command, "--database_path", str(database)], check=True,
                       capture_output=True, env=env, timeout=120)
    return database, folder / "images"


# COLMAP 3.8's schema (from a database its feature_extractor wrote): no rigs, frames,
# pose_priors; images hold pose priors; descriptors have no type column.
SCHEMA_38 = """
CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL,
  width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL);
CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE,
  camera_id INTEGER NOT NULL, prior_qw REAL, prior_qx REAL, prior_qy REAL, prior_qz REAL,
  prior_tx REAL, prior_ty REAL, prior_tz REAL,
  CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
  FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE UNIQUE INDEX index_name ON images(name);
CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB);
CREATE TABLE two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB);
"""


def make_38_schema_database(source: Path, target: Path) -> None:
    """The features and matches of a 4.x database in COLMAP 3.8's schema."""
    with closing(sqlite3.connect(target)) as conn:
        conn.executescript(SCHEMA_38)
        conn.execute("ATTACH DATABASE ? AS src", (str(source),))
        conn.executescript("""
            INSERT INTO cameras
              SELECT camera_id, model, width, height, params, prior_focal_length FROM src.cameras;
            INSERT INTO images (image_id, name, camera_id) SELECT image_id, name, camera_id FROM src.images;
            INSERT INTO keypoints SELECT image_id, rows, cols, data FROM src.keypoints;
            INSERT INTO descriptors SELECT image_id, rows, cols, data FROM src.descriptors;
            INSERT INTO matches SELECT pair_id, rows, cols, data FROM src.matches;
            PRAGMA user_version = 3800;
        """)
        conn.commit()
        conn.execute("DETACH DATABASE src")
        conn.execute("PRAGMA journal_mode = WAL")  # as COLMAP leaves its databases


@pytest.fixture(scope="session")
def assets(tmp_path_factory) -> Assets:
    return Assets(tmp_path_factory.mktemp("bad_input_assets"))


@pytest.fixture(scope="session")
def commands(assets) -> set[str]:
    """The subcommands `colmap-ext --help` lists, each of which starts (`colmap-ext NAME
    --help` imports its module). A CLI or a subcommand that cannot start, e.g. on an import
    error, fails every case instead of skipping it."""
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=120,
                              env={**os.environ, "HOME": str(assets.home),
                                   "MPLCONFIGDIR": str(assets.home)})

    result = run("--help")
    assert result.returncode == 0, f"`colmap-ext --help` is broken:\n{result.stderr}"
    names = sorted(set(re.findall(r"^    (\w+)\s", result.stdout, re.MULTILINE)))
    with ThreadPoolExecutor(max_workers=2) as pool:
        helps = dict(zip(names, pool.map(lambda name: run(name, "--help"), names)))
    broken = {name: shown.stderr.strip().splitlines()[-1:] for name, shown in helps.items()
              if shown.returncode != 0}
    assert not broken, f"subcommands that cannot start: {broken}"
    return set(names)


@pytest.fixture(scope="session")
def unprivileged() -> str | None:
    """Why permission cases cannot run here, or None. As root, chmod does not bite, so those
    cases run the CLI as the user `nobody` on a folder it owns."""
    if not IS_ROOT:
        return None
    home = tempfile.mkdtemp(prefix="bad-input-probe-")
    try:
        os.chmod(home, 0o755)
        os.chown(home, NOBODY, NOBODY)
        result = subprocess.run([*CLI, "--version"], capture_output=True, text=True, timeout=60,
                                user=NOBODY, group=NOBODY, extra_groups=[], cwd=home,
                                env={**os.environ, "HOME": home, "MPLCONFIGDIR": home})
        problem = result.stderr.strip().splitlines()[-1:] if result.returncode else None
    except OSError as exc:
        problem = [str(exc)]
    finally:
        shutil.rmtree(home, ignore_errors=True)
    if problem is not None:
        return ("running as root, where permissions do not bite, and the user nobody cannot "
                f"run this Python ({' '.join(problem)}); the /proc and /sys cases stand in")
    return None


# ---------------------------------------------------------------- the case table


@dataclass
class Env:
    """One case's folder: inputs (hashed before and after), out, and a TMPDIR of its own."""

    root: Path
    assets: Assets
    home: Path | None = None  # HOME of the run: the shared one unless it runs as nobody
    protected: list[Path] = field(default_factory=list)  # also hashed, e.g. a previous model
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.home is None:
            self.home = self.assets.home
        for folder in (self.inputs, self.tmp, self.home):
            folder.mkdir(parents=True, exist_ok=True)

    inputs = property(lambda self: self.root / "in")
    out = property(lambda self: self.root / "out")
    tmp = property(lambda self: self.root / "tmp")

    def copy(self, source: Path, name: str | None = None) -> Path:
        target = self.inputs / (name or source.name)
        (shutil.copytree if source.is_dir() else shutil.copyfile)(source, target)
        return target

    def small_db(self) -> Path:
        return self.copy(self.assets.small[0])

    def images(self) -> Path:
        return self.copy(self.assets.small[1])

    def previous_model(self) -> Path:
        """OUT holding a model from an earlier run, protected like an input."""
        shutil.copytree(self.assets.model, self.out)
        self.protected.append(self.out)
        return self.out

    def mapper(self, database: Path | str, images: Path | str | None = None,
               out: Path | str | None = None, *extra: str) -> list[str]:
        return ["mapper", "--database_path", str(database),
                "--image_path", str(images if images is not None else self.images()),
                "--output_path", str(out if out is not None else self.out), *extra]

    def evaluate(self, model: Path | str | None = None, truth: Path | str | None = None,
                 *extra: str) -> list[str]:
        if model is None:
            model = self.copy(self.assets.model / "0", "model")
        if truth is None:
            truth = self.copy(self.assets.ground_truth)
        return ["evaluate", "--model_path", str(model), "--ground_truth", str(truth), *extra]


@dataclass(frozen=True)
class Case:
    id: str
    build: Callable[[Env], list[str]]  # makes the inputs, returns the arguments
    message: str  # a fragment of the last stderr line (of stdout when code is 0)
    code: int = 1
    command: str = "mapper"  # the subcommand run: the case fails if the CLI lacks it
    unprivileged: bool = False  # relies on file permissions: run as nobody when root
    run: Callable[[Env, list[str]], subprocess.CompletedProcess] | None = None  # custom runner
    after: Callable[[Env, subprocess.CompletedProcess], None] | None = None  # more checks
    xfail: str | None = None  # a known bug outside this suite's reach, until it is fixed


CASES: list[Case] = []


def case(id: str, message: str, code: int = 1, **options) -> Callable:
    def register(build: Callable[[Env], list[str]]) -> Callable:
        CASES.append(Case(id, build, message, code, **options))
        return build
    return register


def edit_database(path: Path, *statements: tuple) -> Path:
    """Run SQL on a crafted database (our own copy, not a user's)."""
    with closing(sqlite3.connect(path)) as conn:
        for statement in statements:
            conn.execute(*statement) if isinstance(statement, tuple) else conn.execute(statement)
        conn.commit()
    return path


# ---- paths


@case("db_missing", "database not found")
def _(env):
    return env.mapper(env.inputs / "nope.db")


@case("db_is_a_folder", "database path is a folder, not a file")
def _(env):
    (env.inputs / "database.db").mkdir()
    return env.mapper(env.inputs / "database.db")


@case("db_unreadable_chmod", "cannot read database", unprivileged=True)
def _(env):
    database = env.small_db()
    database.chmod(0)
    return env.mapper(database)


@case("db_unopenable_even_for_root", "cannot read database")
def _(env):
    # A regular file that no one can open for reading (write-only, EINVAL), root or not.
    return env.mapper("/proc/self/clear_refs")


@case("db_unreadable_even_for_root", "cannot read database")
def _(env):
    # A regular file that opens but whose offset 0 cannot be read (EIO), root or not.
    return env.mapper("/proc/self/mem")


@case("images_missing", "image path not found")
def _(env):
    return env.mapper(env.small_db(), env.inputs / "no_such_folder")


@case("image_list_missing", "cannot read image list")
def _(env):
    return env.mapper(env.small_db(), None, None, "--image_list_path", str(env.inputs / "nope.txt"))


@case("image_list_empty", "is empty")
def _(env):
    (env.inputs / "list.txt").write_text("\n\n")
    return env.mapper(env.small_db(), None, None, "--image_list_path", str(env.inputs / "list.txt"))


@case("image_list_unknown_names", "images in the image list are not in the database")
def _(env):
    (env.inputs / "list.txt").write_text("ring0000.png\nnot_an_image.png\n")
    return env.mapper(env.small_db(), None, None, "--image_list_path", str(env.inputs / "list.txt"))


@case("image_list_one_image", "no model could be reconstructed")
def _(env):
    (env.inputs / "list.txt").write_text("ring0000.png\n")
    return env.mapper(env.small_db(), None, None, "--image_list_path", str(env.inputs / "list.txt"))


# ---- what is in the database


@case("db_not_sqlite", "not an SQLite database")
def _(env):
    (env.inputs / "database.db").write_text("cameras, images, keypoints\n")
    return env.mapper(env.inputs / "database.db")


@case("db_zero_bytes", "not an SQLite database")
def _(env):
    (env.inputs / "database.db").touch()
    return env.mapper(env.inputs / "database.db")


@case("db_truncated", "cannot read database")
def _(env):
    data = env.assets.small[0].read_bytes()
    (env.inputs / "database.db").write_bytes(data[:100] + b"\x00" * 4096)
    return env.mapper(env.inputs / "database.db")


@case("db_sqlite_without_tables", "not a COLMAP database (no table")
def _(env):
    database = edit_database(env.inputs / "database.db", "PRAGMA user_version = 1")
    assert database.stat().st_size > 0
    return env.mapper(database)


@case("db_colmap_without_images", "the database has no images")
def _(env):
    import pycolmap

    pycolmap.Database.open(env.inputs / "database.db").close()
    return env.mapper(env.inputs / "database.db")


@case("db_images_without_keypoints", "the database has no keypoints")
def _(env):
    database = edit_database(env.small_db(), "DELETE FROM keypoints", "DELETE FROM descriptors",
                             "DELETE FROM matches", "DELETE FROM two_view_geometries")
    return env.mapper(database)


@case("db_keypoints_without_matches", "the database has no matches")
def _(env):
    database = edit_database(env.small_db(), "DELETE FROM matches", "DELETE FROM two_view_geometries")
    return env.mapper(database)


@case("db_matches_beyond_keypoints", "refer to keypoints that do not exist")
def _(env):
    database = env.small_db()
    with closing(sqlite3.connect(database)) as conn:
        pair_id, rows, data = conn.execute("SELECT pair_id, rows, data FROM matches LIMIT 1").fetchone()
        matches = np.frombuffer(data, np.uint32).reshape(rows, 2).copy()
        matches[0, 1] = 10**6
        conn.execute("UPDATE matches SET data = ? WHERE pair_id = ?", (matches.tobytes(), pair_id))
        conn.commit()
    return env.mapper(database)


@case("db_descriptors_not_one_per_keypoint", "expected one SIFT descriptor (128 values) per keypoint")
def _(env):
    return env.mapper(edit_database(
        env.small_db(), "UPDATE descriptors SET rows = rows - 1, data = substr(data, 1, (rows - 1) * cols) "
        "WHERE image_id = (SELECT MIN(image_id) FROM descriptors)"))


@case("db_image_without_camera", "which is not in the database")
def _(env):
    return env.mapper(edit_database(env.small_db(), "DELETE FROM cameras"))


@case("db_unknown_camera_model", "model id 99, which is no COLMAP camera model")
def _(env):
    return env.mapper(edit_database(env.small_db(), "UPDATE cameras SET model = 99"))


@case("db_wrong_number_of_params", "has 3 params; its model OPENCV takes 8")
def _(env):
    params = np.array([600.0, 600.0, 318.0])  # OPENCV has 8
    return env.mapper(edit_database(env.small_db(), ("UPDATE cameras SET params = ?", (params.tobytes(),))))


@case("db_nan_params", "has no valid parameters")
def _(env):
    params = np.full(8, np.nan)
    return env.mapper(edit_database(env.small_db(), ("UPDATE cameras SET params = ?", (params.tobytes(),))))


@case("db_pending_wal_is_read", "has no valid parameters")
def _(env):
    """A database as a crashed COLMAP leaves it: committed changes still in its `-wal` file
    (here: NaN parameters). They are part of the database; reading them changes nothing."""
    database = env.small_db()
    crashed = env.inputs / "crashed"
    crashed.mkdir()
    with closing(sqlite3.connect(database)) as conn:
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA wal_autocheckpoint = 0")
        conn.execute("UPDATE cameras SET params = ?", (np.full(8, np.nan).tobytes(),))
        conn.commit()
        for suffix in ("", "-wal"):
            shutil.copyfile(f"{database}{suffix}", crashed / f"database.db{suffix}")
    assert (crashed / "database.db-wal").stat().st_size > 0
    return env.mapper(crashed / "database.db")


# Issue 33, defects 8 and 9: values that gave a traceback, or a wrong result in silence.


def edit_blob(database: Path, table: str, key: str, edit: Callable[[np.ndarray, int], tuple],
              dtype: type = np.float32) -> Path:
    """Rewrite the first row of `table` (keyed by `key`): edit(array of rows x cols, cols)
    gives the new (rows, cols, data)."""
    with closing(sqlite3.connect(database)) as conn:
        row_id, rows, cols, data = conn.execute(
            f"SELECT {key}, rows, cols, data FROM {table} WHERE rows > 0 ORDER BY {key} LIMIT 1"
        ).fetchone()
        rows, cols, data = edit(np.frombuffer(data, dtype).reshape(rows, cols).copy(), cols)
        conn.execute(f"UPDATE {table} SET rows = ?, cols = ?, data = ? WHERE {key} = ?",
                     (rows, cols, data, row_id))
        conn.commit()
    return database


def _set_first(value: float) -> Callable[[np.ndarray, int], tuple]:
    def edit(array, cols):
        array[0, 0] = value
        return len(array), cols, array.tobytes()
    return edit


@case("db_keypoint_nan", "are not all finite numbers")
def _(env):
    return env.mapper(edit_blob(env.small_db(), "keypoints", "image_id", _set_first(np.nan)))


@case("db_keypoint_inf", "are not all finite numbers")
def _(env):
    return env.mapper(edit_blob(env.small_db(), "keypoints", "image_id", _set_first(np.inf)))


@case("db_keypoints_blob_short", "rows of 2, 4 or 6 4-byte numbers")
def _(env):
    return env.mapper(edit_blob(env.small_db(), "keypoints", "image_id",
                                lambda a, cols: (len(a), cols, a.tobytes()[:-4])))


@case("db_matches_blob_long", "expected 1 rows of 2 keypoint indices")
def _(env):
    return env.mapper(edit_blob(env.small_db(), "matches", "pair_id",
                                lambda a, cols: (1, cols, a.tobytes()), np.uint32))


@case("db_matches_three_columns", "expected 2 rows of 2 keypoint indices")
def _(env):
    return env.mapper(edit_blob(env.small_db(), "matches", "pair_id",
                                lambda a, cols: (2, 3, a[:3].tobytes()), np.uint32))


def verified_db(env) -> Path:
    """The small database with its matches also as verified (calibrated) two-view
    geometries, each with F, E, H, qvec and tvec blobs of their sizes."""
    identity, rotation, translation = np.eye(3).tobytes(), np.array([1.0, 0, 0, 0]).tobytes(), \
        np.array([0.0, 0, 1]).tobytes()
    return edit_database(env.small_db(), (
        "INSERT INTO two_view_geometries (pair_id, rows, cols, data, config, F, E, H, qvec, tvec) "
        "SELECT pair_id, rows, cols, data, 2, ?, ?, ?, ?, ? FROM matches",
        (identity, identity, identity, rotation, translation)))


@case("db_verified_matches_blob_short", "two_view_geometries of images")
def _(env):
    return env.mapper(edit_blob(verified_db(env), "two_view_geometries", "pair_id",
                                lambda a, cols: (len(a), cols, a.tobytes()[:-4]), np.uint32))


@case("db_fundamental_matrix_blob_short", "F holds 64 bytes; expected 72")
def _(env):
    return env.mapper(edit_database(verified_db(env), "UPDATE two_view_geometries SET F = zeroblob(64)"))


@case("db_essential_matrix_blob_long", "E holds 80 bytes; expected 72")
def _(env):
    return env.mapper(edit_database(verified_db(env), "UPDATE two_view_geometries SET E = zeroblob(80)"))


def _with_focal_length(env, focal_length: float) -> Path:
    database = env.small_db()
    with closing(sqlite3.connect(database)) as conn:
        params = np.frombuffer(conn.execute("SELECT params FROM cameras").fetchone()[0]).copy()
    params[:2] = focal_length
    return edit_database(database, ("UPDATE cameras SET params = ?", (params.tobytes(),)))


@case("db_focal_length_zero", "has focal length 0, 0; expected a positive one")
def _(env):
    return env.mapper(_with_focal_length(env, 0.0))


@case("db_focal_length_negative", "has focal length -600, -600; expected a positive one")
def _(env):
    return env.mapper(_with_focal_length(env, -600.0))


@case("db_match_index_all_ones", "refer to keypoints that do not exist")
def _(env):
    """0xFFFFFFFF was read as -1: the image's last keypoint."""
    def last_index_all_ones(array, cols):
        array[0, 1] = 0xFFFFFFFF
        return len(array), cols, array.tobytes()
    return env.mapper(edit_blob(env.small_db(), "matches", "pair_id", last_index_all_ones,
                                np.uint32))


@case("db_negative_image_size", "has an image size of -5 x -5; expected positive integers")
def _(env):
    """Mapped with exit 0, and cameras.bin said 18446744073709551611."""
    return env.mapper(edit_database(env.small_db(), "UPDATE cameras SET width = -5, height = -5"))


@case("flag_threshold_infinite", "--Mapper.init_max_error: expected a finite number", code=2)
def _(env):
    return env.mapper(env.small_db(), None, None, "--Mapper.init_max_error", "inf")


@case("flag_threads_beyond_int32", "--num_threads: expected an integer from", code=2)
def _(env):
    return env.mapper(env.small_db(), None, None, "--Mapper.num_threads", str(2**31))


@case("flag_iterations_beyond_int32", "--Mapper.ba_global_max_num_iterations: expected an integer",
      code=2)
def _(env):
    return env.mapper(env.small_db(), None, None, "--Mapper.ba_global_max_num_iterations",
                      str(2**40))


@case("flag_seed_beyond_64_bits", "--seed: expected an integer from", code=2)
def _(env):
    return env.mapper(env.small_db(), None, None, "--seed", str(2**64))


@case("image_list_binary", "is not text")
def _(env):
    (env.inputs / "list.txt").write_bytes(bytes(range(256)))
    return env.mapper(env.small_db(), None, None, "--image_list_path", str(env.inputs / "list.txt"))


@case("models_below_min_model_size", "1 model was reconstructed, all below --Mapper.min_model_size 20")
def _(env):
    """Issue 33, defect 10: said "no image pair gave a relative pose"."""
    return env.mapper(env.small_db(), None, None, "--seed", "0", "--Mapper.min_model_size", "20")


@case("db_pycolmap4_positive_control", "Registered 6 images in 1 model", code=0)
def _(env):
    return env.mapper(env.small_db(), None, None, "--seed", "0")


def _colmap38_after(env, result):
    """Every image of the 3.8 database in one model, with the database's intrinsics."""
    import pycolmap

    env.notes.append(f"the COLMAP 3.8 database was {env.assets.colmap38[2]}")
    with closing(sqlite3.connect(env.assets.colmap38[0])) as conn:
        names = {row[0] for row in conn.execute("SELECT name FROM images")}
        params = np.frombuffer(conn.execute("SELECT params FROM cameras").fetchone()[0], np.float64)
    assert f"Registered {len(names)} images in 1 model" in result.stdout, result.stdout
    assert sorted(p.name for p in env.out.iterdir()) == ["0", "mapper_summary.json"]
    model = pycolmap.Reconstruction(env.out / "0")
    assert {image.name for image in model.images.values() if image.has_pose} == names
    [camera] = model.cameras.values()
    np.testing.assert_array_equal(camera.params, params)


@case("db_colmap38", "Registered", code=0, after=_colmap38_after)
def _(env):
    database, images, _ = env.assets.colmap38
    return env.mapper(env.copy(database), env.copy(images), None, "--seed", "0")


# ---- images


def _warns_about(name: str) -> Callable:
    def after(env, result):
        assert name in result.stderr, f"no word on stderr about the unreadable {name}"
    return after


@case("image_zero_bytes", "Registered 6 images", code=0, after=_warns_about("ring0001.png"))
def _(env):
    images = env.images()
    (images / "ring0001.png").write_bytes(b"")
    return env.mapper(env.small_db(), images, None, "--seed", "0")


@case("image_corrupt", "Registered 6 images", code=0, after=_warns_about("ring0002.png"))
def _(env):
    images = env.images()
    (images / "ring0002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    return env.mapper(env.small_db(), images, None, "--seed", "0")


# ---- options


@case("bad_output_type", "invalid choice", code=2)
def _(env):
    return env.mapper(env.small_db(), None, None, "--output_type", "PLY")


NO_IMAGE_99 = "--Mapper.init_image_id1/2: no image with id 99 in the database"


def _says_exactly(message: str) -> Callable:
    def after(env, result):
        assert message_lines(result.stderr) == [f"colmap-ext: error: {message}"], result.stderr
    return after


@case("init_image_not_in_database", NO_IMAGE_99, after=_says_exactly(NO_IMAGE_99))
def _(env):
    return env.mapper(env.small_db(), None, None, "--Mapper.init_image_id1", "99",
                      "--Mapper.init_image_id2", "1")


# ---- output


@case("output_holds_a_model", "already holds a model; pass --overwrite")
def _(env):
    return env.mapper(env.small_db(), None, env.previous_model())


def _replaced(env, result):
    import pycolmap

    out = env.out
    assert sorted(p.name for p in out.iterdir()) == ["0", "mapper_summary.json"], \
        "a stale model or a temporary folder was left beside the new model"
    assert pycolmap.Reconstruction(out / "0").num_reg_images() == 6
    assert sha256(out / "0" / "images.bin") != sha256(env.assets.model / "0" / "images.bin")


@case("output_overwrite_replaces", "Registered 6 images", code=0, after=_replaced)
def _(env):
    shutil.copytree(env.assets.model, env.out)
    shutil.copytree(env.out / "0", env.out / "1")  # a second model of the earlier run
    summary = env.out / "mapper_summary.json"
    summary.write_text(json.dumps({**json.loads(summary.read_text()), "num_models": 2}))
    return env.mapper(env.small_db(), None, None, "--seed", "5", "--overwrite")


@case("output_is_a_file", "output path is a file")
def _(env):
    (env.inputs / "out").write_text("not a folder")
    return env.mapper(env.small_db(), None, env.inputs / "out")


@case("output_below_a_file", "cannot create output folder")
def _(env):
    (env.inputs / "file").write_text("not a folder")
    return env.mapper(env.small_db(), None, env.inputs / "file" / "out")


@case("output_under_proc", "cannot create output folder")
def _(env):
    return env.mapper(env.small_db(), None, "/proc/colmap-ext-out")


def _before_mapping(env, result):
    assert "registered:" not in result.stderr, "the output was checked only after mapping"


@case("output_not_writable", "cannot write in", unprivileged=True, after=_before_mapping)
def _(env):
    env.out.mkdir()
    env.out.chmod(0o555)
    return env.mapper(env.small_db())


@case("output_not_creatable_even_for_root", "cannot create output folder")
def _(env):
    return env.mapper(env.small_db(), None, "/sys/colmap-ext-out")  # EPERM, root or not


@case("output_not_writable_even_for_root", "cannot write in /sys/kernel", after=_before_mapping)
def _(env):
    return env.mapper(env.small_db(), None, "/sys/kernel")  # a folder no one can add to


def _no_space(limit: int) -> Callable[[], None]:
    def preexec() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


def _run_disk_full_from_start(env, args):
    return run_cli(env, args, preexec_fn=_no_space(16 * 1024))


@case("disk_full_from_start", "File too large", run=_run_disk_full_from_start)
def _(env):
    env.previous_model()
    return env.mapper(env.small_db(), None, None, "--overwrite")


# The database is read (copied to TMPDIR) with room to spare; then the disk is full.
DISK_FULL_AFTER_READ = """
import resource, signal, sys
import colmap_ext.mapper.pipeline as pipeline
from colmap_ext.cli import main
limit = int(sys.argv.pop(1))
read_database = pipeline.read_database
def read_then_fill_disk(*args, **kwargs):
    contents = read_database(*args, **kwargs)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return contents
pipeline.read_database = read_then_fill_disk
sys.argv[0] = "colmap-ext"
sys.exit(main())
"""


def _run_disk_full_at_write(env, args):
    return run_cli(env, args, cli=[sys.executable, "-c", DISK_FULL_AFTER_READ, "4096"])


@case("disk_full_while_writing_model", "the previous model is unchanged", run=_run_disk_full_at_write)
def _(env):
    env.previous_model()
    return env.mapper(env.small_db(), None, None, "--overwrite", "--seed", "0")


class Running:
    """A CLI run in the background, its stderr read as it comes. The child gets Ctrl-C's
    default action, as in a terminal: started from a background job (`make test &`), it
    would inherit SIGINT ignored, and Python then never raises KeyboardInterrupt."""

    def __init__(self, env: Env, args: list[str]) -> None:
        self.stdout = open(env.root / f"stdout-{len(list(env.root.glob('stdout-*')))}.txt", "w+")
        self.process = subprocess.Popen(
            [*CLI, *args], stdout=self.stdout, stderr=subprocess.PIPE, env=child_env(env),
            cwd=env.root, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        self.chunks: list[bytes] = []  # what stderr has said so far, as it comes
        fd = self.process.stderr.fileno()
        self.reader = threading.Thread(
            target=lambda: self.chunks.extend(iter(lambda: os.read(fd, 65536), b"")))
        self.reader.start()

    @property
    def stderr(self) -> str:
        return b"".join(self.chunks).decode(errors="replace")

    def wait_for(self, marker: str) -> bool:
        """Wait until `marker` is on stderr; True if the run is still going then."""
        deadline = time.monotonic() + 120
        while marker not in self.stderr and self.process.poll() is None \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.process.poll() is None

    def result(self) -> subprocess.CompletedProcess:
        self.process.wait(timeout=120)
        self.reader.join()
        self.stdout.seek(0)
        result = subprocess.CompletedProcess(self.process.args, self.process.returncode,
                                             self.stdout.read(), self.stderr)
        self.stdout.close()
        self.process.stderr.close()
        return result


def interrupted(marker: str, signum: int = signal.SIGINT, delay: float = 0.05) -> Callable:
    """A runner that sends `signum` `delay` seconds after `marker` appears on stderr (a
    stage has begun; "": after the start)."""
    def run(env: Env, args: list[str]) -> subprocess.CompletedProcess:
        running = Running(env, args)
        still_running = running.wait_for(marker)
        time.sleep(delay)
        running.process.send_signal(signum)
        result = running.result()
        assert still_running, f"the run finished before {marker!r}: nothing to interrupt\n{result.stderr}"
        return result
    return run


@case("ctrl_c_while_mapping", "interrupted by SIGINT", code=130, run=interrupted("registered:"))
def _(env):
    database, images, _ = env.assets.big
    env.previous_model()
    return env.mapper(env.copy(database), env.copy(images), None, "--overwrite", "--seed", "0")


@case("sigterm_while_mapping", "interrupted by SIGTERM", code=143,
      run=interrupted("registered:", signal.SIGTERM))
def _(env):
    """Issue 33, defect 6: glog's handler printed a stack dump, and the private copy of
    the database stayed in TMPDIR (the harness checks TMPDIR is empty)."""
    database, images, _ = env.assets.big
    env.previous_model()
    return env.mapper(env.copy(database), env.copy(images), None, "--overwrite", "--seed", "0")


def _run_beside_a_running_mapper(env, args):
    """Start a mapper on the big scene into OUT, and run `args` (a second mapper into the
    same OUT) while the first one registers images. The first finishes with its model."""
    import pycolmap

    first = Running(env, env.mapper(env.inputs / "big.db", env.inputs / "big_images", None,
                                    "--seed", "0"))
    assert first.wait_for("registered:"), "the first mapper finished before the second started"
    second = run_cli(env, args)
    finished = first.result()
    assert finished.returncode == 0, finished.stderr
    assert pycolmap.Reconstruction(env.out / "0").num_reg_images() > 6, "not the first run's model"
    return second


@case("two_mappers_into_one_output", "is being written by another colmap-ext run (pid",
      run=_run_beside_a_running_mapper)
def _(env):
    """Issue 33, defect 7: both runs exited 0 and the later replaced the earlier's model."""
    database, images, _ = env.assets.big
    env.copy(database, "big.db")
    env.copy(images, "big_images")
    return env.mapper(env.small_db(), None, None, "--seed", "0")


@case("overwrite_keeps_numbered_folders_that_are_no_models", "/2024 is not a model written by")
def _(env):
    """Issue 33, defect 2: --overwrite deleted every folder whose name is digits."""
    out = env.previous_model()
    (out / "2024").mkdir()
    (out / "2024" / "notes.txt").write_text("my notes\n")
    (out / "7").mkdir()
    (out / "7" / "IMG_0002.JPG").write_bytes(b"\xff\xd8 a photo")
    return env.mapper(env.small_db(), None, None, "--overwrite")


def _lock_released(env, result):
    assert sorted(p.name for p in env.out.iterdir()) == ["0", "mapper_summary.json"], \
        "the lock file was not removed"


@case("stale_lock_is_taken_over", "Registered 6 images", code=0, after=_lock_released)
def _(env):
    """A lock file left by a killed run (its pid long gone) does not keep the folder locked."""
    env.out.mkdir()
    (env.out / ".colmap-ext.lock").write_text("999999999\n")
    return env.mapper(env.small_db(), None, None, "--seed", "0")


def _nothing_in_the_working_folder(env, result):
    written = {p.name for p in env.root.iterdir()} - {"home", "in", "out", "tmp"}
    assert not written, f"the run wrote {written} into its working folder"


@case("output_path_empty", "the output path is empty", after=_nothing_in_the_working_folder)
def _(env):
    """Issue 33, defect 5: `--output_path ""` wrote ./0, then failed with a traceback."""
    return env.mapper(env.small_db(), None, "")


# ---- evaluate


@case("evaluate_positive_control", "registered: 6 / 6", code=0, command="evaluate")
def _(env):
    return env.evaluate()


@case("evaluate_model_missing", "model not found", command="evaluate")
def _(env):
    return env.evaluate(env.inputs / "nope")


@case("evaluate_model_folder_empty", "not a readable COLMAP model", command="evaluate")
def _(env):
    (env.inputs / "model").mkdir()
    return env.evaluate(env.inputs / "model")


@case("evaluate_model_truncated", "not a readable COLMAP model", command="evaluate")
def _(env):
    model = env.copy(env.assets.model / "0", "model")
    data = (model / "images.bin").read_bytes()
    (model / "images.bin").write_bytes(data[: len(data) // 2])
    return env.evaluate(model)


def _text_model(env, edit: Callable[[str], str]) -> Path:
    import pycolmap

    model = env.inputs / "model"
    model.mkdir()
    pycolmap.Reconstruction(env.assets.model / "0").write_text(model)
    cameras = model / "cameras.txt"
    cameras.write_text(edit(cameras.read_text()))
    return model


@case("evaluate_unknown_camera_model_name", "not a readable COLMAP model", command="evaluate")
def _(env):
    return env.evaluate(_text_model(env, lambda text: text.replace(" OPENCV ", " FANCY_LENS ")))


@case("evaluate_wrong_number_of_params", "not a readable COLMAP model", command="evaluate")
def _(env):
    return env.evaluate(_text_model(env, lambda text: re.sub(r"(OPENCV 640 480 \S+ \S+ \S+).*",
                                                             r"\1", text)))


@case("gt_missing", "ground truth not found", command="evaluate")
def _(env):
    return env.evaluate(None, env.inputs / "nope_par.txt")


def _edited_truth(env, edit: Callable[[list[str]], list[str]]) -> Path:
    lines = env.assets.ground_truth.read_text().splitlines()
    path = env.inputs / "small_par.txt"
    path.write_text("\n".join(edit(lines)) + "\n")
    return path


@case("gt_empty", "empty file", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda lines: []))


@case("gt_too_few_numbers", "expected 21 numbers", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda l: [*l[:3], " ".join(l[3].split()[:-1]), *l[4:]]))


@case("gt_not_a_number", "not a number", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda l: [*l[:2], l[2].replace(" ", " x", 1), *l[3:]]))


@case("gt_nan", "non-finite number", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda l: [*l[:2], re.sub(r"\S+$", "nan", l[2]), *l[3:]]))


@case("gt_count_mismatch", "announces 6 images, found 4", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda lines: lines[:5]))


@case("gt_binary_garbage", "cannot read", command="evaluate")
def _(env):
    path = env.inputs / "small_par.txt"
    path.write_bytes(bytes(range(256)) * 4)
    return env.evaluate(None, path)


@case("gt_no_matching_images", "registered image(s) match", command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda lines: [l.replace("ring", "other") for l in lines]))


@case("gt_covers_half_the_model", "registered: 3 / 3", code=0, command="evaluate")
def _(env):
    return env.evaluate(None, _edited_truth(env, lambda lines: ["3", *lines[1:4]]))


@case("evaluate_output_below_a_file", "cannot write", command="evaluate")
def _(env):
    (env.inputs / "file").write_text("not a folder")
    return env.evaluate(None, None, "--output", str(env.inputs / "file" / "report.json"))


# ---- reconstruct (images and known intrinsics in)


def _reconstruct(env, *extra: str, model: str = "PINHOLE", params: str = "600,600,4,4") -> list[str]:
    images = env.images()
    return ["reconstruct", "--image_path", str(images), "--workspace_path", str(env.out),
            "--camera_model", model, "--camera_params", params, *extra]


@case("reconstruct_nan_params", "finite", command="reconstruct")
def _(env):
    return _reconstruct(env, params="nan,600,4,4")


@case("reconstruct_unknown_camera_model", "unknown camera model", command="reconstruct")
def _(env):
    return _reconstruct(env, model="FANCY_LENS")


@case("reconstruct_wrong_number_of_params", "takes 4 params", command="reconstruct")
def _(env):
    return _reconstruct(env, params="600,600,4")


@case("reconstruct_pooling_not_a_boolean", "invalid boolean value", code=2, command="reconstruct")
def _(env):
    return _reconstruct(env, "--SiftExtraction.domain_size_pooling", "maybe")


@case("reconstruct_zero_byte_image", "image file is empty", command="reconstruct")
def _(env):
    args = _reconstruct(env)
    (env.inputs / "images" / "ring0001.png").write_bytes(b"")
    return args


@case("reconstruct_corrupt_image", "cannot read image", command="reconstruct")
def _(env):
    args = _reconstruct(env)
    (env.inputs / "images" / "ring0002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    return args


@case("reconstruct_workspace_is_a_file", "workspace path is a file", command="reconstruct")
def _(env):
    args = _reconstruct(env)
    env.out.write_text("not a folder")
    env.protected.append(env.out)
    return args


@case("reconstruct_principal_point_outside", "principal point", command="reconstruct")
def _(env):
    return _reconstruct(env, params="600,600,400,4")  # the images are 8x8


@case("reconstruct_workspace_has_database", "pass --overwrite", command="reconstruct")
def _(env):
    args = _reconstruct(env)
    env.out.mkdir()
    shutil.copyfile(env.assets.small[0], env.out / "database.db")
    env.protected.append(env.out)
    return args


# ---- evaluate: more ground-truth formats and outputs


@case("gt_strecha_malformed", "expected 3 numbers", command="evaluate")
def _(env):
    truth = env.inputs / "strecha"
    truth.mkdir()
    rows = ["600 0 318", "0 600 242", "0 0 1", "0 0 0", "1 0 0", "0 1 0", "0 0 1", "0 0 0", "640 480"]
    for index in range(6):
        broken = rows[:7] + ["0 0"] + rows[8:] if index == 3 else rows  # the centre lost a number
        (truth / f"ring{index:04d}.png.camera").write_text("\n".join(broken) + "\n")
    return env.evaluate(None, truth)


@case("evaluate_plot_below_a_file", "cannot write", command="evaluate")
def _(env):
    (env.inputs / "file").write_text("not a folder")
    return env.evaluate(None, None, "--plot", str(env.inputs / "file" / "errors.png"))


# ---- rig_config_from_kalibr (Kalibr camchain files to COLMAP's rig configuration)

CAMCHAIN = """cam0:
  camera_model: pinhole
  distortion_model: equidistant
  distortion_coeffs: [0.01, -0.002, 0.0005, 0.0]
  intrinsics: [350.0, 350.0, 360.0, 270.0]
  resolution: [720, 540]
cam1:
  camera_model: pinhole
  distortion_model: equidistant
  distortion_coeffs: [0.01, -0.002, 0.0005, 0.0]
  intrinsics: [350.0, 350.0, 360.0, 270.0]
  resolution: [720, 540]
  T_cn_cnm1:
  - [1.0, 0.0, 0.0, -0.11]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
"""


def _kalibr(env, camchain: str, output: Path | None = None, *extra: str) -> list[str]:
    path = env.inputs / "camchain.yaml"
    path.write_text(camchain)
    return ["rig_config_from_kalibr", "--camchain", str(path),
            "--output_path", str(output or env.out / "rig.json"), *extra]


@case("kalibr_positive_control", "Rig configuration of 2 cameras", code=0,
      command="rig_config_from_kalibr")
def _(env):
    env.out.mkdir()
    return _kalibr(env, CAMCHAIN)


@case("kalibr_camchain_missing", "cannot read", command="rig_config_from_kalibr")
def _(env):
    return ["rig_config_from_kalibr", "--camchain", str(env.inputs / "nope.yaml"),
            "--output_path", str(env.out / "rig.json")]


@case("kalibr_not_yaml", "not YAML", command="rig_config_from_kalibr")
def _(env):
    return _kalibr(env, "cam0: [unclosed\n")


@case("kalibr_unsupported_distortion", "is not supported", command="rig_config_from_kalibr")
def _(env):
    return _kalibr(env, CAMCHAIN.replace("equidistant", "fov", 1))


@case("kalibr_output_exists_is_kept", "exists; pass --overwrite", command="rig_config_from_kalibr")
def _(env):
    existing = env.inputs / "rig.json"
    existing.write_text("[]\n")  # an input: hashed before and after
    return _kalibr(env, CAMCHAIN, existing)


# ---- rig inputs (issue 45): every value of a rig configuration, camchain file and rig
# database checked before any costly step, with a message naming it


RIG_PINHOLE = {"camera_model_name": "PINHOLE", "camera_params": [6.0, 6.0, 4.0, 4.0]}


def _rig_config(**right: object) -> list[dict]:
    """Two PINHOLE cameras on left/ and right/, the second placed 0.1 to the side; `right`
    changes its entry (a value None removes the key)."""
    entry = {"image_prefix": "right/", "cam_from_rig_rotation": [1.0, 0.0, 0.0, 0.0],
             "cam_from_rig_translation": [0.1, 0.0, 0.0], **RIG_PINHOLE, **right}
    return [{"cameras": [{"image_prefix": "left/", "ref_sensor": True, **RIG_PINHOLE},
                         {key: value for key, value in entry.items() if value is not None}]}]


def _rig(env, config: list | str, *extra: str) -> list[str]:
    """reconstruct --rig_config on left/N.png and right/N.png (8x8); `config`: the JSON's
    content, or its text."""
    for side in ("left", "right"):
        for index in range(3):
            write_png(env.inputs / "rig" / side / f"{index}.png")
    path = env.inputs / "rig.json"
    path.write_text(config if isinstance(config, str) else json.dumps(config))
    return ["reconstruct", "--image_path", str(env.inputs / "rig"), "--workspace_path",
            str(env.out), "--rig_config", str(path), *extra]


DEEP_JSON = "[" * 100_000 + "]" * 100_000


@case("rig_json_nested_100000_deep", "nested 100000 levels deep", command="reconstruct")
def _(env):
    """Issue 45, defect 5: pycolmap's reader overflowed its stack (SIGSEGV)."""
    return _rig(env, DEEP_JSON)


@case("rig_json_too_large", "larger than 1 MiB", command="reconstruct")
def _(env):
    return _rig(env, json.dumps(_rig_config()) + " " * 2**20)


@case("rig_ref_sensor_false_without_pose", '"ref_sensor": false needs cam_from_rig_rotation',
      command="reconstruct")
def _(env):
    """Issue 45, defect 6: an AttributeError in initial_pair.py after extraction."""
    return _rig(env, _rig_config(ref_sensor=False, cam_from_rig_rotation=None,
                                 cam_from_rig_translation=None))


@case("rig_lowercase_camera_model", "unknown camera model 'pinhole'", command="reconstruct")
def _(env):
    """Issue 45, defect 6: a ValueError in matching.py after extraction."""
    return _rig(env, _rig_config(camera_model_name="pinhole"))


@case("rig_wrong_number_of_camera_params", "camera model PINHOLE takes 4 params",
      command="reconstruct")
def _(env):
    return _rig(env, _rig_config(camera_params=[6.0, 6.0, 4.0]))


@case("rig_zero_quaternion", "is not a unit quaternion (norm 0)", command="reconstruct")
def _(env):
    """Issue 45, defect 8: written into the model's rig."""
    return _rig(env, _rig_config(cam_from_rig_rotation=[0, 0, 0, 0]))


@case("rig_rotation_of_3_numbers", "cam_from_rig_rotation [w, x, y, z] must be a list of 4",
      command="reconstruct")
def _(env):
    """Issue 45, defect 8: became the identity."""
    return _rig(env, _rig_config(cam_from_rig_rotation=[0.0, 0.0, 1.0]))


@case("rig_rotation_a_string", "cam_from_rig_rotation [w, x, y, z] must be a list of 4",
      command="reconstruct")
def _(env):
    return _rig(env, _rig_config(cam_from_rig_rotation="identity"))


@case("rig_translation_of_2_numbers", "cam_from_rig_translation must be a list of 3",
      command="reconstruct")
def _(env):
    """Issue 45, defect 8: became zero."""
    return _rig(env, _rig_config(cam_from_rig_translation=[0.1, 0.0]))


@case("rig_principal_point_outside", "principal point (100000, 4) is outside the 8x8 images",
      command="reconstruct")
def _(env):
    """Issue 45, defect 9: accepted, where --camera_params is refused."""
    return _rig(env, _rig_config(camera_params=[6.0, 6.0, 1e5, 4.0]))


@case("rig_focal_length_1e300", "is no lens's", command="reconstruct")
def _(env):
    return _rig(env, _rig_config(camera_params=[1e300, 1e300, 4.0, 4.0]))


@case("rig_focal_length_negative", "focal lengths must be positive", command="reconstruct")
def _(env):
    """Issue 45, defect 9: refused after extraction, naming a deleted temporary path."""
    return _rig(env, _rig_config(camera_params=[-6.0, -6.0, 4.0, 4.0]))


@case("rig_with_camera_flags", "not both", command="reconstruct")
def _(env):
    """Issue 45, defect 11: the flags were ignored, and the summary recorded them."""
    return _rig(env, _rig_config(), "--camera_model", "OPENCV_FISHEYE",
                "--camera_params", "6,6,4,4,0,0,0,0")


def _equirectangular(params: list[float]) -> Callable[[Env], list[str]]:
    return lambda env: _rig(env, _rig_config(camera_model_name="EQUIRECTANGULAR",
                                             camera_params=params))


for _params, _message in (([0.0, 0.0], "camera params must be positive"),
                          ([-8.0, -8.0], "camera params must be positive"),
                          ([1e12, 1e12], "are not the images' size 8x8")):
    # Issue 45, defect 15: "no model could be reconstructed" after extraction.
    case(f"rig_equirectangular_params_{_params[0]:g}", _message,
         command="reconstruct")(_equirectangular(_params))


@case("rig_overlapping_prefixes", "image prefix 'left/' and 'left/a' overlap",
      command="reconstruct")
def _(env):
    return _rig(env, _rig_config(image_prefix="left/a"))


@case("evaluate_rig_json_nested_100000_deep", "nested 100000 levels deep", command="evaluate")
def _(env):
    """Issue 45, defect 5."""
    (env.inputs / "rig.json").write_text(DEEP_JSON)
    return env.evaluate(None, None, "--rig_config", str(env.inputs / "rig.json"))


@case("evaluate_rig_prefixes_match_nothing", "no image of the model is under the rig "
      "configuration's image prefixes", command="evaluate")
def _(env):
    """Issue 45, defect 13: evaluated without a word about the rig."""
    (env.inputs / "rig.json").write_text(json.dumps(_rig_config()))
    return env.evaluate(None, None, "--rig_config", str(env.inputs / "rig.json"))


@case("gt_translation_1e300", "a number beyond 1e+12", command="evaluate")
def _(env):
    """Issue 45, defect 15: "first two ground-truth camera centres coincide", with NumPy
    overflow warnings."""
    return env.evaluate(None, _edited_truth(env, lambda lines: lines[:1] + [
        " ".join(line.split()[:-3] + ["1e300", "0", "0"]) for line in lines[1:]]))


def _rig_database(env, *statements: tuple | str) -> Path:
    """A copy of the rig database (one rig of 2 cameras, 4 frames), SQL run on it."""
    return edit_database(env.copy(env.assets.rig_database), *statements)


def _sensor_from_rig(values: list[float] | None) -> tuple:
    blob = None if values is None else np.array(values, np.float64).tobytes()
    return ("UPDATE rig_sensors SET sensor_from_rig = ?", (blob,))


@case("db_rig_positive_control", "Registered 8 images in 1 model", code=0)
def _(env):
    return env.mapper(_rig_database(env), env.inputs, None, "--seed", "0")


@case("db_rig_sensor_from_rig_null", "camera 2's sensor_from_rig is NULL")
def _(env):
    """Issue 45, defect 6: a traceback."""
    return env.mapper(_rig_database(env, _sensor_from_rig(None)), env.inputs)


@case("db_rig_zero_quaternion", "camera 2's sensor_from_rig is [0, 0, 0, 0, 0.1, 0, 0]")
def _(env):
    """Issue 45, defect 8: mapped 4 of 12 images."""
    return env.mapper(_rig_database(env, _sensor_from_rig([0, 0, 0, 0, 0.1, 0, 0])), env.inputs)


@case("db_rig_nan_sensor_from_rig", "camera 2's sensor_from_rig is [nan")
def _(env):
    """Issue 45, defect 15: "no model could be reconstructed" after 10 s."""
    return env.mapper(_rig_database(env, _sensor_from_rig([np.nan] * 7)), env.inputs)


@case("db_frame_with_two_images_of_one_camera", "of one camera (1); a frame holds one image "
      "per camera")
def _(env):
    """Issue 45, defect 10: both images got one pose."""
    return env.mapper(_rig_database(
        env, "UPDATE images SET camera_id = 1", "UPDATE frame_data SET sensor_id = 1"), env.inputs)


@case("db_constant_rig_not_in_the_database", "--Mapper.constant_rig_list_path: no rig with id 7")
def _(env):
    """Issue 45, defect 13: ignored without a word."""
    (env.inputs / "rigs.txt").write_text("7\n")
    return env.mapper(_rig_database(env), env.inputs, None, "--Mapper.constant_rig_list_path",
                      str(env.inputs / "rigs.txt"))


@case("db_equirectangular_size_not_its_params", "is 1 x 1 with params 1024, 512")
def _(env):
    """Issue 45, defect 12: accepted, its reprojection errors wrong."""
    import pycolmap

    return env.mapper(edit_database(env.small_db(), (
        "UPDATE cameras SET model = ?, width = 1, height = 1, params = ?",
        (int(pycolmap.CameraModelId.EQUIRECTANGULAR), np.array([1024.0, 512.0]).tobytes()))))


@case("db_keypoints_outside_the_image", "are outside its camera's")
def _(env):
    """Issue 45, defect 12: accepted."""
    return env.mapper(edit_blob(env.small_db(), "keypoints", "image_id", _set_first(1e6)))


def _kalibr_camera(**changes: object) -> str:
    """CAMCHAIN with cam1's lines changed (key: YAML text of its value)."""
    lines = CAMCHAIN.splitlines()
    start = lines.index("cam1:")
    for key, value in changes.items():
        index = next(i for i in range(start, len(lines)) if lines[i].startswith(f"  {key}:"))
        lines[index] = f"  {key}: {value}"
    return "\n".join(lines) + "\n"


for _id, _changes, _message in (
        # Issue 45, defect 6: tracebacks
        ("kalibr_intrinsics_not_numbers", {"intrinsics": "[a, b, c, d]"},
         "intrinsics [fu, fv, pu, pv] must be a list of 4 numbers"),
        ("kalibr_distortion_model_a_list", {"distortion_model": "[equidistant]"},
         "distortion_model ['equidistant'] is not supported"),
        # Issue 45, defect 9: NaN and Infinity written into rig.json; focal lengths of 0 taken
        ("kalibr_intrinsics_nan", {"intrinsics": "[.nan, 350.0, 360.0, 270.0]"}, "must be finite"),
        ("kalibr_intrinsics_infinite", {"intrinsics": "[.inf, 350.0, 360.0, 270.0]"},
         "must be finite"),
        ("kalibr_focal_length_zero", {"intrinsics": "[0.0, 0.0, 360.0, 270.0]"},
         "focal lengths must be positive"),
        ("kalibr_focal_length_negative", {"intrinsics": "[-350.0, 350.0, 360.0, 270.0]"},
         "focal lengths must be positive"),
        ("kalibr_principal_point_outside", {"intrinsics": "[350.0, 350.0, 3600.0, 270.0]"},
         "is outside the 720x540 images"),
        # Issue 45, defect 18: dropped without a word
        ("kalibr_extra_distortion_coefficients",
         {"distortion_coeffs": "[0.01, -0.002, 0.0005, 0.0, 0.03]"},
         "COLMAP's model would drop the others")):
    case(_id, _message, command="rig_config_from_kalibr")(
        lambda env, changes=_changes: _kalibr(env, _kalibr_camera(**changes)))


@case("kalibr_not_utf8", "not UTF-8 text", command="rig_config_from_kalibr")
def _(env):
    """Issue 45, defect 6: a UnicodeDecodeError traceback."""
    args = _kalibr(env, "")
    (env.inputs / "camchain.yaml").write_bytes(CAMCHAIN.encode("utf-16"))
    return args


@case("kalibr_binary", "not text", command="rig_config_from_kalibr")
def _(env):
    args = _kalibr(env, "")
    (env.inputs / "camchain.yaml").write_bytes(b"cam0:\x00\x01\x02" * 100)
    return args


@case("kalibr_16_megabytes", "larger than 1 MiB", command="rig_config_from_kalibr")
def _(env):
    """Issue 45, defect 18: 40 s and 1.2 GB to read."""
    return _kalibr(env, CAMCHAIN + "".join(f"# {index:09d}\n" for index in range(2**20)))


for _id, _prefixes, _message in (
        ("kalibr_nested_prefixes", ["cam/", "cam/1/"], "image prefix 'cam/' and 'cam/1/' overlap"),
        ("kalibr_empty_prefix", ["", "cam1/"], "image prefix '' and 'cam1/' overlap"),
        ("kalibr_same_prefix_twice", ["cam/", "cam/"], "image prefix 'cam/' is given twice")):
    # Issue 45, defect 18: written, and refused only by reconstruct.
    case(_id, _message, command="rig_config_from_kalibr")(
        lambda env, prefixes=_prefixes: _kalibr(env, CAMCHAIN, None, "--image_prefix", *prefixes))


# ---- demo


@case("demo_output_is_a_file", "output path is a file", command="demo")
def _(env):
    (env.inputs / "demo").write_text("not a folder")
    return ["demo", "--output_path", str(env.inputs / "demo")]


@case("demo_too_few_images", "--num_images must be at least 3", command="demo")
def _(env):
    return ["demo", "--output_path", str(env.out), "--num_images", "2"]


@case("demo_already_there", "already holds a demo; pass --overwrite", command="demo")
def _(env):
    shutil.copytree(env.assets.model, env.out / "workspace" / "sparse")  # an earlier demo's
    env.protected.append(env.out)
    return ["demo", "--output_path", str(env.out)]


@case("demo_overwrite_keeps_the_users_files", "is not a demo written by colmap-ext", command="demo")
def _(env):
    """Issue 33, defect 1: --overwrite removed images/ and ground_truth/ whole, the
    user's files in them included."""
    shutil.copytree(env.assets.model, env.out / "workspace" / "sparse")  # an earlier demo's
    (env.out / "images").mkdir()
    (env.out / "images" / "holiday.jpg").write_bytes(b"\xff\xd8 the user's photo")
    (env.out / "ground_truth").mkdir()
    (env.out / "ground_truth" / "notes.txt").write_text("the user's notes\n")
    env.protected.append(env.out)
    return ["demo", "--output_path", str(env.out), "--overwrite", "--num_images", "3"]


@case("demo_seed_negative", "--seed: expected a seed from 0", code=2, command="demo")
def _(env):
    return ["demo", "--output_path", str(env.out), "--seed", "-5"]


@case("demo_too_many_images", "--num_images must be at least 3 and at most 1000", command="demo")
def _(env):
    """Issue 33, defect 11: rendered on until memory ran out (7.6 GB after 400 s)."""
    return ["demo", "--output_path", str(env.out), "--num_images", "100000000"]


# ---- compare (our mapper and COLMAP's on one database)


def _compare(env, *extra: str, database: Path | None = None) -> list[str]:
    return ["compare", "--database_path", str(database or env.small_db()),
            "--image_path", str(env.images()), "--output_path", str(env.out), *extra]


@case("compare_not_sqlite", "not an SQLite database", command="compare")
def _(env):
    (env.inputs / "database.db").write_text("not a database")
    return _compare(env, database=env.inputs / "database.db")


@case("compare_unknown_mapper", "unknown mapper", command="compare")
def _(env):
    return _compare(env, "--mappers", "ours,bundler")


@case("compare_ground_truth_of_other_images", "ground-truth images are in", command="compare")
def _(env):
    truth = _edited_truth(env, lambda lines: [l.replace("ring", "other") for l in lines])
    return _compare(env, "--ground_truth", str(truth))


@case("compare_report_exists", "pass --overwrite", command="compare")
def _(env):
    env.out.mkdir()
    (env.out / "report.json").write_text("{}\n")
    env.protected.append(env.out)
    return _compare(env)


def _compare_over_a_comparison(env, database: Path, images: Path, *extra: str) -> list[str]:
    """compare --overwrite over the output of an earlier comparison."""
    for mapper in ("ours", "colmap_incremental"):
        shutil.copytree(env.assets.model, env.out / mapper)
    (env.out / "report.json").write_text('{"an earlier": "comparison"}\n')
    (env.out / "report.md").write_text("# an earlier comparison\n")
    env.protected.append(env.out)
    return ["compare", "--database_path", str(env.copy(database)), "--image_path",
            str(env.copy(images, "images")), "--output_path", str(env.out), "--overwrite",
            "--seed", "0", *extra]


# Issue 33, defect 4: an interrupt could leave ours/0 of the new run beside the old report.
@case("compare_ctrl_c_in_the_second_mapper", "interrupted by SIGINT", code=130,
      command="compare", run=interrupted("[2/3] colmap_incremental", delay=0.0))
def _(env):
    """On the rendered ring's database, from which COLMAP's mappers register images, with
    its ground truth: evaluating and plotting keep the run going after the mappers."""
    images, truth = env.assets.ring
    return _compare_over_a_comparison(env, env.assets.workspace / "database.db", images,
                                      "--ground_truth", str(env.copy(truth)))


@case("compare_sigterm_in_our_mapper", "interrupted by SIGTERM", code=143, command="compare",
      run=interrupted("registered:", signal.SIGTERM))
def _(env):
    database, images, _ = env.assets.big
    return _compare_over_a_comparison(env, database, images)


# ---- Issue 45: what --overwrite replaces, damaged model files, the database's copy,
# interrupts while loading, leftovers of killed runs


def _all_kept(names: list[str]) -> Callable:
    def after(env, result):
        assert sorted(p.name for p in env.out.iterdir()) == names, "an entry was removed"
    return after


@case("reconstruct_overwrite_keeps_the_users_masks", "Model 0:", code=0, command="reconstruct",
      after=_all_kept(["database.db", "masks", "reconstruct_summary.json", "sparse"]))
def _(env):
    """Issue 45, defect 1: WS/masks, this run's --mask_path, was taken for our own output
    (it holds PNG files) and deleted."""
    import cv2

    args = _reconstruct_over_a_workspace(env)
    env.protected.remove(env.out)  # the database and sparse/ are replaced, the masks kept
    masks = env.out / "masks"
    masks.mkdir()
    for image in sorted(env.assets.ring[0].iterdir()):
        assert cv2.imwrite(str(masks / f"{image.name}.png"), np.full((240, 320), 255, np.uint8))
    env.protected.append(masks)
    return [*args, "--mask_path", str(masks)]


@case("evaluate_output_exists_is_kept", "report.json exists; pass --overwrite", command="evaluate")
def _(env):
    """Issue 45, defect 2: --output replaced any file."""
    (env.inputs / "report.json").write_text('{"an earlier": "report"}\n')
    return env.evaluate(None, None, "--output", str(env.inputs / "report.json"))


@case("evaluate_plot_keeps_the_users_scene_figure", "fig_scene.png exists; pass --overwrite",
      command="evaluate")
def _(env):
    """Issue 45, defect 2: --plot fig.png replaced the user's fig_scene.png."""
    write_png(env.inputs / "fig_scene.png")
    return env.evaluate(None, None, "--plot", str(env.inputs / "fig.png"))


@case("evaluate_output_is_the_ground_truth", "is an input of this run", command="evaluate")
def _(env):
    """Issue 45, defect 2: `--output GT` turned the ground truth into JSON, --overwrite or not."""
    truth = env.copy(env.assets.ground_truth)
    return env.evaluate(None, truth, "--output", str(truth), "--overwrite")


@case("overwrite_keeps_model_folders_it_did_not_write", "Registered 6 images", code=0,
      after=_all_kept(["0", "7", "mapper_summary.json"]))
def _(env):
    """Issue 45, defect 3: --overwrite removed OUT/7, a model the earlier run (whose
    summary records one model, OUT/0) did not write."""
    shutil.copytree(env.assets.model, env.out)
    shutil.copytree(env.out / "0", env.out / "7")
    env.protected.append(env.out / "7")
    return env.mapper(env.small_db(), None, None, "--seed", "0", "--overwrite")


# An address-space limit for runs that read damaged models: pycolmap's unbounded
# allocation (issue 45, defect 4: 16.5 GB) ends in bad_alloc instead of taking the machine.
MEMORY_LIMIT_BYTES = 8 * 2**30


def _run_with_memory_limit(env, args):
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    return run_cli(env, args, preexec_fn=preexec)


def _model_with(env, name: str, edit: Callable[[bytes], bytes]) -> Path:
    """A copy of the small scene's model with its file `name` edited."""
    model = env.copy(env.assets.model / "0", "model")
    (model / name).write_bytes(edit((model / name).read_bytes()))
    return model


for _name, _cut in (("to_0_bytes", lambda data: b""), ("to_4096_bytes", lambda data: data[:4096]),
                   ("by_one_byte", lambda data: data[:-1])):
    @case(f"evaluate_points3D_truncated_{_name}", "points3D.bin is truncated", command="evaluate",
          run=_run_with_memory_limit)
    def _(env, cut=_cut):
        """Issue 45, defect 4: a points3D.bin cut short (a full disk) made pycolmap allocate
        without bound."""
        return env.evaluate(_model_with(env, "points3D.bin", cut))


@case("mapper_input_model_truncated", "points3D.bin is truncated", run=_run_with_memory_limit)
def _(env):
    """Issue 45, defect 4, through `mapper --input_path`."""
    model = _model_with(env, "points3D.bin", lambda data: data[:4096])
    return env.mapper(env.small_db(), None, None, "--input_path", str(model))


@case("evaluate_images_bin_image_without_frame", "images.bin is corrupt: its image 999 is in no frame",
      command="evaluate", run=_run_with_memory_limit)
def _(env):
    """Issue 45, defects 4 and 15: "unordered_map::at" for an images.bin whose image is in
    no frame."""
    return env.evaluate(_model_with(
        env, "images.bin", lambda data: data[:8] + (999).to_bytes(4, "little") + data[12:]))


# A writer that changes the cameras in a transaction large enough to spill to the database
# file (a rollback journal beside it), prints "spilled", then dies without committing
# (argv[2] "die") or waits to be killed.
UNCOMMITTED_WRITER = """
import os, sqlite3, sys, time
import numpy as np
conn = sqlite3.connect(sys.argv[1], isolation_level=None)
conn.execute("PRAGMA cache_size = 1")
conn.execute("BEGIN")
conn.execute("UPDATE cameras SET params = ?", (np.full(8, np.nan).tobytes(),))
conn.execute("UPDATE descriptors SET data = data || x'00'")
print("spilled", flush=True)
if sys.argv[2] == "die":
    os._exit(0)
time.sleep(600)
"""


def _uncommitted_write(database: Path, mode: str) -> subprocess.Popen:
    """The writer on `database`, turned into a rollback-journal database (COLMAP leaves
    them in WAL mode, whose uncommitted frames stay in the log), once it has spilled."""
    edit_database(database, "PRAGMA journal_mode = DELETE")
    writer = subprocess.Popen([sys.executable, "-c", UNCOMMITTED_WRITER, str(database), mode],
                              stdout=subprocess.PIPE, text=True)
    assert writer.stdout.readline().strip() == "spilled"
    with closing(sqlite3.connect(f"{database.as_uri()}?immutable=1", uri=True)) as conn:
        params = np.frombuffer(conn.execute("SELECT params FROM cameras").fetchone()[0])
    assert np.isnan(params).all(), "the uncommitted parameters did not reach the file"
    assert Path(f"{database}-journal").stat().st_size > 0
    return writer


@case("db_hot_journal_is_rolled_back", "Registered 6 images", code=0)
def _(env):
    """Issue 45, defect 7: the pages of a transaction whose writer died (a hot journal
    beside the database) were read as the database: NaN parameters, or "malformed". Its
    committed content maps; the database and its journal stay as they are."""
    database = env.small_db()
    _uncommitted_write(database, "die").wait()
    return env.mapper(database, None, None, "--seed", "0")


def _run_beside_the_writer(env, args):
    try:
        return run_cli(env, args)
    finally:
        env.writer.kill()
        env.writer.wait()


@case("db_uncommitted_transaction_is_not_read", "is being written by another process",
      run=_run_beside_the_writer)
def _(env):
    """Issue 45, defect 7: another process's uncommitted transaction (spilled to the file)
    was read: NaN parameters here, focal lengths x3 in the issue."""
    database = env.small_db()
    env.writer = _uncommitted_write(database, "wait")
    return env.mapper(database, None, None, "--seed", "0")


# The CLI, with SIGTERM sent as soon as the subcommand's modules (pycolmap) are loaded.
SIGTERM_AFTER_LOADING = """
import os, signal, sys
import colmap_ext.cli as cli
build_parser = cli.build_parser
def build_then_terminate(*args, **kwargs):
    parser = build_parser(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGTERM)
    return parser
cli.build_parser = build_then_terminate
sys.argv[0] = "colmap-ext"
sys.exit(cli.main())
"""


def _run_terminated_after_loading(env, args):
    return run_cli(env, args, cli=[sys.executable, "-c", SIGTERM_AFTER_LOADING])


@case("sigterm_while_loading", "interrupted by SIGTERM", code=143,
      run=_run_terminated_after_loading)
def _(env):
    """Issue 45, defect 16: SIGTERM in the first 0.35 s printed glog's stack dump."""
    return env.mapper(env.small_db(), None, None, "--seed", "0")


@case("hier_sigterm_while_mapping_clusters", "interrupted by SIGTERM", code=143,
      command="hierarchical_mapper", run=interrupted("| 1/", signal.SIGTERM))
def _(env):
    """Issue 45, defect 16: multiprocessing's "leaked semaphore" warnings came after the
    last line (interrupted once a cluster is mapped: the workers have run a task)."""
    database, images, _ = env.assets.big
    return _hierarchical(env, "--leaf_max_num_images", "12", "--image_overlap", "2",
                         "--num_workers", "2", database=env.copy(database))


def _killed_then_run_again(marker: str) -> Callable:
    """A runner: the command killed (SIGKILL) once `marker` is on stderr, then run again."""
    def run(env: Env, args: list[str]) -> subprocess.CompletedProcess:
        killed = Running(env, args)
        assert killed.wait_for(marker), f"the run finished before {marker!r}\n{killed.stderr}"
        killed.process.kill()
        killed.result()
        left = [p.name for folder in (env.out, env.tmp) for p in folder.iterdir()
                if p.name.startswith(TEMP_PREFIXES)]
        assert left, "the killed run left nothing to clean up"
        env.notes.append(f"the killed run left {sorted(left)}")
        return run_cli(env, args)
    return run


@case("mapper_removes_a_killed_runs_leftovers", "Registered", code=0,
      run=_killed_then_run_again("registered:"))
def _(env):
    """Issue 45, defect 17: after kill -9, OUT/.colmap-ext-* and TMPDIR/colmap-ext-db-*
    stayed for ever; the next run removes them (the harness checks none is left)."""
    database, images, _ = env.assets.big
    return env.mapper(env.copy(database), env.copy(images), None, "--overwrite", "--seed", "0")


@case("reconstruct_removes_a_killed_runs_leftovers", "Model 0:", code=0, command="reconstruct",
      run=_killed_then_run_again("extract"))
def _(env):
    """Issue 45, defect 17: after kill -9, WS/.colmap-ext-* and TMPDIR/colmap-ext-sift-*
    stayed for ever."""
    args = _reconstruct_over_a_workspace(env)
    env.protected.remove(env.out)  # the second run replaces the workspace
    return args


# ---- Ray and hierarchical_mapper


def unreachable_address() -> str:
    """HOST:PORT where nothing listens (a port just bound and released)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{sock.getsockname()[1]}"


@case("reconstruct_ray_unreachable", "cannot reach the Ray cluster at 127.0.0.1:",
      command="reconstruct")
def _(env):
    return _reconstruct(env, "--ray_address", unreachable_address())


@case("reconstruct_ray_unreachable_keeps_the_old_database",
      "cannot reach the Ray cluster at 127.0.0.1:", command="reconstruct")
def _(env):
    args = _reconstruct(env, "--overwrite", "--ray_address", unreachable_address())
    env.out.mkdir()
    shutil.copyfile(env.assets.small[0], env.out / "database.db")
    env.protected.append(env.out)
    return args


def _reconstruct_over_a_workspace(env) -> list[str]:
    """reconstruct --overwrite on the rendered ring, over the workspace of an earlier run."""
    shutil.copytree(env.assets.workspace, env.out)
    env.protected.append(env.out)
    return ["reconstruct", "--image_path", str(env.copy(env.assets.ring[0], "images")),
            "--workspace_path", str(env.out), "--camera_model", "PINHOLE",
            "--camera_params", ",".join(map(str, RING_PARAMS)), "--seed", "0", "--overwrite"]


# Issue 33, defect 3: an interrupt replaced WS/database.db with a partial one while the
# old sparse/0 stayed. Now each moment leaves the earlier workspace whole.
@case("reconstruct_ctrl_c_while_extracting", "interrupted by SIGINT", code=130,
      command="reconstruct", run=interrupted("extract", delay=0.0))
def _(env):
    return _reconstruct_over_a_workspace(env)


@case("reconstruct_sigterm_while_verifying", "interrupted by SIGTERM", code=143,
      command="reconstruct", run=interrupted("match and verify", signal.SIGTERM, delay=0.0))
def _(env):
    return _reconstruct_over_a_workspace(env)


@case("reconstruct_ctrl_c_while_mapping", "interrupted by SIGINT", code=130,
      command="reconstruct", run=interrupted("registered:"))
def _(env):
    return _reconstruct_over_a_workspace(env)


@case("reconstruct_ray_address_malformed", "--ray_address must be auto, local or HOST:PORT",
      command="reconstruct")
def _(env):
    return _reconstruct(env, "--ray_address", "cluster.example")


def _hierarchical(env, *extra: str, database: Path | None = None) -> list[str]:
    return ["hierarchical_mapper", "--database_path", str(database or env.small_db()),
            "--image_path", str(env.images()), "--output_path", str(env.out), *extra]


@case("hier_db_missing", "database not found", command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, database=env.inputs / "nope.db")


@case("hier_not_sqlite", "not an SQLite database", command="hierarchical_mapper")
def _(env):
    (env.inputs / "database.db").write_text("not a database")
    return _hierarchical(env, database=env.inputs / "database.db")


@case("hier_leaf_too_small", "--leaf_max_num_images must be at least 3",
      command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--leaf_max_num_images", "2")


@case("hier_leaf_not_a_number", "invalid int value", code=2, command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--leaf_max_num_images", "many")


@case("hier_negative_overlap", "--image_overlap must be >= 0", command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--image_overlap", "-5")


@case("hier_zero_workers", "--num_workers must be positive or -1", command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--num_workers", "0")


@case("hier_ray_unreachable", "cannot reach the Ray cluster at 127.0.0.1:",
      command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--ray_address", unreachable_address())


@case("hier_missing_database_flag", "the following arguments are required: --database_path",
      code=2, command="hierarchical_mapper")
def _(env):
    return ["hierarchical_mapper", "--image_path", str(env.images()), "--output_path", str(env.out)]


@case("hier_previous_model", "already holds a model; pass --overwrite",
      command="hierarchical_mapper")
def _(env):
    env.previous_model()
    return _hierarchical(env)


@case("hier_unknown_mapper_flag", "unrecognized arguments: --Mapper.no_such_option", code=2,
      command="hierarchical_mapper")
def _(env):
    return _hierarchical(env, "--Mapper.no_such_option", "1")


# ---------------------------------------------------------------- running and checking


def child_env(env: Env) -> dict[str, str]:
    return {**os.environ, "TMPDIR": str(env.tmp), "HOME": str(env.home),
            "MPLCONFIGDIR": str(env.home), "PYTHONDONTWRITEBYTECODE": "1"}


def run_cli(env: Env, args: list[str], cli: list[str] = CLI, **options) -> subprocess.CompletedProcess:
    return subprocess.run([*cli, *args], capture_output=True, text=True, timeout=300,
                          env=child_env(env), cwd=env.root, **options)


def snapshot(paths: list[Path]) -> dict[str, tuple | None]:
    """Every file's bytes (hash) and mode, every folder's mode, under `paths`."""
    state: dict[str, tuple | None] = {}
    for top in paths:
        if not top.exists():
            state[str(top)] = None
            continue
        for path in [top, *sorted(top.rglob("*"))] if top.is_dir() else [top]:
            mode = path.lstat().st_mode
            if path.is_dir():
                state[str(path)] = ("folder", mode)
            else:
                try:
                    state[str(path)] = ("file", mode, sha256(path))
                except PermissionError:  # chmod 000 when not root
                    state[str(path)] = ("file", mode, path.stat().st_size)
    return state


def message_lines(stderr: str) -> list[str]:
    """stderr without progress bars: what the user reads."""
    lines = [segment.strip() for line in stderr.split("\n") for segment in line.split("\r")]
    return [line for line in lines if line and not PROGRESS_LINE.search(line)]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, assets, commands, unprivileged, tmp_path, request):
    assert case.command in commands, f"`colmap-ext --help` lists no {case.command} subcommand"
    if case.xfail:
        request.applymarker(pytest.mark.xfail(reason=case.xfail, strict=True))
    as_nobody = case.unprivileged and IS_ROOT
    if case.unprivileged and unprivileged:
        pytest.skip(unprivileged)
    root = Path(tempfile.mkdtemp(prefix="bad-input-", dir="/tmp")) if as_nobody else tmp_path
    try:
        env = Env(root / "case", assets, home=root / "case" / "home" if as_nobody else None)
        args = case.build(env)
        if as_nobody:  # the user nobody owns the case folder; modes stay as built
            os.chmod(root, 0o755)
            for path in [env.root, *env.root.rglob("*")]:
                os.lchown(path, NOBODY, NOBODY)
        watched = [env.inputs, *env.protected]
        before = snapshot(watched)
        if case.run is not None:
            result = case.run(env, args)
        elif as_nobody:
            result = run_cli(env, args, user=NOBODY, group=NOBODY, extra_groups=[])
        else:
            result = run_cli(env, args)
        check(case, env, result, before, watched)
    finally:
        if as_nobody:
            for path in [root, *root.rglob("*")]:
                path.chmod(0o700)
            shutil.rmtree(root)
        else:
            for path in [root, *root.rglob("*")]:  # chmod 000 would stop pytest's clean-up
                if path.is_dir() or path.is_file():
                    path.chmod(0o700)


def check(case: Case, env: Env, result: subprocess.CompletedProcess, before: dict,
          watched: list[Path]) -> None:
    said = f"exit {result.returncode}\n--- stdout\n{result.stdout}\n--- stderr\n{result.stderr}"
    assert "Traceback" not in result.stderr, said
    assert result.returncode == case.code, said
    lines = message_lines(result.stderr)
    if case.code == 0:
        assert case.message in result.stdout, said
    elif case.code in INTERRUPTED_CODES:  # the stage's own log lines, then one line, no stack dump
        assert "stack trace" not in result.stderr and "*** " not in result.stderr, said
        assert lines[-1].startswith("colmap-ext: ") and case.message in lines[-1], said
    elif case.code == 2:  # a command-line error: one line, as COLMAP's
        assert len(lines) == 1, f"expected one line on stderr\n{said}"
        assert lines[0].startswith("colmap-ext ") and case.message in lines[0], said
    else:
        assert len(lines) == 1, f"expected one line on stderr\n{said}"
        assert lines[0].startswith("colmap-ext: "), said
        assert case.message in lines[0], said
    assert snapshot(watched) == before, f"an input or a previous model changed\n{said}"
    left = [p for folder in (env.out, env.tmp, env.root) if folder.is_dir()
            for p in folder.iterdir() if p.name.startswith(TEMP_PREFIXES)]
    left += list(env.tmp.iterdir())
    assert not left, f"temporary files left behind: {left}\n{said}"
    if case.after is not None:
        case.after(env, result)
    for note in env.notes:
        print(note)


def test_case_table_covers_every_subcommand(commands):
    """The help lists every subcommand the CLI defines, and each of them has cases."""
    from colmap_ext.cli import COMMANDS

    assert len(CASES) >= 25
    assert commands == set(COMMANDS), "`colmap-ext --help` does not list the CLI's subcommands"
    assert {c.command for c in CASES} == commands, "a subcommand without cases, or cases without one"


def test_same_seed_same_model_from_the_cli(assets, tmp_path):
    """Two runs with --seed write the same model, bit for bit."""
    database, images, _ = assets.small
    env = Env(tmp_path / "case", assets)
    outputs = []
    for index in range(2):
        out = tmp_path / f"out{index}"
        result = run_cli(env, env.mapper(database, images, out, "--seed", "3"))
        assert result.returncode == 0, result.stderr
        outputs.append({p.name: sha256(p) for p in sorted((out / "0").iterdir())})
    assert outputs[0] == outputs[1], "two runs with --seed 3 wrote different models"
    assert set(outputs[0]) >= {"cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin"}
