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

    @cached_property
    def quad_grid(self) -> GridIndex:
        """The quads' centres by cells of the ground plane, for quads_near."""
        return GridIndex(self.quad_corners.mean(axis=1)[:, :2], QUAD_GRID_CELL)

    def quads_near(self, center: np.ndarray, distance: float) -> np.ndarray:
        """Indices (sorted) of the quads that may come within `distance` of `center` (a superset)."""
        half_diagonals = np.linalg.norm(self.quad_corners[:, 2] - self.quad_corners[:, 0], axis=1) / 2
        return self.quad_grid.near(np.asarray(center)[:2], distance + half_diagonals.max())


QUAD_GRID_CELL = 16.0  # metres: cell of Scene.quad_grid


class GridIndex:
    """Items at 2D places (points or quad centres on the ground plane) by square cells, so
    that what lies near one place is found without scanning all of them."""

    def __init__(self, xy: np.ndarray, cell: float) -> None:
        self.cell = cell
        keys = np.floor(np.asarray(xy) / cell).astype(np.int64)
        self.low = keys.min(axis=0) if len(keys) else np.zeros(2, np.int64)
        self.high = keys.max(axis=0) if len(keys) else np.full(2, -1, np.int64)
        flat = self._flat(keys)
        self.order = np.argsort(flat, kind="stable")
        self.sorted_keys = flat[self.order]

    def _flat(self, keys: np.ndarray) -> np.ndarray:
        return (keys[:, 0] - self.low[0]) * (self.high[1] - self.low[1] + 1) + keys[:, 1] - self.low[1]

    def near(self, center: np.ndarray, radius: float) -> np.ndarray:
        """Indices (sorted) of the items in the cells that meet the square of half-side `radius` around center."""
        first = np.maximum(np.floor((center - radius) / self.cell).astype(np.int64), self.low)
        last = np.minimum(np.floor((center + radius) / self.cell).astype(np.int64), self.high)
        if np.any(last < first):
            return np.zeros(0, np.int64)
        cells = np.stack(np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(first, last)), indexing="ij"), -1)
        flat = self._flat(cells.reshape(-1, 2))
        starts = np.searchsorted(self.sorted_keys, flat, side="left")
        ends = np.searchsorted(self.sorted_keys, flat, side="right")
        return np.sort(np.concatenate([self.order[a:b] for a, b in zip(starts, ends)]))


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
    return facade_panels(np.arange(-8.0, length + 8.0, 4.0), 4.0, depth, -4.0, rng)


def facade_panels(
    starts: np.ndarray, width: float, depth: float, pavement_from: float, rng: np.random.Generator
) -> list[Quad]:
    """Facade panels [x, x + width] in the plane y = depth, 8 m high, each with a protruding box
    and the pavement in front of it, from y = pavement_from to the facade."""
    quads = []
    for x in starts:
        quads.append(Quad(np.array([x, depth, 0.0]), np.array([width, 0, 0.0]), np.array([0, 0, 8.0]), 0.03))
        quads.append(
            Quad(
                np.array([x, pavement_from, 0.0]),
                np.array([width, 0, 0.0]),
                np.array([0, depth - pavement_from, 0.0]),
                0.03,
            )
        )
        size = rng.uniform([0.6, 0.5, 0.6], [2.0, 1.5, 3.0])
        center = np.array([x + rng.uniform(1.0, width - 1.0), depth - size[1] / 2, rng.choice([0.0, 1.0, 2.0])])
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


