"""Synthetic scenes with known cameras: textured planar quads seen by one calibrated camera.

A scene is a set of rectangles (box faces, floor, walls, facade panels) and a list of
camera poses. The renderer ray-casts the rectangles to make images; the database
generator samples 3D points on them and uses the same ray casting for occlusion.
World frame: z up; cameras in COLMAP's convention (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pycolmap


@dataclass(frozen=True)
class Quad:
    """A textured rectangle: corners origin, origin+edge_u, origin+edge_u+edge_v, origin+edge_v.

    `detail` is the size in metres of the smallest texture feature; it sets the texel
    size, so a far wall gets coarser texture than a small object seen from close up.
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    detail: float

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))

    @property
    def corners(self) -> np.ndarray:
        o, u, v = self.origin, self.edge_u, self.edge_v
        return np.stack([o, o + u, o + u + v, o + v])


@dataclass
class Scene:
    """Known camera, poses and structure. Image i has pose cams_from_world[i] and name image_names[i]."""

    camera: pycolmap.Camera
    cams_from_world: list[pycolmap.Rigid3d]
    image_names: list[str]
    quads: list[Quad]

    @property
    def num_images(self) -> int:
        return len(self.image_names)

    @cached_property
    def quad_corners(self) -> np.ndarray:
        """Corners of all quads, Qx4x3 (world frame), for culling."""
        return np.stack([q.corners for q in self.quads])


@dataclass
class RayHits:
    """Nearest quad hit per ray: depth (camera z; inf on a miss), quad index (-1 on a miss), texture coords in [0, 1]."""

    depth: np.ndarray
    quad_index: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def view(self, rows: slice, cols: slice) -> RayHits:
        """The hits of a block of a ray grid, sharing memory with self."""
        return RayHits(self.depth[rows, cols], self.quad_index[rows, cols], self.u[rows, cols], self.v[rows, cols])


def default_camera() -> pycolmap.Camera:
    """Calibrated 640x480 OPENCV camera, f = 600 px, off-centre principal point, barrel distortion k1 = -0.1."""
    return pycolmap.Camera(
        camera_id=1,
        model="OPENCV",
        width=640,
        height=480,
        params=[600.0, 600.0, 318.0, 242.0, -0.1, 0.01, 0.0, 0.0],
        has_prior_focal_length=True,
    )


def look_at(center: np.ndarray, target: np.ndarray, roll_deg: float = 0.0) -> pycolmap.Rigid3d:
    """cam_from_world of a camera at `center` looking at `target`, world z up, image y down."""
    forward = target - center
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    roll = np.deg2rad(roll_deg)
    right, down = (np.cos(roll) * right + np.sin(roll) * down, -np.sin(roll) * right + np.cos(roll) * down)
    rotation = np.stack([right, down, forward])
    return pycolmap.Rigid3d(np.hstack([rotation, (-rotation @ center)[:, None]]))


def box_quads(center: np.ndarray, size: np.ndarray, yaw_deg: float, detail: float) -> list[Quad]:
    """The six faces of a box whose bottom is centred at `center`, turned by yaw about z; normals point out."""
    yaw = np.deg2rad(yaw_deg)
    ex = np.array([np.cos(yaw), np.sin(yaw), 0.0]) * size[0]
    ey = np.array([-np.sin(yaw), np.cos(yaw), 0.0]) * size[1]
    ez = np.array([0.0, 0.0, size[2]])
    o = np.asarray(center, float) - ex / 2 - ey / 2
    return [
        Quad(o, ex, ez, detail),
        Quad(o + ey, ez, ex, detail),
        Quad(o, ez, ey, detail),
        Quad(o + ex, ey, ez, detail),
        Quad(o + ez, ex, ey, detail),
        Quad(o, ey, ex, detail),
    ]


def room_quads(half_size: float, height: float, detail: float) -> list[Quad]:
    """Floor and four walls of a square room centred on the origin."""
    h = half_size
    up = np.array([0.0, 0.0, height])
    floor = Quad(np.array([-h, -h, 0.0]), np.array([2 * h, 0, 0.0]), np.array([0, 2 * h, 0.0]), detail * 0.8)
    corners = [np.array(c, float) for c in ([-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0])]
    walls = [Quad(a, b - a, up, detail) for a, b in zip(corners, corners[1:] + corners[:1])]
    return [floor, *walls]


