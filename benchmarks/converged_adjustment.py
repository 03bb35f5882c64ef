"""How far each mapper's model is from the least-squares optimum of its own observations:
every model a neutral.py run wrote, measured as written and again after a global
least-squares adjustment run to convergence (Ceres tolerances 0, at most 1000 iterations),
the intrinsics and the rigs held and one frame fixing the gauge
(bundle_adjustment.hold_rigs_and_fix_gauge). A model already at its optimum does not move;
one whose last adjustment stopped early does, and where the two mappers' models differ, this
says whether they differ in their observations or in where their adjustments stopped.

    python benchmarks/converged_adjustment.py WORK_DIR   (neutral.py's --work_dir)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np  # before pycolmap (README, "Known problem")
import pycolmap

from neutral import measure

from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.mapper.bundle_adjustment import hold_rigs_and_fix_gauge
from colmap_ext.mapper.options import BundleAdjustmentOptions

MAX_ITERATIONS = 1000


def adjust_to_convergence(reconstruction: pycolmap.Reconstruction) -> int:
    """Adjust every registered pose and point in least squares until Ceres stops moving
    them; returns the number of steps."""
    config = pycolmap.BundleAdjustmentConfig()
    image_ids = sorted(reconstruction.reg_image_ids())
    for image_id in image_ids:
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    hold_rigs_and_fix_gauge(config, reconstruction, image_ids, set(), BundleAdjustmentOptions())
    options = pycolmap.BundleAdjustmentOptions(print_summary=False)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    solver = options.ceres.solver_options
    solver.max_num_iterations = MAX_ITERATIONS
    solver.function_tolerance = solver.gradient_tolerance = solver.parameter_tolerance = 0.0
    summary = pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    return summary.ceres_summary.num_successful_steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work_dir", type=Path)
    args = parser.parse_args(argv)
    print("| case | seed | mapper | observations | R_err max / median as written [deg] "
          "| steps | R_err max / median converged [deg] |\n|---|---|---|---|---|---|---|")
    for seed_folder in sorted(args.work_dir.glob("*/seed*")):
        truth_model = pycolmap.Reconstruction(seed_folder / "truth")
        truth = read_ground_truth(seed_folder / "truth")
        for model_folder in sorted(seed_folder.glob("runs/*/out/0")):
            model = pycolmap.Reconstruction(model_folder)
            written = measure(model, truth, truth_model)
            steps = adjust_to_convergence(model)
            converged = measure(model, truth, truth_model)
            print(f"| {seed_folder.parent.name} | {seed_folder.name[4:]} | "
                  f"{model_folder.parents[1].name} | {model.compute_num_observations()} | "
                  f"{written['R_err_max_deg']:.5f} / {written['R_err_median_deg']:.5f} | {steps} | "
                  f"{converged['R_err_max_deg']:.5f} / {converged['R_err_median_deg']:.5f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
