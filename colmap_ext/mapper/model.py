"""The growing model: a pycolmap.Reconstruction, and what the steps derive from it.

The reconstruction is the model: cameras, rigs, frames, images, poses, points and
tracks live there alone, and change through the edits below (register, add_point,
add_observation, delete_observation, ...), which are pycolmap's own methods. A frame
is what gets a pose: registering an image poses its frame, and with it every image of
the frame through the rig's `sensor_from_rig` (a database without rigs has one frame
per image). Bundle adjustment solves on the reconstruction in place.

Derived from it, for the vectorised geometry of the steps, and read-only for them:
per image, unit rays in any direction and the angle a pixel spans at each keypoint
(colmap_ext/cameras.py), from the reconstruction's cameras (`refresh_cameras` after
intrinsics change); `point_of`, the point each keypoint observes or -1, an index that
the edits keep; and `xyz`, the points' positions by point id, read again from the
reconstruction for the points a step modified (`refresh_points`), as COLMAP's
`modified_points3D`. Our bundle adjuster moves points in `xyz` alone (`move_points`);
the reconstruction takes their positions when something reads it whole: pycolmap's
adjuster, a transform, an export (`write_points`). A point keeps at least two
observations, as in COLMAP: deleting one of two deletes the point.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np
import pycolmap

from colmap_ext.cameras import pixel_angles, rays
from colmap_ext.database import DatabaseContents
from colmap_ext.mapper.descriptors import NearestDescriptors

logger = logging.getLogger(__name__)

# Points this close (px) to their keypoint's ray that the camera model cannot project are
# named in the log (Model._note_unprojectable): the mapper's thresholds, a few pixels,
# would have kept them; points farther off are not observations worth a word.
NOTED_UNPROJECTABLE_PX = 10.0


def database_reconstruction(db: DatabaseContents,
                            image_ids: Iterable[int]) -> pycolmap.Reconstruction:
    """A reconstruction of the database's images `image_ids` with their keypoints,
    cameras, rigs and frames (each frame holding just the images among `image_ids`),
    nothing posed. A database without rigs gives each camera a rig of its own and each
    image a frame of its own."""
    image_ids = sorted(image_ids)
    reconstruction = pycolmap.Reconstruction()
    if not db.frames:
        for camera_id in sorted({db.images[i].camera_id for i in image_ids}):
            reconstruction.add_camera_with_trivial_rig(db.cameras[camera_id])
        for image_id in image_ids:
            reconstruction.add_image_with_trivial_frame(_image(db, image_id))
        return reconstruction
    frame_ids = sorted({db.images[i].frame_id for i in image_ids})
    rig_ids = sorted({db.frames[frame_id].rig_id for frame_id in frame_ids})
    for rig_id in rig_ids:
        for camera_id in db.rigs[rig_id].camera_ids:
            if not reconstruction.exists_camera(camera_id):
                reconstruction.add_camera(db.cameras[camera_id])
        reconstruction.add_rig(db.rigs[rig_id].rig(rig_id))
    wanted = set(image_ids)
    for frame_id in frame_ids:
        frame = pycolmap.Frame()
        frame.frame_id, frame.rig_id = frame_id, db.frames[frame_id].rig_id
        for other_id in db.frames[frame_id].image_ids:
            if other_id in wanted:
                frame.add_data_id(_image_data_id(db, other_id))
        reconstruction.add_frame(frame)
    for image_id in image_ids:
        image = _image(db, image_id)
        image.frame_id = db.images[image_id].frame_id
        reconstruction.add_image(image)
    return reconstruction


def _image_data_id(db: DatabaseContents, image_id: int) -> pycolmap.data_t:
    return pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA,
                                             db.images[image_id].camera_id), image_id)


def _image(db: DatabaseContents, image_id: int) -> pycolmap.Image:
    features = db.images[image_id]
    return pycolmap.Image(name=features.name, keypoints=features.keypoints,
                          camera_id=features.camera_id, image_id=image_id)


class Model:
    def __init__(self, db: DatabaseContents, nearest: NearestDescriptors,
                 image_ids: list[int] | None = None) -> None:
        self.db = db
        self.nearest = nearest  # descriptor searches, shared by every model of a run
        self.image_ids = sorted(image_ids if image_ids is not None else db.images)
        self.reconstruction = database_reconstruction(db, self.image_ids)
        self.keypoints: dict[int, np.ndarray] = {}
        self.rays: dict[int, np.ndarray] = {}
        # Radians per pixel at each keypoint: a pixel threshold times this is the angle the
        # geometric tests compare with. NaN where the camera model gives the keypoint no
        # ray (its ray is then a placeholder, and no test passes with it).
        self.pixel_angles: dict[int, np.ndarray] = {}
        self.descriptors = db.descriptors  # read when asked: see database.DescriptorReader
        # point_of[image_id] is a view of one array over every image's keypoints, which
        # looks up the points of many images' keypoints at once (flat_offset + keypoint).
        sizes = [len(db.images[image_id].keypoints) for image_id in self.image_ids]
        starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.flat_offset = np.zeros(max(self.image_ids, default=0) + 1, np.int64)  # by image id
        self.flat_offset[self.image_ids] = starts[:-1]
        self.point_of_flat = np.full(int(starts[-1]), -1, dtype=np.int64)
        self.image_of_flat = np.repeat(np.array(self.image_ids, np.int32), sizes)
        self.rays_flat = np.zeros((int(starts[-1]), 3))  # rays[image_id] are views of it
        self.point_of: dict[int, np.ndarray] = {}
        for image_id, start, stop in zip(self.image_ids, starts[:-1], starts[1:]):
            self.keypoints[image_id] = db.images[image_id].keypoints
            self.point_of[image_id] = self.point_of_flat[start:stop]
        self.refresh_cameras()
        self.xyz = np.zeros((1024, 3))
        # Per point id, the number of registered images when the point was made, and
        # whether the reconstruction holds an older position than xyz (move_points).
        self.born = np.zeros(len(self.xyz), np.int64)
        self._moved = np.zeros(len(self.xyz), bool)
        # Per point id, a range [first, last] of point_of_flat that holds all its
        # observations: widened as they come, never narrowed (flat_span).
        self._flat_range = np.zeros((len(self.xyz), 2), np.int64)
        self.fixed_frame_ids: set[int] = set()  # frames whose poses bundle adjustment holds
        self.registration_order: list[int] = []  # image ids
        # Images whose observations changed since the mapper last looked (take_changed).
        self._changed: set[int] = set()
        self._noted_unprojectable = False

    # --- cameras ----------------------------------------------------------------
    def camera(self, image_id: int) -> pycolmap.Camera:
        return self.reconstruction.cameras[self.db.images[image_id].camera_id]

    def has_rays(self, image_id: int, kps: np.ndarray) -> np.ndarray:
        """Whether the camera model gives each keypoint a ray (solvers take no others)."""
        return np.isfinite(self.pixel_angles[image_id][kps])

    def refresh_cameras(self) -> None:
        """The rays and pixel angles of every image from the reconstruction's cameras."""
        for image_id in self.image_ids:
            camera, keypoints = self.camera(image_id), self.keypoints[image_id]
            ray = rays(camera, keypoints)
            angles = pixel_angles(camera, keypoints)
            angles[~np.isfinite(ray).all(axis=1)] = np.nan
            ray[~np.isfinite(angles)] = (0.0, 0.0, 1.0)
            start = int(self.flat_offset[image_id])
            self.rays_flat[start:start + len(ray)] = ray
            self.rays[image_id] = self.rays_flat[start:start + len(ray)]
            self.pixel_angles[image_id] = angles

    # --- frames and poses -------------------------------------------------------
    def frame_id(self, image_id: int) -> int:
        return self.reconstruction.images[image_id].frame_id

    def frame_images(self, image_id: int) -> list[int]:
        """The images of `image_id`'s frame (itself among them), in this model."""
        frame = self.reconstruction.frames[self.frame_id(image_id)]
        return sorted(data_id.id for data_id in frame.image_ids)

    def is_registered(self, image_id: int) -> bool:
        """Whether the image is one of this model's and has a pose."""
        images = self.reconstruction.images
        return image_id in images and images[image_id].has_pose

    @property
    def registered(self) -> list[int]:
        """The registered images' ids."""
        return sorted(self.reconstruction.reg_image_ids())

    @property
    def num_registered(self) -> int:
        return self.reconstruction.num_reg_images()

    def pose(self, image_id: int) -> pycolmap.Rigid3d:
        """cam_from_world of a registered image (its frame's pose through the rig)."""
        return self.reconstruction.images[image_id].cam_from_world()

    def centre(self, image_id: int) -> np.ndarray:
        return self.reconstruction.images[image_id].projection_center()

    def cam_from_rig(self, image_id: int) -> pycolmap.Rigid3d:
        """The image's camera pose in its frame's rig (identity for the reference camera)."""
        rig = self.reconstruction.rigs[self.reconstruction.frames[self.frame_id(image_id)].rig_id]
        sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, self.db.images[image_id].camera_id)
        return pycolmap.Rigid3d() if rig.is_ref_sensor(sensor) else rig.sensor_from_rig(sensor)

    def register(self, image_id: int, cam_from_world: pycolmap.Rigid3d) -> list[int]:
        """Pose the image's frame so that the image has `cam_from_world`, and register it.
        Returns the frame's images, now all registered."""
        frame = self.reconstruction.frames[self.frame_id(image_id)]
        frame.set_cam_from_world(self.db.images[image_id].camera_id, cam_from_world)
        return self.register_frame(image_id, frame.rig_from_world)

    def register_frame(self, image_id: int, rig_from_world: pycolmap.Rigid3d) -> list[int]:
        """Pose and register the frame of `image_id`. Returns its images, now registered."""
        frame_id = self.frame_id(image_id)
        self.reconstruction.frames[frame_id].rig_from_world = rig_from_world
        self.reconstruction.register_frame(frame_id)
        images = self.frame_images(image_id)
        self.registration_order.extend(images)
        self._changed.update(images)
        return images

    def deregister(self, image_id: int) -> None:
        """Remove the pose of the image's frame and the observations of its images (a
        point left with one goes)."""
        images = self.frame_images(image_id)
        for other_id in images:
            for kp in self.observations(other_id)[0].tolist():
                self.delete_observation(other_id, kp)
        self.reconstruction.deregister_frame(self.frame_id(image_id))
        for other_id in images:
            self.registration_order.remove(other_id)
        self._changed.update(images)

    # --- points -----------------------------------------------------------------
    def add_point(self, xyz: np.ndarray, track: dict[int, int]) -> int:
        point_id = self.reconstruction.add_point3D(
            xyz, pycolmap.Track([pycolmap.TrackElement(image_id, kp)
                                 for image_id, kp in track.items()]))
        while point_id >= len(self.xyz):
            self.xyz = np.vstack([self.xyz, np.zeros_like(self.xyz)])
            self.born = np.concatenate([self.born, np.zeros_like(self.born)])
            self._moved = np.concatenate([self._moved, np.zeros_like(self._moved)])
            self._flat_range = np.vstack([self._flat_range, np.zeros_like(self._flat_range)])
        self.xyz[point_id] = xyz
        self._moved[point_id] = False
        self.born[point_id] = self.num_registered
        flat = [int(self.flat_offset[image_id]) + kp for image_id, kp in track.items()]
        self._flat_range[point_id] = min(flat), max(flat)
        for image_id, kp in track.items():
            self.point_of[image_id][kp] = point_id
        self._changed.update(track)
        return point_id

    def add_observation(self, point_id: int, image_id: int, kp: int) -> None:
        self.reconstruction.add_observation(point_id, pycolmap.TrackElement(image_id, kp))
        self.point_of[image_id][kp] = point_id
        flat = int(self.flat_offset[image_id]) + kp
        first, last = self._flat_range[point_id]
        self._flat_range[point_id] = min(first, flat), max(last, flat)
        self._changed.add(image_id)

    def add_observations_within(self, image_id: int, kps: np.ndarray, point_ids: np.ndarray,
                                max_error_px: float) -> int:
        """Keypoints `kps` of `image_id` join the tracks of `point_ids` (pairwise) where
        the point reprojects within `max_error_px`: one keypoint per point and one point
        per keypoint, the closest first, and none to a point the image already observes.
        Returns the observations added."""
        observed_ids = self.observations(image_id)[1]
        new_point = (point_ids >= 0) & ~np.isin(point_ids, observed_ids)
        # int64: the keys below exceed int32 on large models.
        kps, point_ids = kps[new_point].astype(np.int64), point_ids[new_point].astype(np.int64)
        if not len(kps):
            return 0
        # Each (keypoint, point) once, the first in the given order (a point seen in
        # several neighbours comes once from each).
        _, first = np.unique(kps * (int(point_ids.max()) + 1) + point_ids, return_index=True)
        first.sort()
        kps, point_ids = kps[first], point_ids[first]
        observed = set(observed_ids.tolist())
        errors = self.reprojection_errors(image_id, kps, self.xyz[point_ids])
        ok = errors <= max_error_px
        kps, point_ids, errors = kps[ok], point_ids[ok], errors[ok]
        added = 0
        for i in np.argsort(errors, kind="stable"):
            kp, point_id = int(kps[i]), int(point_ids[i])
            if self.point_of[image_id][kp] < 0 and point_id not in observed:
                self.add_observation(point_id, image_id, kp)
                observed.add(point_id)
                added += 1
        return added

    def delete_observation(self, image_id: int, kp: int) -> None:
        """Delete keypoint `kp`'s observation; of a point's last two, the point (COLMAP's rule)."""
        point_id = int(self.point_of[image_id][kp])
        if self.track_length(point_id) <= 2:
            self.delete_point(point_id)
            return
        self.reconstruction.delete_observation(image_id, kp)
        self.point_of[image_id][kp] = -1
        self._changed.add(image_id)

    def delete_point(self, point_id: int) -> None:
        track = self.track(point_id)
        for image_id, kp in track.items():
            self.point_of[image_id][kp] = -1
        self._changed.update(track)
        self.reconstruction.delete_point3D(point_id)

    def has_point(self, point_id: int) -> bool:
        return self.reconstruction.exists_point3D(point_id)

    @property
    def point_ids(self) -> list[int]:
        return list(self.reconstruction.point3D_ids())

    def track(self, point_id: int) -> dict[int, int]:
        """The point's observations: image id -> keypoint index."""
        return {element.image_id: element.point2D_idx
                for element in self.reconstruction.points3D[point_id].track.elements}

    def track_length(self, point_id: int) -> int:
        return self.reconstruction.points3D[point_id].track.length()

    def track_images(self, point_ids: list[int] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The observing images of many points at once, from `point_of`: each point's
        track length, and the image ids of every track, point after point."""
        index = np.full(len(self.xyz), -1, np.int64)
        index[point_ids] = np.arange(len(point_ids))
        flat = self.observed_flat(self.flat_span(point_ids))
        owner = index[self.point_of_flat[flat]]
        observed = owner >= 0
        owner, flat = owner[observed], flat[observed]
        order = np.argsort(owner, kind="stable")
        return np.bincount(owner, minlength=len(point_ids)), self.image_of_flat[flat[order]]

    def flat_span(self, point_ids: list[int] | np.ndarray,
                  image_ids: Iterable[int] = ()) -> slice:
        """A range of point_of_flat that holds every observation of `point_ids` and
        every keypoint of `image_ids`. The images' keypoints lie in image id order, so on
        a sequence this is the keypoints of the frames around them: what looks up their
        tracks touches the neighbourhood, not the whole model."""
        ranges = self._flat_range[np.asarray(point_ids, np.int64)]
        image_ids = list(image_ids)
        firsts = [int(self.flat_offset[i]) for i in image_ids]
        lasts = [first + len(self.keypoints[i]) for first, i in zip(firsts, image_ids)]
        if len(ranges):
            firsts.append(int(ranges[:, 0].min()))
            lasts.append(int(ranges[:, 1].max()) + 1)
        return slice(min(firsts, default=0), max(lasts, default=0))

    def observed_flat(self, span: slice) -> np.ndarray:
        """The indices into point_of_flat within `span` that observe a point."""
        return span.start + np.flatnonzero(self.point_of_flat[span] >= 0)

    def refresh_points(self, point_ids: Iterable[int]) -> None:
        """Read the positions of `point_ids` (a step moved them in the reconstruction)
        into `xyz`."""
        points = self.reconstruction.points3D
        for point_id in point_ids:
            self.xyz[point_id] = points[point_id].xyz

    def move_points(self, point_ids: np.ndarray, xyz: np.ndarray) -> None:
        """Set the positions of `point_ids` in `xyz`; the reconstruction takes them at
        the next write_points."""
        self.xyz[point_ids] = xyz
        self._moved[point_ids] = True

    def write_points(self) -> None:
        """Give the reconstruction the positions move_points set since the last call."""
        points = self.reconstruction.points3D
        for point_id in np.flatnonzero(self._moved).tolist():
            if self.has_point(point_id):
                points[point_id].xyz = self.xyz[point_id]
        self._moved[:] = False

    def transform(self, similarity: pycolmap.Sim3d) -> None:
        """Move every pose and point by a similarity."""
        self.write_points()
        self.reconstruction.transform(similarity)
        self.refresh_points(self.point_ids)

    def take_changed(self) -> set[int]:
        """The images registered, deregistered or whose observations changed since the
        last call: what the mapper's cached counts per image must look at again."""
        changed, self._changed = self._changed, set()
        return changed

    def flat_index(self, image_ids: np.ndarray, kps: np.ndarray) -> np.ndarray:
        """Indices into point_of_flat / rays_flat of keypoints `kps` of `image_ids` (pairwise)."""
        return self.flat_offset[image_ids] + kps

    def observations(self, image_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Keypoint indices of an image that observe points, and those point ids."""
        kps = np.flatnonzero(self.point_of[image_id] >= 0)
        return kps, self.point_of[image_id][kps]

    # --- geometry ---------------------------------------------------------------
    def reprojection_errors(self, image_id: int, kps: np.ndarray, xyz: np.ndarray,
                            cam_from_world: pycolmap.Rigid3d | None = None) -> np.ndarray:
        """Reprojection errors in pixels: the angle between each keypoint's ray and its
        point `xyz`, over the angle a pixel spans there. inf where the point is 90 degrees
        or more from the ray (behind it), or where the camera model cannot project the
        point (a fisheye's directions at 90 degrees or more from its axis): bundle
        adjustment could not take such an observation. `cam_from_world`: the image's pose
        (default: its registered one)."""
        pose = (self.pose(image_id) if cam_from_world is None else cam_from_world).matrix()
        x_cam = xyz @ pose[:, :3].T + pose[:, 3]
        ray = self.rays[image_id][kps]
        along = np.einsum("ij,ij->i", x_cam, ray)
        angles = np.arctan2(cross_norms(x_cam, ray), along)
        errors = angles / self.pixel_angles[image_id][kps]
        errors[~(along > 0) | np.isnan(errors)] = np.inf
        if len(x_cam):
            # NaN behind a camera with an image plane (z <= 0), never for EQUIRECTANGULAR.
            projected = self.camera(image_id).img_from_cam(x_cam)
            outside = ~np.isfinite(projected).all(axis=1)
            near = int(np.count_nonzero(outside & (errors <= NOTED_UNPROJECTABLE_PX)))
            errors[outside] = np.inf
            if near:
                self._note_unprojectable(image_id, near)
        return errors

    def _note_unprojectable(self, image_id: int, count: int) -> None:
        """One log line per model: observations whose points the camera model cannot
        project are left out (pycolmap's bundle adjustment could not take them)."""
        if not self._noted_unprojectable:
            self._noted_unprojectable = True
            logger.warning("colmap-ext: %d observation(s) of image %d left out: camera model "
                           "%s cannot project their points (beyond its field of view); "
                           "later ones are left out without a word", count, image_id,
                           self.camera(image_id).model.name)

    def covisible_images(self, image_id: int) -> dict[int, int]:
        """Registered images sharing points with `image_id`, with the number shared
        (from `point_of`, in one pass over the keypoints of flat_span: faster than
        reading the tracks of the image's points one by one)."""
        _, point_ids = self.observations(image_id)
        shared = np.zeros(len(self.xyz), bool)
        shared[point_ids] = True
        observed = self.observed_flat(self.flat_span(point_ids))
        observed = observed[shared[self.point_of_flat[observed]]]
        images, counts = np.unique(self.image_of_flat[observed], return_counts=True)
        return {other: count for other, count in zip(images.tolist(), counts.tolist())
                if other != image_id}

    def export(self) -> pycolmap.Reconstruction:
        """A copy of the model with its registered images alone (COLMAP's TearDown),
        point ids kept and their errors computed."""
        self.write_points()
        reconstruction = pycolmap.Reconstruction(self.reconstruction)
        reconstruction.tear_down()
        reconstruction.update_point_3d_errors()
        return reconstruction


def cross_norms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.linalg.norm(np.cross(a, b), axis=1) of (n, 3) arrays: the same operations in the
    same order, so the same values to the last bit, without np.cross's set-up per call."""
    a0, a1, a2 = a.T
    b0, b1, b2 = b.T
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    return np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
