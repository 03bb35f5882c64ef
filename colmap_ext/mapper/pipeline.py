"""The incremental loop and `run()`: initial pair, then register, triangulate,
adjust and filter image after image; several models when the images fall apart,
joined again where they can be (merging.py); each finished model triangulated again
from its final poses."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_ext.database import DatabaseContents, read_database
from colmap_ext.errors import UserError
from colmap_ext.mapper.bundle_adjustment import bundle_adjust
from colmap_ext.mapper.descriptors import NearestDescriptors
from colmap_ext.mapper.initial_pair import choose_initial_pair, initialize
from colmap_ext.mapper.merging import find_similarity, join
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import MapperOptions
from colmap_ext.mapper.filtering import (error_limit, filter_images, filter_points,
                                          median_reprojection_error)
from colmap_ext.mapper.registration import (Correspondences, Outcome,
                                            descriptor_correspondences, register_frame,
                                            track_correspondences)
from colmap_ext.mapper.triangulation import triangulate_image
from colmap_ext.mapper.two_view import Pair, pair_graph, verified_matches
from colmap_ext.model_io import MAPPER_OUTPUT, read_model, replacing, write_json, write_models
from colmap_ext.timing import StageTimer


logger = logging.getLogger(__name__)

# Images tried per round before the mapper gives up on growing the model.
MAX_CANDIDATES_PER_ROUND = 10
# Memory for the descriptor searches kept between guided matchings of the same pair.
NEAREST_DESCRIPTORS_BYTES = 64 * 2**20


class IncrementalMapper:
    """Grows one model from an initial pair over a set of images."""

    def __init__(self, model: Model, matches: dict[Pair, np.ndarray], options: MapperOptions,
                 timer: StageTimer, progress: tqdm | None, final_adjustment: bool = True) -> None:
        self.model = model
        # False: the model ends on its last filtering, not on a global adjustment (a
        # cluster of the hierarchical mapper, which adjusts the joined model as a whole).
        self.final_adjustment = final_adjustment
        self.matches = matches
        self.graph = pair_graph(matches)
        # Raw matches of every pair, verified or not: putative 2D-3D correspondences for
        # P3P RANSAC, which bridges pairs whose two-view verification failed.
        self.raw_graph = pair_graph({p: m for p, m in model.db.raw_matches.items()
                                     if p[0] in model.point_of and p[1] in model.point_of})
        self.options = options
        self.timer = timer
        self.progress = progress
        self.sequence_index = {image_id: i for i, image_id in enumerate(
            sorted(model.image_ids, key=lambda i: model.db.images[i].name))}
        self.trials: dict[int, int] = defaultdict(int)
        self.num_images_at_global_ba = 0
        # The robust loss's scale, raised where the measured noise reaches it (see
        # BundleAdjustmentOptions.noise_loss_scale_ratio); set at each global adjustment.
        self.loss_scale_px = options.bundle_adjustment.loss_scale_px
        # Per unregistered image: model points it sees through verified matches, kept
        # between rounds and counted again only when a neighbour's observations change.
        self._visible: dict[int, int] = {}
        self._connected: set[int] = set()  # images with raw matches to a registered one
        self._marked = np.zeros(0, bool)  # scratch for _count_visible, all False
        # Per image, its verified matches as the other images, their numbers of matches,
        # and each match's keypoint of the other image as a flat index into
        # model.point_of_flat: the points it sees, in one lookup. Four bytes a match: on
        # a turntable, where every image matches every other, this is gigabytes in int64.
        flat_type = np.int32 if len(model.point_of_flat) < 2**31 else np.int64
        self._matched_keypoints = {
            image_id: (np.fromiter(pairs, np.int64, len(pairs)),
                       np.array([len(m) for m in pairs.values()]),
                       np.concatenate([m[:, 1].astype(flat_type) + model.flat_offset[other]
                                       for other, m in pairs.items()]))
            for image_id, pairs in self.graph.items() if pairs}

    def run(self, excluded_pairs: set[Pair]) -> bool:
        """Reconstruct from the best initial pair, or go on from the model's registered
        images when it has some (a continued model); False when no pair initialises."""
        if self.model.num_registered:
            self.num_images_at_global_ba = self.model.num_registered
            self._advance(self.model.num_registered)
        elif not self._initialize(excluded_pairs):
            return False
        while self._register_next():
            pass
        if self.final_adjustment:
            self._global_adjustment(final=True)
        else:
            with self.timer("filtering"):
                filter_points(self.model, self.model.registered, self.options, final=True)
        return True

    def _initialize(self, excluded_pairs: set[Pair]) -> bool:
        with self.timer("initial pair"):
            two_view = choose_initial_pair(self.model, self.matches, self.options, excluded_pairs)
        if two_view is None:
            return False
        initialize(self.model, two_view)
        with self.timer("triangulation"):
            # Every image of the second frame against every image of both frames (a
            # rig's other cameras see across its baseline too).
            registered = self.model.registered
            for image_id in self.model.frame_images(two_view.pair[1]):
                triangulate_image(self.model, image_id,
                                  [other for other in registered if other != image_id],
                                  self.options, min_views=2)
        self._global_adjustment()
        self._advance(self.model.num_registered)
        return True

    def refine_joined(self) -> None:
        """Adjust a model joined from two (merging.py): global adjustment, then rounds
        of retriangulation and global adjustment. Retriangulation is guided matching of
        every image against its neighbours, which now include the images across the
        junction; the better poses of each round let the next match more of them."""
        self._global_adjustment()
        num_images = self.options.guided_matching.num_images
        for _ in range(self.options.merging.refinement_rounds):
            with self.timer("triangulation"):
                for image_id in self.model.registered:
                    triangulate_image(self.model, image_id,
                                      self._neighbours(image_id, num_images),
                                      self.options, min_views=2)
            self._global_adjustment(final=True)

    def retriangulate(self) -> int:
        """Triangulate the finished model's points again from its poses, then adjust it
        (final). The points it grew with were accepted within max_reproj_error_px while
        the poses were still moving; again from the final poses, each observation must lie
        within retriangulation_max_error_ratio x the model's median reprojection error
        (filtering.error_limit), which leaves out the near-miss matches. Returns the
        number of points."""
        model, options = self.model, self.options
        registered = model.registered
        limit = error_limit(options.triangulation.max_reproj_error_px,
                            median_reprojection_error(model, registered), options,
                            options.triangulation.retriangulation_max_error_ratio)
        strict = dataclasses.replace(options, triangulation=dataclasses.replace(
            options.triangulation, max_reproj_error_px=limit))
        with self.timer("triangulation"):
            for point_id in model.point_ids:
                model.delete_point(point_id)
            for image_id in model.registration_order:
                triangulate_image(model, image_id,
                                  self._neighbours(image_id, options.guided_matching.num_images),
                                  strict, min_views=2)
        with self.timer("filtering"):
            # The points the final filter would drop anyway (two-view tracks, narrow
            # angles) go first: the adjustment then solves the model's size, not twice it.
            filter_points(model, registered, options, final=True)
        # One round: the observations are fresh, and a second changed nothing measured.
        self._global_adjustment(final=True, rounds=1)
        return model.reconstruction.num_points3D()

    def _advance(self, n: int) -> None:
        if self.progress is not None:
            self.progress.update(n)

    def _candidates(self) -> list[int]:
        """Unregistered images to try, best first, in the configured order."""
        model = self.model
        changed = model.take_changed()
        registered = model.registered
        for image_id in changed.intersection(registered):
            self._connected.update(self.raw_graph.get(image_id, {}))
        is_registered = np.zeros(max(model.image_ids) + 1, bool)
        is_registered[registered] = True
        unregistered = [i for i in model.image_ids if not is_registered[i]
                        and self.trials[i] < self.options.registration.max_trials
                        and i in self._connected]
        for i in unregistered:
            if i not in self._visible or not changed.isdisjoint(self.graph.get(i, {})):
                self._visible[i] = self._count_visible(i, is_registered)
        visible = self._visible
        if self.options.registration.order == "sequence":
            indices = np.array([self.sequence_index[i] for i in registered])
            distance = {i: np.abs(indices - self.sequence_index[i]).min() for i in unregistered}
            ordered = sorted(unregistered, key=lambda i: (distance[i], -visible[i]))
        else:
            ordered = sorted(unregistered, key=lambda i: (-visible[i], self.sequence_index[i]))
        # One image a frame: registering it registers the frame.
        frames = {}
        for image_id in ordered:
            frames.setdefault(model.frame_id(image_id), image_id)
        return list(frames.values())

    def _count_visible(self, image_id: int, is_registered: np.ndarray) -> int:
        """Model points an image sees through its verified matches to registered images
        (as track_correspondences finds them, counted once each)."""
        if image_id not in self._matched_keypoints:
            return 0
        others, num_matches, flat_index = self._matched_keypoints[image_id]
        points = self.model.point_of_flat[flat_index]
        points = points[(points >= 0) & np.repeat(is_registered[others], num_matches)]
        # Distinct points by marking them in a buffer kept clear between calls: linear
        # in the matches, where a sort is not (every image is counted again each round).
        if len(self._marked) < len(self.model.xyz):
            self._marked = np.zeros(len(self.model.xyz), bool)
        self._marked[points] = True
        count = int(np.count_nonzero(self._marked))
        self._marked[points] = False
        return count

    def _neighbours(self, image_id: int, limit: int) -> list[int]:
        """Registered images most connected to `image_id`: shared points, then matches."""
        model = self.model
        shared = model.covisible_images(image_id) if model.is_registered(image_id) else {}
        verified = {o: len(m) for o, m in self.graph.get(image_id, {}).items()
                    if model.is_registered(o)}
        raw = {o: len(m) for o, m in self.raw_graph.get(image_id, {}).items()
               if model.is_registered(o)}
        others = set(shared) | set(verified) or set(raw)
        return sorted(others, key=lambda o: (
            -shared.get(o, 0), -verified.get(o, 0), -raw.get(o, 0)))[:limit]

    def _register_next(self) -> bool:
        for image_id in self._candidates()[:MAX_CANDIDATES_PER_ROUND]:
            with self.timer("registration"):
                registered = self._register(image_id)
            if not registered:
                self.trials[image_id] += 1
                continue
            self._after_registration(image_id)
            self._advance(len(self.model.frame_images(image_id)))
            self._write_snapshot()
            self.trials.clear()  # the model has grown: failed images deserve a new chance
            return True
        return False

    def _write_snapshot(self) -> None:
        """Every snapshot_frames_freq registrations, the model so far in a new folder of
        snapshot_path named by the time in milliseconds, as COLMAP's snapshots."""
        options = self.options
        if not options.snapshot_path or not options.snapshot_frames_freq or \
                self.model.num_registered % options.snapshot_frames_freq:
            return
        with self.timer("export"):
            folder = Path(options.snapshot_path) / f"{int(time.time() * 1000):013d}"
            try:
                folder.mkdir(parents=True, exist_ok=True)
                self.model.export().write_binary(folder)
            except (OSError, ValueError, RuntimeError) as exc:
                raise UserError(f"cannot write a snapshot to {folder}: "
                                f"{getattr(exc, 'strerror', None) or exc}") from None

    def _register(self, image_id: int) -> bool:
        """Register the image's frame: P3P (GP3P for a rig's frame) on correspondences
        through verified matches and descriptor matches to nearby points. A pose off the
        verified matches' epipolar lines is tried again through verified matches alone
        (descriptor matches on repeated texture can pull it away); too few inliers,
        through raw matches too (pairs whose two-view verification failed can still hold
        enough inliers for an absolute pose)."""
        model, options = self.model, self.options
        image_ids = model.frame_images(image_id)
        descriptor = {i: descriptor_correspondences(
            model, i, self._neighbours(i, options.guided_matching.num_images), options)
            for i in image_ids}
        verified = {i: track_correspondences(model, i, self.graph) for i in image_ids}
        outcome = register_frame(model, _joined(descriptor, verified), self.graph, options)
        if outcome is Outcome.INCONSISTENT:
            outcome = register_frame(model, verified, self.graph, options)
        elif outcome is Outcome.TOO_FEW_INLIERS:
            raw = {i: track_correspondences(model, i, self.raw_graph) for i in image_ids}
            if any(len(kps) for kps, _ in raw.values()):
                outcome = register_frame(model, _joined(descriptor, verified, raw), self.graph,
                                         options)
        return outcome is Outcome.REGISTERED

    def _after_registration(self, image_id: int) -> None:
        options = self.options
        image_ids = self.model.frame_images(image_id)
        with self.timer("triangulation"):
            for new_id in image_ids:
                neighbours = self._neighbours(new_id, options.guided_matching.num_images)
                triangulate_image(self.model, new_id, neighbours, options, min_views=2)
        ratio = options.bundle_adjustment.global_images_ratio
        if self.model.num_registered >= ratio * self.num_images_at_global_ba:
            self._global_adjustment()
            return
        local = image_ids + [other for other in self._neighbours(
            image_id, options.bundle_adjustment.local_num_images) if other not in image_ids]
        self._bundle_adjust(local, options.bundle_adjustment.local_max_iterations)
        with self.timer("filtering"):
            filter_points(self.model, local, options)

    def _global_adjustment(self, final: bool = False, rounds: int = 2) -> None:
        """Adjust every registered image, then filter. `final`, the model's end: `rounds`
        rounds, their filter also relative to the model's median error
        (final_max_error_ratio), and one more adjustment on what the last filter kept,
        with the final loss (BundleAdjustmentOptions.final_loss), if that filter dropped
        observations or the final loss is not the robust one."""
        model, options = self.model, self.options
        ba = options.bundle_adjustment
        registered = model.registered
        ratio = options.filtering.final_max_error_ratio if final else 0.0
        for _ in range(rounds if final else 1):
            with self.timer("filtering"):
                self.loss_scale_px = max(ba.loss_scale_px, ba.noise_loss_scale_ratio *
                                         median_reprojection_error(model, registered))
            self._bundle_adjust(registered, ba.global_max_iterations, refine_intrinsics=True)
            with self.timer("filtering"):
                removed, _ = filter_points(model, registered, options, final=final,
                                           max_error_ratio=ratio)
        if final and (ratio > 0 and removed or ba.final_loss != ba.loss):
            self._bundle_adjust(registered, ba.global_max_iterations, refine_intrinsics=True,
                                loss=ba.final_loss)
        self.num_images_at_global_ba = model.num_registered

    def _bundle_adjust(self, image_ids: list[int], max_iterations: int,
                       refine_intrinsics: bool = False, loss: str | None = None) -> None:
        with self.timer("bundle adjustment"):
            iterations = bundle_adjust(self.model, image_ids, self.options, max_iterations,
                                       refine_intrinsics, loss, self.loss_scale_px)
        self.timer.counts["bundle adjustment solves"] += 1
        self.timer.counts["bundle adjustment iterations"] += iterations


