#include "absolute_pose.hpp"

#include <opengv/absolute_pose/CentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/methods.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::points_t;
using opengv::absolute_pose::CentralAbsoluteAdapter;

// Least squares over the inliers' reprojection errors (see refinement.hpp) in normalized
// image units, in the rotation (exp(w) R) and the translation (t + u): 6 degrees of freedom.
class ReprojectionRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  ReprojectionRefinement(const points_t& points, const std::vector<Eigen::Vector2d>& xy,
                         const std::vector<int>& inliers, Pose* cam_from_world)
      : points_(points), xy_(xy), inliers_(inliers), pose_(*cam_from_world) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      const Eigen::Vector3d RX = pose_.R * points_[i];
      const Eigen::Vector3d x = RX + pose_.t;
      const double inv_z = 1.0 / x.z();
      const Eigen::Vector2d r = x.head<2>() * inv_z - xy_[i];
      Eigen::Matrix<double, 2, 3> dproject;  // d(x/z, y/z)/dx
      dproject << inv_z, 0, -x.x() * inv_z * inv_z, 0, inv_z, -x.y() * inv_z * inv_z;
      Eigen::Matrix<double, 2, 6> J;
      J << dproject * -skew(RX), dproject;  // dx/dw = -[R X]x, dx/du = I
      *JtJ += J.transpose() * J;
      *Jtr += J.transpose() * r;
      cost += r.squaredNorm();
    }
    return cost;
  }

  double cost(const Vec& delta) const {
    const Pose pose = moved(delta);
    double cost = 0.0;
    for (int i : inliers_) {
      const Eigen::Vector3d x = pose.R * points_[i] + pose.t;
      cost += (x.head<2>() / x.z() - xy_[i]).squaredNorm();
    }
    return cost;
  }

  void commit(const Vec& delta) { pose_ = moved(delta); }

 private:
  Pose moved(const Vec& delta) const {
    return {rotate_by(delta.head<3>(), pose_.R), pose_.t + delta.tail<3>()};
  }

  const points_t& points_;
  const std::vector<Eigen::Vector2d>& xy_;
  const std::vector<int>& inliers_;
  Pose& pose_;
};

class AbsolutePoseEstimator {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  AbsolutePoseEstimator(const bearingVectors_t& rays, const points_t& points, P3PMethod method)
      : rays_(rays), points_(points), method_(method) {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    xy_.reserve(rays.size());
    for (const auto& f : rays)
      xy_.push_back(f.z() > kMinRayZ ? Eigen::Vector2d(f.head<2>() / f.z()) : Eigen::Vector2d(kNaN, kNaN));
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

  // Reprojection error in normalized image units; points behind the camera never fit,
  // nor do rays without normalized coordinates (NaN).
  double squared_error(const Model& cam_from_world, size_t i) const {
    const Eigen::Vector3d x = cam_from_world.R * points_[i] + cam_from_world.t;
    if (x.z() <= kMinRayZ) return std::numeric_limits<double>::infinity();
    return (x.head<2>() / x.z() - xy_[i]).squaredNorm();
  }

  // Levenberg-Marquardt on the inliers' reprojection errors (6 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* cam_from_world) const {
    ReprojectionRefinement problem(points_, xy_, inliers, cam_from_world);
    return levenberg_marquardt<6>(problem);
  }

 private:
  const bearingVectors_t& rays_;
  const points_t& points_;
  P3PMethod method_;
  std::vector<Eigen::Vector2d> xy_;  // normalized image coordinates; NaN if none
};

}  // namespace

std::vector<Pose> p3p(const bearingVectors_t& rays, const points_t& points, P3PMethod method) {
  CentralAbsoluteAdapter adapter(rays, points);
  const std::vector<int> indices = {0, 1, 2};
  const opengv::transformations_t solutions =
      method == P3PMethod::kKneip ? opengv::absolute_pose::p3p_kneip(adapter, indices)
                                  : opengv::absolute_pose::p3p_gao(adapter, indices);
  // OpenGV also returns poses from the real parts of complex roots (a third to half of
  // its solutions): they do not fit the three pairs, or put points behind the camera.
  // Keep the poses that see each point along its ray, to within kTolerance (unit rays).
  constexpr double kTolerance = 1e-4;
  std::vector<Pose> poses;
  for (const auto& T : solutions) {
    if (!T.allFinite()) continue;
    const Pose pose = from_opengv(T);
    bool fits = true;
    for (int i = 0; i < 3; ++i) {
      const Eigen::Vector3d x = pose.R * points[i] + pose.t;
      fits &= (x.normalized() - rays[i].normalized()).norm() < kTolerance;
    }
    if (fits) poses.push_back(pose);
  }
  return poses;
}

RansacResult<Pose> estimate_absolute_pose(const bearingVectors_t& rays, const points_t& points,
                                          P3PMethod method, const RansacOptions& options) {
  const AbsolutePoseEstimator estimator(rays, points, method);
  return ransac(estimator, options);
}

}  // namespace colmap_ext
