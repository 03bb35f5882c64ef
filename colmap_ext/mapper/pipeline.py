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
from collections.abc import Collection
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from colmap_ext.database import DatabaseContents, read_database
from colmap_ext.errors import UserError
from colmap_ext.mapper.descriptors import NearestDescriptors
from colmap_ext.mapper.initial_pair import choose_initial_pair, initialize
from colmap_ext.mapper.merging import find_similarity, join
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import BundleAdjustmentOptions, MapperOptions
from colmap_ext.mapper.filtering import error_limit, filter_images, filter_points
from colmap_ext.mapper.refinement import (MatchGraphs, ModelAdjuster, refine_joined,
                                          retriangulate, triangulate_images)
from colmap_ext.mapper.registration import (Correspondences, Outcome,
                                            descriptor_correspondences, register_frame,
                                            searches_descriptors, track_correspondences)
from colmap_ext.mapper.triangulation import complete_tracks, merge_tracks, triangulate_image
from colmap_ext.mapper.two_view import Pair, pair_graph, verified_matches
from colmap_ext.memory import return_freed_memory
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
        self.graphs = MatchGraphs.of(model, matches)
        self.options = options
        self.timer = timer
        self.adjuster = ModelAdjuster.of(model, options, timer)
        self.progress = progress
        self.sequence_index = {image_id: i for i, image_id in enumerate(
            sorted(model.image_ids, key=lambda i: model.db.images[i].name))}
        self.trials: dict[int, int] = defaultdict(int)
        self.num_images_at_global_ba = 0
        self.num_images_at_window_ba = 0
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
                       np.concatenate([m[:, 1].astype(flat_type) + int(model.flat_offset[other])
                                       for other, m in pairs.items()]))
            for image_id, pairs in self.graphs.verified.items() if pairs}

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
        # Registration is over: what it kept for matching is memory the model's last
        # adjustments need (ModelAdjuster.global_adjustment gives up the searches).
        self._matched_keypoints.clear()
        return_freed_memory()
        if self.final_adjustment:
            # Retriangulation, where it follows, ends the model on an exact adjustment.
            self.adjuster.global_adjustment(
                final=True, exact=not self.options.triangulation.retriangulates)
        else:
            with self.timer("filtering"):
                filter_points(self.model, self.model.registered, self.options.filtering,
                              final=True)
        return True

    def _initialize(self, excluded_pairs: set[Pair]) -> bool:
        options = self.options
        with self.timer("initial pair"):
            initial = choose_initial_pair(self.model, self.matches, options.initialization,
                                          options.two_view, options.triangulation,
                                          excluded_pairs, options.seed)
        if initial is None:
            return False
        new_images = initialize(self.model, initial)
        with self.timer("triangulation"):
            # Every image of the second frame (of the frame start) against every
            # registered image (a rig's other cameras see across its baseline too).
            registered = self.model.registered
            for image_id in new_images:
                triangulate_image(self.model, image_id,
                                  [other for other in registered if other != image_id],
                                  options.guided_matching, options.triangulation, min_views=2,
                                  verified=self.graphs.verified.get(image_id, {}))
        self._global_adjustment()
        self._advance(self.model.num_registered)
        return True

    def _advance(self, n: int) -> None:
        if self.progress is not None:
            self.progress.update(n)

    def _candidates(self) -> list[int]:
        """Unregistered images to try, best first, in the configured order."""
        model = self.model
        changed = model.take_changed()
        registered = model.registered
        for image_id in changed.intersection(registered):
            self._connected.update(self.graphs.raw.get(image_id, {}))
        is_registered = np.zeros(max(model.image_ids) + 1, bool)
        is_registered[registered] = True
        unregistered = [i for i in model.image_ids if not is_registered[i]
                        and self.trials[i] < self.options.registration.max_trials
                        and i in self._connected]
        for i in unregistered:
            if i not in self._visible or not changed.isdisjoint(self.graphs.verified.get(i, {})):
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
        through verified matches and descriptor matches to nearby points (where
        searches_descriptors). A pose off the verified matches' epipolar lines is tried
        again through verified matches alone (descriptor matches on repeated texture can
        pull it away); too few inliers, through raw matches too (pairs whose two-view
        verification failed can still hold enough inliers for an absolute pose)."""
        model, graphs, options = self.model, self.graphs, self.options
        guided = options.guided_matching

        def register(correspondences: Correspondences) -> Outcome:
            return register_frame(model, correspondences, graphs.verified, options.registration,
                                  options.seed)

        image_ids = model.frame_images(image_id)
        verified = {i: track_correspondences(model, i, graphs.verified) for i in image_ids}
        descriptor = {i: descriptor_correspondences(
            model, i, graphs.neighbours(model, i, guided.num_images), guided)
            if searches_descriptors(model, i, verified[i][0], guided)
            else (np.zeros(0, np.int64), np.zeros(0, np.int64)) for i in image_ids}
        outcome = register(_joined(descriptor, verified))
        if outcome is Outcome.INCONSISTENT:
            outcome = register(verified)
        elif outcome is Outcome.TOO_FEW_INLIERS:
            raw = {i: track_correspondences(model, i, graphs.raw) for i in image_ids}
            if any(len(kps) for kps, _ in raw.values()):
                outcome = register(_joined(descriptor, verified, raw))
        return outcome is Outcome.REGISTERED

    def _after_registration(self, image_id: int) -> None:
        options = self.options
        image_ids = self.model.frame_images(image_id)
        with self.timer("triangulation"):
            triangulate_images(self.model, image_ids, self.graphs, options.guided_matching,
                               options.triangulation)
        ba = options.bundle_adjustment
        last = self.num_images_at_global_ba
        if self.model.num_registered >= min(ba.global_images_ratio * last,
                                            last + ba.global_images_freq):
            self._global_adjustment()
            return
        local = image_ids + [other for other in self.graphs.neighbours(
            self.model, image_id, options.bundle_adjustment.local_num_images)
            if other not in image_ids]
        self.adjuster.local_adjustment(local)
        if self._window_adjustment_due():
            self.adjuster.local_adjustment(
                self.model.registration_order[-ba.window_num_images:])
            self.num_images_at_window_ba = self.model.num_registered

    def _window_adjustment_due(self) -> bool:
        """Whether the last registered images are due an adjustment together
        (BundleAdjustmentOptions.window_num_images)."""
        ba, num_registered = self.options.bundle_adjustment, self.model.num_registered
        last = max(self.num_images_at_global_ba, self.num_images_at_window_ba)
        return bool(ba.window_num_images) and num_registered >= 2 * ba.window_num_images \
            and num_registered >= last + ba.window_images_freq

    def _global_adjustment(self) -> None:
        """Adjust the whole model; where its errors look Gaussian, complete and merge its
        tracks from the adjusted poses (complete_tracks; merge_tracks, whose joined tracks
        reproject within the noise's limit, filtering.error_limit: a long track crosses a
        fixed threshold by noise alone). There a verified match within the threshold is a
        true observation; elsewhere the near-miss matches they would add cost the real
        sets accuracy, and the finished model's retriangulation completes the tracks
        within the noise's limits."""
        self.adjuster.global_adjustment()
        if self.adjuster.errors_gaussian:
            triangulation = self.options.triangulation
            within_noise = dataclasses.replace(triangulation, max_reproj_error_px=error_limit(
                triangulation.max_reproj_error_px, self.adjuster.median_error_px,
                self.options.filtering.noise_max_error_ratio))
            with self.timer("triangulation"):
                self.timer.counts["observations completed"] += complete_tracks(
                    self.model, self.graphs.verified, triangulation)
                self.timer.counts["points merged"] += merge_tracks(
                    self.model, self.graphs.verified, within_noise)
        self.num_images_at_global_ba = self.model.num_registered


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
        matches = verified_matches(model, options.two_view, options.seed, progress)
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
            options = options_for_model(options)
            matches = {p: m for p, m in matches.items() if p[0] in remaining and p[1] in remaining}
    finally:
        bar.close()
    # Retriangulation, where it follows, ends each model on an exact adjustment.
    retriangulates = final_adjustment and options.triangulation.retriangulates
    models = merge_models(models, all_matches, options, timer, exact=not retriangulates)
    if retriangulates:
        for model in models:
            retriangulate(model, all_matches, options, timer)
    with timer("filtering"):
        for model in models:
            filter_images(model, options.filtering)
    timer.counts["models below min_model_size"] += sum(
        m.num_registered < options.min_model_size for m in models)
    models = [m for m in models if m.num_registered >= options.min_model_size]
    with timer("export"):
        reconstructions = [model.export() for model in models]
    nearest.close()  # on an exception, its idle threads end with it
    return sorted(reconstructions, key=lambda r: (-r.num_reg_images(), -r.num_points3D()))


