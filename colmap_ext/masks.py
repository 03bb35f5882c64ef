"""Object masks for turntable sequences, in COLMAP's layout.

On a turntable the object turns in front of a fixed camera: features on the background
agree with "no motion" and pin every pose to the first one, so only the object may be
used. For a dark or otherwise uniform background (any colour):

- threshold: Otsu on the (square-rooted) colour distance of the blurred image from the
  background colour, the median of the image border; morphological clean-up, the
  largest components, holes filled.
- grabcut: OpenCV's GrabCut started from the threshold mask (sure object well inside
  it, sure background well outside), for soft or shadowed silhouettes.

Masks are written as `MASK_PATH/<image name>.png`: 0 = ignore, 255 = use, the layout
`ImageReaderOptions.mask_path` (`--ImageReader.mask_path`) reads.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from colmap_ext.errors import UserError
from colmap_ext.features import list_images

METHODS = ("threshold", "grabcut")
# Components at least this fraction of the largest one are kept (an object in pieces).
MIN_COMPONENT_FRACTION = 0.1
GRABCUT_ITERATIONS = 5


def make_masks(image_path: str | os.PathLike, mask_path: str | os.PathLike,
               method: str = "threshold", image_names: Sequence[str] | None = None,
               progress: bool = True) -> dict[str, float]:
    """Write a mask per image; returns the fraction of each image the object covers."""
    if method not in METHODS:
        raise UserError(f"unknown segmentation method {method!r}; choose one of "
                        f"{', '.join(METHODS)}")
    image_path, mask_path = Path(image_path), Path(mask_path)
    names = list_images(image_path, image_names)
    segment = threshold_mask if method == "threshold" else grabcut_mask

    def work(name: str) -> float:
        image = read_color(image_path / name)
        mask = segment(image)
        if not mask.any():
            raise UserError(f"no object found in {image_path / name}: the background is "
                            "not uniform enough; give masks with --mask_path")
        write_mask(mask_path / f"{name}.png", mask)
        return float(np.count_nonzero(mask)) / mask.size

    with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
        coverage = list(tqdm(pool.map(work, names), total=len(names), desc=f"masks ({method})",
                             unit="image", disable=not progress))
    return dict(zip(names, coverage))


def read_color(path: Path) -> np.ndarray:
    """An image as 8-bit BGR in stored pixel order (no EXIF rotation, as COLMAP reads it)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise UserError(f"cannot read image {path}")
    return image


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a 0/255 PNG, creating sub-folders as image names need."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.where(mask, 255, 0).astype(np.uint8)):
        raise UserError(f"cannot write mask {path}")


def threshold_mask(image: np.ndarray) -> np.ndarray:
    """Boolean object mask: Otsu on each pixel's colour distance from the background.

    The background colour is the median of the image border. The distance (in Lab, on
    the blurred image) is square-rooted before Otsu: that spreads the small distances,
    so shaded parts of the object stay apart from the background instead of being
    lumped with it by a threshold set halfway to the bright, lit parts.
    """
    size = kernel_size(image.shape)
    blurred = cv2.GaussianBlur(image, (0, 0), sigmaX=size / 4)
    lab = cv2.cvtColor(blurred, cv2.COLOR_BGR2LAB).astype(np.float32)
    background = np.median(border_pixels(lab), axis=0)
    distance = np.sqrt(np.linalg.norm(lab - background, axis=2))
    scaled = np.round(255 * distance / max(float(distance.max()), 1e-6)).astype(np.uint8)
    _, binary = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    return fill_holes(largest_components(binary > 0))


def grabcut_mask(image: np.ndarray) -> np.ndarray:
    """Boolean object mask from GrabCut, started from the threshold mask."""
    initial = threshold_mask(image)
    if not initial.any():
        return initial
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3 * kernel_size(image.shape),) * 2)
    inner = cv2.erode(initial.astype(np.uint8), kernel) > 0
    outer = cv2.dilate(initial.astype(np.uint8), kernel) > 0
    labels = np.full(initial.shape, cv2.GC_BGD, np.uint8)
    labels[outer] = cv2.GC_PR_BGD
    labels[initial] = cv2.GC_PR_FGD
    labels[inner] = cv2.GC_FGD
    background_model = np.zeros((1, 65), np.float64)
    foreground_model = np.zeros((1, 65), np.float64)
    cv2.grabCut(image, labels, None, background_model, foreground_model,
                GRABCUT_ITERATIONS, cv2.GC_INIT_WITH_MASK)
    mask = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    return fill_holes(largest_components(mask))


def kernel_size(shape: tuple[int, ...]) -> int:
    """An odd structuring-element size of about 1% of the image's shorter side."""
    return 2 * max(1, round(min(shape[:2]) / 200)) + 1


def border_pixels(image: np.ndarray) -> np.ndarray:
    """The pixels of the image's outer frame."""
    return np.concatenate([image[0], image[-1], image[1:-1, 0], image[1:-1, -1]])


def largest_components(mask: np.ndarray) -> np.ndarray:
    """Keep the largest connected component and any at least MIN_COMPONENT_FRACTION of it."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), 8)
    if count <= 1:
        return np.zeros_like(mask, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = 1 + np.flatnonzero(areas >= MIN_COMPONENT_FRACTION * areas.max())
    return np.isin(labels, keep)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill what the object encloses (dark cavities, shadows) by filling its outer contours."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros(mask.shape, np.uint8)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    return filled > 0
