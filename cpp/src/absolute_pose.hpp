// Calibrated absolute pose: P3P minimal solvers (OpenGV) inside LO-MSAC, and GP3P for
// camera rigs.
#pragma once

#include <vector>

#include "geometry.hpp"
#include "ransac.hpp"

namespace colmap_ext {

enum class P3PMethod { kKneip, kGao };

// All cam_from_world poses consistent with exactly three ray/point pairs.
std::vector<Pose> p3p(const opengv::bearingVectors_t& rays, const opengv::points_t& points,
                      P3PMethod method);

// Robust cam_from_world from unit rays in any direction and world points; max_errors[i]
// bounds observation i's reprojection error (tangent of the angle, about radians; see
// absolute_pose.cpp). options.max_error is not read.
RansacResult<Pose> estimate_absolute_pose(const opengv::bearingVectors_t& rays,
                                          const opengv::points_t& points,
                                          const std::vector<double>& max_errors,
                                          P3PMethod method, RansacOptions options);

// All rig_from_world poses consistent with exactly three ray/point pairs, ray i seen by
// camera camera_index[i] of the rig (OpenGV's GP3P; up to eight).
std::vector<Pose> gp3p(const opengv::bearingVectors_t& rays, const std::vector<int>& camera_index,
                       const opengv::points_t& points, const Rig& rig);

// Robust rig_from_world from unit rays of a rig's cameras, in any direction, and world
// points; max_errors[i] bounds observation i's reprojection error through its camera, as
// estimate_absolute_pose's. options.max_error is not read.
RansacResult<Pose> estimate_generalized_absolute_pose(const opengv::bearingVectors_t& rays,
                                                      const std::vector<int>& camera_index,
                                                      const opengv::points_t& points,
                                                      const Rig& rig,
                                                      const std::vector<double>& max_errors,
                                                      RansacOptions options);

}  // namespace colmap_ext
