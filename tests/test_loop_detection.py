"""Sequential matching's loop detection, on a vocabulary trained on the sequence itself:
a synthetic camera path that goes round a room one and a half times, so that its last
third revisits its first."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_ext.errors import UserError
from colmap_ext.features import FeatureOptions, extract_features
from colmap_ext.mapper import MapperOptions
from colmap_ext.mapper import run as run_mapper
from colmap_ext.matching import MatchingOptions, match_features

NUM_IMAGES, TURNS = 36, 1.5  # 15 deg apart: image i + 24 is image i's place again
REVISIT = round(NUM_IMAGES / TURNS)
OVERLAP = 3
# The index steps of sequential matching's pairs: the overlap and the quadratic 2^k, k < 3.
SEQUENTIAL_STEPS = {1, 2, 3, 4}
OPTIONS = dict(matcher="sequential", overlap=OVERLAP, loop_closure=False, loop_detection=True,
               loop_detection_period=3, loop_detection_num_images=5, seed=0)


def index_of(name: str) -> int:
    return int(Path(name).stem[len("ring"):])


def is_revisit(pair: tuple[str, str]) -> bool:
    """Two images of the two turns at most 15 deg apart."""
    first, second = sorted(index_of(name) for name in pair)
    return abs(second - first - REVISIT) <= 1


@pytest.fixture(scope="module")
def loop_database(tmp_path_factory) -> Path:
    """SIFT features of the path round the room, on a small camera (fast)."""
    from colmap_ext.synthetic.render import render_images
    from colmap_ext.synthetic.scene import ring_scene

    root = tmp_path_factory.mktemp("loop")
    camera = pycolmap.Camera(model="PINHOLE", width=320, height=240,
                             params=[300.0, 300.0, 160.0, 120.0])
    scene = ring_scene(num_images=NUM_IMAGES, seed=0, camera=camera, turns=TURNS)
    render_images(scene, root / "images", supersample=1)
    extract_features(root / "database.db", root / "images",
                     FeatureOptions("PINHOLE", list(camera.params)), progress=False)
    return root


def matched(loop_database: Path, tmp_path: Path, **options):
    """A copy of the database matched with OPTIONS and `options`: the summary."""
    shutil.copy(loop_database / "database.db", tmp_path / "database.db")
    return match_features(tmp_path / "database.db", MatchingOptions(**{**OPTIONS, **options}),
                          progress=False)


def test_sequential_matching_alone_misses_the_revisits(loop_database, tmp_path) -> None:
    summary = matched(loop_database, tmp_path, loop_detection=False)
    assert summary.loop_detection_seconds == 0
    assert not any(is_revisit((pair.name1, pair.name2)) for pair in summary.pairs)


def test_loop_detection_finds_the_revisits(loop_database, tmp_path) -> None:
    """Every 3rd image's 5 most similar images by a vocabulary of the sequence's own
    descriptors: the revisits of the queried images are found and verified, and few
    pairs proposed beyond the sequential ones are not revisits."""
    summary = matched(loop_database, tmp_path)
    names = sorted(p.name for p in (loop_database / "images").iterdir())
    queried = {name for index, name in enumerate(names) if index % 3 == 0}
    true_pairs = {(a, b) for a in names for b in names
                  if a < b and (a in queried or b in queried) and is_revisit((a, b))}
    beyond_sequential = [pair for pair in summary.pairs if abs(
        index_of(pair.name1) - index_of(pair.name2)) not in SEQUENTIAL_STEPS]
    found = {(pair.name1, pair.name2) for pair in beyond_sequential if pair.num_inliers > 0}
    recall = len(true_pairs & found) / len(true_pairs)
    not_revisits = [pair for pair in beyond_sequential
                    if not is_revisit((pair.name1, pair.name2))]
    print(f"loop detection: {len(true_pairs & found)} of {len(true_pairs)} revisit pairs "
          f"verified, {len(not_revisits)} of {len(beyond_sequential)} proposed pairs not "
          f"revisits, {summary.loop_detection_seconds:.1f} s")
    assert recall >= 0.8
    assert len(not_revisits) <= len(beyond_sequential) // 2


def test_loop_detection_closes_the_loop(loop_database, tmp_path) -> None:
    """The mapper on the matched database: one model with every image, where each image
    of the second turn is where its first-turn twin is, within the model's drift."""
    matched(loop_database, tmp_path)
    models = run_mapper(tmp_path / "database.db", loop_database / "images", tmp_path / "sparse",
                        MapperOptions(seed=0))
    assert len(models) == 1
    model = next(iter(models.values()))
    assert model.num_reg_images() == NUM_IMAGES
    centres = {image.name: image.projection_center() for image in model.images.values()}
    names = sorted(centres)
    radius = np.median([np.linalg.norm(centres[name] - np.mean(list(centres.values()), axis=0))
                        for name in names])
    gaps = [np.linalg.norm(centres[names[i]] - centres[names[i + REVISIT]])
            for i in range(NUM_IMAGES - REVISIT)]
    assert max(gaps) < 0.2 * radius


def test_a_given_vocabulary_tree_is_used(loop_database, tmp_path) -> None:
    """--vocab_tree_path: COLMAP's file, read as it is (here one written by pycolmap);
    a file that is not one is a one-line error."""
    from colmap_ext.matching import trained_vocabulary

    with pycolmap.Database.open(loop_database / "database.db") as db:
        trained_vocabulary(db).write(tmp_path / "vocabulary.bin")
    (tmp_path / "given").mkdir()
    summary = matched(loop_database, tmp_path / "given", vocab_tree_path=tmp_path / "vocabulary.bin")
    assert any(is_revisit((pair.name1, pair.name2)) and pair.num_inliers > 0
               for pair in summary.pairs)
    (tmp_path / "bad").mkdir()
    (tmp_path / "not_a_tree.bin").write_bytes(b"not a vocabulary tree")
    with pytest.raises(UserError, match="vocabulary tree"):
        matched(loop_database, tmp_path / "bad", vocab_tree_path=tmp_path / "not_a_tree.bin")
    with pytest.raises(UserError, match="vocabulary tree not found"):
        matched(loop_database, tmp_path / "bad", vocab_tree_path=tmp_path / "missing.bin")