def _joined(*correspondences: Correspondences) -> Correspondences:
    """Per image, (keypoints, point ids) of several correspondence sets, one after the other."""
    return {image_id: (np.concatenate([c[image_id][0] for c in correspondences]),
                       np.concatenate([c[image_id][1] for c in correspondences]))
            for image_id in correspondences[0]}


def reconstruct(db: DatabaseContents, options: MapperOptions,
                image_names: list[str] | None = None, timer: StageTimer | None = None,
                progress: bool = True, existing: pycolmap.Reconstruction | None = None,
                final_adjustment: bool = True) -> list[pycolmap.Reconstruction]:
    """All models that the database's images give, largest first (nothing written).
    `existing`, a model of this database's images, is continued: the first model starts
    from its poses and points, and the database's other images are registered into it.
    `final_adjustment` False leaves out each model's closing global adjustment and its
    retriangulation (see IncrementalMapper)."""
    options.check()
    timer = timer or StageTimer()
    existing_ids = _existing_image_ids(db, existing) if existing is not None else {}
    image_ids = sorted(set(_select_images(db, image_names)) | set(existing_ids.values()))
    nearest = NearestDescriptors(db.descriptors,
                                 {i: len(db.images[i].keypoints) for i in image_ids},
                                 options.guided_matching.num_neighbors, NEAREST_DESCRIPTORS_BYTES,
                                 options.threads(), db.raw_matches,
                                 options.guided_matching.max_search_pairs)
    with timer("two-view geometry"):
        model = Model(db, nearest, image_ids)
        matches = verified_matches(model, options, progress)
    if existing is not None:
        _continue_from(model, existing, existing_ids, options.fix_existing_images)
    all_matches = matches
    models: list[Model] = []
    remaining = image_ids
    excluded_pairs: set[Pair] = set()
    max_num_models = options.max_num_models if options.multiple_models else 1
    bar = tqdm(total=len(image_ids), desc="registered", unit="image", disable=not progress)
    try:
        while len(remaining) >= 2 and len(models) < max_num_models:
            mapper = IncrementalMapper(model, matches, options, timer, bar, final_adjustment)
            if not mapper.run(excluded_pairs):
                break
            if model.num_registered >= options.min_model_size:
                models.append(model)
            else:
                timer.counts["models below min_model_size"] += 1
            remaining = [i for i in remaining if not model.is_registered(i)]
            model = Model(db, nearest, remaining)
            options = options.choosing_initial_pair()
            matches = {p: m for p, m in matches.items() if p[0] in remaining and p[1] in remaining}
    finally:
        bar.close()
    models = merge_models(models, all_matches, options, timer)
    if final_adjustment and options.triangulation.retriangulates:
        for model in models:
            _refiner(model, all_matches, options, timer).retriangulate()
    with timer("filtering"):
        for model in models:
            filter_images(model, options)
    timer.counts["models below min_model_size"] += sum(
        m.num_registered < options.min_model_size for m in models)
    models = [m for m in models if m.num_registered >= options.min_model_size]
    with timer("export"):
        reconstructions = [model.export() for model in models]
    return sorted(reconstructions, key=lambda r: (-r.num_reg_images(), -r.num_points3D()))


