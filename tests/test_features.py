"""Feature extraction with the adaptive SIFT threshold, input checks, and turntable masks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from colmap_ext.errors import UserError
from colmap_ext.executors import LocalExecutor
from colmap_ext.features import DEFAULT_PEAK_THRESHOLD, FeatureOptions, extract_features
from colmap_ext.masks import make_masks

WIDTH, HEIGHT = 320, 240
PARAMS = "300,300,160,120"


def noise_texture(shape: tuple[int, int], seed: int, contrast: float) -> np.ndarray:
    """Multi-scale smooth noise around grey 128; `contrast` 1 gives ~2000 SIFT keypoints
    at 320x240, 0.1 only a few dozen at COLMAP's default peak threshold."""
    rng = np.random.default_rng(seed)
    height, width = shape
    image = np.zeros(shape, np.float32)
    for cell in (4, 8, 16, 32):
        grid = rng.random((height // cell + 2, width // cell + 2)).astype(np.float32)
        image += cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    image = (image - image.mean()) / image.std()
    return np.clip(128 + 40 * contrast * image, 0, 255).astype(np.uint8)


@pytest.fixture
def images(tmp_path: Path) -> Path:
    """A textured image and a low-contrast one."""
    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "rich.png"), noise_texture((HEIGHT, WIDTH), 0, 1.0))
    cv2.imwrite(str(folder / "poor.png"), noise_texture((HEIGHT, WIDTH), 1, 0.1))
    return folder


