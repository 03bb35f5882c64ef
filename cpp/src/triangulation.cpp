#include "triangulation.hpp"

#include <Eigen/Eigenvalues>
#include <cmath>

namespace colmap_ext {

TriangulationResult triangulate_tracks(const std::vector<Pose>& cams_from_world,
                                       const std::vector<Observation>& observations,
                                       int num_points, double min_angle_rad) {
  std::vector<Eigen::Matrix4d> normal_equations(num_points, Eigen::Matrix4d::Zero());
  std::vector<std::vector<int>> point_observations(num_points);
  for (size_t k = 0; k < observations.size(); ++k) {
    const Observation& obs = observations[k];
    const Pose& pose = cams_from_world[obs.view];
    Eigen::Matrix<double, 3, 4> P;
    P << pose.R, pose.t;
    const Eigen::Matrix3d reject = Eigen::Matrix3d::Identity() - obs.ray * obs.ray.transpose();
    normal_equations[obs.point] += P.transpose() * reject * P;
    point_observations[obs.point].push_back(static_cast<int>(k));
  }

  const double cos_min_angle = std::cos(min_angle_rad);
  TriangulationResult result;
  result.points.assign(num_points, Eigen::Vector3d::Constant(std::nan("")));
  result.valid.assign(num_points, 0);
  for (int p = 0; p < num_points; ++p) {
    if (point_observations[p].size() < 2) continue;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> eigen(normal_equations[p]);
    const Eigen::Vector4d X_h = eigen.eigenvectors().col(0);
    if (std::abs(X_h.w()) < 1e-12 * X_h.head<3>().norm()) continue;  // at infinity
    const Eigen::Vector3d X = X_h.head<3>() / X_h.w();
    if (!X.allFinite()) continue;
    result.points[p] = X;

    bool in_front = true;
    std::vector<Eigen::Vector3d> directions;  // world-frame viewing directions
    for (int k : point_observations[p]) {
      const Observation& obs = observations[k];
      const Pose& pose = cams_from_world[obs.view];
      const Eigen::Vector3d x_cam = pose.R * X + pose.t;
      in_front &= x_cam.dot(obs.ray) > 0;  // along its ray, whatever the ray's direction
      const Eigen::Vector3d centre = -pose.R.transpose() * pose.t;
      directions.push_back((X - centre).normalized());
    }
    double min_cos = 1.0;
    for (size_t a = 0; a < directions.size(); ++a)
      for (size_t b = a + 1; b < directions.size(); ++b)
        min_cos = std::min(min_cos, directions[a].dot(directions[b]));
    result.valid[p] = in_front && min_cos <= cos_min_angle;
  }
  return result;
}

}  // namespace colmap_ext
