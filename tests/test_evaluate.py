"""Evaluation measures on hand-made poses with known answers, the report, the CLI step and the plots."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from colmap_ext.errors import UserError
from colmap_ext.evaluate import (
    add_arguments,
    aligned_to_ground_truth,
    evaluate,
    evaluate_and_write,
    main,
    rotation_angles_deg,
    scene_plot_path,
    vector_angles_deg,
)
from colmap_ext.ground_truth import GroundTruth, read_ground_truth, to_reconstruction
from colmap_ext.plots import plot_errors, plot_scene, view_frame

REPORT_KEYS = {
    "num_gt_images", "num_registered", "R_err_max_deg", "R_err_median_deg", "T_err_max_deg",
    "T_err_median_deg", "C_err_max", "C_err_median", "C_err_aligned_max", "C_err_aligned_median",
    "AUC_percent", "per_image",
}
PER_IMAGE_KEYS = {"name", "R_err_deg", "T_err_deg", "C_err", "C_err_aligned"}
CAMERA = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[1500, 1500, 320, 240])


def rotation(axis_angle) -> pycolmap.Rotation3d:
    return pycolmap.Rotation3d(np.asarray(axis_angle, dtype=float))


def pose_at(R: pycolmap.Rotation3d, centre) -> pycolmap.Rigid3d:
    """cam_from_world of a camera with rotation R at world position `centre`."""
    return pycolmap.Rigid3d(R, -R.matrix() @ np.asarray(centre, dtype=float))


def ground_truth(poses: dict[str, pycolmap.Rigid3d]) -> GroundTruth:
    return GroundTruth(poses=dict(poses), cameras={name: CAMERA for name in poses})


def model(poses: dict[str, pycolmap.Rigid3d]) -> pycolmap.Reconstruction:
    return to_reconstruction(ground_truth(poses))


def ring(count: int = 8) -> dict[str, pycolmap.Rigid3d]:
    """Cameras on a tilted ring looking roughly at the origin, named img00.png, img01.png, ..."""
    poses = {}
    for index in range(count):
        angle = 2 * np.pi * index / count
        centre = [2 * np.cos(angle), 2 * np.sin(angle), 0.5 + 0.2 * np.sin(3 * angle)]
        R = rotation([0.3, 0.1 * index, angle])
        poses[f"img{index:02d}.png"] = pose_at(R, centre)
    return poses


def errors_of(report: dict, key: str) -> np.ndarray:
    return np.array([np.nan if entry[key] is None else entry[key] for entry in report["per_image"]])


def rotated_in_place(pose: pycolmap.Rigid3d, R: pycolmap.Rotation3d) -> pycolmap.Rigid3d:
    """The camera turned by R about its own centre (R applied in the camera frame)."""
    return pycolmap.Rigid3d(R, np.zeros(3)) * pose


# --- measures with known answers ----------------------------------------------------------


def test_identical_model_has_zero_errors_and_exact_keys() -> None:
    report = evaluate(model(ring()), ground_truth(ring()))
    assert set(report) == REPORT_KEYS
    assert all(set(entry) == PER_IMAGE_KEYS for entry in report["per_image"])
    assert (report["num_gt_images"], report["num_registered"]) == (8, 8)
    for key in REPORT_KEYS - {"per_image", "num_gt_images", "num_registered", "AUC_percent"}:
        assert report[key] == pytest.approx(0.0, abs=1e-9), key
    assert report["AUC_percent"] == {"0.5": 100.0, "1": 100.0, "5": 100.0, "10": 100.0}


def test_relative_pose_auc_of_a_hand_computed_example() -> None:
    """Four cameras facing +z: img0 at the origin, turned 2 deg about z in the estimate
    (its rotation and every translation direction it takes part in are 2 deg off), img3
    unregistered. 12 ordered pairs: (1,2) and (2,1) exact, the 4 with img0 at 2 deg, the 6
    with img3 infinite. Recall: 2/12 from 0 deg, rising linearly to 3/12 at 2 deg, 6/12
    after. AUC@0.5 and @1: 2/12; @5: (2 * (2 + 3) / 2 + 3 * 6) / 12 / 5 = 23/60;
    @10: (5 + 8 * 6) / 12 / 10 = 53/120."""
    truth = {f"img{index}.png": pose_at(rotation([0, 0, 0]), centre)
             for index, centre in enumerate([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)])}
    estimate = dict(truth)
    estimate["img0.png"] = rotated_in_place(truth["img0.png"], rotation([0, 0, np.radians(2)]))
    del estimate["img3.png"]
    auc = evaluate(model(estimate), ground_truth(truth))["AUC_percent"]
    assert list(auc) == ["0.5", "1", "5", "10"]
    np.testing.assert_allclose(list(auc.values()), [100 * 2 / 12, 100 * 2 / 12, 100 * 23 / 60,
                                                    100 * 53 / 120], atol=1e-9)


def test_rotation_perturbation_of_one_image() -> None:
    estimate = ring()
    estimate["img03.png"] = rotated_in_place(estimate["img03.png"], rotation([0, 0, np.radians(0.3)]))
    report = evaluate(model(estimate), ground_truth(ring()))
    R_err = errors_of(report, "R_err_deg")
    assert R_err[3] == pytest.approx(0.3, abs=1e-12)
    np.testing.assert_allclose(np.delete(R_err, 3), 0.0, atol=1e-12)
    np.testing.assert_allclose(errors_of(report, "C_err"), 0.0, atol=1e-12)
    assert report["R_err_max_deg"] == pytest.approx(0.3, abs=1e-12)


def test_rotation_perturbation_of_reference_shows_on_every_other_image() -> None:
    estimate = ring()
    estimate["img00.png"] = rotated_in_place(estimate["img00.png"], rotation(np.radians([0.3, 0, 0])))
    R_err = errors_of(evaluate(model(estimate), ground_truth(ring())), "R_err_deg")
    assert R_err[0] == 0.0
    np.testing.assert_allclose(R_err[1:], 0.3, atol=1e-12)


@pytest.mark.parametrize("degrees", [1e-6, 1e-3, 0.3, 45.0, 90.0, 179.0])
def test_rotation_angle_is_accurate_from_tiny_to_large(degrees: float) -> None:
    R = rotation(np.radians(degrees) * np.array([2.0, -1.0, 2.0]) / 3).matrix()
    assert rotation_angles_deg(R[None])[0] == pytest.approx(degrees, rel=1e-9)


@pytest.mark.parametrize("degrees", [1e-7, 0.3, 90.0, 180.0])
def test_vector_angle_is_accurate_from_tiny_to_large(degrees: float) -> None:
    a = np.array([[2.0, 0.0, 0.0]])
    b = 5 * np.array([[np.cos(np.radians(degrees)), np.sin(np.radians(degrees)), 0.0]])
    assert vector_angles_deg(a, b)[0] == pytest.approx(degrees, rel=1e-9)


def square(z_offsets=(0.0, 0.0, 0.0, 0.0)) -> dict[str, pycolmap.Rigid3d]:
    """Four world-aligned cameras on the unit square, adjacent first two (|C2 - C1| = 1)."""
    corners = [(0.5, 0.5), (0.5, -0.5), (-0.5, -0.5), (-0.5, 0.5)]
    return {f"sq{i}.png": pose_at(rotation([0, 0, 0]), (x, y, z))
            for i, ((x, y), z) in enumerate(zip(corners, z_offsets))}


def test_perturbed_centres_give_expected_errors() -> None:
    """Diagonal corners lifted by +h and -h: every measure has a closed form.

    Relative to camera 1 the estimated centres are (0,0,0), (0,-1,-2h), (-1,-1,0), (-1,0,-2h);
    their spread is 2 + 4h^2 against 2, so s = sqrt(2 / (2 + 4h^2)). The best similarity is
    the identity rotation with scale 1 / (1 + 2h^2) about the common centroid.
    """
    h = 0.05
    report = evaluate(model(square((h, -h, h, -h))), ground_truth(square()))
    s = np.sqrt(2 / (2 + 4 * h**2))
    side = np.hypot(1 - s, 2 * h * s)
    np.testing.assert_allclose(errors_of(report, "C_err"), [0, side, np.sqrt(2) * (1 - s), side], atol=1e-12)
    scale = 1 / (1 + 2 * h**2)
    aligned = np.hypot(np.sqrt(0.5) * (1 - scale), scale * h)
    np.testing.assert_allclose(errors_of(report, "C_err_aligned"), 4 * [aligned], atol=1e-12)
    lift = np.degrees(np.arctan(2 * h))
    np.testing.assert_allclose(errors_of(report, "T_err_deg"), [0, lift, 0, lift], atol=1e-12)
    np.testing.assert_allclose(errors_of(report, "R_err_deg"), 0.0, atol=1e-12)
    assert report["C_err_max"] == pytest.approx(side)
    assert report["C_err_median"] == pytest.approx((side + np.sqrt(2) * (1 - s)) / 2)


def test_perturbed_centre_is_measured_in_units_of_first_baseline() -> None:
    """The same model in a ground truth ten times larger gives the same C_err."""
    def scaled(poses, factor):
        return {n: pycolmap.Rigid3d(p.rotation, factor * p.translation) for n, p in poses.items()}

    estimate = square((0.0, 0.0, 0.0, 0.1))
    small = evaluate(model(estimate), ground_truth(square()))
    large = evaluate(model(scaled(estimate, 10)), ground_truth(scaled(square(), 10)))
    np.testing.assert_allclose(errors_of(large, "C_err"), errors_of(small, "C_err"), atol=1e-12)
    assert small["C_err_max"] > 0.05


@settings(max_examples=25, deadline=None)
@given(
    scale=st.floats(0.01, 100.0),
    axis_angle=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    shift=st.lists(st.floats(-100.0, 100.0), min_size=3, max_size=3),
)
def test_similar_copy_of_ground_truth_has_zero_errors(scale, axis_angle, shift) -> None:
    reconstruction = model(ring())
    reconstruction.transform(pycolmap.Sim3d(scale, rotation(axis_angle), np.array(shift)))
    report = evaluate(reconstruction, ground_truth(ring()))
    for key in ("R_err_deg", "T_err_deg", "C_err", "C_err_aligned"):
        np.testing.assert_allclose(errors_of(report, key), 0.0, atol=1e-7, err_msg=key)


def test_aligned_error_never_exceeds_first_camera_error_in_sum_of_squares() -> None:
    rng = np.random.default_rng(4)
    estimate = {name: pose_at(pose.rotation, pose.inverse().translation + rng.normal(0, 0.05, 3))
                for name, pose in ring().items()}
    report = evaluate(model(estimate), ground_truth(ring()))
    assert np.sum(errors_of(report, "C_err_aligned") ** 2) <= np.sum(errors_of(report, "C_err") ** 2)
    assert report["C_err_aligned_max"] > 0


def test_view_from_the_reference_centre_has_no_translation_direction() -> None:
    """A ring closed on itself (last view where the first was) has t = 0: T_err reported as 0."""
    poses = ring(4)
    poses["img04.png"] = rotated_in_place(poses["img00.png"], rotation([0, 0.2, 0]))
    estimate = dict(poses, **{"img04.png": pose_at(poses["img04.png"].rotation,
                                                   poses["img04.png"].inverse().translation + 0.01)})
    report = evaluate(model(estimate), ground_truth(poses))
    assert errors_of(report, "T_err_deg")[4] == 0.0
    assert errors_of(report, "C_err")[4] > 0


# --- matching, unregistered and refused input ---------------------------------------------


def test_unregistered_images_are_counted_and_null() -> None:
    estimate = {name: pose for name, pose in ring().items() if name not in ("img02.png", "img05.png")}
    report = evaluate(model(estimate), ground_truth(ring()))
    assert (report["num_gt_images"], report["num_registered"]) == (8, 6)
    for entry in report["per_image"]:
        missing = entry["name"] in ("img02.png", "img05.png")
        assert all((entry[key] is None) == missing for key in PER_IMAGE_KEYS - {"name"})
    assert [entry["name"] for entry in report["per_image"]] == list(ring())


def test_image_without_pose_in_model_is_unregistered() -> None:
    estimate = {name: pose for name, pose in ring().items() if name != "img03.png"}
    reconstruction = model(estimate)
    reconstruction.add_image_with_trivial_frame(pycolmap.Image(name="img03.png", camera_id=1, image_id=99))
    report = evaluate(reconstruction, ground_truth(ring()))
    assert report["num_registered"] == 7
    assert report["per_image"][3]["R_err_deg"] is None


def test_first_gt_image_unregistered_moves_the_reference() -> None:
    estimate = ring()
    del estimate["img00.png"]
    estimate["img01.png"] = rotated_in_place(estimate["img01.png"], rotation([0, np.radians(0.3), 0]))
    R_err = errors_of(evaluate(model(estimate), ground_truth(ring())), "R_err_deg")
    assert np.isnan(R_err[0]) and R_err[1] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(R_err[2:], 0.3, atol=1e-12)


def test_model_images_without_ground_truth_are_ignored_with_a_warning(caplog) -> None:
    estimate = dict(ring(), **{"extra1.png": ring()["img01.png"], "extra2.png": ring()["img02.png"]})
    with caplog.at_level(logging.WARNING, logger="colmap_ext.evaluate"):
        report = evaluate(model(estimate), ground_truth(ring()))
    assert report["num_registered"] == 8
    assert "2 registered model image(s) have no ground truth" in caplog.text


def test_matching_by_basename() -> None:
    estimate = {f"sub/{name}": pose for name, pose in ring().items()}
    report = evaluate(model(estimate), ground_truth(ring()))
    assert report["num_registered"] == 8
    reverse = evaluate(model(ring()), ground_truth({f"cam/{n}": p for n, p in ring().items()}))
    assert reverse["num_registered"] == 8


def test_ambiguous_basename_is_not_matched() -> None:
    poses = ring()
    estimate = dict(poses, **{"a/x.png": poses["img01.png"], "b/x.png": poses["img02.png"]})
    truth = dict(poses, **{"x.png": poses["img03.png"]})
    assert evaluate(model(estimate), ground_truth(truth))["num_registered"] == 8


def test_fewer_than_two_matches_is_refused() -> None:
    with pytest.raises(UserError, match="only 1 registered image"):
        evaluate(model({"img00.png": ring()["img00.png"], "other.png": ring()["img01.png"]}),
                 ground_truth(ring()))


def test_coinciding_estimated_centres_are_refused() -> None:
    estimate = {name: pose_at(pose.rotation, [0, 0, 0]) for name, pose in ring().items()}
    with pytest.raises(UserError, match="estimated camera centres coincide"):
        evaluate(model(estimate), ground_truth(ring()))


def test_coinciding_first_ground_truth_centres_are_refused() -> None:
    poses = ring()
    poses["img01.png"] = rotated_in_place(poses["img00.png"], rotation([0, 0.3, 0]))
    with pytest.raises(UserError, match="first two ground-truth camera centres coincide"):
        evaluate(model(ring()), ground_truth(poses))


# --- the CLI step -------------------------------------------------------------------------


def write_model(folder: Path, poses: dict[str, pycolmap.Rigid3d]) -> Path:
    folder.mkdir(parents=True)
    model(poses).write(str(folder))
    return folder


def write_par(path: Path, poses: dict[str, pycolmap.Rigid3d]) -> Path:
    """A Middlebury file of `poses`, with full precision so errors stay at zero."""
    K = "1500 0 320 0 1500 240 0 0 1"
    lines = [str(len(poses))] + [
        f"{name} {K} " + " ".join(f"{v:.17g}" for v in [*pose.rotation.matrix().ravel(), *pose.translation])
        for name, pose in poses.items()
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_arguments_match_main() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--model_path", "m", "--ground_truth", "g", "--format", "strecha"])
    assert set(vars(args)) == {"model_path", "ground_truth", "output", "plot", "format",
                               "rig_config", "overwrite"}
    with pytest.raises(SystemExit):
        parser.parse_args(["--model_path", "m", "--ground_truth", "g", "--format", "bundler"])


def test_main_prints_table_writes_json_and_plot(tmp_path: Path, capsys, record_figures,
                                                assert_figure_shows, assert_scene_shows) -> None:
    """The errors plot draws the report's numbers, labelled with the model path; the scene
    plot beside it the aligned cameras over the ground truth."""
    estimate = {name: pose for name, pose in ring().items() if name != "img04.png"}
    estimate["img03.png"] = rotated_in_place(estimate["img03.png"], rotation([0, 0, 0.01]))
    model_path = write_model(tmp_path / "sparse" / "0", estimate)
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    output, plot = tmp_path / "out" / "report.json", tmp_path / "out" / "errors.png"
    with record_figures() as figures:
        returned = main(model_path, gt_path, output=output, plot=plot)
    table = capsys.readouterr().out
    assert "img04.png" in table and "unregistered" in table
    assert "registered: 7 / 8" in table
    assert "C_err_aligned" in table
    report = json.loads(output.read_text())
    assert report == returned
    assert set(report) == REPORT_KEYS and report["num_registered"] == 7
    assert report["per_image"][4]["C_err"] is None
    with Image.open(plot) as image:
        assert image.format == "PNG" and image.size[0] > 600
    assert sorted(p.name for p in output.parent.iterdir()) == [
        "errors.png", "errors_scene.png", "report.json"]
    [(figure, path), (scene, scene_path)] = figures
    assert (path, scene_path) == (plot, plot.with_name("errors_scene.png"))
    assert_figure_shows(figure, {str(model_path): report})
    truth = read_ground_truth(gt_path)
    cameras, points = aligned_to_ground_truth(pycolmap.Reconstruction(model_path), truth)
    assert_scene_shows(scene, truth.poses, cameras, points, report)
    assert report["R_err_max_deg"] == pytest.approx(np.degrees(0.01))  # the plot is not all zeros


def test_main_through_cli_style_keywords(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    model_path = write_model(tmp_path / "model", ring())
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    args = parser.parse_args(["--model_path", str(model_path), "--ground_truth", str(gt_path),
                              "--format", "middlebury"])
    assert main(**vars(args))["C_err_max"] == pytest.approx(0.0, abs=1e-9)


def test_main_missing_model(tmp_path: Path) -> None:
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    with pytest.raises(UserError, match="model not found"):
        main(tmp_path / "nowhere", gt_path)


def test_main_unreadable_model(tmp_path: Path) -> None:
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "cameras.txt").write_text("garbage\n")
    with pytest.raises(UserError, match="not a readable COLMAP model"):
        main(tmp_path / "model", write_par(tmp_path / "ring_par.txt", ring()))


def test_main_missing_ground_truth(tmp_path: Path) -> None:
    model_path = write_model(tmp_path / "model", ring())
    with pytest.raises(UserError, match="ground truth not found"):
        main(model_path, tmp_path / "missing_par.txt")


def test_main_refuses_model_with_no_matching_names(tmp_path: Path) -> None:
    model_path = write_model(tmp_path / "model", {f"other{n}": p for n, p in ring().items()})
    with pytest.raises(UserError, match="only 0 registered image"):
        main(model_path, write_par(tmp_path / "ring_par.txt", ring()))


def test_json_write_failure_is_a_user_error_and_leaves_nothing(tmp_path: Path) -> None:
    model_path = write_model(tmp_path / "model", ring())
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    blocked = tmp_path / "blocked"
    blocked.mkdir()
    (blocked / "report.json").mkdir()  # os.replace cannot put a file over a folder
    with pytest.raises(UserError, match="output path is a folder"):  # main checks first
        main(model_path, gt_path, output=blocked / "report.json", overwrite=True)
    with pytest.raises(UserError, match="cannot write"):
        evaluate_and_write(pycolmap.Reconstruction(model_path), read_ground_truth(gt_path),
                           blocked / "report.json", None, label="model")
    assert [p.name for p in blocked.iterdir()] == ["report.json"]


def test_existing_outputs_are_replaced_only_with_overwrite(tmp_path: Path) -> None:
    """Issue 45, defect 2 (the CLI cases are in test_bad_input.py)."""
    model_path = write_model(tmp_path / "model", ring())
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    report = tmp_path / "report.json"
    report.write_text("{}\n")
    with pytest.raises(UserError, match="report.json exists; pass --overwrite"):
        main(model_path, gt_path, output=report)
    assert report.read_text() == "{}\n"
    main(model_path, gt_path, output=report, overwrite=True)
    assert json.loads(report.read_text())["num_registered"] == len(ring())


# --- the plot -----------------------------------------------------------------------------


def test_plot_of_several_reports(tmp_path: Path, record_figures, assert_figure_shows) -> None:
    """Each report's per-image errors are drawn as they are, in its own colour, whatever the format."""
    partial = {name: pose for name, pose in ring().items() if name != "img02.png"}
    partial["img05.png"] = pose_at(partial["img05.png"].rotation,
                                   partial["img05.png"].inverse().translation + [0.05, 0, 0])
    reports = {"perfect": evaluate(model(ring()), ground_truth(ring())),
               "partial": evaluate(model(partial), ground_truth(ring()))}
    with record_figures() as figures:
        plot_errors(reports, tmp_path / "compare.png")
        plot_errors(reports, tmp_path / "compare.pdf")
    with Image.open(tmp_path / "compare.png") as image:
        assert image.format == "PNG"
    assert (tmp_path / "compare.pdf").read_bytes().startswith(b"%PDF")
    assert [path.name for _, path in figures] == ["compare.png", "compare.pdf"]
    for figure, _ in figures:
        assert_figure_shows(figure, reports)
    assert reports["partial"]["C_err_max"] > 0.01  # non-zero data to compare


