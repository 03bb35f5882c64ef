"""Time our RANSAC solvers against pycolmap's and OpenCV's on the same synthetic problems.

Relative pose: ours (5-point, OpenGV), pycolmap.estimate_essential_matrix, and
cv2.findEssentialMat + cv2.recoverPose. Absolute pose: ours (P3P, OpenGV),
pycolmap.estimate_absolute_pose, and cv2.solvePnPRansac (P3P, AP3P). Camera rigs: ours
(GP3P; 5+1-point, 6-point and 17-point generalized relative pose, OpenGV) against
pycolmap.estimate_generalized_absolute_pose and estimate_generalized_relative_pose. Each
library runs with its default RANSAC settings except the inlier threshold (1 px for all;
ours takes it as the angle 1 px subtends at the principal point, 1 / focal radians);
every method sees the same problems. Prints Markdown tables.

    python benchmarks/solvers.py [--problems 20] [--sizes 200 2000] [--outliers 0.2 0.5]
        [--rig-problems 5] [--rig-sizes 300] [--rig-outliers 0.2 0.5] [--tables single rig]
"""

from __future__ import annotations

import argparse
import inspect
import os
import platform
import subprocess
import time
from dataclasses import dataclass
from importlib.metadata import version

import cv2
import numpy as np
import pycolmap

import solvers

FOCAL = 1000.0
SIZE = 1000  # image width and height in pixels
NOISE_PX = 0.5
THRESHOLD_PX = 1.0
THRESHOLD_RAD = THRESHOLD_PX / FOCAL  # ours: the angle of THRESHOLD_PX at the principal point
K = np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1]])
CAMERA = pycolmap.Camera(model="PINHOLE", width=SIZE, height=SIZE,
                         params=[FOCAL, FOCAL, SIZE / 2, SIZE / 2])


# Rigs: three cameras on a ring of radius 1, looking outwards (cams_from_rig).
RIG_RADIUS = 1.0
RIG = [pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0, -yaw, 0])), [0, 0, -RIG_RADIUS])
       for yaw in 2 * np.pi * np.arange(3) / 3]


@dataclass
class Problem:
    pose: pycolmap.Rigid3d  # cam2_from_cam1 or rig2_from_rig1 (relative), cam_from_world or
    # rig_from_world (absolute)
    pixels1: np.ndarray  # (N, 2) first image (relative) or the only image (absolute)
    pixels2: np.ndarray | None  # (N, 2) second image (relative)
    points3D: np.ndarray | None  # (N, 3) world points (absolute)
    cameras1: np.ndarray | None = None  # (N,) rigs: the camera of each pixels1 row
    cameras2: np.ndarray | None = None  # (N,) rigs: the camera of each pixels2 row


def random_rotation(rng: np.random.Generator, max_deg: float) -> pycolmap.Rotation3d:
    axis = rng.normal(size=3)
    angle = np.deg2rad(rng.uniform(0, max_deg))
    return pycolmap.Rotation3d(axis / np.linalg.norm(axis) * angle)


def project(pose: pycolmap.Rigid3d, X: np.ndarray) -> np.ndarray:
    Xc = X @ pose.rotation.matrix().T + pose.translation
    return Xc[:, :2] / Xc[:, 2:] * FOCAL + SIZE / 2


