"""Images and ground truth of a synthetic scene: ray-cast textured quads through the distorted camera.

Every pixel centre of the distorted image is unprojected with the camera model
(`Camera.cam_from_img`), so the images carry exactly the camera's distortion. A camera
without an image plane (EQUIRECTANGULAR) is cast face by face of a cube around it
(`Camera.cam_ray_from_img`, each ray through the face it points at). Rendering
is supersampled and box-filtered for antialiasing. Textures are procedural and
multi-scale (noise octaves plus overlapping shapes: blobs and corners for SIFT).
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from colmap_ext.panorama import FACE_FORWARD_DOWN, face_from_cam, owning_faces
from colmap_ext.synthetic.scene import Quad, RayHits, Scene, cast_rays, image_rays

BACKGROUND = 0.5
LIGHT = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
MAX_TEXTURE_SIZE = 4096
SHIFT = 4  # fractional bits of cv2's fixed-point drawing coordinates


def noise_octaves(shape: tuple[int, int], cells: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Smooth value noise in [0, 1]: random grids of `cells`-texel spacing, upsampled and summed."""
    height, width = shape
    total = np.zeros(shape, np.float32)
    for cell in cells:
        grid = rng.random((height // cell + 2, width // cell + 2), dtype=np.float32)
        total += cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(total / len(cells), 0.0, 1.0)


def fixed_point(values: np.ndarray | list[float]) -> np.ndarray:
    """Coordinates in cv2's fixed-point drawing format (SHIFT fractional bits), for subpixel shapes."""
    return np.round(np.asarray(values) * (1 << SHIFT)).astype(np.int32)


def polygon(kind: int, size: float, centre: np.ndarray, angles: np.ndarray, aspect: float) -> np.ndarray:
    """Corners of a rotated rectangle (kind 2) or of a random triangle (kind 3) of diameter ~size."""
    if kind == 2:
        local = np.array([[-1, -aspect], [1, -aspect], [1, aspect], [-1, aspect]]) * size / 2
        c, s = np.cos(angles[0]), np.sin(angles[0])
        return local @ np.array([[c, s], [-s, c]]) + centre
    return centre + size / 2 * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def draw_shapes(canvas: np.ndarray, rng: np.random.Generator, min_size: float, max_size: float) -> None:
    """Paint discs, ellipses, rotated rectangles and triangles (sizes log-uniform), largest first, about twice over."""
    height, width = canvas.shape
    mean_square = (max_size**2 - min_size**2) / (2 * np.log(max_size / min_size))
    count = int(2 * height * width / mean_square)
    sizes = np.sort(np.exp(rng.uniform(np.log(min_size), np.log(max_size), count)))[::-1]
    centres = rng.uniform([0, 0], [width, height], (count, 2))
    greys = rng.integers(0, 256, count).tolist()
    kinds = rng.integers(0, 4, count).tolist()
    angles = rng.uniform(0, 2 * np.pi, (count, 3))
    aspects = rng.uniform(0.3, 1.0, count)
    for size, centre, grey, kind, angle, aspect in zip(sizes, centres, greys, kinds, angles, aspects):
        if kind < 2:
            axes = fixed_point([size / 2, size / 2 * (aspect if kind == 1 else 1.0)])
            centre_fp = fixed_point(centre)
            cv2.ellipse(canvas, centre_fp.tolist(), axes.tolist(), np.rad2deg(angle[0]), 0, 360, grey, -1, cv2.LINE_AA, SHIFT)
        else:
            cv2.fillConvexPoly(canvas, fixed_point(polygon(kind, size, centre, angle, aspect)), grey, cv2.LINE_AA, SHIFT)


def make_texture(quad: Quad, rng: np.random.Generator) -> np.ndarray:
    """Grey texture in [0, 1] for a quad, 4 texels per `detail`: shapes, shading octaves, fine grain.

    Each quad gets its own mean grey and contrast, so adjacent surfaces stand apart.
    """
    texel = quad.detail / 4
    width = int(np.clip(np.ceil(np.linalg.norm(quad.edge_u) / texel), 8, MAX_TEXTURE_SIZE))
    height = int(np.clip(np.ceil(np.linalg.norm(quad.edge_v) / texel), 8, MAX_TEXTURE_SIZE))
    canvas = (noise_octaves((height, width), (64, 16), rng) * 255).astype(np.uint8)
    draw_shapes(canvas, rng, min_size=4.0, max_size=48.0)
    shading = 0.7 + 0.6 * noise_octaves((height, width), (128, 32), rng)
    grain = cv2.GaussianBlur(rng.standard_normal((height, width), dtype=np.float32), (0, 0), 1.0)
    mean, contrast = rng.uniform(0.35, 0.65), rng.uniform(0.6, 1.0)
    texture = mean + contrast * (canvas.astype(np.float32) / 255 * shading - 0.5) + 0.04 * grain
    return np.clip(texture, 0.0, 1.0)


def sample_bilinear(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Texture values at texel positions (x, y) by cv2.remap, the points laid out in rows (remap caps rows at 32767)."""
    width = 1024
    padding = -len(x) % width
    map_x = np.pad(x, (0, padding)).reshape(-1, width)
    map_y = np.pad(y, (0, padding)).reshape(-1, width)
    sampled = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return sampled.ravel()[: len(x)]


def shade(quad: Quad) -> float:
    """Fixed diffuse lighting factor of a quad (two-sided), so faces of a box differ in brightness."""
    return 0.55 + 0.45 * abs(float(quad.normal @ LIGHT))


def pixel_grid(camera: pycolmap.Camera, supersample: int) -> np.ndarray:
    """Image positions of the sub-pixel centres, row-major, in COLMAP's convention (pixel (0,0) spans [0,1)^2)."""
    xs = (np.arange(camera.width * supersample) + 0.5) / supersample
    ys = (np.arange(camera.height * supersample) + 0.5) / supersample
    grid_x, grid_y = np.meshgrid(xs, ys)
    return np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)


class Renderer:
    """Renders the views of one scene. Random streams: (seed, 0, quad index) for a quad's texture,
    made on first use; (seed, 1, image index) for a view's sensor noise."""

    def __init__(self, scene: Scene, seed: int = 0, supersample: int = 2) -> None:
        self.scene = scene
        self.seed = seed
        self.supersample = supersample
        self.shape = (scene.camera.height * supersample, scene.camera.width * supersample)
        grid = pixel_grid(scene.camera, supersample)
        self.rays = image_rays(scene.camera, grid).reshape(*self.shape, 2) \
            if scene.camera.focal_length_idxs() else None
        # Without an image plane: per cube face, face_from_cam, its rays' flat indices and
        # their (x, y) on the face's plane, laid out N x 1 x 2.
        self.face_rays: list[tuple[pycolmap.Rigid3d, np.ndarray, np.ndarray]] = []
        if self.rays is None:
            rays = scene.camera.cam_ray_from_img(grid)
            owners = owning_faces(rays)
            for face in range(len(FACE_FORWARD_DOWN)):
                selected = np.flatnonzero(owners == face)
                on_face = rays[selected] @ face_from_cam(face).T
                self.face_rays.append((
                    pycolmap.Rigid3d(pycolmap.Rotation3d(face_from_cam(face)), np.zeros(3)),
                    selected, (on_face[:, :2] / on_face[:, 2:])[:, None, :]))
        self.textures: dict[int, np.ndarray] = {}

    def texture(self, index: int) -> np.ndarray:
        """Texture of quad `index`, the same whichever views are rendered first."""
        if index not in self.textures:
            rng = np.random.default_rng([self.seed, 0, index])
            self.textures[index] = make_texture(self.scene.quads[index], rng)
        return self.textures[index]

    def hits(self, image_index: int) -> RayHits:
        """The nearest quad per supersample of view `image_index` (depth along the ray's
        cube face's axis, for a camera without an image plane)."""
        cam_from_world = self.scene.cams_from_world[image_index]
        if self.rays is not None:
            return cast_rays(self.scene, cam_from_world, self.rays)
        hits = RayHits(np.full(self.shape, np.inf, np.float32), np.full(self.shape, -1, np.int32),
                       np.zeros(self.shape, np.float32), np.zeros(self.shape, np.float32))
        for face_from_camera, selected, rays in self.face_rays:
            found = cast_rays(self.scene, face_from_camera * cam_from_world, rays)
            for field in fields(RayHits):
                getattr(hits, field.name).ravel()[selected] = getattr(found, field.name).ravel()
        return hits

    def radiance(self, image_index: int) -> np.ndarray:
        """Supersampled image in [0, 1]: texture of the nearest quad per ray, times its lighting."""
        hits = self.hits(image_index)
        labels, u, v = hits.quad_index.ravel(), hits.u.ravel(), hits.v.ravel()
        values = np.full(labels.shape, BACKGROUND, np.float32)
        order = np.argsort(labels, kind="stable")
        indices, starts = np.unique(labels[order], return_index=True)
        for index, selected in zip(indices, np.split(order, starts[1:])):
            if index < 0:
                continue
            texture = self.texture(int(index))
            map_x = u[selected] * texture.shape[1] - 0.5
            map_y = v[selected] * texture.shape[0] - 0.5
            values[selected] = sample_bilinear(texture, map_x, map_y) * shade(self.scene.quads[index])
        return values.reshape(hits.quad_index.shape)

    def render(self, image_index: int) -> np.ndarray:
        """8-bit image: box-filtered supersamples plus a little sensor noise (deterministic per view)."""
        camera, s = self.scene.camera, self.supersample
        image = self.radiance(image_index).reshape(camera.height, s, camera.width, s).mean(axis=(1, 3))
        rng = np.random.default_rng([self.seed, 1, image_index])
        image = image * 255 + rng.normal(0.0, 1.0, image.shape)
        return np.clip(np.round(image), 0, 255).astype(np.uint8)


def render_images(scene: Scene, output_dir: str | Path, seed: int = 0, supersample: int = 2) -> None:
    """Write one 8-bit grey PNG per view, named scene.image_names[i], into output_dir."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    renderer = Renderer(scene, seed, supersample)
    for index, name in enumerate(scene.image_names):
        path = output_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), renderer.render(index)):
            raise OSError(f"could not write {path}")


def write_par_file(scene: Scene, path: str | Path) -> None:
    """Middlebury `*_par.txt`: N, then `name k11..k33 r11..r33 t1 t2 t3` per view, P = K[R|t].

    K is the pinhole part of the camera (COLMAP's calibration matrix, pixel (0,0)'s centre
    at (0.5, 0.5)); the distortion is not representable in this format.
    """
    k = scene.camera.calibration_matrix().ravel()
    lines = [str(scene.num_images)]
    for name, pose in zip(scene.image_names, scene.cams_from_world):
        numbers = np.concatenate([k, pose.rotation.matrix().ravel(), pose.translation])
        lines.append(" ".join([name, *(f"{x:.17g}" for x in numbers)]))
    Path(path).write_text("\n".join(lines) + "\n")


def ground_truth_reconstruction(scene: Scene) -> pycolmap.Reconstruction:
    """The scene's camera and poses as a COLMAP model (trivial rig and frames, no points)."""
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(scene.camera.todict())
    reconstruction.add_camera_with_trivial_rig(camera)
    for image_id, (name, pose) in enumerate(zip(scene.image_names, scene.cams_from_world), start=1):
        image = pycolmap.Image(name=name, camera_id=camera.camera_id, image_id=image_id)
        reconstruction.add_image_with_trivial_frame(image, pose)
    return reconstruction


def write_placeholder_images(folder: str | Path, names: list[str]) -> None:
    """A black 8x8 PNG under each image name: a synthetic database has no images, but
    our mapper reads point colours from the image files."""
    placeholder = cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()
    for name in names:
        (Path(folder) / name).parent.mkdir(parents=True, exist_ok=True)
        (Path(folder) / name).write_bytes(placeholder)


def write_ground_truth(scene: Scene, path: str | Path) -> None:
    """Write the ground-truth COLMAP model (binary cameras/images/rigs/frames/points3D) into directory `path`."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    ground_truth_reconstruction(scene).write(path)
