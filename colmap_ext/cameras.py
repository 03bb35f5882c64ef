"""Keypoints as bearing vectors, for every central COLMAP camera model.

The mapper's geometry works on unit rays (`Camera.cam_ray_from_img`), which hold any
direction, behind the image plane too (EQUIRECTANGULAR, wide fisheyes). A user's
thresholds are in pixels; `pixel_angles` turns them into angles at each keypoint, from
the camera's own angular resolution there. Nothing here reads a focal length:
pycolmap 4.2.1's `Camera.focal_length*` accessors read out of bounds (SIGSEGV) on a
model without one, such as EQUIRECTANGULAR.
"""

from __future__ import annotations

import numpy as np
import pycolmap

# Half the step (pixels) over which pixel_angles measures the rays' spread.
HALF_PIXEL = 0.5
# A ray must project back to within this of its pixel (rays).
MAX_ROUND_TRIP_PX = 0.01


def rays(camera: pycolmap.Camera, points2D: np.ndarray) -> np.ndarray:
    """(N, 3) unit rays through pixel positions; NaN rows where the model has none, or
    where the ray does not project back onto its pixel: pycolmap 4.2.1's fisheye models
    return wrong rays, not NaN, for pixels 90 degrees or more from their axis (a lens
    wider than 180 degrees)."""
    points2D = np.asarray(points2D, np.float64).reshape(-1, 2)
    if not len(points2D):
        return np.zeros((0, 3))
    found = np.asarray(camera.cam_ray_from_img(points2D), np.float64).reshape(-1, 3)
    back = np.asarray(camera.img_from_cam(found), np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        found[~(np.linalg.norm(back - points2D, axis=1) <= MAX_ROUND_TRIP_PX)] = np.nan
    return found


def pixel_angles(camera: pycolmap.Camera, points2D: np.ndarray) -> np.ndarray:
    """Radians per pixel at each position: the angle between the rays half a pixel to
    either side, the mean of the x and y directions. A pinhole camera's is 1/f at the
    principal point; an EQUIRECTANGULAR camera's shrinks along x towards the poles.
    NaN where the model gives no ray."""
    points2D = np.asarray(points2D, np.float64).reshape(-1, 2)
    angles = np.zeros(len(points2D))
    for step in np.eye(2) * HALF_PIXEL:
        before, after = rays(camera, points2D - step), rays(camera, points2D + step)
        sine = np.linalg.norm(np.cross(before, after), axis=1)
        angles += np.arctan2(sine, np.einsum("ij,ij->i", before, after))
    return angles / 2


def pixels_from_tangent(camera: pycolmap.Camera, rays: np.ndarray,
                        step: float = 1e-6) -> np.ndarray:
    """(N, 2, 3): at each unit ray, the camera model's pixels per unit of the plane tangent
    to it at unit distance (central differences), as a linear map of 3-vectors on that
    plane. Times a point's offset from the ray on the plane, it is the point's
    reprojection error in pixels to first order: what the bundle adjuster minimises,
    for any camera model."""
    rays = np.asarray(rays, np.float64).reshape(-1, 3)
    # Two unit vectors orthogonal to each ray and to each other.
    helper = np.where(np.abs(rays[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    first = np.cross(rays, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(rays, first)
    jacobian = np.stack([(camera.img_from_cam(rays + step * axis) -
                          camera.img_from_cam(rays - step * axis)) / (2 * step)
                         for axis in (first, second)], axis=2)
    return np.einsum("nij,njk->nik", jacobian, np.stack([first, second], axis=1))
