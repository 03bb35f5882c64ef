"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session")
def write_drive():
    """A function that writes a synthetic drive of `num_frames` into `folder` and returns
    its scene: `driving_scene` with a corner every 40 m or so and 8 frames standing still
    every 50; database.db with 500 keypoints an image, 0.5 px noise, 20 % wrong matches,
    each frame matched with the next 10 (COLMAP's sequential matching), verified
    geometries; placeholder images/ (our mapper reads point colours)."""
    from colmap_ext.synthetic import (driving_scene, points_for_keypoints, sequential_pairs,
                                      write_placeholder_images, write_synthetic_database)

    def write(folder: Path, num_frames: int):
        scene = driving_scene(num_images=num_frames, seed=0, block_length=40.0, stop_every=50,
                              stop_frames=8)
        write_synthetic_database(folder / "database.db", scene,
                                 points_for_keypoints(scene, 500, seed=0, max_distance=40.0),
                                 noise_px=0.5, outlier_ratio=0.2, max_distance=40.0, seed=0,
                                 two_view_geometries=True, pairs=sequential_pairs(num_frames, 10))
        write_placeholder_images(folder / "images", scene.image_names)
        return scene
    return write


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The folder of real image sets with ground truth (COLMAP_EXT_DATA, as .ci/run sets
    it); tests that need it are skipped, saying so, when it is not set."""
    data = os.environ.get("COLMAP_EXT_DATA")
    if not data:
        pytest.skip("COLMAP_EXT_DATA is not set (the folder holding templeSparseRing/ and "
                    "dinoSparseRing/): the real-data test is skipped")
    return Path(data)


@pytest.fixture(scope="session")
def synthetic_ring(tmp_path_factory):
    """A 12-view ring database (0.5 px noise, 20 % wrong matches), blank images (the
    mapper reads point colours from them) and the scene: (folder, scene). Read only."""
    import cv2

    from colmap_ext.synthetic.database import scene_points, write_synthetic_database
    from colmap_ext.synthetic.scene import ring_scene

    folder = tmp_path_factory.mktemp("synthetic_ring")
    scene = ring_scene(num_images=12, seed=3)
    write_synthetic_database(folder / "database.db", scene, scene_points(scene, 1500, seed=3),
                             noise_px=0.5, outlier_ratio=0.2, seed=3)
    (folder / "images").mkdir()
    for name in scene.image_names:
        cv2.imwrite(str(folder / "images" / name), np.zeros((8, 8), np.uint8))
    return folder, scene


@pytest.fixture(scope="session")
def record_figures():
    """A context manager listing every (Figure, path) that colmap_ext.plots saves within it;
    the figures are still saved."""
    from colmap_ext import plots

    @contextmanager
    def record() -> Iterator[list]:
        saved: list = []
        save = plots._save

        def keep(figure, path):
            saved.append((figure, Path(path)))
            save(figure, path)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(plots, "_save", keep)
            yield saved

    return record


def _assert_figure_shows(figure, reports: dict[str, dict]) -> None:
    """Per report (colour C0, C1, ... in order), the left panel draws exactly its per-image
    R_err and T_err, the right one C_err and C_err_aligned, against the 1-based image index
    (NaN where unregistered), with an x at 0 per unregistered image; the legend names each
    report with its registered count."""
    panels = zip(figure.axes, ((("R_err_deg", "o"), ("T_err_deg", "s")),
                               (("C_err", "o"), ("C_err_aligned", "^"))))
    for axes, series in panels:
        lines = {(line.get_color(), line.get_marker()): line for line in axes.get_lines()}
        expected = set()
        for index, (label, report) in enumerate(reports.items()):
            colour, entries = f"C{index}", report["per_image"]
            image_index = np.arange(1, len(entries) + 1)
            for key, marker in series:
                expected.add((colour, marker))
                assert (colour, marker) in lines, f"no {key} line in {colour} for {label}"
                values = [np.nan if entry[key] is None else entry[key] for entry in entries]
                np.testing.assert_array_equal(lines[colour, marker].get_xdata(), image_index)
                np.testing.assert_array_equal(lines[colour, marker].get_ydata(), values, err_msg=key)
            missing = image_index[[entry[series[0][0]] is None for entry in entries]]
            if missing.size:
                expected.add((colour, "x"))
                assert (colour, "x") in lines, f"no x for the unregistered images of {label}"
                np.testing.assert_array_equal(lines[colour, "x"].get_xdata(), missing)
                np.testing.assert_array_equal(lines[colour, "x"].get_ydata(), 0)
        assert set(lines) == expected and len(axes.get_lines()) == len(expected)
    [legend] = figure.legends
    assert [text.get_text() for text in legend.get_texts()] == [
        f"{label} ({report['num_registered']}/{report['num_gt_images']} registered)"
        for label, report in reports.items()]


@pytest.fixture(scope="session")
def assert_figure_shows():
    """The check that a saved errors figure draws exactly the given reports (label -> report)."""
    return _assert_figure_shows


_SCENE_MARKS = ("points", "truth centres", "estimated centres", "unregistered")
_SCENE_SEGMENTS = ("truth directions", "estimated directions", "errors")


def _scene_data(figure) -> dict:
    """What a scene figure draws, by artist gid, in view coordinates (u, v, w): u and v from
    the top view, w from the side view, whose u must be the top view's. Marks are (n,3),
    segments (n,2,3); "named" lists the image names written beside cameras."""
    top, side = figure.axes
    data = {}
    for gid in _SCENE_MARKS:
        [above] = [line for line in top.get_lines() if line.get_gid() == gid]
        [beside] = [line for line in side.get_lines() if line.get_gid() == gid]
        np.testing.assert_array_equal(above.get_xdata(), beside.get_xdata(), err_msg=gid)
        data[gid] = np.column_stack([above.get_xdata(), above.get_ydata(), beside.get_ydata()])
    for gid in _SCENE_SEGMENTS:
        [above] = [lines for lines in top.collections if lines.get_gid() == gid]
        [beside] = [lines for lines in side.collections if lines.get_gid() == gid]
        above = np.array(above.get_segments()).reshape(-1, 2, 2)
        beside = np.array(beside.get_segments()).reshape(-1, 2, 2)
        np.testing.assert_array_equal(above[:, :, 0], beside[:, :, 0], err_msg=gid)
        data[gid] = np.concatenate([above, beside[:, :, 1:]], axis=2)
    names = [[text.get_text() for text in axes.texts if text.get_gid() == "named"]
             for axes in (top, side)]
    assert names[0] == names[1]
    data["named"] = names[0]
    return data


def _assert_scene_shows(figure, truth: dict, cameras: dict, points: np.ndarray,
                        report: dict, max_points: int | None = None) -> dict:
    """The scene figure draws, in the axes of `plots.view_frame(truth)`, within 1e-9: the
    ground-truth centres (cam_from_world `truth`); the aligned estimated centres `cameras`
    (by name), each as far from its ground truth as the report's C_err_aligned says; one
    viewing-direction segment per camera, along its optical axis; an x on exactly the
    unregistered ground-truth centres; and only points of `points`, all of them up to
    `max_points` (by default the figure's). Returns the figure's data (`_scene_data`)."""
    from colmap_ext.plots import MAX_SCENE_POINTS, view_frame

    view = view_frame(list(truth.values()))
    data = _scene_data(figure)
    names = list(truth)
    registered = [name for name in names if name in cameras]
    assert len(registered) == len(cameras) == report["num_registered"]

    def in_view(poses: list) -> tuple[np.ndarray, np.ndarray]:
        centres = np.array([pose.inverse().translation for pose in poses])
        axes = np.array([pose.rotation.matrix()[2] for pose in poses])  # R^T (0, 0, 1)
        return view * centres, view.rotation * axes

    truth_centres, truth_axes = in_view(list(truth.values()))
    estimated, estimated_axes = in_view([cameras[name] for name in registered])
    np.testing.assert_allclose(data["truth centres"], truth_centres, rtol=0, atol=1e-9)
    np.testing.assert_allclose(data["estimated centres"], estimated, rtol=0, atol=1e-9)

    truth_registered = truth_centres[[names.index(name) for name in registered]]
    unit = np.linalg.norm(truth_registered[1] - truth_registered[0])
    by_name = {entry["name"]: entry for entry in report["per_image"]}
    np.testing.assert_allclose(
        np.linalg.norm(data["estimated centres"] - truth_registered, axis=1) / unit,
        [by_name[name]["C_err_aligned"] for name in registered], rtol=0, atol=1e-9)

    for gid, centres, axes in (("truth directions", truth_centres, truth_axes),
                               ("estimated directions", estimated, estimated_axes)):
        segments = data[gid]
        assert len(segments) == len(centres), gid
        np.testing.assert_allclose(segments[:, 0], centres, rtol=0, atol=1e-9, err_msg=gid)
        steps = segments[:, 1] - segments[:, 0]
        lengths = np.linalg.norm(steps, axis=1)
        assert lengths.min() > 0 and np.ptp(lengths) < 1e-9 * lengths.max(), gid
        np.testing.assert_allclose(steps / lengths[:, None], axes, rtol=0, atol=1e-9, err_msg=gid)
    np.testing.assert_allclose(data["errors"], np.stack([truth_registered, estimated], axis=1),
                               rtol=0, atol=1e-9)

    unregistered = [names.index(name) for name in names if name not in cameras]
    assert len(unregistered) == report["num_gt_images"] - report["num_registered"]
    np.testing.assert_allclose(data["unregistered"], truth_centres[unregistered], rtol=0,
                               atol=1e-9)

    drawn, model = data["points"], view * np.asarray(points).reshape(-1, 3)
    assert len(drawn) == min(len(model), max_points or MAX_SCENE_POINTS)
    # Each drawn point is a model point, drawn at most as often as the model holds it (a
    # model may hold two points at one place): count per first model index at that place.
    drawn_per_place: dict[int, int] = {}
    copies_per_place: dict[int, int] = {}
    for chunk in np.array_split(drawn, len(drawn) // 64 + 1):  # bounded memory
        if len(chunk):
            here = np.linalg.norm(chunk[:, None] - model[None], axis=2) < 1e-9
            assert here.any(axis=1).all(), "a drawn point is not a model point"
            for place, copies in zip(here.argmax(axis=1).tolist(), here.sum(axis=1).tolist()):
                drawn_per_place[place] = drawn_per_place.get(place, 0) + 1
                copies_per_place[place] = copies
    assert all(drawn_per_place[place] <= copies_per_place[place] for place in drawn_per_place), \
        "a point is drawn more often than the model holds it"
    return data


@pytest.fixture(scope="session")
def assert_scene_shows():
    """The check that a saved scene figure draws exactly the given cameras and points."""
    return _assert_scene_shows