def test_plot_unknown_format_is_a_user_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="cannot write"):
        plot_errors({"m": evaluate(model(ring()), ground_truth(ring()))}, tmp_path / "errors.xyz")
    assert list(tmp_path.iterdir()) == []


# --- the scene figure ---------------------------------------------------------------------

# Where the scene models' own world lies from the ground truth's (as a mapper's gauge would).
MODEL_FROM_TRUTH = pycolmap.Sim3d(0.3, rotation([0.4, 1.0, -0.2]), np.array([5.0, 1.0, 2.0]))


def scene_model(poses: dict[str, pycolmap.Rigid3d], points: np.ndarray) -> pycolmap.Reconstruction:
    """A model of `poses` and `points` (n,3), given in ground-truth coordinates, moved into a
    world of its own by MODEL_FROM_TRUTH."""
    reconstruction = model(poses)
    for xyz in points:
        reconstruction.add_point3D(xyz, pycolmap.Track(), np.zeros(3))
    reconstruction.transform(MODEL_FROM_TRUTH)
    return reconstruction


def look_at(centre, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> pycolmap.Rigid3d:
    """cam_from_world of a camera at `centre` looking at `target`, upright for `up`."""
    z = np.asarray(target, dtype=float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.array([x, np.cross(z, x), z])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ np.asarray(centre, dtype=float))


def test_aligned_to_ground_truth_undoes_the_model_gauge() -> None:
    """A similar copy of the ground truth comes back onto it: cameras and points."""
    points = np.random.default_rng(0).normal(0, 0.5, (50, 3))
    cameras, aligned = aligned_to_ground_truth(scene_model(ring(), points), ground_truth(ring()))
    assert list(cameras) == list(ring())
    for name, pose in ring().items():
        np.testing.assert_allclose(cameras[name].matrix(), pose.matrix(), atol=1e-9, err_msg=name)
    np.testing.assert_allclose(aligned, points, atol=1e-9)


def test_scene_plot_shows_drifted_flipped_and_unregistered_cameras(
        tmp_path: Path, record_figures, assert_scene_shows) -> None:
    """`evaluate --plot` draws the aligned model over the ground truth: a camera moved off
    its place lies far from its ground-truth centre, a camera turned round looks the other
    way, both are named, and the unregistered camera is crossed out."""
    estimate = ring()
    del estimate["img02.png"]
    estimate["img05.png"] = pose_at(estimate["img05.png"].rotation,
                                    estimate["img05.png"].inverse().translation + [0.6, 0, 0.3])
    estimate["img06.png"] = rotated_in_place(estimate["img06.png"], rotation([0, np.pi, 0]))
    points = np.random.default_rng(1).normal(0, 0.5, (300, 3))
    model_path = tmp_path / "model"
    model_path.mkdir()
    scene_model(estimate, points).write(str(model_path))
    gt_path = write_par(tmp_path / "ring_par.txt", ring())
    with record_figures() as figures:
        report = main(model_path, gt_path, plot=tmp_path / "errors.png")
    [_, (scene, path)] = figures
    assert path == tmp_path / "errors_scene.png"
    with Image.open(path) as image:
        assert image.format == "PNG"
    truth = read_ground_truth(gt_path)
    cameras, aligned = aligned_to_ground_truth(pycolmap.Reconstruction(model_path), truth)
    data = assert_scene_shows(scene, truth.poses, cameras, aligned, report)

    assert len(data["estimated directions"]) == report["num_registered"] == 7
    names = list(ring())
    np.testing.assert_allclose(data["unregistered"], data["truth centres"][[2]], atol=1e-9)
    registered = [names.index(name) for name in cameras]
    offsets = np.linalg.norm(data["estimated centres"] - data["truth centres"][registered], axis=1)
    drifted = list(cameras).index("img05.png")
    assert offsets[drifted] > 0.5 and offsets[drifted] > 2.5 * np.delete(offsets, drifted).max()
    steps = [segments[:, 1] - segments[:, 0] for segments in
             (data["estimated directions"], data["truth directions"][registered])]
    cosines = np.sum(steps[0] * steps[1], axis=1) / np.sum(steps[1] ** 2, axis=1)
    flipped = list(cameras).index("img06.png")
    assert cosines[flipped] < -0.99 and np.delete(cosines, flipped).min() > 0.99
    assert sorted(data["named"]) == ["img05.png", "img06.png"]


def test_scene_plot_draws_a_fixed_sample_of_many_points(tmp_path: Path, record_figures,
                                                        assert_scene_shows) -> None:
    """Beyond `max_points` the same sample of distinct model points is drawn on every run."""
    points = np.random.default_rng(2).normal(0, 0.5, (500, 3))
    report = evaluate(model(ring()), ground_truth(ring()))
    with record_figures() as figures:
        for name in ("a.png", "b.png"):
            plot_scene(ring(), ring(), points, tmp_path / name, max_points=50)
    drawn = [assert_scene_shows(figure, ring(), ring(), points, report, max_points=50)["points"]
             for figure, _ in figures]
    np.testing.assert_array_equal(drawn[0], drawn[1])
    legend = [text.get_text() for text in figures[0][0].legends[0].get_texts()]
    assert "sparse points (50 of 500)" in legend


def horizontal_ring(count: int = 12, up=(0.0, 0.0, 1.0)) -> list[pycolmap.Rigid3d]:
    """Cameras on a circle at height 1 looking at the origin, upright for `up`."""
    return [look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), up=up)
            for a in np.linspace(0, 2 * np.pi, count, endpoint=False)]


