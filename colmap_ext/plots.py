"""Figures of evaluation reports, as in the paper: per-image errors against image index
(`plot_errors`), and the sparse points with the cameras, estimated beside the ground truth,
in a top and a side view (`plot_scene`, the paper's Fig. 3).

Drawn on matplotlib's Agg canvas directly (no pyplot), so it works headless and leaves
any interactive backend of the caller alone.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import pycolmap
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from colmap_ext.errors import UserError

# (report key, legend label, line style, marker) per panel.
_ANGLE_SERIES = (("R_err_deg", "R_err", "-", "o"), ("T_err_deg", "T_err", "--", "s"))
_CENTRE_SERIES = (("C_err", "C_err", "-", "o"), ("C_err_aligned", "C_err aligned", ":", "^"))

# The scene figure draws at most this many sparse points (a fixed-seed sample), so a large
# model stays quick to draw and its cameras stay visible.
MAX_SCENE_POINTS = 20_000
# (colour, centre marker) of the estimated and ground-truth cameras, and of unregistered ones;
# the lines from ground-truth to estimated centres take the unregistered ones' colour.
_ESTIMATED_STYLE, _TRUTH_STYLE, _UNREGISTERED_STYLE = ("C0", "o"), ("C1", "s"), ("C3", "x")
# An estimated camera whose centre or segment tip lies this far from its ground truth's, in
# segment lengths, is named in the figure (at most _MAX_NAMED, the farthest first).
_NAMED_ERROR = 0.5
_MAX_NAMED = 10


def plot_errors(reports: dict[str, dict], path: str | os.PathLike) -> None:
    """Draw per-image errors of one or more reports (label -> report) into the image file `path`.

    Left: R_err and T_err in degrees; right: C_err and C_err_aligned in units of the
    distance between the first two ground-truth cameras. Colour tells the report (legend
    on top), line style the measure (legend in each panel); an unregistered image leaves
    a gap in the lines and an x on the axis.
    """
    figure = Figure(figsize=(12, 5), layout="constrained")
    FigureCanvasAgg(figure)
    angles, centres = figure.subplots(1, 2)
    report_handles = []
    for index, (label, report) in enumerate(reports.items()):
        colour = f"C{index % 10}"
        _draw_series(angles, report, _ANGLE_SERIES, colour)
        _draw_series(centres, report, _CENTRE_SERIES, colour)
        registered = f"{report['num_registered']}/{report['num_gt_images']} registered"
        report_handles.append(Line2D([], [], color=colour, linewidth=3, label=f"{label} ({registered})"))
    figure.legend(handles=report_handles, loc="outside upper center", ncols=min(len(reports), 4))
    any_missing = any(report["num_registered"] < report["num_gt_images"] for report in reports.values())
    _style(angles, "R_err and T_err (relative to the first image)", "error [deg]", 0.05,
           _ANGLE_SERIES, any_missing)
    _style(centres, "Camera centre error", "error [|C2 - C1| of ground truth]", 0.005,
           _CENTRE_SERIES, any_missing)
    _save(figure, Path(path))


def _draw_series(axes, report: dict, series: tuple, colour: str) -> None:
    """Lines of one report's measures against the 1-based image index, with its unregistered images."""
    entries = report["per_image"]
    index = np.arange(1, len(entries) + 1)
    for key, _, style, marker in series:
        values = np.array([np.nan if entry[key] is None else entry[key] for entry in entries])
        axes.plot(index, values, linestyle=style, marker=marker, color=colour, markersize=4, clip_on=False)
    missing = index[[entry[series[0][0]] is None for entry in entries]]
    if missing.size:
        axes.plot(missing, np.zeros(missing.size), "x", color=colour, markersize=9,
                  markeredgewidth=2, clip_on=False)


def _style(axes, title: str, ylabel: str, least_top: float, series: tuple, any_missing: bool) -> None:
    """Titles, integer image ticks, grid and the legend of line styles.

    The y range starts at zero and spans at least `least_top`, so the rounding noise of a
    perfect model does not fill the panel.
    """
    axes.set_title(title)
    axes.set_xlabel("image index (ground-truth order)")
    axes.set_ylabel(ylabel)
    axes.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_ylim(0, max(axes.get_ylim()[1], least_top))
    axes.grid(True, alpha=0.3)
    handles = [Line2D([], [], color="0.25", linestyle=style, marker=marker, label=name)
               for _, name, style, marker in series]
    if any_missing:
        handles.append(Line2D([], [], color="0.25", linestyle="", marker="x", markersize=9,
                              markeredgewidth=2, label="not registered"))
    axes.legend(handles=handles, fontsize="small")


