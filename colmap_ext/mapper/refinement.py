"""What the incremental loop (pipeline.py) and the refinement of a finished model share:
the match graphs that choose an image's neighbours, triangulation of images against
their neighbours, and bundle adjustment with its filtering. Refinement is two
functions: after a merge (`refine_joined`) and at a model's end (`retriangulate`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from colmap_ext.mapper.bundle_adjustment import bundle_adjust
from colmap_ext.mapper.filtering import (error_limit, errors_look_gaussian, filter_points,
                                          reprojection_errors)
from colmap_ext.mapper.model import Model
from colmap_ext.mapper.options import (BundleAdjustmentOptions, FilteringOptions,
                                       GuidedMatchingOptions, MapperOptions,
                                       TriangulationOptions)
from colmap_ext.mapper.triangulation import (complete_tracks, merge_tracks, track_links,
                                             triangulate_image)
from colmap_ext.mapper.two_view import Pair, pair_graph
from colmap_ext.memory import return_freed_memory
from colmap_ext.timing import StageTimer

# Rounds of complete_and_merge_tracks at most (drive800: 3 changed the model, the 4th nothing).
MAX_TRACK_ROUNDS = 10


@dataclass
class MatchGraphs:
    """A model's images' matches as graphs (two_view.pair_graph): the verified ones, and
    the raw ones, verified or not: putative 2D-3D correspondences for P3P RANSAC, which
    bridges pairs whose two-view verification failed."""

    verified: dict[int, dict[int, np.ndarray]]
    raw: dict[int, dict[int, np.ndarray]]

    @classmethod
    def of(cls, model: Model, matches: dict[Pair, np.ndarray]) -> MatchGraphs:
        """The graphs of `matches` (verified) and the database's raw matches, between
        the model's images."""
        def within(pairs: dict[Pair, np.ndarray]) -> dict[Pair, np.ndarray]:
            return {p: m for p, m in pairs.items()
                    if p[0] in model.point_of and p[1] in model.point_of}
        return cls(pair_graph(within(matches)), pair_graph(within(model.db.raw_matches)))

    def neighbours(self, model: Model, image_id: int, limit: int) -> list[int]:
        """Registered images most connected to `image_id`: shared points, then matches."""
        shared = model.covisible_images(image_id) if model.is_registered(image_id) else {}
        verified = {o: len(m) for o, m in self.verified.get(image_id, {}).items()
                    if model.is_registered(o)}
        raw = {o: len(m) for o, m in self.raw.get(image_id, {}).items()
               if model.is_registered(o)}
        others = set(shared) | set(verified) or set(raw)
        return sorted(others, key=lambda o: (
            -shared.get(o, 0), -verified.get(o, 0), -raw.get(o, 0)))[:limit]


def triangulate_images(model: Model, image_ids: Iterable[int], graphs: MatchGraphs,
                       guided: GuidedMatchingOptions, triangulation: TriangulationOptions) -> None:
    """Triangulate each image, in turn, against its guided_matching.num_images neighbours
    (chosen as it comes: the images before it may have added shared points)."""
    for image_id in image_ids:
        triangulate_image(model, image_id, graphs.neighbours(model, image_id, guided.num_images),
                          guided, triangulation, min_views=2,
                          verified=graphs.verified.get(image_id, {}))


