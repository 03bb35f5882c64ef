"""How far each mapper's model is from the least-squares optimum of its own observations:
every model a neutral.py run wrote, measured as written and again after a global
adjustment in least squares run to convergence (bundle_adjustment.adjust_reconstruction:
Ceres's function tolerance 0, at most 1000 iterations, the intrinsics and the rigs held,
the gauge fixed). A model already at its optimum does not move; one whose last adjustment
stopped early does. Where two mappers' models differ, this tells a difference in their
observations from one in where their adjustments stopped.

    python benchmarks/converged_adjustment.py WORK_DIR   (neutral.py's --work_dir)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np  # before pycolmap (README, "Known problem")
import pycolmap

from neutral import LEAST_SQUARES_TO_CONVERGENCE, measure

from colmap_ext.ground_truth import read_ground_truth
from colmap_ext.mapper.bundle_adjustment import adjust_reconstruction


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work_dir", type=Path)
    args = parser.parse_args(argv)
    print("| case | seed | mapper | observations | R_err max / median as written [deg] "
          "| converged [deg] |\n|---|---|---|---|---|---|")
    for seed_folder in sorted(args.work_dir.glob("*/seed*")):
        truth_model = pycolmap.Reconstruction(seed_folder / "truth")
        truth = read_ground_truth(seed_folder / "truth")
        for model_folder in sorted(seed_folder.glob("runs/*/out/0")):
            model = pycolmap.Reconstruction(model_folder)
            written = measure(model, truth, truth_model)
            adjust_reconstruction(model, LEAST_SQUARES_TO_CONVERGENCE, num_threads=1)
            converged = measure(model, truth, truth_model)
            print(f"| {seed_folder.parent.name} | {seed_folder.name[4:]} | "
                  f"{model_folder.parents[1].name} | {model.compute_num_observations()} | "
                  f"{written['R_err_max_deg']:.5f} / {written['R_err_median_deg']:.5f} | "
                  f"{converged['R_err_max_deg']:.5f} / {converged['R_err_median_deg']:.5f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
