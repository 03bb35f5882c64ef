"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest


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