class ModelAdjuster:
    """Bundle adjustment of one model, each solve followed by its filtering, timed. The
    loss follows the model's reprojection errors, measured before each global
    adjustment and kept for the local ones after it: least squares
    (BundleAdjustmentOptions.gaussian_loss) where they look like Gaussian noise
    (filtering.errors_look_gaussian), the robust loss elsewhere, its scale raised where
    the noise reaches it (BundleAdjustmentOptions.noise_loss_scale_ratio)."""

    def __init__(self, model: Model, ba: BundleAdjustmentOptions, filtering: FilteringOptions,
                 num_threads: int, timer: StageTimer) -> None:
        self.model = model
        self.ba = ba
        self.filtering = filtering
        self.num_threads = num_threads
        self.timer = timer
        self.loss = ba.loss
        self.loss_scale_px = ba.loss_scale_px
        # Whether the errors looked Gaussian before the last global adjustment, and their median.
        self.errors_gaussian = False
        self.median_error_px = 0.0

    @classmethod
    def of(cls, model: Model, options: MapperOptions, timer: StageTimer) -> ModelAdjuster:
        """The adjuster of `model` with the options' components and threads."""
        return cls(model, options.bundle_adjustment, options.filtering, options.threads(), timer)

    def local_adjustment(self, image_ids: list[int]) -> None:
        """Adjust `image_ids` (bundle_adjust's local rule for the points), then filter them."""
        self._bundle_adjust(image_ids, local=True)
        with self.timer("filtering"):
            filter_points(self.model, image_ids, self.filtering)

    def global_adjustment(self, final: bool = False, rounds: int = 2,
                          exact: bool = True) -> None:
        """Adjust every registered image, then filter. `final`, the model's end:
        `rounds` rounds, their filter also relative to the model's median error
        (final_max_error_ratio), and one more adjustment if the last filter dropped
        observations or the errors it left call for another loss; on the camera model's
        own reprojection errors (bundle_adjust's `exact`) unless `exact` is False (a
        model retriangulated after it, whose last adjustment is exact). A round whose
        filter removed nothing ends the rounds: the next would solve the same problem
        again from its optimum. The descriptor searches kept go first: a global adjustment
        is the model's peak of memory, and a search is quick to run again."""
        exact = final and exact
        model = self.model
        model.nearest.release()
        return_freed_memory()
        registered = model.registered
        ratio = self.filtering.final_max_error_ratio if final else 0.0
        for _ in range(rounds if final else 1):
            self._follow_errors()
            self._bundle_adjust(registered, local=False, refine_intrinsics=True, exact=exact)
            with self.timer("filtering"):
                removed, removed_points = filter_points(model, registered, self.filtering,
                                                        final=final, max_error_ratio=ratio)
            if not removed and not removed_points:
                break
        if final:
            loss = self.loss
            self._follow_errors()
            if ratio > 0 and removed or self.loss != loss:
                self._bundle_adjust(registered, local=False, refine_intrinsics=True, exact=exact)

    def _follow_errors(self) -> None:
        """Choose the loss and its scale from the registered images' reprojection errors."""
        ba = self.ba
        with self.timer("filtering"):
            errors = reprojection_errors(self.model, self.model.registered)
        median = float(np.median(errors)) if len(errors) else 0.0
        self.median_error_px = median
        self.loss_scale_px = max(ba.loss_scale_px, ba.noise_loss_scale_ratio * median)
        self.errors_gaussian = errors_look_gaussian(errors, self.filtering)
        self.loss = ba.gaussian_loss if self.errors_gaussian else ba.loss

    def _bundle_adjust(self, image_ids: list[int], local: bool,
                       refine_intrinsics: bool = False, exact: bool = False) -> None:
        with self.timer("bundle adjustment"):
            iterations = bundle_adjust(self.model, image_ids, self.ba, local,
                                       self.num_threads, refine_intrinsics, self.loss,
                                       self.loss_scale_px, exact)
        self.timer.counts["bundle adjustment solves"] += 1
        self.timer.counts["bundle adjustment iterations"] += iterations


def refine_joined(model: Model, matches: dict[Pair, np.ndarray], options: MapperOptions,
                  timer: StageTimer, exact: bool = True) -> None:
    """Adjust a model joined from two (merging.py): global adjustment, then rounds
    of retriangulation and global adjustment. Retriangulation is guided matching of
    every image against its neighbours, which now include the images across the
    junction; the better poses of each round let the next match more of them. `exact`:
    the rounds' adjustments on the camera model's own errors (False where the finished
    model's retriangulation follows, whose adjustment is exact)."""
    graphs = MatchGraphs.of(model, matches)
    adjuster = ModelAdjuster.of(model, options, timer)
    adjuster.global_adjustment()
    for _ in range(options.merging.refinement_rounds):
        with timer("triangulation"):
            triangulate_images(model, model.registered, graphs, options.guided_matching,
                               options.triangulation)
        adjuster.global_adjustment(final=True, exact=exact)