def scene_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points seen by a camera at the origin looking along +z, depths 4 to 8."""
    depth = rng.uniform(4, 8, n)
    xy = rng.uniform(-0.4, 0.4, (n, 2)) * depth[:, None]
    return np.column_stack([xy, depth])


def corrupt(rng: np.random.Generator, pixels: np.ndarray, outlier_ratio: float) -> np.ndarray:
    noisy = pixels + rng.normal(0, NOISE_PX, pixels.shape)
    num_outliers = int(round(outlier_ratio * len(pixels)))
    noisy[:num_outliers] = rng.uniform(0, SIZE, (num_outliers, 2))
    return noisy


def relative_problem(rng: np.random.Generator, n: int, outlier_ratio: float) -> Problem:
    X = scene_points(rng, n)
    direction = rng.normal(size=3) * [1, 1, 0.3]
    # Turn camera 2 back towards the scene so that most points stay in its view.
    centre = direction / np.linalg.norm(direction)
    look = np.array([0, 0, 6]) - centre
    z = look / np.linalg.norm(look)
    x = np.cross([0, 1, 0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z]) @ random_rotation(rng, 3).matrix()
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ centre)
    return Problem(pose, corrupt(rng, project(pycolmap.Rigid3d(), X), 0.0),
                   corrupt(rng, project(pose, X), outlier_ratio), None)


def absolute_problem(rng: np.random.Generator, n: int, outlier_ratio: float) -> Problem:
    X_cam = scene_points(rng, n)
    pose = pycolmap.Rigid3d(random_rotation(rng, 180), rng.normal(size=3))
    X = (X_cam - pose.translation) @ pose.rotation.matrix()  # world points
    return Problem(pose, corrupt(rng, project(pose, X), outlier_ratio), None, X)


def rig_absolute_problem(rng: np.random.Generator, n: int, outlier_ratio: float) -> Problem:
    """Points seen by the rig's cameras at random, the rig anywhere."""
    pose = pycolmap.Rigid3d(random_rotation(rng, 180), rng.normal(size=3))
    cameras = rng.integers(0, len(RIG), n)
    X_cam = scene_points(rng, n)
    X = np.empty_like(X_cam)
    for c, cam_from_rig in enumerate(RIG):
        seen = cameras == c
        world_from_cam = (cam_from_rig * pose).inverse()
        X[seen] = X_cam[seen] @ world_from_cam.rotation.matrix().T + world_from_cam.translation
    pixels = corrupt(rng, project(pycolmap.Rigid3d(), X_cam), outlier_ratio)
    return Problem(pose, pixels, None, X, cameras)


