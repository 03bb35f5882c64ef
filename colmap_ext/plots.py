"""Figures of evaluation reports: per-image errors against image index, as in the paper.

Drawn on matplotlib's Agg canvas directly (no pyplot), so it works headless and leaves
any interactive backend of the caller alone.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator

from colmap_ext.errors import UserError

# (report key, legend label, line style, marker) per panel.
_ANGLE_SERIES = (("R_err_deg", "R_err", "-", "o"), ("T_err_deg", "T_err", "--", "s"))
_CENTRE_SERIES = (("C_err", "C_err", "-", "o"), ("C_err_aligned", "C_err aligned", ":", "^"))


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
