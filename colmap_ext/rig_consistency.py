"""How well a model keeps a camera rig: for every two registered images a, b of one frame (b
after a by name), their relative pose cam_b_from_cam_a in the model against the one the rig
fixes (sensor_b_from_rig * sensor_a_from_rig^-1).

The rig comes from the model's own rigs and frames, from a database's (as `colmap
rig_configurator` or `apply_rig_config` wrote them), or from a rig configuration JSON (frames
then by image name, as COLMAP makes them). A mapper that ignores rigs gives its model a scale
of its own, so the model's baselines are first scaled by the one factor that fits them to the
rig's best (least squares; reported as `scale`, 1 for a model held to a metric rig):
translation deviations are in the rig's unit.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np
import pycolmap

from colmap_ext.errors import UserError
from colmap_ext.geometry import rotation_angles_deg
from colmap_ext.rigs import read_rig_config

# A frame: image name -> sensor_from_rig of its camera.
RigFrame = dict[str, pycolmap.Rigid3d]


def rig_frames(rigs: dict[int, pycolmap.Rig], frames: dict[int, pycolmap.Frame],
               image_names: dict[int, str]) -> dict[str, RigFrame]:
    """The frames of two images or more (by frame id, as text), each image's sensor_from_rig
    from its rig; `image_names`: image id -> name."""
    result: dict[str, RigFrame] = {}
    for frame_id, frame in frames.items():
        rig = rigs[frame.rig_id]
        members: RigFrame = {}
        for data_id in frame.data_ids:
            if data_id.sensor_id.type != pycolmap.SensorType.CAMERA:
                continue
            sensor_from_rig = pycolmap.Rigid3d() if data_id.sensor_id == rig.ref_sensor_id \
                else rig.sensor_from_rig(data_id.sensor_id)
            members[image_names[data_id.id]] = sensor_from_rig
        if len(members) >= 2:
            result[str(frame_id)] = members
    return result


def model_rig_frames(reconstruction: pycolmap.Reconstruction) -> dict[str, RigFrame]:
    """The frames of several images in a model's own rigs."""
    return rig_frames(dict(reconstruction.rigs), dict(reconstruction.frames),
                      {image_id: image.name for image_id, image in reconstruction.images.items()})


def database_rig_frames(database_path: str | Path) -> dict[str, RigFrame]:
    """The frames of several images in a database's rigs (none before rigs are configured)."""
    with pycolmap.Database.open(str(database_path)) as db:
        return rig_frames({rig.rig_id: rig for rig in db.read_all_rigs()},
                          {frame.frame_id: frame for frame in db.read_all_frames()},
                          {image.image_id: image.name for image in db.read_all_images()})


def config_rig_frames(configs: list[pycolmap.RigConfig],
                      image_names: list[str]) -> dict[str, RigFrame]:
    """The frames a rig configuration makes of `image_names`: the images with the same name
    after each camera's prefix (by that name); a UserError if no image is under a prefix."""
    prefixes = [camera.image_prefix for config in configs for camera in config.cameras]
    if not any(name.startswith(prefix) for name in image_names for prefix in prefixes):
        raise UserError(f"no image of the model is under the rig configuration's image "
                        f"prefixes ({', '.join(map(repr, prefixes))})")
    result: dict[str, RigFrame] = {}
    for index, config in enumerate(configs):
        frames: dict[str, RigFrame] = {}
        for camera in config.cameras:
            sensor_from_rig = pycolmap.Rigid3d() if camera.ref_sensor else camera.cam_from_rig
            for name in image_names:
                if name.startswith(camera.image_prefix):
                    frames.setdefault(name[len(camera.image_prefix):], {})[name] = sensor_from_rig
        key = "{}" if len(configs) == 1 else f"rig{index}:{{}}"
        result.update({key.format(name): members for name, members in frames.items()
                       if len(members) >= 2})
    return result


def rig_frames_of(reconstruction: pycolmap.Reconstruction,
                  rig_config: str | os.PathLike | None = None) -> dict[str, RigFrame]:
    """The frames of a rig configuration JSON, if given, else the model's own."""
    if rig_config is None:
        return model_rig_frames(reconstruction)
    return config_rig_frames(read_rig_config(rig_config),
                             [image.name for image in reconstruction.images.values()])


def rig_consistency(reconstruction: pycolmap.Reconstruction,
                    frames: dict[str, RigFrame]) -> dict | None:
    """The largest rotation (deg) and translation deviation of the model's relative poses
    within `frames` from the rig's, overall and per frame; None when no frame has two
    registered images in the model."""
    cams_from_world = {image.name: image.cam_from_world()
                       for image in reconstruction.images.values() if image.has_pose}
    pairs = []  # (frame, model's cam_b_from_cam_a, rig's)
    for key, members in frames.items():
        names = sorted(name for name in members if name in cams_from_world)
        for a, b in itertools.combinations(names, 2):
            pairs.append((key, cams_from_world[b] * cams_from_world[a].inverse(),
                          members[b] * members[a].inverse()))
    if not pairs:
        return None
    model_R = np.array([model.rotation.matrix() for _, model, _ in pairs])
    rig_R = np.array([rig.rotation.matrix() for _, _, rig in pairs])
    model_t = np.array([model.translation for _, model, _ in pairs])
    rig_t = np.array([rig.translation for _, _, rig in pairs])
    squared = float(np.sum(model_t * model_t))
    scale = float(np.sum(model_t * rig_t)) / squared if squared > 0 else 1.0
    rotation_deg = rotation_angles_deg(np.swapaxes(model_R, 1, 2) @ rig_R)
    translation = np.linalg.norm(scale * model_t - rig_t, axis=1)
    per_frame: dict[str, dict] = {}
    for (key, _, _), rotation, offset in zip(pairs, rotation_deg, translation):
        entry = per_frame.setdefault(key, {"frame": key, "num_pairs": 0,
                                           "rotation_max_deg": 0.0, "translation_max": 0.0})
        entry["num_pairs"] += 1
        entry["rotation_max_deg"] = max(entry["rotation_max_deg"], float(rotation))
        entry["translation_max"] = max(entry["translation_max"], float(offset))
    return {"num_frames": len(per_frame), "num_pairs": len(pairs), "scale": scale,
            "rotation_max_deg": float(np.max(rotation_deg)),
            "translation_max": float(np.max(translation)),
            "per_frame": list(per_frame.values())}


def format_rig_consistency(consistency: dict) -> str:
    """One line: the largest deviations and over how many frames."""
    return (f"rig: {consistency['num_frames']} frames, {consistency['num_pairs']} image pairs; "
            f"largest deviation from the rig {consistency['rotation_max_deg']:.4f} deg, "
            f"{consistency['translation_max']:.4g} (rig unit; model scale "
            f"{consistency['scale']:.4g})")