def rig_relative_problem(rng: np.random.Generator, n: int, outlier_ratio: float) -> Problem:
    """The rig turns by a third of a turn (up to 30 deg more) and moves about 0.5: points
    seen by one camera in frame 1 are seen by another in frame 2."""
    third = pycolmap.Rotation3d(np.array([0, 2 * np.pi / len(RIG), 0]))
    pose = pycolmap.Rigid3d(random_rotation(rng, 30) * third, rng.normal(size=3) * 0.3)
    cameras1, pixels1, cameras2, pixels2 = [], [], [], []
    while sum(map(len, cameras1)) < n:
        c1 = int(rng.integers(0, len(RIG)))
        X_cam1 = scene_points(rng, max(n // 10, 10))
        X_rig1 = (X_cam1 - RIG[c1].translation) @ RIG[c1].rotation.matrix()
        X_rig2 = X_rig1 @ pose.rotation.matrix().T + pose.translation
        for c2, cam_from_rig in enumerate(RIG):
            X_cam2 = X_rig2 @ cam_from_rig.rotation.matrix().T + cam_from_rig.translation
            pixels = project(pycolmap.Rigid3d(), X_cam2)
            seen = (X_cam2[:, 2] > 1) & np.all((pixels >= 0) & (pixels < SIZE), axis=1)
            cameras1.append(np.full(seen.sum(), c1))
            pixels1.append(project(pycolmap.Rigid3d(), X_cam1[seen]))
            cameras2.append(np.full(seen.sum(), c2))
            pixels2.append(pixels[seen])
    pixels1, pixels2 = np.concatenate(pixels1)[:n], np.concatenate(pixels2)[:n]
    return Problem(pose, corrupt(rng, pixels1, 0.0), corrupt(rng, pixels2, outlier_ratio), None,
                   np.concatenate(cameras1)[:n], np.concatenate(cameras2)[:n])


def rays(pixels: np.ndarray) -> np.ndarray:
    """Unit rays of pixels of CAMERA, as the mapper gives them to the solvers."""
    xy1 = np.column_stack([(pixels - SIZE / 2) / FOCAL, np.ones(len(pixels))])
    return xy1 / np.linalg.norm(xy1, axis=1, keepdims=True)


def rotation_error_deg(a: pycolmap.Rigid3d, b: pycolmap.Rigid3d) -> float:
    return float(np.rad2deg((a.rotation.inverse() * b.rotation).angle()))


def direction_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return float(np.rad2deg(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def rigid(R: np.ndarray, t: np.ndarray) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), np.asarray(t, dtype=np.float64).reshape(3))


# Each method takes a Problem and returns the estimated pose, or None on failure.

def ours_relative(method):
    def run(p: Problem):
        return solvers.relative_pose(rays(p.pixels1), rays(p.pixels2),
                                     max_error=THRESHOLD_RAD, method=method).cam2_from_cam1
    return run


def pycolmap_relative(p: Problem):
    options = pycolmap.RANSACOptions()
    options.max_error = THRESHOLD_PX
    out = pycolmap.estimate_essential_matrix(p.pixels1, p.pixels2, CAMERA, CAMERA, options)
    return None if out is None else out["cam2_from_cam1"]


def opencv_relative(p: Problem):
    E, mask = cv2.findEssentialMat(p.pixels1, p.pixels2, K, method=cv2.RANSAC,
                                   threshold=THRESHOLD_PX)
    if E is None or E.shape != (3, 3):  # several stacked solutions when degenerate
        return None
    _, R, t, _ = cv2.recoverPose(E, p.pixels1, p.pixels2, K, mask=mask)
    return rigid(R, t)


def ours_absolute(method):
    def run(p: Problem):
        return solvers.absolute_pose(rays(p.pixels1), p.points3D,
                                     max_error=THRESHOLD_RAD, method=method).cam_from_world
    return run


def pycolmap_absolute(p: Problem):
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = THRESHOLD_PX
    out = pycolmap.estimate_absolute_pose(p.pixels1, p.points3D, CAMERA, options)
    return None if out is None else out["cam_from_world"]


def opencv_absolute(flag):
    def run(p: Problem):
        ok, rvec, tvec, _ = cv2.solvePnPRansac(p.points3D, p.pixels1, K, None, flags=flag,
                                               reprojectionError=THRESHOLD_PX)
        return rigid(cv2.Rodrigues(rvec)[0], tvec) if ok else None
    return run


def ours_rig_relative(method):
    def run(p: Problem):
        return solvers.generalized_relative_pose(
            rays(p.pixels1), p.cameras1, rays(p.pixels2), p.cameras2, RIG,
            max_error=THRESHOLD_RAD, method=method).rig2_from_rig1
    return run


def pycolmap_rig_relative(p: Problem):
    options = pycolmap.RANSACOptions()
    options.max_error = THRESHOLD_PX
    out = pycolmap.estimate_generalized_relative_pose(
        p.pixels1, p.pixels2, p.cameras1.tolist(), p.cameras2.tolist(), RIG,
        [CAMERA] * len(RIG), options)
    # pycolmap returns "pano2_from_pano1" (no metric translation) where it finds no scale.
    return None if out is None else out.get("rig2_from_rig1")


def ours_rig_absolute(p: Problem):
    return solvers.generalized_absolute_pose(rays(p.pixels1), p.cameras1, p.points3D, RIG,
                                             max_error=THRESHOLD_RAD).rig_from_world


def pycolmap_rig_absolute(p: Problem):
    options = pycolmap.RANSACOptions()
    options.max_error = THRESHOLD_PX
    out = pycolmap.estimate_generalized_absolute_pose(
        p.pixels1, p.points3D, p.cameras1.tolist(), RIG, [CAMERA] * len(RIG), options)
    return None if out is None else out["rig_from_world"]


RELATIVE = {
    "ours (5-point Stewenius, OpenGV; default)": ours_relative("stewenius"),
    "ours (5-point Nister, OpenGV)": ours_relative("nister"),
    "pycolmap.estimate_essential_matrix": pycolmap_relative,
    "cv2.findEssentialMat + recoverPose": opencv_relative,
}
ABSOLUTE = {
    "ours (P3P Kneip, OpenGV; default)": ours_absolute("kneip"),
    "ours (P3P Gao, OpenGV)": ours_absolute("gao"),
    "pycolmap.estimate_absolute_pose": pycolmap_absolute,
    "cv2.solvePnPRansac P3P": opencv_absolute(cv2.SOLVEPNP_P3P),
    "cv2.solvePnPRansac AP3P": opencv_absolute(cv2.SOLVEPNP_AP3P),
}
RIG_RELATIVE = {
    "ours (5+1-point, OpenGV's 5-point; default)": ours_rig_relative("fivept_plus_one"),
    "ours (6-point, OpenGV)": ours_rig_relative("sixpt"),
    "ours (17-point, OpenGV)": ours_rig_relative("seventeenpt"),
    "pycolmap.estimate_generalized_relative_pose": pycolmap_rig_relative,
}
RIG_ABSOLUTE = {
    "ours (GP3P, OpenGV)": ours_rig_absolute,
    "pycolmap.estimate_generalized_absolute_pose": pycolmap_rig_absolute,
}


def run_one(method, problem: Problem, direction_only: bool):
    start = time.perf_counter()
    try:
        estimate = method(problem)
    except solvers.EstimationError:
        estimate = None
    elapsed = time.perf_counter() - start
    if estimate is None:
        return elapsed, np.nan, np.nan, True
    if direction_only:  # the translation of a single camera's relative pose has no scale
        t_err = direction_error_deg(estimate.translation, problem.pose.translation)
    else:  # camera or rig centre distance relative to the distance of the scene (about 6)
        t_err = float(np.linalg.norm(estimate.inverse().translation
                                     - problem.pose.inverse().translation))
    return elapsed, rotation_error_deg(estimate, problem.pose), t_err, False


def benchmark(methods: dict, make_problem, direction_only: bool, sizes, outlier_ratios,
              num_problems: int, seed: int) -> list[str]:
    """Table rows; times relative to the pycolmap method (the one named pycolmap.*)."""
    reference = next(name for name in methods if name.startswith("pycolmap."))
    rows = []
    for n in sizes:
        for ratio in outlier_ratios:
            rng = np.random.default_rng(seed)
            problems = [make_problem(rng, n, ratio) for _ in range(num_problems)]
            stats = {name: [] for name in methods}
            for problem in problems:  # interleaved, so that load changes hit every method
                for name, method in methods.items():
                    stats[name].append(run_one(method, problem, direction_only))
            reference_ms = np.median([s[0] for s in stats[reference]]) * 1e3
            for name, values in stats.items():
                times, r_err, t_err, failed = map(np.asarray, zip(*values))
                ms = np.median(times) * 1e3
                rows.append(
                    f"| {n} | {ratio:.0%} | {name} | {ms:.2f} | {reference_ms / ms:.1f}x "
                    f"| {np.nanmedian(r_err) if not failed.all() else np.nan:.4f} "
                    f"| {np.nanmedian(t_err) if not failed.all() else np.nan:.4f} "
                    f"| {failed.sum()} |")
    return rows


def opengv_version() -> str:
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", "libopengv-dev"],
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown version"
    return out or "unknown version"


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=20, help="random problems per setting")
    parser.add_argument("--sizes", type=int, nargs="+", default=[200, 2000])
    parser.add_argument("--outliers", type=float, nargs="+", default=[0.2, 0.5])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rig-problems", type=int, default=5,
                        help="random rig problems per setting (pycolmap's take seconds each)")
    parser.add_argument("--rig-sizes", type=int, nargs="+", default=[300])
    parser.add_argument("--rig-outliers", type=float, nargs="+", default=[0.2, 0.5])
    parser.add_argument("--tables", nargs="+", choices=["single", "rig"], default=["single", "rig"],
                        help="single cameras, camera rigs or both")
    args = parser.parse_args()

    # Warm-up: first calls pay for lazy initialisation in every library.
    warm = np.random.default_rng(1)
    for methods, make, direction_only in ((RELATIVE, relative_problem, True),
                                          (ABSOLUTE, absolute_problem, False),
                                          (RIG_RELATIVE, rig_relative_problem, False),
                                          (RIG_ABSOLUTE, rig_absolute_problem, False)):
        for method in methods.values():
            run_one(method, make(warm, 100, 0.0), direction_only)

    ours = inspect.signature(solvers.relative_pose).parameters
    essential = pycolmap.RANSACOptions()
    pnp = pycolmap.AbsolutePoseEstimationOptions().ransac
    print(f"Machine: {cpu_model()}, {os.cpu_count()} cores (load average "
          f"{os.getloadavg()[0]:.1f} at the start); Python {platform.python_version()}, "
          f"colmap-ext {version('colmap-ext')} (OpenGV {opengv_version()}), "
          f"pycolmap {pycolmap.__version__}, OpenCV {cv2.__version__}, NumPy {np.__version__}.\n")
    print(f"Inputs: f = {FOCAL:.0f} px, {SIZE}x{SIZE} images, {NOISE_PX} px Gaussian noise, "
          f"scene depth 4 to 8, outliers uniform over the image, {args.problems} random "
          f"problems per row of the single-camera tables (seed {args.seed}), the same problems "
          "for every method. "
          f"Threshold {THRESHOLD_PX} px for every method; every other RANSAC setting is the "
          f"library's default: ours confidence {ours['confidence'].default}, "
          f"{ours['min_iterations'].default} to {ours['max_iterations'].default} iterations; "
          f"pycolmap confidence {essential.confidence}, {essential.min_num_trials} to "
          f"{essential.max_num_trials} trials and {essential.dyn_num_trials_multiplier}x the "
          f"confidence-based count (essential matrix), confidence {pnp.confidence}, "
          f"{pnp.min_num_trials} to {pnp.max_num_trials} trials (absolute pose); OpenCV "
          "findEssentialMat prob 0.999, 1000 iterations, solvePnPRansac 100 iterations, "
          "confidence 0.99. Ours takes the threshold as an angle, "
          f"{THRESHOLD_PX} px / f radians (the angle at the principal point). Time: median wall "
          "time per call, from pixel coordinates (ours includes their conversion to unit rays). "
          "Errors: "
          "median over the problems; rotation in degrees; translation as the angle to the "
          "true direction in degrees (relative pose) or as the camera-centre distance in "
          "scene units (absolute pose). 'failed': calls without a result.")
    print(f"Rigs: three cameras on a ring of radius {RIG_RADIUS} (scene units), looking "
          f"outwards; {args.rig_problems} random problems per row (seed {args.seed}). "
          "Absolute: each point seen by one camera at random. Relative: the rig turns by a "
          "third of a turn (up to 30 deg more: exactly a third would carry each camera onto "
          "another's place and leave the scale open) and moves about 0.5, points seen by one "
          "camera in each frame (mostly different cameras). Translation errors: distance of the rig "
          "centres in scene units (the rig's baseline gives the relative pose its scale). "
          "Same thresholds and default RANSAC settings (pycolmap: RANSACOptions()).")
    header = ["| N | outliers | method | time (ms) | pycolmap time / this | rotation err (deg) "
              "| {} | failed |", "|---|---|---|---|---|---|---|---|"]
    tables = []
    if "single" in args.tables:
        tables += [("Relative pose (essential matrix)", "translation dir. err (deg)", RELATIVE,
                    relative_problem, True, args.sizes, args.outliers, args.problems),
                   ("Absolute pose (P3P)", "centre err", ABSOLUTE, absolute_problem, False,
                    args.sizes, args.outliers, args.problems)]
    if "rig" in args.tables:
        tables += [("Generalized relative pose (camera rigs)", "rig centre err", RIG_RELATIVE,
                    rig_relative_problem, False, args.rig_sizes, args.rig_outliers,
                    args.rig_problems),
                   ("Generalized absolute pose (camera rigs)", "rig centre err", RIG_ABSOLUTE,
                    rig_absolute_problem, False, args.rig_sizes, args.rig_outliers,
                    args.rig_problems)]
    for title, error_name, methods, make, direction_only, sizes, outliers, problems in tables:
        print(f"\n### {title}\n")
        print(header[0].format(error_name))
        print(header[1])
        print("\n".join(benchmark(methods, make, direction_only, sizes, outliers, problems,
                                  args.seed)), flush=True)


if __name__ == "__main__":
    main()
