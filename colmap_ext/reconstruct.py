"""`colmap-ext reconstruct`: images and known intrinsics in, COLMAP model out.

The whole method in one command, in a workspace laid out like COLMAP's automatic
reconstructor: WS/masks/ (with --segment), WS/database.db, WS/sparse/0, 1, ...,
and WS/reconstruct_summary.json, built beside WS and moved into it together at the end.
Every input is checked before any work starts, so a wrong camera parameter fails in a
second, not after feature extraction.
"""

from __future__ import annotations

import argparse
import dataclasses
import secrets
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import pycolmap

from colmap_ext import distributed, rigs
from colmap_ext.errors import UserError
from colmap_ext.features import (
    CAMERA_MODES,
    DEFAULT_MIN_NUM_KEYPOINTS,
    DEFAULT_PANORAMA_FEATURES,
    PANORAMA_FEATURES,
    FeatureOptions,
    check_images,
    extract_features,
    list_images,
)
from colmap_ext.mapper import MapperOptions
from colmap_ext.mapper import run as run_mapper
from colmap_ext.mapper.flags import boolean, random_seed
from colmap_ext.masks import METHODS, make_masks
from colmap_ext.matching import MATCHERS, MatchingOptions, match_features
from colmap_ext.model_io import (MAPPER_OUTPUT, OUTPUT_TYPES, OutputLayout, holds_only,
                                 is_file, moved, replacing, write_json)
from colmap_ext.timing import StageTimer

DATABASE_NAME = "database.db"
WORKSPACE = OutputLayout("a workspace", {
    DATABASE_NAME: is_file, f"{DATABASE_NAME}-wal": is_file, f"{DATABASE_NAME}-shm": is_file,
    "sparse": MAPPER_OUTPUT.is_output, "reconstruct_summary.json": is_file})