def merge_models(models: list[Model], matches: dict[Pair, np.ndarray], options: MapperOptions,
                 timer: StageTimer, exact: bool = True) -> list[Model]:
    """Join models two at a time while a pair of them gives a similarity (merging.py),
    the larger one as the target, and adjust each joined model (refine_joined, `exact`
    as it says); largest first."""
    # The larger model is the target, unless the other holds fixed poses (a continued model).
    models = sorted(models, key=lambda model: (not model.fixed_frame_ids, -model.num_registered))
    if len(models) < 2:
        return models
    raw_graph = pair_graph(models[0].db.raw_matches)
    while True:
        for target, source in itertools.combinations(models, 2):
            with timer("merging"):
                found = find_similarity(target, source, raw_graph, options.merging,
                                        options.registration, options.guided_matching,
                                        options.seed)
            if found is not None:
                break
        else:
            return models
        with timer("merging"):
            joined = join(target, source, *found)
        refine_joined(joined, matches, options, timer, exact)
        models = sorted([m for m in models if m is not target and m is not source] + [joined],
                        key=lambda model: (not model.fixed_frame_ids, -model.num_registered))


def options_for_model(options: MapperOptions,
                      image_ids: Collection[int] | None = None) -> MapperOptions:
    """The options for a model over `image_ids` (None: a later model): a requested
    initial pair starts it only if it holds both images and is the first model;
    otherwise the mapper chooses the pair, as COLMAP's does for its later models."""
    initialization = options.initialization
    if image_ids is not None and \
            {initialization.image_id1, initialization.image_id2} <= set(image_ids):
        return options
    return dataclasses.replace(options, initialization=dataclasses.replace(
        initialization, image_id1=-1, image_id2=-1))


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
        check_listed_ids(db, options.bundle_adjustment)
        extract_colors = options.extract_colors and colours_readable(db, image_path)
        reconstructions = reconstruct(db, options, image_names, timer, progress, existing)
        if not reconstructions:
            raise UserError(f"no model could be reconstructed: {_why_none(timer, options)}")
        write_result(reconstructions, new_output, image_path, extract_colors, output_type, timer,
                     start)
    return dict(enumerate(reconstructions))


def check_listed_ids(db: DatabaseContents, ba: BundleAdjustmentOptions) -> None:
    """The rigs and cameras that --Mapper.constant_rig_list_path and
    --Mapper.constant_camera_list_path name are in the database."""
    for flag, ids, known in (("constant_rig_list_path", ba.constant_rig_ids, db.rigs),
                             ("constant_camera_list_path", ba.constant_camera_ids, db.cameras)):
        unknown = [value for value in ids if value not in known]
        if unknown:
            kind = flag.split("_")[1]
            raise UserError(f"--Mapper.{flag}: no {kind} with id {unknown[0]} in the database "
                            f"(its {kind}s: {', '.join(map(str, sorted(known))) or 'none'})")


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