def driving_scene(
    num_images: int = 500,
    seed: int = 0,
    camera: pycolmap.Camera | None = None,
    *,
    step: float = 1.0,
    street_half_width: float = 8.0,
    block_length: float | None = 60.0,
    turn_frames: int = 6,
    stop_every: int = 300,
    stop_frames: int = 10,
    loop: bool = False,
) -> Scene:
    """A drive down streets between facades, the camera looking forward along its path.

    The camera (1.65 m above a textured road) advances `step` metres a frame, wandering a
    little across its lane, and looks along its direction of travel (within about 2 deg:
    yaw and roll jitter, a slight downward pitch). The streets are 2 * street_half_width
    wide, between 8 m high facades with protruding boxes, built only along the path, so the
    scene grows with num_images. With block_length, the path turns 90 deg, alternately left
    and right, every block_length (+-20 %) metres, each corner taken over turn_frames
    frames (a staircase that never comes back); with None, one straight street. Every
    stop_every frames the camera stands still for stop_frames frames (one pose; 0: no stops).
    With loop, the path goes round a square block instead, and its last frame stands one
    step behind the first, looking the same way.
    """
    radius = 2 * turn_frames * step / np.pi  # a quarter circle of turn_frames steps
    shortest_block = 2 * street_half_width + 4.0
    if radius > street_half_width - 1.0:
        raise ValueError(f"turns of {turn_frames} steps of {step} m do not fit a street {2 * street_half_width} m wide")
    if block_length is not None and 0.8 * block_length < shortest_block:
        raise ValueError(f"block_length must be at least {shortest_block / 0.8:.1f} m, got {block_length}")
    if stop_every > 0 and not 0 <= stop_frames <= stop_every:
        raise ValueError(f"stop_frames must be in [0, stop_every], got {stop_frames}")
    rng = np.random.default_rng(seed)
    places = stop_places(num_images, stop_every, stop_frames)
    num_places = int(places[-1]) + 1
    if loop:
        corner_saving = (2 - np.pi / 2) * radius  # a rounded corner is shorter than the sharp one
        side = (num_places * step + 4 * corner_saving) / 4
        if side < shortest_block:
            raise ValueError(f"a loop of {num_places} places of {step} m is too short for its street")
        vertices = side * np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
        path = rounded_path(vertices, radius, closed=True)
        length = path_lengths(path)[-1]
        s = np.arange(num_places) * (length / num_places)
    else:
        ahead = 5 * street_half_width  # street beyond the last frame, for it to look down
        vertices = street_corners((num_places - 1) * step + ahead, block_length, radius, rng)
        path = rounded_path(vertices, radius, closed=False)
        length = path_lengths(path)[-1]
        s = np.arange(num_places) * step
    position, tangent = along_path(path, s)
    lateral, height = (lane_wander(s, length, wavelength, amplitude, rng)
                       for wavelength, amplitude in ((70.0, 0.5), (23.0, 0.05)))
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    centers = np.column_stack([position + lateral[0][:, None] * normal, 1.65 + height[0]])
    travel = np.column_stack([tangent + lateral[1][:, None] * normal, height[1]])
    heading = np.arctan2(travel[:, 1], travel[:, 0]) + np.deg2rad(rng.uniform(-1.0, 1.0, num_places))
    pitch = np.arcsin(travel[:, 2] / np.linalg.norm(travel, axis=1)) + np.deg2rad(
        rng.uniform(-2.0, -1.0, num_places)
    )
    forward = np.stack([np.cos(pitch) * np.cos(heading), np.cos(pitch) * np.sin(heading), np.sin(pitch)], axis=1)
    rolls = rng.uniform(-1.0, 1.0, num_places)
    poses = [look_at(c, c + f, r) for c, f, r in zip(centers, forward, rolls)]
    quads = street_quads(vertices, street_half_width, loop, rng)
    names = [f"drive{i:05d}.png" for i in range(num_images)]
    return Scene(camera or default_camera(), [poses[p] for p in places], names, quads)


def rig_scene(scene: Scene, cams_from_rig: list[pycolmap.Rigid3d], image_prefixes: list[str]) -> Scene:
    """The scene seen by a rig whose frames stand at the scene's poses (rig_from_world): per
    frame, one image per camera of the rig (the scene's intrinsics each), image
    frame * len(cams_from_rig) + camera, named the camera's prefix + the frame's name."""
    if len(image_prefixes) != len(cams_from_rig):
        raise ValueError(f"{len(image_prefixes)} image prefixes for {len(cams_from_rig)} cameras")
    poses = [cam_from_rig * rig_from_world for rig_from_world in scene.cams_from_world for cam_from_rig in cams_from_rig]
    names = [prefix + name for name in scene.image_names for prefix in image_prefixes]
    return Scene(scene.camera, poses, names, scene.quads)


def side_by_side_rig(num_cameras: int, baseline: float) -> list[pycolmap.Rigid3d]:
    """cams_from_rig of a rig of cameras looking the same way, each `baseline` metres to the
    right of the one before (the first is the rig's frame): 2, a stereo pair."""
    return [pycolmap.Rigid3d(pycolmap.Rotation3d(), [-index * baseline, 0.0, 0.0]) for index in range(num_cameras)]


