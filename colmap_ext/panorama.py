"""Cube faces of equirectangular panoramas: pinhole views for SIFT, keypoints back in
panorama pixels.

SIFT on the equirectangular image itself sees the scene stretched along x towards the
poles and cut at the left and right edges; on six 90-degree pinhole faces rendered from
it, it sees the scene as a perspective camera would. Each keypoint found on a face is
mapped back through its bearing vector (face pixel -> ray -> the panorama camera's
`img_from_cam`), with its affine shape carried by the mapping's Jacobian, so a database
keeps one image per panorama with its EQUIRECTANGULAR camera.

The faces are rendered a little wider than 90 degrees (FACE_MARGIN), so that a feature
at a face's edge is detected with its whole support, and a keypoint is kept only by the
face whose own 90-degree square holds its ray: each direction is described once. (A
keypoint found twice, by two faces, would be two near-identical descriptors in one image,
and the ratio test would then reject the matches of both.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

# Per face: the direction it looks along and its image's "down", in camera coordinates
# (COLMAP's: x right, y down, z forward): front, right, back, left, up, down.
FACE_FORWARD_DOWN = (((0, 0, 1), (0, 1, 0)), ((1, 0, 0), (0, 1, 0)), ((0, 0, -1), (0, 1, 0)),
                     ((-1, 0, 0), (0, 1, 0)), ((0, -1, 0), (0, 0, 1)), ((0, 1, 0), (0, 0, -1)))
FACE_FORWARDS = np.array([forward for forward, _ in FACE_FORWARD_DOWN], float)
# The faces' margin beyond their 90-degree square, on each side, as a fraction of its width.
FACE_MARGIN = 1 / 16
# Panorama columns copied across its left and right edges, for bilinear sampling there.
WRAP_COLUMNS = 2
# COLMAP's SIFT scales larger images down to this width or height.
SIFT_MAX_IMAGE_SIZE = pycolmap.FeatureExtractionOptions().eff_max_image_size()


def face_from_cam(face: int) -> np.ndarray:
    """Rotation from the panorama's camera frame into the face's (rows: right, down, forward)."""
    forward, down = (np.array(axis, float) for axis in FACE_FORWARD_DOWN[face])
    return np.stack([np.cross(down, forward), down, forward])


def owning_faces(rays: np.ndarray) -> np.ndarray:
    """Per ray (n, 3) in the camera frame, the face whose 90-degree square holds it: the
    axis the ray is closest to."""
    return np.argmax(rays @ FACE_FORWARDS.T, axis=1)


@dataclass(frozen=True)
class CubeFaces:
    """The six pinhole faces of the panoramas of one EQUIRECTANGULAR camera: square images
    of `size` pixels, focal length `focal`, principal point at their centre."""

    camera: pycolmap.Camera
    focal: float

    @classmethod
    def of_panorama(cls, width: int, height: int) -> CubeFaces:
        """The faces of `width` x `height` equirectangular panoramas, as finely sampled at
        their centres as the panorama's equator is where SIFT sees it (scaled down to
        SIFT_MAX_IMAGE_SIZE)."""
        return cls(pycolmap.Camera(model="EQUIRECTANGULAR", width=width, height=height,
                                   params=[width, height]),
                   min(width, SIFT_MAX_IMAGE_SIZE) / (2 * np.pi))

    @property
    def size(self) -> int:
        return int(round(2 * self.focal * (1 + 2 * FACE_MARGIN)))

    def face_rays(self, face: int, points: np.ndarray) -> np.ndarray:
        """Rays (n, 3) in the panorama's camera frame of face pixel positions (n, 2)
        (COLMAP's convention: pixel (0, 0) spans [0, 1)^2)."""
        centred = (np.asarray(points, float) - self.size / 2) / self.focal
        return np.column_stack([centred, np.ones(len(centred))]) @ face_from_cam(face)

    def panorama_points(self, face: int, points: np.ndarray) -> np.ndarray:
        """Panorama pixel positions (n, 2) of face pixel positions (n, 2)."""
        return self.camera.img_from_cam(self.face_rays(face, points))

    def render(self, panorama: np.ndarray) -> list[np.ndarray]:
        """The six faces of a panorama image (height x width, grey or colour), bilinear."""
        if panorama.shape[:2] != (self.camera.height, self.camera.width):
            raise ValueError(f"panorama is {panorama.shape[1]}x{panorama.shape[0]}, the "
                             f"camera {self.camera.width}x{self.camera.height}")
        wrapped = np.concatenate([panorama[:, -WRAP_COLUMNS:], panorama,
                                  panorama[:, :WRAP_COLUMNS]], axis=1)
        centres = np.arange(self.size) + 0.5
        grid = np.stack(np.meshgrid(centres, centres), axis=-1).reshape(-1, 2)
        faces = []
        for face in range(len(FACE_FORWARD_DOWN)):
            source = self.panorama_points(face, grid) - 0.5  # cv2: pixel centres at integers
            map_x = (source[:, 0] + WRAP_COLUMNS).reshape(self.size, self.size)
            map_y = source[:, 1].reshape(self.size, self.size)
            faces.append(cv2.remap(wrapped, map_x.astype(np.float32), map_y.astype(np.float32),
                                   cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
        return faces

    def to_panorama(self, face: int, keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """COLMAP keypoints (n, 6: x, y, a11, a12, a21, a22) of one face as keypoints of
        the panorama, and which of them the face owns (owning_faces)."""
        keypoints = np.asarray(keypoints, np.float64).reshape(-1, 6)
        points = keypoints[:, :2]
        owned = owning_faces(self.face_rays(face, points)) == face
        mapped = self.panorama_points(face, points)
        # The mapping's Jacobian by central differences of half a pixel, across the seam too.
        step = 0.5
        columns = []
        for offset in ([step, 0.0], [0.0, step]):
            difference = (self.panorama_points(face, points + offset)
                          - self.panorama_points(face, points - offset))
            difference[:, 0] = (difference[:, 0] + self.camera.width / 2) % self.camera.width \
                - self.camera.width / 2
            columns.append(difference / (2 * step))
        jacobian = np.stack(columns, axis=2)  # (n, 2, 2): d(panorama) / d(face)
        shapes = jacobian @ keypoints[:, 2:].reshape(-1, 2, 2)
        return np.column_stack([mapped, shapes.reshape(-1, 4)]).astype(np.float32), owned


def keypoint_scales(keypoints: np.ndarray) -> np.ndarray:
    """The scale of COLMAP keypoints (n, 6): the square root of their affine shape's area."""
    shapes = np.asarray(keypoints, np.float64)[:, 2:].reshape(-1, 2, 2)
    return np.sqrt(np.abs(np.linalg.det(shapes)))


def inside_mask(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which points (n, 2) fall on a non-zero pixel of a mask (COLMAP's rule: the pixel at
    the truncated coordinates; outside the image counts as masked out)."""
    columns, rows = np.asarray(points, np.float64).T.astype(np.int64)
    height, width = mask.shape[:2]
    inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    kept = np.zeros(len(columns), bool)
    kept[inside] = mask[rows[inside], columns[inside]] != 0
    return kept