@pytest.mark.parametrize("cameras, up", [
    (horizontal_ring(), [0, 0, 1]),                # the normal of the ring, as the cameras' up
    (horizontal_ring(up=(0, 0, -1)), [0, 0, -1]),  # upside-down cameras: the side view turns
    ([look_at(np.array([x, 0.0, 0.0]), target=(x, 5.0, 0.0)) for x in range(5)], [0, 0, 1]),
    ([look_at(np.array([x, 0.0, 0.0]), target=(x, 5.0, 0.0)) for x in range(2)], [0, 0, 1]),
], ids=["ring", "upside-down", "line", "two"])
def test_view_frame_is_centred_upright_and_right_handed(cameras, up) -> None:
    """w is the normal of the centres' plane (the cameras' up when they lie on a line),
    signed as the cameras' up; u, v, w are a right-handed frame about the centroid."""
    frame = view_frame(cameras)
    R = frame.rotation.matrix()
    np.testing.assert_allclose(R[2], up, atol=1e-9)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    centres = np.array([pose.inverse().translation for pose in cameras])
    np.testing.assert_allclose(frame * centres.mean(axis=0), 0.0, atol=1e-9)


@pytest.mark.parametrize("plot, scene", [("errors.png", "errors_scene.png"),
                                         ("out/fig.pdf", "out/fig_scene.pdf")])
def test_scene_plot_path_is_beside_the_errors_plot(plot: str, scene: str) -> None:
    assert scene_plot_path(plot) == Path(scene)


# --- the real set -------------------------------------------------------------------------


def test_temple_sparse_ring_ground_truth_model_has_zero_errors(tmp_path: Path,
                                                               real_data: Path) -> None:
    par = real_data / "templeSparseRing" / "templeSR_par.txt"
    gt = read_ground_truth(par)
    assert len(gt.poses) == 16 and gt.cameras["templeSR0001.png"].width == 640
    model_path = tmp_path / "temple"
    model_path.mkdir()
    to_reconstruction(gt).write(str(model_path))
    report = main(model_path, par, output=tmp_path / "report.json", plot=tmp_path / "errors.png")
    assert report["num_registered"] == report["num_gt_images"] == 16
    for key in REPORT_KEYS - {"per_image", "num_gt_images", "num_registered", "AUC_percent"}:
        assert report[key] == pytest.approx(0.0, abs=1e-9), key
    assert report["AUC_percent"] == {"0.5": 100.0, "1": 100.0, "5": 100.0, "10": 100.0}