def retriangulate(model: Model, matches: dict[Pair, np.ndarray], options: MapperOptions,
                  timer: StageTimer) -> int:
    """Triangulate the finished model's points again from its poses, then adjust it
    (final). The points it grew with were accepted within max_reproj_error_px while
    the poses were still moving; again from the final poses, each observation must lie
    within retriangulation_max_error_ratio x the model's median reprojection error
    (filtering.error_limit), which leaves out the near-miss matches. Where the errors
    look like Gaussian noise alone (filtering.errors_look_gaussian) there are none, and
    that cap would only cut the noise's tail: the points are those the noise split or
    kept from observations, the ones verified matches disagree with (points_off_matches),
    and none where they agree with every track; the tracks are then completed and merged
    to the end (complete_and_merge_tracks). Returns the number of points."""
    registered = model.registered
    triangulation = options.triangulation
    errors = reprojection_errors(model, registered)
    gaussian = errors_look_gaussian(errors, options.filtering)
    limit = error_limit(triangulation.max_reproj_error_px,
                        float(np.median(errors)) if len(errors) else np.inf,
                        options.filtering.noise_max_error_ratio,
                        0.0 if gaussian else triangulation.retriangulation_max_error_ratio)
    point_ids = points_off_matches(model, matches, limit) if gaussian else model.point_ids
    if gaussian and not point_ids:
        timer.counts["retriangulations left out"] += 1
        ModelAdjuster.of(model, options, timer).global_adjustment(final=True, rounds=1)
        return model.reconstruction.num_points3D()
    graphs = MatchGraphs.of(model, matches)
    strict = dataclasses.replace(triangulation, max_reproj_error_px=limit)
    with timer("triangulation"):
        for point_id in point_ids:
            model.delete_point(point_id)
        triangulate_images(model, model.registration_order, graphs, options.guided_matching,
                           strict)
        if gaussian:
            complete_and_merge_tracks(model, graphs.verified, strict, timer)
    with timer("filtering"):
        # The points the final filter would drop anyway (two-view tracks, narrow
        # angles) go first: the adjustment then solves the model's size, not twice it.
        filter_points(model, registered, options.filtering, final=True)
    del graphs  # memory the adjustment, the model's peak, needs
    # One round: the observations are fresh, and a second changed nothing measured.
    ModelAdjuster.of(model, options, timer).global_adjustment(final=True, rounds=1)
    return model.reconstruction.num_points3D()


def complete_and_merge_tracks(model: Model, verified: dict[int, dict[int, np.ndarray]],
                              triangulation: TriangulationOptions, timer: StageTimer) -> None:
    """complete_tracks and merge_tracks again until neither changes the model (at most
    MAX_TRACK_ROUNDS): merge_tracks joins a point to one other a call, a merged point
    can reach more keypoints, and a completed track link more points. On a long
    sequence the tracks that growth left split or short are many, and every one
    missing weakens the links between distant frames (BENCHMARKS.md, "Sequences")."""
    for _ in range(MAX_TRACK_ROUNDS):
        added = complete_tracks(model, verified, triangulation)
        merged = merge_tracks(model, verified, triangulation)
        timer.counts["observations completed"] += added
        timer.counts["points merged"] += merged
        if not added and not merged:
            break


def points_off_matches(model: Model, matches: dict[Pair, np.ndarray],
                       max_error_px: float) -> list[int]:
    """The points whose tracks a triangulation from the final poses can change. They come
    from the verified matches between the model's registered images whose two keypoints
    are not observations of one point (track_links): where one side's point reprojects
    within `max_error_px` onto the other side's keypoint, and has no observation in that
    keypoint's image (a track the noise split, an observation left out or taken by another
    point) or one farther from it, that point and the keypoint's point, if any. A point
    that holds its own, nearer keypoint there stays as it is: a wrong match that got
    through verification links it, or a point projecting close to it."""
    links = track_links(model, pair_graph(matches), max_error_px)
    tracks: dict[int, dict[int, int]] = {}

    def track(point_id: int) -> dict[int, int]:
        if point_id not in tracks:
            tracks[point_id] = model.track(point_id)
        return tracks[point_id]

    point_ids = set()
    for points, near, images, kps, owners in (
            (links.first, links.first_near, links.second_image, links.second_kp, links.second),
            (links.second, links.second_near, links.first_image, links.first_kp, links.first)):
        for point_id, image_id, kp, owner in set(zip(points[near].tolist(),
                                                     images[near].tolist(),
                                                     kps[near].tolist(), owners[near].tolist())):
            observed = track(point_id).get(image_id)
            if observed is not None:
                errors = model.reprojection_errors(image_id, np.array([kp, observed]),
                                                   model.xyz[[point_id, point_id]])
                if errors[0] >= errors[1]:
                    continue
            point_ids.add(point_id)
            if owner >= 0:
                point_ids.add(owner)
    return sorted(point_ids)
