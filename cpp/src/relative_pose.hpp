// Calibrated relative pose: 5-point minimal solvers (OpenGV) inside LO-MSAC, and the
// generalized (6-point, 5+1-point, 17-point) solvers for camera rigs.
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

// kSixPoint: OpenGV's 6-point solver (Stewenius). kFivePlusOne: OpenGV's 5-point solver
// on five pairs of one camera pair, the scale from a sixth of another (samples drawn so).
// kSeventeenPoint: OpenGV's linear 17-point solver (Li).
enum class GeneralizedRelativeMethod { kSixPoint, kFivePlusOne, kSeventeenPoint };

// Robust rig2_from_rig1 between two frames of one rig (metric translation: the rig's
// baseline fixes the scale) from ray pairs in any direction, ray i of camera cameras1[i]
// in frame 1 and of cameras2[i] in frame 2; max_errors[i] bounds pair i's angular Sampson
// error in its camera pair (radians). options.max_error is not read.
RansacResult<Pose> estimate_generalized_relative_pose(const opengv::bearingVectors_t& rays1,
                                                      const std::vector<int>& cameras1,
                                                      const opengv::bearingVectors_t& rays2,
                                                      const std::vector<int>& cameras2,
                                                      const Rig& rig,
                                                      const std::vector<double>& max_errors,
                                                      GeneralizedRelativeMethod method,
                                                      const RansacOptions& options);

}  // namespace colmap_ext
