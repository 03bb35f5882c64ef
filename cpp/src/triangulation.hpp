// Linear multi-view triangulation of many points at once, from unit rays.
#pragma once

#include <vector>

#include "geometry.hpp"

namespace colmap_ext {

struct Observation {
  int view;   // index into cams_from_world
  int point;  // index of the point it observes
  Eigen::Vector3d ray;  // unit ray in the camera frame
};

struct TriangulationResult {
  std::vector<Eigen::Vector3d> points;
  std::vector<char> valid;  // in front of every observing camera, with a usable angle
};

// Each point minimises sum_v |(I - f f^T)(R_v X + t_v)|^2 over its observations: the
// distance of X's camera-frame position from each ray, linear in homogeneous X.
TriangulationResult triangulate_tracks(const std::vector<Pose>& cams_from_world,
                                       const std::vector<Observation>& observations,
                                       int num_points, double min_angle_rad);

}  // namespace colmap_ext