def stop_places(num_images: int, stop_every: int, stop_frames: int) -> np.ndarray:
    """Per frame, the index of its place along the path: frame k * stop_every (k >= 1) and the
    stop_frames - 1 frames after it share one place."""
    frames = np.arange(num_images)
    standing = np.zeros(num_images, bool)
    if stop_every > 0:
        standing = (frames > stop_every) & (frames % stop_every >= 1) & (frames % stop_every < stop_frames)
    return np.cumsum(~standing) - 1


def street_corners(length: float, block_length: float | None, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Corners (x, y) of a path along +x at least `length` long once its corners are rounded
    by `radius`: one street, or blocks of block_length (+-20 %) turning left, right, left..."""
    if block_length is None:
        return np.array([[0.0, 0.0], [length, 0.0]])
    corner_saving = (2 - np.pi / 2) * radius
    vertices = [np.zeros(2)]
    directions = np.array([[1.0, 0.0], [0.0, 1.0]])
    while len(vertices) < 2 or sum(np.linalg.norm(np.diff(vertices, axis=0), axis=1)) - (
        len(vertices) - 2
    ) * corner_saving < length:
        block = block_length * rng.uniform(0.8, 1.2)
        vertices.append(vertices[-1] + block * directions[(len(vertices) - 1) % 2])
    return np.array(vertices)


def rounded_path(vertices: np.ndarray, radius: float, closed: bool) -> np.ndarray:
    """A polyline (Kx2) through `vertices`, each 90 deg corner replaced by a quarter circle of
    `radius` (in 2 deg chords). A closed path starts and ends half-way along its first street."""
    count = len(vertices)
    corners = [*range(1, count), 0] if closed else range(1, count - 1)
    angles = np.linspace(0.0, np.pi / 2, 46)[:, None]
    start = (vertices[0] + vertices[1]) / 2 if closed else vertices[0]
    points = [start[None]]
    for i in corners:
        into = vertices[i] - vertices[i - 1]
        out = vertices[(i + 1) % count] - vertices[i]
        into, out = into / np.linalg.norm(into), out / np.linalg.norm(out)
        center = vertices[i] - radius * into + radius * out
        points.append(center - np.cos(angles) * radius * out + np.sin(angles) * radius * into)
    points.append((start if closed else vertices[-1])[None])
    return np.concatenate(points)


def path_lengths(path: np.ndarray) -> np.ndarray:
    """Distance along a polyline to each of its points."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def along_path(path: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (Nx2) and unit tangents (Nx2) at distances s along a polyline."""
    lengths = path_lengths(path)
    position = np.stack([np.interp(s, lengths, path[:, k]) for k in range(2)], axis=1)
    segment = np.clip(np.searchsorted(lengths, s, side="right") - 1, 0, len(path) - 2)
    tangent = path[segment + 1] - path[segment]
    return position, tangent / np.linalg.norm(tangent, axis=1, keepdims=True)


def lane_wander(
    s: np.ndarray, length: float, wavelength: float, amplitude: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth offset along the path and its derivative; whole periods over `length`, so a closed path closes."""
    wavelength = length / max(1, round(length / wavelength))
    phase = rng.uniform(0, 2 * np.pi)
    angle = 2 * np.pi * s / wavelength + phase
    return amplitude * np.sin(angle), amplitude * 2 * np.pi / wavelength * np.cos(angle)


def street_quads(vertices: np.ndarray, half_width: float, closed: bool, rng: np.random.Generator) -> list[Quad]:
    """Facades (facade_panels) on both sides of the streets between the corners, with the road.

    At a corner the outer facades run on to meet, the inner ones stop where the crossing
    street begins, and a road patch fills the inner corner of the crossing.
    """
    count = len(vertices)
    segments = range(count) if closed else range(count - 1)
    directions = np.array([vertices[(i + 1) % count] - vertices[i] for i in segments])
    lengths = np.linalg.norm(directions, axis=1)
    directions /= lengths[:, None]

    def turn(i: int) -> float:
        """+1 where the path turns left at the start of segment i, -1 right, 0 at an open end."""
        if not closed and i in (0, count - 1):
            return 0.0
        before, after = directions[i - 1], directions[i % len(directions)]
        return float(np.sign(before[0] * after[1] - before[1] * after[0]))

    quads = []
    for i, (direction, length) in enumerate(zip(directions, lengths)):
        normal = np.array([-direction[1], direction[0]])
        for side in (1.0, -1.0):  # left, right
            # Where this side's facade starts and ends along the segment: short of the
            # crossing street on the inside of a corner, on to the far facade outside.
            start = side * turn(i) * half_width if turn(i) else -half_width
            end = length - side * turn(i + 1) * half_width
            origin, along = vertices[i], direction
            if side < 0:  # the street seen from its other end: its right side is on the left
                origin, along, start, end = vertices[i] + length * direction, -direction, length - end, length - start
            panels = int(np.ceil((end - start) / 4.0))
            width = (end - start) / panels
            quads += placed(facade_panels(start + width * np.arange(panels), width, half_width, 0.0, rng), origin, along)
        if turn(i + 1):
            corner = vertices[(i + 1) % count]
            quads.append(Quad(np.append(corner - half_width * direction, 0.0), np.append(half_width * direction, 0.0),
                              np.append(turn(i + 1) * half_width * normal, 0.0), 0.03))
    return quads


def placed(quads: list[Quad], origin: np.ndarray, direction: np.ndarray) -> list[Quad]:
    """Quads moved from a local frame (x along the street, y to its left, z up) to the world:
    the local origin at `origin` (x, y), local x along the unit vector `direction`."""
    rotation = np.array([[direction[0], -direction[1], 0.0], [direction[1], direction[0], 0.0], [0.0, 0.0, 1.0]])
    shift = np.append(origin, 0.0)
    return [Quad(rotation @ q.origin + shift, rotation @ q.edge_u, rotation @ q.edge_v, q.detail) for q in quads]


def image_rays(camera: pycolmap.Camera, points2D: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates (x, y) of the rays through pixel positions (rays are (x, y, 1)).

    COLMAP's convention: the centre of pixel (0, 0) is at (0.5, 0.5).
    """
    return camera.cam_from_img(np.asarray(points2D, np.float64))


def in_frustum(corners: np.ndarray, lo: np.ndarray, hi: np.ndarray, far: float = np.inf) -> np.ndarray:
    """Per quad (corners Qx4x3, camera frame): False if all corners lie outside one side of the
    view pyramid, or beyond depth `far`."""
    x, y, z = corners[..., 0], corners[..., 1], corners[..., 2]
    outside = [x > hi[0] * z, x < lo[0] * z, y > hi[1] * z, y < lo[1] * z, z > far]
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
    far: float = np.inf,
) -> RayHits:
    """Nearest quad of the scene hit by each camera-frame ray (x, y, 1), for rays laid out as an HxWx2 array.

    A z-buffer over the quads: for a plane n.X = c in the camera frame the ray t*(x, y, 1)
    hits at depth t = c / (n.(x, y, 1)). Each quad is only tested on the rows and columns
    of `rays` whose x, y ranges meet its projected bounding box, which is what makes
    rendering fast (a pixel grid); any other layout (e.g. Nx1x2 points) stays correct.
    Quads wholly beyond depth `far` are left out (hits there are missed): with a finite
    `far`, only the quads near the camera are looked at, however large the scene.
    """
    x = np.ascontiguousarray(rays[..., 0], np.float32)
    y = np.ascontiguousarray(rays[..., 1], np.float32)
    shape = x.shape
    zeros = np.zeros(shape, np.float32)
    hits = RayHits(np.full(shape, np.inf, np.float32), np.full(shape, -1, np.int32), zeros, zeros.copy())
    rotation, translation = cam_from_world.rotation.matrix(), cam_from_world.translation
    if np.isfinite(far):
        longest_ray = np.sqrt(np.nanmax(x * x + y * y) + 1.0)  # per unit of depth
        candidates = scene.quads_near(cam_from_world.inverse().translation, far * longest_ray)
    else:
        candidates = np.arange(len(scene.quads))
    corners = scene.quad_corners[candidates] @ rotation.T + translation
    lo, hi = np.array([np.nanmin(x), np.nanmin(y)]), np.array([np.nanmax(x), np.nanmax(y)])
    col_min, col_max = np.nanmin(x, axis=0), np.nanmax(x, axis=0)
    row_min, row_max = np.nanmin(y, axis=1), np.nanmax(y, axis=1)
    for k in np.flatnonzero(in_frustum(corners, lo, hi, far)):
        index = candidates[k]
        rows, cols = slice(None), slice(None)
        if np.all(corners[k, :, 2] > near):
            projected = corners[k, :, :2] / corners[k, :, 2:]
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
    normal = np.array([eu[1] * ev[2] - eu[2] * ev[1], eu[2] * ev[0] - eu[0] * ev[2], eu[0] * ev[1] - eu[1] * ev[0]])
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