def ring_scene(
    num_images: int = 24,
    radius: float = 3.0,
    seed: int = 0,
    camera: pycolmap.Camera | None = None,
    turns: float = 1.0,
) -> Scene:
    """Ring capture of an object on a pedestal in a textured room, like a turntable sequence.

    Cameras are evenly spaced on a circle around the origin (15 deg apart for 24 views),
    with a little height, aim and roll jitter, all looking at the object. With `turns`
    above 1 the path goes round again: a sequence that revisits its first views.
    """
    rng = np.random.default_rng(seed)
    quads = room_quads(half_size=6.0, height=4.0, detail=0.05)
    quads += box_quads(np.array([0.0, 0.0, 0.0]), np.array([1.2, 1.0, 0.7]), 10.0, 0.015)
    quads += box_quads(np.array([0.15, -0.1, 0.7]), np.array([0.5, 0.4, 0.45]), 40.0, 0.012)
    quads += box_quads(np.array([-0.4, 0.3, 0.7]), np.array([0.18, 0.18, 0.8]), -15.0, 0.01)
    quads += box_quads(np.array([1.3, 0.9, 0.0]), np.array([0.4, 0.4, 0.4]), 30.0, 0.015)
    quads += box_quads(np.array([-1.1, -1.2, 0.0]), np.array([0.5, 0.3, 0.3]), -25.0, 0.015)
    angles = np.linspace(0.0, 2 * np.pi * turns, num_images, endpoint=False)
    heights = 1.5 + rng.uniform(-0.15, 0.15, num_images)
    targets = np.array([0.0, 0.0, 0.5]) + rng.uniform(-0.1, 0.1, (num_images, 3))
    rolls = rng.uniform(-3.0, 3.0, num_images)
    centers = np.stack([radius * np.cos(angles), radius * np.sin(angles), heights], axis=1)
    poses = [look_at(c, t, r) for c, t, r in zip(centers, targets, rolls)]
    names = [f"ring{i:04d}.png" for i in range(num_images)]
    return Scene(camera or default_camera(), poses, names, quads)


def facade_quads(length: float, depth: float, rng: np.random.Generator) -> list[Quad]:
    """A street: facade panels in the plane y = depth, with protruding boxes, and the pavement in front."""
    panel = 4.0
    starts = np.arange(-8.0, length + 8.0, panel)
    quads = []
    for x in starts:
        quads.append(Quad(np.array([x, depth, 0.0]), np.array([panel, 0, 0.0]), np.array([0, 0, 8.0]), 0.03))
        quads.append(Quad(np.array([x, -4.0, 0.0]), np.array([panel, 0, 0.0]), np.array([0, depth + 4.0, 0.0]), 0.03))
        size = rng.uniform([0.6, 0.5, 0.6], [2.0, 1.5, 3.0])
        center = np.array([x + rng.uniform(1.0, panel - 1.0), depth - size[1] / 2, rng.choice([0.0, 1.0, 2.0])])
        quads += box_quads(center, size, 0.0, 0.02)
    return quads


def trajectory_scene(
    num_images: int = 100,
    seed: int = 0,
    camera: pycolmap.Camera | None = None,
    step: float = 0.35,
    depth: float = 5.0,
) -> Scene:
    """A walk along a long facade: each image sees a few metres of it, so overlap is local.

    The path wanders in height and distance (centres are not collinear) and the view
    direction yaws a little; the street grows with num_images, for scaling benchmarks.
    """
    rng = np.random.default_rng(seed)
    length = step * max(num_images - 1, 1)
    quads = facade_quads(length, depth, rng)
    s = np.arange(num_images) * step
    phase = rng.uniform(0, 2 * np.pi, 2)
    centers = np.stack(
        [s, 0.4 * np.sin(s / 7.0 + phase[0]), 1.6 + 0.3 * np.sin(s / 5.0 + phase[1])], axis=1
    )
    yaws = np.deg2rad(rng.uniform(-12.0, 12.0, num_images))
    targets = centers + np.stack([depth * np.sin(yaws), depth * np.cos(yaws), np.full(num_images, -0.5)], axis=1)
    rolls = rng.uniform(-2.0, 2.0, num_images)
    poses = [look_at(c, t, r) for c, t, r in zip(centers, targets, rolls)]
    names = [f"traj{i:04d}.png" for i in range(num_images)]
    return Scene(camera or default_camera(), poses, names, quads)