def merge_models(models: list[Model], matches: dict[Pair, np.ndarray], options: MapperOptions,
                 timer: StageTimer) -> list[Model]:
    """Join models two at a time while a pair of them gives a similarity (merging.py),
    the larger one as the target, and adjust each joined model; largest first."""
    # The larger model is the target, unless the other holds fixed poses (a continued model).
    models = sorted(models, key=lambda model: (not model.fixed_frame_ids, -model.num_registered))
    if len(models) < 2:
        return models
    raw_graph = pair_graph(models[0].db.raw_matches)
    while True:
        for target, source in itertools.combinations(models, 2):
            with timer("merging"):
                found = find_similarity(target, source, raw_graph, options)
            if found is not None:
                break
        else:
            return models
        with timer("merging"):
            joined = join(target, source, *found)
        _refiner(joined, matches, options, timer).refine_joined()
        models = sorted([m for m in models if m is not target and m is not source] + [joined],
                        key=lambda model: (not model.fixed_frame_ids, -model.num_registered))


def _refiner(model: Model, matches: dict[Pair, np.ndarray], options: MapperOptions,
             timer: StageTimer) -> IncrementalMapper:
    """An IncrementalMapper over a finished model's images, to refine it."""
    images = set(model.image_ids)
    return IncrementalMapper(model, {p: m for p, m in matches.items()
                                     if p[0] in images and p[1] in images},
                             options, timer, None)