def plot_scene(truth: dict[str, pycolmap.Rigid3d], estimated: dict[str, pycolmap.Rigid3d],
               points: np.ndarray, path: str | os.PathLike, title: str = "",
               max_points: int = MAX_SCENE_POINTS) -> None:
    """Draw the points and cameras of a model beside the ground truth into the image file `path`.

    `truth` holds the ground-truth cam_from_world poses; `estimated` those of the registered
    images (by ground-truth name) and `points` (n,3) the model's points, both already moved
    into the ground truth's world (`evaluate.aligned_to_ground_truth`). Top view above, side
    view below, in the axes of `view_frame`; each camera is its centre with a short segment
    along its viewing direction, an unregistered one is crossed out, and estimated cameras
    visibly off their ground truth are named, so a drifting or flipped camera stands out.
    """
    view_from_world = view_frame(list(truth.values()))
    names = [name for name in truth if name in estimated]
    registered = np.array([name in estimated for name in truth])
    truth_centres, truth_directions = _cameras_in_view(view_from_world, list(truth.values()))
    estimated_centres, estimated_directions = _cameras_in_view(
        view_from_world, [estimated[name] for name in names])
    matched_truth = truth_centres[registered]
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    shown = _sample(points, max_points)
    shown_points = view_from_world * shown
    # Segments a tenth of the rig, markers and lines full size, up to 30 cameras; beyond,
    # all shrink with the spacing of the cameras, so 1000 of them stay apart.
    size = max(0.3, min(1.0, np.sqrt(30 / len(truth))))
    length = 0.1 * np.ptp(truth_centres, axis=0).max() * min(1.0, np.sqrt(30 / len(truth)))

    limits = _scene_limits(shown_points, [truth_centres, estimated_centres,
                                          truth_centres + length * truth_directions,
                                          estimated_centres + length * estimated_directions])
    (u_low, u_high), (v_low, v_high), (w_low, w_high) = limits
    u_range, v_range, w_range = u_high - u_low, v_high - v_low, w_high - w_low
    height = float(np.clip(8 * (v_range + w_range) / u_range, 4, 13)) + 1.6
    figure = Figure(figsize=(9, height), layout="constrained")
    FigureCanvasAgg(figure)
    top, side = figure.subplots(2, 1, sharex=True, height_ratios=[v_range, w_range])
    # How far each estimated camera is off: its centre, or the tip of its segment (a turn).
    tips = length * (estimated_directions - truth_directions[registered])
    errors = np.maximum(np.linalg.norm(estimated_centres - matched_truth, axis=1),
                        np.linalg.norm(estimated_centres + tips - matched_truth, axis=1))
    named = [index for index in np.argsort(-errors)[:_MAX_NAMED]
             if errors[index] > _NAMED_ERROR * length]
    for axes, (across, up) in ((top, (0, 1)), (side, (0, 2))):
        axes.plot(shown_points[:, across], shown_points[:, up], ".", color="0.55",
                  markersize=1.5, markeredgewidth=0, gid="points")
        axes.add_collection(LineCollection(
            np.stack([matched_truth, estimated_centres], axis=1)[:, :, [across, up]],
            colors=_UNREGISTERED_STYLE[0], linewidths=0.8, gid="errors"))
        for name, centres, directions, (colour, marker) in (
                ("truth", truth_centres, truth_directions, _TRUTH_STYLE),
                ("estimated", estimated_centres, estimated_directions, _ESTIMATED_STYLE)):
            axes.add_collection(LineCollection(
                np.stack([centres, centres + length * directions], axis=1)[:, :, [across, up]],
                colors=colour, linewidths=1.5 * size, gid=f"{name} directions"))
            filled = colour if name == "estimated" else "none"
            axes.plot(centres[:, across], centres[:, up], marker, linestyle="", color=colour,
                      markerfacecolor=filled, markersize=7 * size, gid=f"{name} centres")
        missing = truth_centres[~registered]
        axes.plot(missing[:, across], missing[:, up], _UNREGISTERED_STYLE[1], linestyle="",
                  color=_UNREGISTERED_STYLE[0], markersize=max(7.0, 11 * size), markeredgewidth=2,
                  gid="unregistered")
        for index in named:
            axes.annotate(names[index], estimated_centres[index, [across, up]], xytext=(4, 4),
                          textcoords="offset points", fontsize="small",
                          color=_ESTIMATED_STYLE[0], gid="named")
        axes.set_aspect("equal", adjustable="box")
        axes.set_ylim(*limits[up])
        axes.grid(True, alpha=0.3)
    top.set_xlim(u_low, u_high)
    top.set_title("Top view (looking down the up axis w)")
    top.set_ylabel("v [ground-truth units]")
    top.tick_params(labelbottom=True)
    top.set_xlabel("u: widest spread of the ground-truth camera centres")
    side.set_title("Side view (looking along v)")
    side.set_xlabel("u [ground-truth units]")
    side.set_ylabel("w: up [ground-truth units]")
    summary = (f"{len(estimated)}/{len(truth)} cameras registered, aligned to the ground truth "
               "by a similarity")
    figure.suptitle(f"{title}\n{summary}" if title else summary)
    figure.legend(handles=_scene_legend(len(shown), len(points), not registered.all()),
                  loc="outside lower center", ncols=3, fontsize="small")
    _save(figure, Path(path))