def read_features(database_path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    db = pycolmap.Database.open(database_path)
    try:
        return {image.name: (db.read_keypoints(image.image_id),
                             db.read_descriptors(image.image_id).data)
                for image in db.read_all_images()}
    finally:
        db.close()


def test_poor_image_is_extracted_again_with_more_keypoints(images: Path, tmp_path: Path) -> None:
    database_path = tmp_path / "database.db"
    summary = extract_features(database_path, images,
                               FeatureOptions("PINHOLE", PARAMS, min_num_keypoints=500),
                               progress=False)
    assert summary.reextracted == ["poor.png"]
    assert summary.initial_keypoints["poor.png"] < 500 <= summary.final_keypoints["poor.png"]
    assert summary.peak_thresholds["rich.png"] == DEFAULT_PEAK_THRESHOLD
    assert summary.final_keypoints["rich.png"] == summary.initial_keypoints["rich.png"]

    features = read_features(database_path)
    keypoints, descriptors = features["poor.png"]
    assert keypoints.shape == (summary.final_keypoints["poor.png"], 6)
    assert descriptors.shape == (len(keypoints), 128) and descriptors.dtype == np.uint8
    # Exactly what COLMAP's extractor gives at the lowered threshold: same rows, same format.
    options = pycolmap.FeatureExtractionOptions()
    options.sift.peak_threshold = summary.peak_thresholds["poor.png"]
    extractor = pycolmap.FeatureExtractor.create(options, device=pycolmap.Device.cpu)
    expected, _ = extractor.extract_from_uint8_array(cv2.imread(str(images / "poor.png"), 0))
    np.testing.assert_allclose(keypoints[:, :2], np.array([[k.x, k.y] for k in expected]),
                               atol=1e-3)
    assert summary.to_dict()["num_reextracted"] == 1


def test_image_ids_follow_names_and_cameras_are_fixed(images: Path, tmp_path: Path) -> None:
    database_path = tmp_path / "database.db"
    extract_features(database_path, images,
                     FeatureOptions("PINHOLE", PARAMS, min_num_keypoints=0), progress=False)
    db = pycolmap.Database.open(database_path)
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        cameras = db.read_all_cameras()
    finally:
        db.close()
    assert ids == {"poor.png": 1, "rich.png": 2}
    assert len(cameras) == 1 and list(cameras[0].params) == [300, 300, 160, 120]


def test_one_camera_per_folder_allows_a_size_per_folder(tmp_path: Path) -> None:
    for folder, shape in (("left", (HEIGHT, WIDTH)), ("right", (HEIGHT // 2, WIDTH // 2))):
        (tmp_path / "images" / folder).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "images" / folder / "view.png"), noise_texture(shape, 0, 1.0))
    database_path = tmp_path / "database.db"
    extract_features(database_path, tmp_path / "images",
                     FeatureOptions("SIMPLE_PINHOLE", "300,80,60", camera_mode="per_folder",
                                    min_num_keypoints=0), progress=False)
    db = pycolmap.Database.open(database_path)
    try:
        cameras = {image.name: db.read_camera(image.camera_id) for image in db.read_all_images()}
    finally:
        db.close()
    assert {name: (camera.width, camera.height) for name, camera in cameras.items()} == \
        {"left/view.png": (WIDTH, HEIGHT), "right/view.png": (WIDTH // 2, HEIGHT // 2)}
    assert all(list(camera.params) == [300, 80, 60] for camera in cameras.values())


def test_masked_pixels_give_no_keypoints(images: Path, tmp_path: Path) -> None:
    masks = tmp_path / "masks"
    masks.mkdir()
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    mask[:, : WIDTH // 2] = 255
    for name in ("rich.png", "poor.png"):
        cv2.imwrite(str(masks / f"{name}.png"), mask)
    database_path = tmp_path / "database.db"
    extract_features(database_path, images,
                     FeatureOptions("PINHOLE", PARAMS, mask_path=masks, min_num_keypoints=500),
                     progress=False)
    for keypoints, _ in read_features(database_path).values():
        assert len(keypoints) > 0 and keypoints[:, 0].max() < WIDTH // 2 + 1


@pytest.mark.parametrize(("model", "params", "message"), [
    ("PINHOL", PARAMS, "unknown camera model 'PINHOL'"),
    ("PINHOLE", "300,160,120", "PINHOLE takes 4 params (fx, fy, cx, cy), got 3"),
    ("PINHOLE", "300,nan,160,120", "finite"),
    ("PINHOLE", "300,300,x,120", "numbers separated by commas"),
    ("PINHOLE", "-300,300,160,120", "focal lengths must be positive"),
    ("PINHOLE", "300,300,1600,1200", "principal point (1600, 1200) is outside the 320x240"),
    ("EQUIRECTANGULAR", "640,320", "camera params 640,320 (w,h) are not the images' size 320x240"),
])
def test_bad_camera_is_refused_before_any_work(images: Path, tmp_path: Path, model: str,
                                               params: str, message: str) -> None:
    database_path = tmp_path / "database.db"
    with pytest.raises(UserError) as error:
        extract_features(database_path, images, FeatureOptions(model, params), progress=False)
    assert message in str(error.value)
    assert not database_path.exists()


def test_zero_byte_image_is_named(images: Path, tmp_path: Path) -> None:
    (images / "empty.jpg").write_bytes(b"")
    with pytest.raises(UserError, match=r"image file is empty \(0 bytes\): .*empty\.jpg"):
        extract_features(tmp_path / "database.db", images, FeatureOptions("PINHOLE", PARAMS),
                         progress=False)
    assert not (tmp_path / "database.db").exists()


def test_corrupt_and_truncated_images_are_named(images: Path, tmp_path: Path) -> None:
    (images / "garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    with pytest.raises(UserError, match=r"cannot read image .*garbage\.png"):
        extract_features(tmp_path / "database.db", images, FeatureOptions("PINHOLE", PARAMS),
                         progress=False)
    (images / "garbage.png").unlink()
    data = (images / "rich.png").read_bytes()
    (images / "rich.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match=r"cannot read image .*rich\.png"):
        extract_features(tmp_path / "database.db", images, FeatureOptions("PINHOLE", PARAMS),
                         progress=False)


def test_missing_or_empty_image_folder(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="image folder not found: .*nowhere"):
        extract_features(tmp_path / "database.db", tmp_path / "nowhere",
                         FeatureOptions("PINHOLE", PARAMS), progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no images in"):
        extract_features(tmp_path / "database.db", tmp_path / "empty",
                         FeatureOptions("PINHOLE", PARAMS), progress=False)


def test_sizes_and_masks_are_checked(images: Path, tmp_path: Path) -> None:
    cv2.imwrite(str(images / "small.png"), noise_texture((120, 160), 2, 1.0))
    with pytest.raises(UserError, match="images sharing one camera must have one size"):
        extract_features(tmp_path / "database.db", images, FeatureOptions("PINHOLE", PARAMS),
                         progress=False)
    (images / "small.png").unlink()
    (tmp_path / "masks").mkdir()
    with pytest.raises(UserError, match=r"file not found: .*masks/poor\.png\.png"):
        extract_features(tmp_path / "database.db", images,
                         FeatureOptions("PINHOLE", PARAMS, mask_path=tmp_path / "masks"),
                         progress=False)


def test_database_with_images_is_not_reused(images: Path, tmp_path: Path) -> None:
    database_path = tmp_path / "database.db"
    extract_features(database_path, images,
                     FeatureOptions("PINHOLE", PARAMS, min_num_keypoints=0), progress=False)
    with pytest.raises(UserError, match="already holds 2 images"):
        extract_features(database_path, images, FeatureOptions("PINHOLE", PARAMS),
                         progress=False)


def turntable_image(background: int) -> tuple[np.ndarray, np.ndarray]:
    """A textured object (an ellipse with a shaded part reaching its outline) on a uniform
    background with sensor noise; returns the BGR image and the true object mask."""
    rng = np.random.default_rng(3)
    truth = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.ellipse(truth, (170, 120), (90, 60), 20, 0, 360, 1, -1)
    texture = noise_texture((HEIGHT, WIDTH), 4, 1.0).astype(np.float32)
    object_grey = 100 + 0.6 * texture  # lit: 100 to 250
    object_grey[:, :150] *= 0.45  # the shaded left side: 45 to 110
    if background > 128:
        object_grey = object_grey * 0.5  # a darker object on a bright background
    grey = np.where(truth > 0, object_grey, background) + rng.normal(0, 3, truth.shape)
    image = cv2.cvtColor(np.clip(grey, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    return image, truth > 0


@pytest.mark.parametrize(("method", "background"), [
    ("threshold", 8), ("grabcut", 8), ("threshold", 235)])
def test_masks_cover_the_object_not_the_background(tmp_path: Path, method: str,
                                                   background: int) -> None:
    image, truth = turntable_image(background)
    (tmp_path / "images" / "ring").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "images" / "ring" / "view.png"), image)
    coverage = make_masks(tmp_path / "images", tmp_path / "masks", method, progress=False)
    mask = cv2.imread(str(tmp_path / "masks" / "ring" / "view.png.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == truth.shape and set(np.unique(mask)) <= {0, 255}
    found = mask > 0
    assert np.count_nonzero(found & truth) / np.count_nonzero(truth) > 0.95
    assert np.count_nonzero(found & ~truth) / np.count_nonzero(~truth) < 0.02
    assert coverage == {"ring/view.png": pytest.approx(found.mean())}


def test_unknown_mask_method(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="unknown segmentation method 'otsu'"):
        make_masks(tmp_path, tmp_path / "masks", "otsu")


@pytest.mark.parametrize("executor", [LocalExecutor(1), LocalExecutor(2, processes=True)],
                         ids=["one thread", "two processes"])
def test_every_executor_writes_the_same_features(images: Path, tmp_path: Path,
                                                 executor: LocalExecutor) -> None:
    """Chunks of images run in one thread or in worker processes: the same rows as in
    this process's threads (the default), the adaptive rule included."""
    options = FeatureOptions("PINHOLE", PARAMS, min_num_keypoints=500)
    expected = extract_features(tmp_path / "threads.db", images, options, progress=False)
    got = extract_features(tmp_path / "other.db", images, options, executor=executor,
                           progress=False)
    assert got.peak_thresholds == expected.peak_thresholds and got.reextracted == ["poor.png"]
    reference = read_features(tmp_path / "threads.db")
    for name, (keypoints, descriptors) in read_features(tmp_path / "other.db").items():
        np.testing.assert_array_equal(keypoints, reference[name][0])
        np.testing.assert_array_equal(descriptors, reference[name][1])
