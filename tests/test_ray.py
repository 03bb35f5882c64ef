"""`reconstruct --ray_address`: extraction and matching as Ray tasks on a two-node cluster
started here (both nodes on this machine, 127.0.0.1), the database equal table by
table to the single-machine run's, and a worker killed mid-extraction retried.

The nodes are `ray start --block` children, each in a process group of its own, ended by
killing those groups: never `ray stop`, which would end every Ray on the machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pycolmap
import pytest

pytest.importorskip("ray", reason="ray is not installed (pip install 'colmap-ext[ray]'): "
                                  "the Ray tests are skipped")

from colmap_ext.evaluate import evaluate  # noqa: E402
from colmap_ext.features import FeatureOptions, extract_features  # noqa: E402
from colmap_ext.ground_truth import GroundTruth  # noqa: E402
from colmap_ext.reconstruct import main as reconstruct  # noqa: E402
from colmap_ext.synthetic.render import render_images  # noqa: E402
from colmap_ext.synthetic.scene import ring_scene  # noqa: E402

CLI = [sys.executable, "-m", "colmap_ext"]
CAMERA = pycolmap.Camera(camera_id=1, model="OPENCV", width=320, height=240,
                         params=[300.0, 300.0, 159.0, 121.0, -0.1, 0.01, 0.0, 0.0])
PARAMS = ",".join(f"{value:g}" for value in CAMERA.params)
NODE_START_TIMEOUT_S = 90


def free_port() -> int:
    with closing(socket.socket()) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_node(arguments: list[str], log: Path) -> subprocess.Popen:
    """`ray start ... --block` in a new session (its own process group)."""
    ray = Path(sys.executable).with_name("ray")
    return subprocess.Popen(
        [str(ray), "start", "--block", "--num-cpus", "1", "--disable-usage-stats",
         "--dashboard-agent-listen-port", str(free_port()),
         "--metrics-export-port", str(free_port()), *arguments],
        stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True,
        env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})


def session_members(session: int) -> list[int]:
    """Pids of the processes in a session: a node's, since it was started in a new one
    (Ray puts each worker in a process group of its own, within the node's session)."""
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.getsid(int(entry.name)) == session:
                    members.append(int(entry.name))
            except OSError:
                continue
    return members


def stop_node(process: subprocess.Popen) -> None:
    """Kill the node's process group (`ray start`, the raylet, the GCS ...), then any
    process left in its session (workers), each by its pid."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            pass
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=5)
        time.sleep(0.5)
        for pid in session_members(process.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)


def count_alive_nodes(address: str) -> int:
    probe = subprocess.run(
        [sys.executable, "-c", "import logging, ray; ray.init(address=%r, logging_level="
         "logging.ERROR); print(sum(n['Alive'] for n in ray.nodes()))" % address],
        capture_output=True, text=True, timeout=60)
    return int(probe.stdout.split()[-1]) if probe.returncode == 0 and probe.stdout.split() else 0


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[tuple[str, list[int]]]:
    """A head and a worker node on 127.0.0.1, one CPU each: (address, the nodes' session
    ids, which are their pids).
    Ray's token authentication is off for this cluster and its drivers (this module's
    processes): it is private to this machine and this test."""
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    # Ray's socket paths live under the temp dir and must stay short: not under pytest's.
    temp = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))
    port = free_port()
    address = f"127.0.0.1:{port}"
    nodes = []
    try:
        nodes.append(start_node(["--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                                 "--include-dashboard", "false",
                                 "--ray-client-server-port", str(free_port()),
                                 "--temp-dir", str(temp / "head")], temp / "head.log"))
        deadline = time.monotonic() + NODE_START_TIMEOUT_S
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline or nodes[0].poll() is not None:
                    pytest.fail(f"the Ray head did not start:\n{(temp / 'head.log').read_text()}")
                time.sleep(0.5)
        nodes.append(start_node(["--address", address, "--node-ip-address", "127.0.0.1",
                                 "--temp-dir", str(temp / "worker")], temp / "worker.log"))
        while count_alive_nodes(address) < 2:
            if time.monotonic() > deadline or nodes[1].poll() is not None:
                pytest.fail(f"the second Ray node did not join:\n{(temp / 'worker.log').read_text()}")
            time.sleep(1)
        yield address, [node.pid for node in nodes]
    finally:
        for node in reversed(nodes):
            stop_node(node)
        shutil.rmtree(temp, ignore_errors=True)
        monkeypatch.undo()


@pytest.fixture(scope="module")
def single_machine(tmp_path_factory) -> tuple[Path, Path, dict]:
    """16 rendered views of the ring scene reconstructed in this process, seed 0:
    (images, workspace, summary)."""
    folder = tmp_path_factory.mktemp("ray_ring")
    scene = ring_scene(num_images=16, seed=0, camera=CAMERA)
    render_images(scene, folder / "images", supersample=1)
    summary = reconstruct(folder / "images", folder / "single", "OPENCV", PARAMS,
                          exact_matching=True, seed=0)
    return folder / "images", folder / "single", summary


def tables(database: Path) -> dict[str, list[tuple]]:
    """Every table's rows, in order."""
    with closing(sqlite3.connect(f"file:{database}?mode=ro", uri=True)) as connection:
        names = [row[0] for row in connection.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
        return {name: connection.execute(f"SELECT * FROM {name} ORDER BY 1").fetchall()
                for name in names}


def registered_names(workspace: Path) -> list[list[str]]:
    """Per model, the names of its registered images."""
    return [sorted(image.name for image in pycolmap.Reconstruction(model).images.values())
            for model in sorted((workspace / "sparse").iterdir()) if model.name.isdigit()]


def assert_same_database(database: Path, reference: Path) -> None:
    got, expected = tables(database), tables(reference)
    assert sorted(got) == sorted(expected)
    for name, rows in expected.items():
        assert len(got[name]) == len(rows), f"table {name}: {len(got[name])} rows, not {len(rows)}"
        assert got[name] == rows, f"table {name} differs"
    assert len(expected["keypoints"]) == 16 and len(expected["two_view_geometries"]) > 16


def run_distributed(images: Path, workspace: Path, address: str) -> subprocess.Popen:
    return subprocess.Popen([*CLI, "reconstruct", "--image_path", str(images),
                             "--workspace_path", str(workspace), "--camera_model", "OPENCV",
                             "--camera_params", PARAMS, "--exact_matching", "--seed", "0",
                             "--ray_address", address],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_distributed_reconstruct_writes_the_same_database(ray_cluster, single_machine, tmp_path):
    """Extraction over chunks and matching over blocks of pairs, on both nodes: every
    table of the database equal to the single-machine run's (both exact matching), row
    for row, and the same images registered in the same models."""
    address, _ = ray_cluster
    images, reference, reference_summary = single_machine
    process = run_distributed(images, tmp_path / "ws", address)
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    assert_same_database(tmp_path / "ws" / "database.db", reference / "database.db")
    assert registered_names(tmp_path / "ws") == registered_names(reference)
    summary = json.loads((tmp_path / "ws" / "reconstruct_summary.json").read_text())
    assert summary["ray"] == {"num_nodes": 2, "num_cpus": 2, "images": "by path"}
    assert summary["inputs"]["exact_matching"] and "Matching (exhaustive, exact)" in stdout
    assert summary["features"]["images"] == reference_summary["features"]["images"]
    assert summary["matching"]["pairs"] == reference_summary["matching"]["pairs"]
    assert not [p for p in (tmp_path / "ws").iterdir() if p.name.startswith(".colmap-ext-")]


def extraction_workers(sessions: list[int]) -> list[int]:
    """Pids of the cluster's worker processes running an extraction task now (Ray names
    a busy worker after its task)."""
    found = []
    for pid in (pid for session in sessions for pid in session_members(session)):
        try:
            title = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0]
        except OSError:
            continue
        if title.startswith(b"ray::extract_chunk"):
            found.append(pid)
    return found


def test_worker_killed_during_extraction_is_retried(ray_cluster, single_machine, tmp_path):
    """A worker process killed (SIGKILL) while it extracts a chunk: Ray runs the task
    again, the run completes, and the database is complete, equal to the
    single-machine one (nothing lost, nothing written twice)."""
    address, sessions = ray_cluster
    images, reference, _ = single_machine
    process = run_distributed(images, tmp_path / "ws", address)
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and process.poll() is None and time.monotonic() < deadline:
        busy = extraction_workers(sessions)
        if busy:
            os.kill(busy[0], signal.SIGKILL)
            killed = busy[0]
        time.sleep(0.02)
    stdout, stderr = process.communicate(timeout=300)
    assert killed is not None, "no extraction task was seen running: nothing was killed"
    assert process.returncode == 0, stderr
    assert_same_database(tmp_path / "ws" / "database.db", reference / "database.db")
    assert registered_names(tmp_path / "ws") == registered_names(reference)


def test_images_sent_as_bytes_give_the_same_features(ray_cluster, single_machine, tmp_path):
    """Nodes without the driver's file system get the images as bytes: the same
    keypoints and descriptors."""
    from colmap_ext import distributed

    address, _ = ray_cluster
    images, reference, _ = single_machine
    with distributed.connect(address, images_by_path=False) as cluster:
        extract_features(tmp_path / "database.db", images, FeatureOptions("OPENCV", PARAMS),
                         executor=cluster, progress=False)
    got, expected = tables(tmp_path / "database.db"), tables(reference / "database.db")
    for name in ("cameras", "images", "keypoints", "descriptors"):
        assert got[name] == expected[name], name


def test_hierarchical_mapper_maps_clusters_as_ray_tasks(ray_cluster, single_machine, tmp_path):
    """`hierarchical_mapper --ray_address`: the 16-view ring's database cut into two
    clusters of 8 + 4 overlapping images, each mapped by a task on the cluster, joined
    into one model of every image the flat mapper registered."""
    address, _ = ray_cluster
    images, reference, _ = single_machine
    out = tmp_path / "out"
    result = subprocess.run(
        [*CLI, "hierarchical_mapper", "--database_path", str(reference / "database.db"),
         "--image_path", str(images), "--output_path", str(out), "--leaf_max_num_images", "8",
         "--image_overlap", "4", "--seed", "0", "--ray_address", address],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "mapper_summary.json").read_text())
    assert [c["num_images"] for c in summary["clusters"]] == [12, 12]
    model = pycolmap.Reconstruction(out / "0")
    assert sorted(image.name for image in model.images.values()) == registered_names(reference)[0]
    assert model.compute_mean_reprojection_error() < 1.0


def test_hierarchical_mapper_joins_a_sequence_mapped_as_ray_tasks(ray_cluster, write_drive,
                                                                   tmp_path):
    """`hierarchical_mapper --ray_address` on a synthetic drive of 100 frames (each
    matched with the next 10) in a chain of 4 clusters, one task each: one model of
    every frame, its rotations within 0.3 deg of the truth (test_hierarchical_mapper's
    drive bound)."""
    address, _ = ray_cluster
    frames = 100
    scene = write_drive(tmp_path, frames)
    out = tmp_path / "out"
    result = subprocess.run(
        [*CLI, "hierarchical_mapper", "--database_path", str(tmp_path / "database.db"),
         "--image_path", str(tmp_path / "images"), "--output_path", str(out),
         "--leaf_max_num_images", "25", "--image_overlap", "10", "--seed", "0",
         "--ray_address", address],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "mapper_summary.json").read_text())
    assert len(summary["clusters"]) == 4
    assert summary["num_models"] == 1 and summary["num_registered"] == frames
    model = pycolmap.Reconstruction(out / "0")
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    assert evaluate(model, truth)["R_err_max_deg"] < 0.3