def view_frame(truth: list[pycolmap.Rigid3d]) -> pycolmap.Rigid3d:
    """view_from_world of the scene figure, from the ground-truth cameras (cam_from_world).

    Origin at the centroid of the camera centres; w ("up") the normal of their best plane,
    or, when they lie near a line, their mean up direction (image -y), signed to agree with
    that mean so the side view is upright; u the widest spread of the centres across w; and
    v = w x u, so the top view looks down w.
    """
    centres = np.array([pose.inverse().translation for pose in truth])
    mean_up = -np.mean([pose.rotation.matrix()[1] for pose in truth], axis=0)
    offsets = centres - centres.mean(axis=0)
    variances, axes = np.linalg.eigh(offsets.T @ offsets)
    up = axes[:, 0]
    planar = variances[1] > max(4 * variances[0], 1e-6 * variances[2])
    if not planar and np.linalg.norm(mean_up) > 0.1:
        up = mean_up / np.linalg.norm(mean_up)
    if up @ mean_up < 0:
        up = -up
    across = np.linalg.svd(up[None])[2][1:]  # two unit rows spanning the plane normal to up
    in_plane = offsets @ across.T
    u = across.T @ np.linalg.eigh(in_plane.T @ in_plane)[1][:, 1]
    if u @ offsets[0] < 0:
        u = -u  # fixed sign: the first camera on the right
    rotation = np.array([u, np.cross(up, u), up])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centres.mean(axis=0))


def _cameras_in_view(view_from_world: pycolmap.Rigid3d,
                     poses: list[pycolmap.Rigid3d]) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n,3) and unit viewing directions (n,3) of cam_from_world poses, in view axes."""
    centres = np.array([pose.inverse().translation for pose in poses]).reshape(-1, 3)
    directions = np.array([pose.rotation.matrix()[2] for pose in poses]).reshape(-1, 3)
    return view_from_world * centres, view_from_world.rotation * directions


def _sample(points: np.ndarray, count: int) -> np.ndarray:
    """At most `count` of the points, the same ones on every run, in their order."""
    if len(points) <= count:
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), count, replace=False))]


def _scene_limits(points: np.ndarray, cameras: list[np.ndarray]) -> list[tuple[float, float]]:
    """(low, high) per view axis: every camera, and the points' 1-99 percentile range, so a
    few far points do not shrink the cameras to a dot; v and w span at least a quarter of u."""
    cameras = np.concatenate(cameras)
    low, high = cameras.min(axis=0), cameras.max(axis=0)
    if len(points):
        low = np.minimum(low, np.percentile(points, 1, axis=0))
        high = np.maximum(high, np.percentile(points, 99, axis=0))
    middle, half = (low + high) / 2, 0.55 * (high - low)
    half[1:] = np.maximum(half[1:], half[0] / 4)
    return [(m - h, m + h) for m, h in zip(middle, half)]


def _scene_legend(shown: int, total: int, any_missing: bool) -> list[Line2D]:
    """Legend handles of the scene figure."""
    handles = [
        Line2D([], [], color=_ESTIMATED_STYLE[0], marker=_ESTIMATED_STYLE[1], markersize=6,
               label="estimated camera, viewing direction (aligned)"),
        Line2D([], [], color=_TRUTH_STYLE[0], marker=_TRUTH_STYLE[1], markerfacecolor="none",
               markersize=6, label="ground-truth camera, viewing direction"),
        Line2D([], [], color=_UNREGISTERED_STYLE[0], linewidth=0.8,
               label="estimated to ground-truth centre"),
        Line2D([], [], color="0.55", marker=".", linestyle="",
               label=f"sparse points ({shown} of {total})" if shown < total
               else f"sparse points ({total})"),
    ]
    if any_missing:
        handles.append(Line2D([], [], color=_UNREGISTERED_STYLE[0], marker=_UNREGISTERED_STYLE[1],
                              linestyle="", markersize=9, markeredgewidth=2,
                              label="not registered (ground-truth centre)"))
    return handles


def _save(figure: Figure, path: Path) -> None:
    """Save through a temporary file, so no reader sees half a figure; format from the suffix."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(temporary, format=path.suffix.lstrip(".").lower() or "png", dpi=120)
        os.replace(temporary, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    except ValueError as exc:  # matplotlib's refusal of an unknown format
        raise UserError(f"cannot write {path}: {exc}") from None