# With --segment the workspace's masks/ is ours too; without, a masks/ there is the user's
# (perhaps this run's --mask_path) and is left alone.
SEGMENTED_WORKSPACE = OutputLayout(WORKSPACE.result,
                                   {**WORKSPACE.entries, "masks": holds_only(r".+\.png")})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--image_path", required=True)
    parser.add_argument("--workspace_path", required=True,
                        help="gets database.db, sparse/0, ... and reconstruct_summary.json")
    parser.add_argument("--camera_model", default=None,
                        help="a COLMAP camera model, e.g. PINHOLE, OPENCV (not with a "
                             "--rig_config, which names each camera's)")
    parser.add_argument("--camera_params", default=None,
                        help='the known intrinsics in COLMAP order, e.g. "fx,fy,cx,cy"')
    parser.add_argument("--rig_config", default=None,
                        help="COLMAP's rig configuration JSON (`colmap rig_configurator`, "
                             "`colmap-ext rig_config_from_kalibr`): each camera's image "
                             "prefix, place on the rig and intrinsics; applied after extraction")
    parser.add_argument("--camera_mode", choices=list(CAMERA_MODES), default="single",
                        help="one camera for all images, or one per sub-folder")
    parser.add_argument("--mask_path", default=None,
                        help="COLMAP masks: MASK_PATH/<image name>.png, 0 = ignore")
    parser.add_argument("--segment", choices=METHODS, default=None,
                        help="make masks of an object on a uniform background (turntables)")
    parser.add_argument("--min_num_keypoints", type=int, default=DEFAULT_MIN_NUM_KEYPOINTS,
                        help="images with fewer keypoints are extracted again with a lower "
                             "SIFT peak threshold")
    parser.add_argument("--SiftExtraction.domain_size_pooling", dest="domain_size_pooling",
                        type=boolean, default=False, metavar="{0,1}",
                        help="COLMAP's DSP-SIFT descriptors: on textured photographs lower "
                             "rotation errors, at twice the extraction time; on low-texture "
                             "turntables worse (BENCHMARKS.md)")
    parser.add_argument("--panorama_features", choices=PANORAMA_FEATURES, default=None,
                        help="EQUIRECTANGULAR cameras: SIFT on the panorama itself (as "
                             "COLMAP does) or on six cube faces rendered from it, the "
                             f"keypoints mapped back (default: {DEFAULT_PANORAMA_FEATURES}; "
                             "BENCHMARKS.md)")
    parser.add_argument("--matcher", choices=MATCHERS, default="auto",
                        help="auto: exhaustive up to 100 images, sequential (with loop "
                             "closure) beyond")
    parser.add_argument("--SequentialMatching.loop_detection", dest="loop_detection",
                        type=boolean, default=False, metavar="{0,1}",
                        help="sequential matching: COLMAP's loop detection, for a sequence "
                             "that revisits a place (off by default, as in COLMAP's "
                             "sequential matcher)")
    parser.add_argument("--SequentialMatching.loop_detection_period",
                        dest="loop_detection_period", type=int, default=10,
                        help="loop detection for every this many-th image")
    parser.add_argument("--SequentialMatching.loop_detection_num_images",
                        dest="loop_detection_num_images", type=int, default=50,
                        help="loop detection: each such image matched with this many most "
                             "similar images")
    parser.add_argument("--vocab_tree_path", default=None,
                        help="COLMAP's vocabulary tree file for loop detection (default: a "
                             "vocabulary trained on the images' own descriptors, no download)")
    parser.add_argument("--exact_matching", action="store_true",
                        help="match descriptors by brute force, not by pycolmap's FAISS "
                             "index (approximate, and rarely not the same twice): the same "
                             "matches on every run and machine, slower on large images")
    parser.add_argument("--seed", type=random_seed, default=None,
                        help="RANSAC seed, for repeatable runs (default: random, recorded "
                             "in the summary)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the database and models of an earlier run")
    parser.add_argument("--output_type", choices=[*OUTPUT_TYPES, *(t.lower() for t in OUTPUT_TYPES)],
                        default="BIN")
    parser.add_argument("--ray_address", default=None,
                        help="extract and match on a Ray cluster: auto (the running cluster), "
                             "local (start one here) or HOST:PORT; the same database as "
                             "without it (row for row with --exact_matching)")


def main(image_path: str, workspace_path: str, camera_model: str | None = None,
         camera_params: str | None = None, rig_config: str | None = None,
         camera_mode: str = "single", mask_path: str | None = None, segment: str | None = None,
         min_num_keypoints: int = DEFAULT_MIN_NUM_KEYPOINTS, matcher: str = "auto",
         exact_matching: bool = False, seed: int | None = None, overwrite: bool = False,
         output_type: str = "BIN", ray_address: str | None = None,
         domain_size_pooling: bool = False, panorama_features: str | None = None,
         loop_detection: bool = False, loop_detection_period: int = 10,
         loop_detection_num_images: int = 50, vocab_tree_path: str | None = None) -> dict:
    """Run masks (optional), features, matching and the mapper; returns the summary.
    With `ray_address`, features and matching run as tasks on that Ray cluster
    (distributed.py), which is reached before anything is written."""
    start = time.perf_counter()
    workspace = Path(workspace_path)
    if ray_address is not None:
        distributed.check_address(ray_address)
    rig_configs = None if rig_config is None else rigs.read_rig_config(rig_config)
    rig_cameras = check_rig_cameras(rig_configs, camera_model, camera_params, camera_mode,
                                    ray_address)
    if rig_cameras is not None:
        camera_model, camera_params = next(iter(rig_cameras.values()))
    if panorama_features is not None and camera_model != "EQUIRECTANGULAR":
        raise UserError(f"--panorama_features is for EQUIRECTANGULAR cameras, not {camera_model}")
    features = FeatureOptions(camera_model, camera_params, camera_mode, mask_path,
                              min_num_keypoints, domain_size_pooling,
                              panorama_features or DEFAULT_PANORAMA_FEATURES, rig_cameras)
    names = check_inputs(image_path, workspace, features, segment, matcher, output_type,
                         rig_configs)
    matching = MatchingOptions(matcher=matcher, exact=exact_matching,
                               seed=secrets.randbits(31) if seed is None else seed,
                               loop_detection=loop_detection,
                               loop_detection_period=loop_detection_period,
                               loop_detection_num_images=loop_detection_num_images,
                               vocab_tree_path=vocab_tree_path)
    matching.check()
    layout = WORKSPACE if segment is None else SEGMENTED_WORKSPACE
    with replacing(workspace_path, layout, overwrite) as new_workspace, \
            distributed.optional_cluster(ray_address) as cluster:
        summary = run_stages(
            image_path, new_workspace, partial(moved, new=new_workspace, final=workspace),
            names, features, matching, start, segment=segment, output_type=output_type,
            cluster=cluster, rig_configs=rig_configs)
    print(format_summary(summary, workspace))
    return summary