def image_rays(camera: pycolmap.Camera, points2D: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates (x, y) of the rays through pixel positions (rays are (x, y, 1)).

    COLMAP's convention: the centre of pixel (0, 0) is at (0.5, 0.5).
    """
    return camera.cam_from_img(np.asarray(points2D, np.float64))


def in_frustum(corners: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per quad (corners Qx4x3, camera frame): False if all corners lie outside one side of the view pyramid."""
    x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
    outside = [x > hi[0] * z, x < lo[0] * z, y > hi[1] * z, y < lo[1] * z]
    return ~np.any([o.all(axis=1) for o in outside], axis=0)


def index_range(mins: np.ndarray, maxs: np.ndarray, low: float, high: float) -> slice:
    """Smallest slice covering every entry whose [min, max] interval meets [low, high] (empty if none)."""
    meets = np.flatnonzero((maxs >= low) & (mins <= high))
    return slice(meets[0], meets[-1] + 1) if len(meets) else slice(0, 0)


def cast_rays(
    scene: Scene,
    cam_from_world: pycolmap.Rigid3d,
    rays: np.ndarray,
    near: float = 1e-3,
) -> RayHits:
    """Nearest quad of the scene hit by each camera-frame ray (x, y, 1), for rays laid out as an HxWx2 array.

    A z-buffer over the quads: for a plane n.X = c in the camera frame the ray t*(x, y, 1)
    hits at depth t = c / (n.(x, y, 1)). Each quad is only tested on the rows and columns
    of `rays` whose x, y ranges meet its projected bounding box, which is what makes
    rendering fast (a pixel grid); any other layout (e.g. Nx1x2 points) stays correct.
    """
    x = np.ascontiguousarray(rays[..., 0], np.float32)
    y = np.ascontiguousarray(rays[..., 1], np.float32)
    shape = x.shape
    zeros = np.zeros(shape, np.float32)
    hits = RayHits(np.full(shape, np.inf, np.float32), np.full(shape, -1, np.int32), zeros, zeros.copy())
    rotation, translation = cam_from_world.rotation.matrix(), cam_from_world.translation
    corners = scene.quad_corners @ rotation.T + translation
    lo, hi = np.array([np.nanmin(x), np.nanmin(y)]), np.array([np.nanmax(x), np.nanmax(y)])
    col_min, col_max = np.nanmin(x, axis=0), np.nanmax(x, axis=0)
    row_min, row_max = np.nanmin(y, axis=1), np.nanmax(y, axis=1)
    for index in np.flatnonzero(in_frustum(corners, lo, hi)):
        rows, cols = slice(None), slice(None)
        if np.all(corners[index, :, 2] > near):
            projected = corners[index, :, :2] / corners[index, :, 2:]
            rows = index_range(row_min, row_max, projected[:, 1].min(), projected[:, 1].max())
            cols = index_range(col_min, col_max, projected[:, 0].min(), projected[:, 0].max())
        quad = scene.quads[index]
        origin = rotation @ quad.origin + translation
        eu, ev = rotation @ quad.edge_u, rotation @ quad.edge_v
        intersect_quad(origin, eu, ev, x[rows, cols], y[rows, cols], near, index, hits.view(rows, cols))
    return hits


def ray_dot(vector: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """vector . (x, y, 1) for every ray, in float32."""
    a, b, c = np.asarray(vector, np.float32)
    return a * x + b * y + c


def intersect_quad(
    origin: np.ndarray,
    eu: np.ndarray,
    ev: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    near: float,
    index: int,
    hits: RayHits,
) -> None:
    """Z-buffer one quad (camera frame: corner `origin`, edges eu, ev) into `hits` for the rays (x, y, 1)."""
    normal = np.cross(eu, ev)
    gu, gv = eu / (eu @ eu), ev / (ev @ ev)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(normal @ origin) / ray_dot(normal, x, y)
    u = depth * ray_dot(gu, x, y) - np.float32(origin @ gu)
    v = depth * ray_dot(gv, x, y) - np.float32(origin @ gv)
    hit = (depth > near) & (depth < hits.depth) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    hits.depth[hit] = depth[hit]
    hits.quad_index[hit] = index
    hits.u[hit] = u[hit]
    hits.v[hit] = v[hit]
