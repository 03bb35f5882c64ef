"""geometry.py: the similarity fit, the rotation mean and the nearest rotation against
known answers."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from colmap_ext.geometry import fit_similarity, mean_rotation, rotation_angles_deg


def rotation(axis_angle: list[float]) -> np.ndarray:
    return pycolmap.Rotation3d(np.array(axis_angle, float)).matrix()


def assert_same_similarity(found: pycolmap.Sim3d, expected: pycolmap.Sim3d) -> None:
    assert found.scale == pytest.approx(expected.scale, rel=1e-9)
    np.testing.assert_allclose(found.rotation.matrix(), expected.rotation.matrix(), atol=1e-9)
    np.testing.assert_allclose(found.translation, expected.translation, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(axis_angle=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
       scale=st.floats(0.1, 10.0), num_points=st.integers(3, 20))
def test_similarity_of_exact_points_is_recovered(axis_angle, scale, num_points) -> None:
    truth = pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation(axis_angle)), [1.0, -2.0, 0.5])
    source = np.random.default_rng(num_points).normal(size=(num_points, 3))
    assert_same_similarity(fit_similarity(source, truth * source), truth)


def test_two_points_and_a_given_rotation_fix_scale_and_translation() -> None:
    """Two points leave the rotation about their line free (pycolmap.estimate_sim3d
    refuses them); with the rotation given, the fit is exact."""
    truth = pycolmap.Sim3d(2.5, pycolmap.Rotation3d(rotation([0.3, -1.2, 0.4])), [3.0, 0.0, -1.0])
    source = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]])
    found = fit_similarity(source, truth * source, truth.rotation.matrix())
    assert_same_similarity(found, truth)


def test_given_rotation_is_kept_and_scale_is_the_least_squares_one() -> None:
    """Under a rotation 2 deg off, the scale is the least-squares one, below the ratio
    of the spreads by the cosine of the misfit."""
    source = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    target = source * 3.0
    off = rotation([0.0, 0.0, np.radians(2.0)])
    found = fit_similarity(source, target, off)
    np.testing.assert_allclose(found.rotation.matrix(), off, atol=1e-12)
    assert found.scale == pytest.approx(3.0 * np.cos(np.radians(2.0)), rel=1e-12)


def test_mean_of_rotations_symmetric_about_one_is_that_one() -> None:
    centre = rotation([0.5, 1.0, -0.3])
    offsets = [rotation([0.1, 0.0, 0.0]), rotation([-0.1, 0.0, 0.0]),
               rotation([0.0, 0.2, 0.0]), rotation([0.0, -0.2, 0.0])]
    mean = mean_rotation(np.array([centre @ offset for offset in offsets]))
    assert rotation_angles_deg((mean.T @ centre)[None])[0] < 1e-9