def _existing_image_ids(db: DatabaseContents,
                        existing: pycolmap.Reconstruction) -> dict[int, int]:
    """The database's id of each registered image of `existing`, matched by name; a
    UserError unless each is in the database with the keypoints the model observes."""
    by_name = {image.name: image_id for image_id, image in db.images.items()}
    registered = [existing.images[i] for i in sorted(existing.reg_image_ids())]
    missing = [image.name for image in registered if image.name not in by_name]
    if missing:
        raise UserError(f"{len(missing)} images of the input model are not in the database: "
                        f"{', '.join(missing[:3])}" + (" ..." if len(missing) > 3 else ""))
    for image in registered:
        keypoints = db.images[by_name[image.name]].keypoints
        observed = [(point2D_idx, point2D.xy) for point2D_idx, point2D in
                    enumerate(image.points2D) if point2D.has_point3D()]
        if len(image.points2D) != len(keypoints) or any(
                np.abs(keypoints[idx] - xy).max() > 0.01 for idx, xy in observed):
            raise UserError(f"image {image.name} of the input model has other keypoints than "
                            "the database's: the model was made from another database")
    return {image.image_id: by_name[image.name] for image in registered}


def _continue_from(model: Model, existing: pycolmap.Reconstruction, image_ids: dict[int, int],
                   fix_poses: bool) -> None:
    """Put the registered images and the points of `existing` into the empty `model`
    (input image id -> database image id: `image_ids`)."""
    for input_id, image_id in image_ids.items():
        if not model.is_registered(image_id):
            model.register(image_id, existing.images[input_id].cam_from_world())
    if fix_poses:
        model.fixed_frame_ids = {model.frame_id(image_id) for image_id in image_ids.values()}
    for point in existing.points3D.values():
        track = {image_ids[element.image_id]: element.point2D_idx
                 for element in point.track.elements if element.image_id in image_ids}
        if len(track) >= 2:
            model.add_point(point.xyz, track)


