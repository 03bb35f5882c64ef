"""The growing model: registered poses and 3D points with their tracks.

One pycolmap.Reconstruction holds the model for the whole run (`Model.reconstruction`):
every edit below is made on it in place, and bundle adjustment solves on it directly,
so nothing is rebuilt for a solve. Beside it, for the vectorised geometry of every
step, live arrays per image (unit rays in any direction and the angle a pixel spans
at each keypoint, see colmap_ext/cameras.py; uint8 SIFT descriptors; and `point_of`,
the point each keypoint observes or -1), the points' positions in a growable (P, 3)
array indexed by point id, and a dict per point for its track (image id -> keypoint
index). A point keeps at least two observations, as in COLMAP: deleting one of two
deletes the point.
"""

from __future__ import annotations

import logging

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


class Model:
    def __init__(self, db: DatabaseContents, nearest: NearestDescriptors,
                 image_ids: list[int] | None = None) -> None:
        self.db = db
        self.nearest = nearest  # descriptor searches, shared by every model of a run
        self.image_ids = sorted(image_ids if image_ids is not None else db.images)
        self.cameras = dict(db.cameras)  # this model's: bundle adjustment may refine them
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
        self.flat_offset = dict(zip(self.image_ids, starts[:-1].tolist()))
        self.point_of_flat = np.full(int(starts[-1]), -1, dtype=np.int64)
        self.point_of: dict[int, np.ndarray] = {}
        for image_id, start, stop in zip(self.image_ids, starts[:-1], starts[1:]):
            image = db.images[image_id]
            self.keypoints[image_id] = image.keypoints
            self.point_of[image_id] = self.point_of_flat[start:stop]
            self._compute_rays(image_id)
        self.reconstruction = pycolmap.Reconstruction()
        for camera_id in sorted({db.images[i].camera_id for i in self.image_ids}):
            self.reconstruction.add_camera_with_trivial_rig(self.cameras[camera_id])
        for image_id in self.image_ids:
            image = db.images[image_id]
            self.reconstruction.add_image_with_trivial_frame(pycolmap.Image(
                name=image.name, keypoints=image.keypoints, camera_id=image.camera_id,
                image_id=image_id))
        self.poses: dict[int, pycolmap.Rigid3d] = {}
        self.fixed_image_ids: set[int] = set()  # poses bundle adjustment holds constant
        self.registration_order: list[int] = []
        self.xyz = np.zeros((1024, 3))
        self.tracks: dict[int, dict[int, int]] = {}
        self.born: dict[int, int] = {}  # point id -> number of registered images at creation
        # Images whose observations changed since the mapper last looked (take_changed).
        self._changed: set[int] = set()
        self._next_point_id = 1  # COLMAP's point ids start at 1
        self._noted_unprojectable = False

    # --- cameras ----------------------------------------------------------------
    def camera(self, image_id: int) -> pycolmap.Camera:
        return self.cameras[self.db.images[image_id].camera_id]

    def has_rays(self, image_id: int, kps: np.ndarray) -> np.ndarray:
        """Whether the camera model gives each keypoint a ray (solvers take no others)."""
        return np.isfinite(self.pixel_angles[image_id][kps])

    def set_camera(self, camera_id: int, camera: pycolmap.Camera) -> None:
        """New intrinsics for a camera, and the rays of its images from them."""
        self.cameras[camera_id] = camera
        self.reconstruction.cameras[camera_id].params = camera.params
        for image_id in self.image_ids:
            if self.db.images[image_id].camera_id == camera_id:
                self._compute_rays(image_id)

    def _compute_rays(self, image_id: int) -> None:
        camera, keypoints = self.camera(image_id), self.keypoints[image_id]
        ray = rays(camera, keypoints)
        angles = pixel_angles(camera, keypoints)
        angles[~np.isfinite(ray).all(axis=1)] = np.nan
        ray[~np.isfinite(angles)] = (0.0, 0.0, 1.0)
        self.rays[image_id] = ray
        self.pixel_angles[image_id] = angles

    def register(self, image_id: int, cam_from_world: pycolmap.Rigid3d) -> None:
        self.set_pose(image_id, cam_from_world)
        self.reconstruction.register_frame(self._frame_id(image_id))
        self.registration_order.append(image_id)
        self._changed.add(image_id)

    def set_pose(self, image_id: int, cam_from_world: pycolmap.Rigid3d) -> None:
        self.poses[image_id] = cam_from_world
        self.reconstruction.frames[self._frame_id(image_id)].rig_from_world = cam_from_world

    def _frame_id(self, image_id: int) -> int:
        return self.reconstruction.images[image_id].frame_id

    def deregister(self, image_id: int) -> None:
        """Remove an image's pose and its observations (a point left with one goes)."""
        _, point_ids = self.observations(image_id)
        for point_id in point_ids.tolist():
            self.delete_observation(point_id, image_id)
        self.reconstruction.deregister_frame(self._frame_id(image_id))
        del self.poses[image_id]
        self.registration_order.remove(image_id)
        self._changed.add(image_id)

    @property
    def num_registered(self) -> int:
        return len(self.poses)

    # --- points -----------------------------------------------------------------
    def add_point(self, xyz: np.ndarray, track: dict[int, int]) -> int:
        point_id = self._next_point_id
        self._next_point_id += 1
        if point_id >= len(self.xyz):
            self.xyz = np.vstack([self.xyz, np.zeros_like(self.xyz)])
        self.xyz[point_id] = xyz
        self.tracks[point_id] = dict(track)
        self.born[point_id] = self.num_registered
        point = pycolmap.Point3D()
        point.xyz = self.xyz[point_id]
        point.track = pycolmap.Track([pycolmap.TrackElement(image_id, kp)
                                      for image_id, kp in track.items()])
        self.reconstruction.add_point3D_with_id(point_id, point)
        for image_id, kp in track.items():
            self.point_of[image_id][kp] = point_id
        self._changed.update(track)
        return point_id

    def add_observation(self, point_id: int, image_id: int, kp: int) -> None:
        self.tracks[point_id][image_id] = kp
        self.point_of[image_id][kp] = point_id
        self.reconstruction.add_observation(point_id, pycolmap.TrackElement(image_id, kp))
        self._changed.add(image_id)

    def delete_observation(self, point_id: int, image_id: int) -> None:
        """Delete one observation; of a point's last two, the point (COLMAP's rule)."""
        if len(self.tracks[point_id]) <= 2:
            self.delete_point(point_id)
            return
        kp = self.tracks[point_id].pop(image_id)
        self.point_of[image_id][kp] = -1
        self.reconstruction.delete_observation(image_id, kp)
        self._changed.add(image_id)

    def delete_point(self, point_id: int) -> None:
        track = self.tracks.pop(point_id)
        for image_id, kp in track.items():
            self.point_of[image_id][kp] = -1
        self._changed.update(track)
        del self.born[point_id]
        self.reconstruction.delete_point3D(point_id)

    def transform(self, similarity: pycolmap.Sim3d) -> None:
        """Move every pose and point by a similarity."""
        for image_id, pose in list(self.poses.items()):
            self.set_pose(image_id, similarity.transform_camera_world(pose))
        for point_id in self.tracks:
            self.xyz[point_id] = similarity * self.xyz[point_id]
            self.reconstruction.points3D[point_id].xyz = self.xyz[point_id]

    def take_changed(self) -> set[int]:
        """The images registered, deregistered or whose observations changed since the
        last call: what the mapper's cached counts per image must look at again."""
        changed, self._changed = self._changed, set()
        return changed

    def observations(self, image_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Keypoint indices of an image that observe points, and those point ids."""
        kps = np.flatnonzero(self.point_of[image_id] >= 0)
        return kps, self.point_of[image_id][kps]

    # --- geometry ---------------------------------------------------------------
    def reprojection_errors(self, image_id: int, kps: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Reprojection errors in pixels: the angle between each keypoint's ray and its
        point `xyz`, over the angle a pixel spans there. inf where the point is 90 degrees
        or more from the ray (behind it), or where the camera model cannot project the
        point (a fisheye's directions at 90 degrees or more from its axis): bundle
        adjustment could not take such an observation."""
        pose = self.poses[image_id].matrix()
        x_cam = xyz @ pose[:, :3].T + pose[:, 3]
        ray = self.rays[image_id][kps]
        along = np.einsum("ij,ij->i", x_cam, ray)
        angles = np.arctan2(np.linalg.norm(np.cross(x_cam, ray), axis=1), along)
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

    def centre(self, image_id: int) -> np.ndarray:
        return self.poses[image_id].inverse().translation

    def covisible_images(self, image_id: int) -> dict[int, int]:
        """Registered images sharing points with `image_id`, with the number shared."""
        _, point_ids = self.observations(image_id)
        counts: dict[int, int] = {}
        for point_id in point_ids:
            for other in self.tracks[point_id]:
                if other != image_id:
                    counts[other] = counts.get(other, 0) + 1
        return counts
