"""SIFT on the cube faces of equirectangular panoramas (colmap_ext/panorama.py): keypoints
back at the right panorama pixels, masks applied there, and `reconstruct` end to end on
rendered panoramas with known poses."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext.errors import UserError
from colmap_ext.evaluate import evaluate
from colmap_ext.features import (DEFAULT_PEAK_THRESHOLD, FeatureOptions, extract_features,
                                 extract_to_memory)
from colmap_ext.ground_truth import GroundTruth
from colmap_ext.panorama import CubeFaces, owning_faces
from colmap_ext.reconstruct import main
from colmap_ext.synthetic import render_images, ring_scene

WIDTH, HEIGHT = 1024, 512


def blob_directions() -> np.ndarray:
    """Unit directions (camera frame) of blobs: at face centres, near the edges and
    corners between faces, across the panorama's left/right seam (straight behind) and
    near the poles."""
    rng = np.random.default_rng(0)
    chosen = [[0, 0, 1], [1, 0.02, 0.98], [0.02, 0.03, -1], [-1, 0.95, 0.1], [0.7, -1, 0.9],
              [0.03, 1, 0.2], [0.3, -1, -0.2], [-0.1, 0.4, -1]]
    directions = np.vstack([chosen, rng.normal(size=(24, 3))])
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


def blob_panorama(directions: np.ndarray) -> np.ndarray:
    """A grey panorama of Gaussian blobs (1.2 degrees) at `directions`, dark and light."""
    camera = CubeFaces.of_panorama(WIDTH, HEIGHT).camera
    columns, rows = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = camera.cam_ray_from_img(np.column_stack([columns.ravel(), rows.ravel()]))
    angles = np.arccos(np.clip(rays @ directions.T, -1, 1))
    signs = np.where(np.arange(len(directions)) % 2, 1.0, -1.0)
    image = 128 + 100 * (np.exp(-0.5 * (angles / np.radians(1.2)) ** 2) * signs).sum(axis=1)
    return np.clip(np.round(image), 0, 255).astype(np.uint8).reshape(HEIGHT, WIDTH)


def wrapped_distances(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Pixel distances (len(points), len(targets)), across the panorama's left/right seam."""
    difference = points[:, None, :] - targets[None, :, :]
    difference[..., 0] = (difference[..., 0] + WIDTH / 2) % WIDTH - WIDTH / 2
    return np.linalg.norm(difference, axis=2)


def extract(tmp_path, mask_path=None) -> np.ndarray:
    """Keypoints of panorama.png in tmp_path, extracted on its cube faces."""
    database = tmp_path / "database.db"
    database.unlink(missing_ok=True)
    options = FeatureOptions("EQUIRECTANGULAR", [WIDTH, HEIGHT], mask_path=mask_path,
                             min_num_keypoints=0, panorama_features="cube_faces")
    extract_features(database, tmp_path / "images", options, progress=False)
    with pycolmap.Database.open(database) as db:
        (image,) = db.read_all_images()
        return db.read_keypoints(image.image_id)


def test_cube_face_keypoints_land_on_their_panorama_pixels(tmp_path):
    """Every blob is found within 0.5 px of its projection into the panorama (measured:
    0.2 px; half a pixel off in the faces' sampling fails), also where it lies on an edge
    between faces, across the panorama's seam or near a pole."""
    directions = blob_directions()
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "panorama.png"), blob_panorama(directions))
    keypoints = extract(tmp_path)
    projections = CubeFaces.of_panorama(WIDTH, HEIGHT).camera.img_from_cam(directions)
    assert wrapped_distances(keypoints[:, :2], projections).min(axis=0).max() < 0.5


def test_a_blob_two_faces_see_is_kept_by_one(tmp_path):
    """A blob on the edge between the front and right faces lies inside both faces'
    margins and is detected on both, at the same panorama pixel; only the face whose
    90-degree square holds its ray keeps it."""
    faces = CubeFaces.of_panorama(WIDTH, HEIGHT)
    directions = blob_directions()
    edge_blob = faces.camera.img_from_cam(directions[1:2])
    reader = pycolmap.ImageReaderOptions(camera_model="SIMPLE_PINHOLE", camera_params="1,1,1")
    kept_by = []
    for face, image in enumerate(faces.render(blob_panorama(directions))[:2]):
        cv2.imwrite(str(tmp_path / f"{face}.png"), image)
        (keypoints, _), = extract_to_memory(tmp_path, reader, [f"{face}.png"],
                                            DEFAULT_PEAK_THRESHOLD, domain_size_pooling=False,
                                            num_threads=1).values()
        mapped, owned = faces.to_panorama(face, keypoints)
        on_blob = wrapped_distances(mapped[:, :2], edge_blob)[:, 0] < 1.0
        assert on_blob.any()
        kept_by += [face] * int((on_blob & owned).any())
    assert kept_by == [owning_faces(directions[1:2])[0]]


def test_cube_face_keypoints_respect_the_panorama_mask(tmp_path):
    """A COLMAP mask of the panorama (MASK_PATH/<name>.png, 0 = ignore) over its lower
    third (the tripod at the nadir) removes the faces' keypoints there, and only there."""
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "panorama.png"), blob_panorama(blob_directions()))
    mask = np.full((HEIGHT, WIDTH), 255, np.uint8)
    mask[2 * HEIGHT // 3:] = 0
    (tmp_path / "masks").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "panorama.png.png"), mask)
    unmasked = extract(tmp_path)
    masked = extract(tmp_path, mask_path=tmp_path / "masks")
    below = unmasked[:, 1] >= 2 * HEIGHT // 3
    assert below.sum() >= 3
    assert not (masked[:, 1] >= 2 * HEIGHT // 3).any()
    assert len(masked) == (~below).sum()


def test_reconstruct_on_cube_faces_registers_every_rendered_panorama(tmp_path):
    """Five panoramas of the synthetic ring scene (768 x 384, poses known): `reconstruct
    --panorama_features cube_faces` puts all five in one model, every rotation within
    0.1 deg of the truth (measured: 0.022 deg max), and records the choice."""
    width, height = 768, 384
    camera = pycolmap.Camera(camera_id=1, model="EQUIRECTANGULAR", width=width, height=height,
                             params=[width, height])
    scene = ring_scene(num_images=5, camera=camera)
    render_images(scene, tmp_path / "images", supersample=1)
    summary = main(tmp_path / "images", tmp_path / "ws", "EQUIRECTANGULAR",
                   f"{width},{height}", seed=0, panorama_features="cube_faces")
    assert summary["inputs"]["panorama_features"] == "cube_faces"
    assert len(summary["models"]) == 1
    truth = GroundTruth(dict(zip(scene.image_names, scene.cams_from_world)), {})
    report = evaluate(pycolmap.Reconstruction(summary["models"][0]["path"]), truth)
    assert report["num_registered"] == 5
    assert report["R_err_max_deg"] < 0.1


def test_panorama_features_are_for_equirectangular_cameras(tmp_path):
    """--panorama_features with a pinhole camera is one clear error, before any work."""
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), np.zeros((48, 64), np.uint8))
    with pytest.raises(UserError, match="--panorama_features is for EQUIRECTANGULAR cameras"):
        main(tmp_path / "images", tmp_path / "ws", "PINHOLE", "50,50,32,24",
             panorama_features="cube_faces")
    assert not (tmp_path / "ws").exists()
    with pytest.raises(UserError, match="unknown panorama features 'cubes'"):
        FeatureOptions("EQUIRECTANGULAR", [WIDTH, HEIGHT], panorama_features="cubes").check()
