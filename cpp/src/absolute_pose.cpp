#include "absolute_pose.hpp"

#include <opengv/absolute_pose/CentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/methods.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::points_t;
using opengv::absolute_pose::CentralAbsoluteAdapter;

class AbsolutePoseEstimator {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  AbsolutePoseEstimator(const bearingVectors_t& rays, const points_t& points, P3PMethod method)
      : rays_(rays), points_(points), method_(method) {
    xy_.reserve(rays.size());
    for (const auto& f : rays) xy_.push_back(f.head<2>() / f.z());
  }

  size_t num_data() const { return rays_.size(); }

  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    bearingVectors_t s_rays;
    points_t s_points;
    for (int i : sample) {
      s_rays.push_back(rays_[i]);
      s_points.push_back(points_[i]);
    }
    for (const Pose& pose : p3p(s_rays, s_points, method_)) models->push_back(pose);
  }

  // Reprojection error in normalized image units; points behind the camera never fit.
  double squared_error(const Model& cam_from_world, size_t i) const {
    const Eigen::Vector3d x = cam_from_world.R * points_[i] + cam_from_world.t;
    if (x.z() <= kMinRayZ || rays_[i].z() <= kMinRayZ) return std::numeric_limits<double>::infinity();
    return (x.head<2>() / x.z() - xy_[i]).squaredNorm();
  }

  // Levenberg-Marquardt on the inliers' reprojection errors (6 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* cam_from_world) const {
    Pose& pose = *cam_from_world;
    const auto moved = [&](const Eigen::Matrix<double, 6, 1>& delta) {
      return Pose{rotate_by(delta.head<3>(), pose.R), pose.t + delta.tail<3>()};
    };
    const auto residuals = [&](const Eigen::Matrix<double, 6, 1>& delta, Eigen::VectorXd* r) {
      const Pose candidate = moved(delta);
      r->resize(2 * inliers.size());
      for (size_t k = 0; k < inliers.size(); ++k) {
        const Eigen::Vector3d x = candidate.R * points_[inliers[k]] + candidate.t;
        r->segment<2>(2 * k) = x.head<2>() / x.z() - xy_[inliers[k]];
      }
    };
    const auto commit = [&](const Eigen::Matrix<double, 6, 1>& delta) { pose = moved(delta); };
    return levenberg_marquardt<6>(residuals, commit);
  }

 private:
  const bearingVectors_t& rays_;
  const points_t& points_;
  P3PMethod method_;
  std::vector<Eigen::Vector2d> xy_;  // normalized image coordinates
};

}  // namespace

std::vector<Pose> p3p(const bearingVectors_t& rays, const points_t& points, P3PMethod method) {
  CentralAbsoluteAdapter adapter(rays, points);
  const std::vector<int> indices = {0, 1, 2};
  const opengv::transformations_t solutions =
      method == P3PMethod::kKneip ? opengv::absolute_pose::p3p_kneip(adapter, indices)
                                  : opengv::absolute_pose::p3p_gao(adapter, indices);
  std::vector<Pose> poses;
  for (const auto& T : solutions) {
    if (T.allFinite()) poses.push_back(from_opengv(T));
  }
  return poses;
}

RansacResult<Pose> estimate_absolute_pose(const bearingVectors_t& rays, const points_t& points,
                                          P3PMethod method, const RansacOptions& options) {
  const AbsolutePoseEstimator estimator(rays, points, method);
  return ransac(estimator, options);
}

}  // namespace colmap_ext