def _select_images(db, image_names: list[str] | None) -> list[int]:
    if not image_names:
        return sorted(db.images)
    by_name = {image.name: image_id for image_id, image in db.images.items()}
    missing = [name for name in image_names if name not in by_name]
    if missing:
        raise UserError(f"images in the image list are not in the database: {', '.join(missing[:5])}")
    return sorted(by_name[name] for name in image_names)


def run(database_path: str | Path, image_path: str | Path, output_path: str | Path,
        options: MapperOptions | None = None, *, overwrite: bool = False,
        output_type: str = "BIN", image_names: list[str] | None = None,
        input_path: str | Path | None = None,
        progress: bool = True) -> dict[int, pycolmap.Reconstruction]:
    """Reconstruct, then write OUTPUT/0, OUTPUT/1, ... and OUTPUT/mapper_summary.json,
    like `pycolmap.incremental_mapping`; with `input_path`, continue that model (read,
    never written). The database is read, never written."""
    options = options or MapperOptions()
    try:
        options.check()
    except ValueError as exc:
        raise UserError(str(exc)) from None
    image_path = Path(image_path)
    if not image_path.is_dir():
        raise UserError(f"image path not found: {image_path}")
    existing = _read_input_model(input_path, output_path) if input_path else None
    with replacing(output_path, MAPPER_OUTPUT, overwrite) as new_output:
        timer = StageTimer()
        start = time.perf_counter()
        with timer("read database"):
            db = read_database(database_path)
        extract_colors = options.extract_colors and colours_readable(db, image_path)
        reconstructions = reconstruct(db, options, image_names, timer, progress, existing)
        if not reconstructions:
            raise UserError(f"no model could be reconstructed: {_why_none(timer, options)}")
        write_result(reconstructions, new_output, image_path, extract_colors, output_type, timer,
                     start)
    return dict(enumerate(reconstructions))