def run_stages(image_path: str | Path, new_workspace: Path, shown: Callable[[str | Path], Path],
               names: list[str], features: FeatureOptions, matching: MatchingOptions,
               start: float, *, segment: str | None = None, output_type: str = "BIN",
               cluster: distributed.Cluster | None = None,
               rig_configs: list | None = None) -> dict:
    """The stages of `main` once the inputs are checked, written into `new_workspace`, a
    folder of model_io.replacing; `shown`: where a path will be once it is moved into place
    (model_io.moved), for the summary; `cluster`: where features and matching run (None:
    here); `rig_configs`: applied after extraction."""
    database_path = new_workspace / DATABASE_NAME
    timer = StageTimer()
    summary: dict = {"inputs": {
        "image_path": str(shown(image_path)),
        **({"camera_model": features.camera_model, "camera_params": features.camera_params}
           if features.rig_cameras is None else {"rig_cameras": {
               prefix: {"camera_model": model, "camera_params": params}
               for prefix, (model, params) in features.rig_cameras.items()}}),
        "camera_mode": features.camera_mode,
        "mask_path": features.mask_path, "segment": segment,
        "min_num_keypoints": features.min_num_keypoints,
        "domain_size_pooling": features.domain_size_pooling,
        "panorama_features": features.panorama_features
        if features.camera_model == "EQUIRECTANGULAR" else None, "matcher": matching.matcher,
        "exact_matching": matching.exact, "loop_detection": matching.loop_detection,
        "vocab_tree_path": None if matching.vocab_tree_path is None
        else str(matching.vocab_tree_path), "seed": matching.seed, "num_images": len(names)}}

    if segment is not None:
        features = dataclasses.replace(features, mask_path=str(new_workspace / "masks"))
        with timer("masks"):
            coverage = make_masks(image_path, features.mask_path, segment, names)
        summary["masks"] = {"path": str(shown(features.mask_path)), "coverage": coverage}
    if cluster is None:
        with timer("features"):
            feature_summary = extract_features(database_path, image_path, features,
                                               image_names=names)
        if rig_configs is not None:
            rigs.apply_rig_config(database_path, rig_configs)
        matching_summary = match_features(database_path, matching)
    else:
        feature_summary, matching_summary, summary["ray"] = distributed.extract_and_match(
            cluster, database_path, image_path, names, features, matching, timer)
    summary["features"] = feature_summary.to_dict()
    if matching.loop_detection and matching_summary.loop_detection_seconds:
        timer.seconds["loop_detection"] = matching_summary.loop_detection_seconds
    timer.seconds["matching"] = matching_summary.matching_seconds
    timer.seconds["verification"] = matching_summary.verification_seconds
    summary["matching"] = matching_summary.to_dict()
    with timer("mapper"):
        models = run_mapper(database_path, image_path, new_workspace / "sparse",
                            MapperOptions(seed=matching.seed), output_type=output_type.upper())
    summary["models"] = [{"path": str(shown(new_workspace / "sparse" / str(index))),
                          "num_registered": model.num_reg_images(),
                          "num_points3D": model.num_points3D()}
                         for index, model in models.items()]
    timer.seconds["total"] = time.perf_counter() - start
    summary["time_s"] = {name: round(seconds, 3) for name, seconds in timer.seconds.items()}
    write_json(summary, new_workspace / "reconstruct_summary.json")
    return summary


