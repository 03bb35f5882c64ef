// Bundle adjustment of rig frame poses and points with the intrinsics held constant:
// Levenberg-Marquardt on the Schur complement of the points, as Ceres's DENSE_SCHUR and
// SPARSE_SCHUR, with its robust losses and stopping rules, on calibrated rays.
#pragma once

#include <vector>

#include "geometry.hpp"

namespace colmap_ext {

enum class Loss { kTrivial, kCauchy, kHuber, kSoftL1 };

struct BundleObservation {
  int image;  // index into the images' sensor_from_rig and frame
  int point;  // index into the points
  Eigen::Vector3d ray;  // unit ray of the keypoint, in the camera frame
  // Pixels per unit of the plane tangent to the ray at unit distance (2x3, rows: image
  // x and y): the camera model's Jacobian there, so that the residual is the
  // reprojection error in pixels to first order, for every camera model.
  Eigen::Matrix<double, 2, 3> pixels_from_tangent;
};

struct BundleOptions {
  Loss loss = Loss::kTrivial;
  double loss_scale = 1.0;  // pixels
  int max_iterations = 50;
  double gradient_tolerance = 1.0;
  double function_tolerance = 0.0;
  double max_step_scale = 16.0;  // largest multiple of an accepted step tried (1: none)
  double initial_trust_region_radius = 1e4;  // Ceres's: the first step's damping is its inverse
  int num_threads = 1;  // threads for the residuals and the Schur complement
};

struct BundleSummary {
  int iterations = 0;  // successful and unsuccessful steps, as Ceres counts them
  double initial_cost = 0.0;
  double final_cost = 0.0;
  bool usable = false;
};

// Adjust `rigs_from_world` (the frames' poses) where `free_parameters` (6 per frame:
// rotation, then translation) says so, and the points where `point_variable`. Image i
// sees through sensors_from_rig[i] (constant) of frame image_frame[i].
BundleSummary bundle_adjust(std::vector<Pose>& rigs_from_world,
                            const std::vector<Eigen::Matrix<bool, 6, 1>>& free_parameters,
                            const std::vector<Pose>& sensors_from_rig,
                            const std::vector<int>& image_frame,
                            std::vector<Eigen::Vector3d>& points,
                            const std::vector<char>& point_variable,
                            const std::vector<BundleObservation>& observations,
                            const BundleOptions& options);

}  // namespace colmap_ext