def write_result(reconstructions: list[pycolmap.Reconstruction], output: Path,
                 image_path: Path, extract_colors: bool, output_type: str,
                 timer: StageTimer, start: float, **details: object) -> dict:
    """Write the models as output/0, output/1, ... (with `extract_colors`, point colours
    from the images) and output/mapper_summary.json, the summary with `details` added;
    `start`: the run's time.perf_counter(). Returns the summary."""
    with timer("export"):
        if extract_colors:
            for reconstruction in reconstructions:
                reconstruction.extract_colors_for_all_images(str(image_path))
        write_models(reconstructions, output, output_type)
    summary = {**summarize(reconstructions, timer, time.perf_counter() - start), **details}
    write_json(summary, output / "mapper_summary.json")
    return summary


def _why_none(timer: StageTimer, options: MapperOptions) -> str:
    """Why `reconstruct` returned no model: models too small to keep, or none at all."""
    dropped = timer.counts["models below min_model_size"]
    if dropped:
        return (f"{dropped} model{'s were' if dropped > 1 else ' was'} reconstructed, all below "
                f"--Mapper.min_model_size {options.min_model_size}")
    return "no image pair gave a relative pose with enough well-triangulated points"


def _read_input_model(input_path: str | Path, output_path: str | Path) -> pycolmap.Reconstruction:
    """The model to continue; refused where writing the output would replace it."""
    input_path, output_path = Path(input_path).resolve(), Path(output_path).resolve()
    if input_path.parent == output_path and input_path.name.isdigit():
        raise UserError(f"--input_path {input_path} is a model of --output_path, which the "
                        "result would replace: write the result to another folder")
    return read_model(input_path)


def colours_readable(db: DatabaseContents, image_path: Path) -> bool:
    """Whether every image of the database is a file under `image_path`, to read the
    points' colours from. If not, the model is made all the same, as `colmap mapper`
    makes it, and one warning says the colours are skipped."""
    missing = [image.name for image in db.images.values()
               if not (image_path / image.name).is_file()]
    if missing:
        logger.warning("colmap-ext: %d images of the database are not under %s (%s): point "
                       "colours not extracted", len(missing), image_path,
                       ", ".join(missing[:3]) + (" ..." if len(missing) > 3 else ""))
    return not missing


def summarize(reconstructions: list[pycolmap.Reconstruction], timer: StageTimer,
              total_seconds: float) -> dict:
    models = [{
        "num_registered": r.num_reg_images(),
        "num_images": r.num_images(),
        "num_points3D": r.num_points3D(),
        "mean_track_length": r.compute_mean_track_length(),
        "mean_reprojection_error": r.compute_mean_reprojection_error(),
    } for r in reconstructions]
    return {
        "num_models": len(reconstructions),
        "num_registered": sum(m["num_registered"] for m in models),
        "models": models,
        "time_s": {**{k: round(v, 3) for k, v in timer.seconds.items()},
                   "total": round(total_seconds, 3)},
        "counts": dict(timer.counts),
    }