def check_rig_cameras(configs: list[pycolmap.RigConfig] | None, camera_model: str | None,
                      camera_params: str | None, camera_mode: str, ray_address: str | None,
                      ) -> dict[str, tuple[str, list[float]]] | None:
    """The cameras of the rig configuration `configs` (None without one), image prefix ->
    (model, params), every camera's from the configuration; the flags otherwise."""
    if configs is None:
        if camera_model is None or camera_params is None:
            raise UserError("give --camera_model and --camera_params (or a --rig_config)")
        return None
    if ray_address is not None:
        raise UserError("--rig_config does not run with --ray_address yet")
    if camera_model is not None or camera_params is not None:
        raise UserError("give --camera_model and --camera_params, or a --rig_config with "
                        "each camera's camera_model_name and camera_params, not both")
    if camera_mode != "single":
        raise UserError(f"--camera_mode {camera_mode} does not go with --rig_config, which "
                        "gives each image prefix its camera")
    cameras = {camera.image_prefix: camera.camera for config in configs
               for camera in config.cameras}
    if any(camera is None for camera in cameras.values()):
        raise UserError("give --camera_model and --camera_params, or a --rig_config with "
                        "camera_model_name and camera_params for every camera")
    return {prefix: (camera.model.name, list(camera.params)) for prefix, camera in cameras.items()}


def check_inputs(image_path: str, workspace: Path, features: FeatureOptions,
                 segment: str | None, matcher: str, output_type: str,
                 rig_configs: list[pycolmap.RigConfig] | None) -> list[str]:
    """Every check that can fail, before any work; returns the image names."""
    if features.mask_path is not None and segment is not None:
        raise UserError("give --mask_path or --segment, not both")
    if segment is not None and segment not in METHODS:
        raise UserError(f"unknown --segment {segment!r}; choose one of {', '.join(METHODS)}")
    if matcher not in MATCHERS:
        raise UserError(f"unknown --matcher {matcher!r}; choose one of {', '.join(MATCHERS)}")
    if output_type.upper() not in OUTPUT_TYPES:
        raise UserError(f"--output_type must be BIN or TXT, got {output_type!r}")
    features.check()
    names = list_images(image_path)
    if rig_configs is not None:
        rigs.check_rig_images(rig_configs, names)
    check_images(image_path, names, features)
    if workspace.exists() and not workspace.is_dir():
        raise UserError(f"workspace path is a file, not a folder: {workspace}")
    return names


def format_summary(summary: dict, workspace: Path) -> str:
    """A few lines: what each stage found, where the models are, and the time per stage."""
    features, matching = summary["features"], summary["matching"]
    low, median, high = features["keypoints_final_min_median_max"]
    lines = [
        f"Features: {features['num_images']} images, {features['num_reextracted']} extracted "
        f"again with a lower threshold; keypoints per image {low}/{median:g}/{high} "
        "(min/median/max)",
        f"Matching ({matching['matcher']}"
        f"{', exact' if summary['inputs']['exact_matching'] else ''}): "
        f"{matching['num_matched_pairs']} matched pairs, "
        f"{matching['num_verified_pairs']} verified, {matching['num_inlier_matches']} inlier "
        "matches",
    ]
    lines += [f"Model {Path(model['path']).name}: {model['num_registered']} images, "
              f"{model['num_points3D']} points, in {model['path']}"
              for model in summary["models"]]
    lines.append("Time: " + ", ".join(f"{name} {seconds:.1f}s"
                                      for name, seconds in summary["time_s"].items()))
    lines.append(f"Summary: {workspace / 'reconstruct_summary.json'}")
    return "\n".join(lines)
