// Calibrated relative pose: 5-point minimal solvers (OpenGV) inside LO-MSAC.
#pragma once

#include <vector>

#include "geometry.hpp"
#include "ransac.hpp"

namespace colmap_ext {

enum class FivePointMethod { kNister, kStewenius };

// All essential matrices (COLMAP convention) consistent with exactly five ray pairs.
std::vector<Eigen::Matrix3d> five_point(const opengv::bearingVectors_t& rays1,
                                        const opengv::bearingVectors_t& rays2,
                                        FivePointMethod method);

// The cam2_from_cam1 among E's four decompositions that puts most of the given ray
// pairs in front of both cameras (unit translation).
Pose decompose_essential(const Eigen::Matrix3d& E, const opengv::bearingVectors_t& rays1,
                         const opengv::bearingVectors_t& rays2, const std::vector<int>& indices);

struct RelativePoseResult {
  RansacResult<Pose> ransac;
  Eigen::Matrix3d E = Eigen::Matrix3d::Zero();
};

// Robust cam2_from_cam1 from unit rays in any direction; max_errors[i] bounds pair i's
// angular Sampson error (radians). options.max_error is not read.
RelativePoseResult estimate_relative_pose(const opengv::bearingVectors_t& rays1,
                                          const opengv::bearingVectors_t& rays2,
                                          const std::vector<double>& max_errors,
                                          FivePointMethod method, RansacOptions options);

}  // namespace colmap_ext
