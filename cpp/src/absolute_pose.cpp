#include "absolute_pose.hpp"

#include <opengv/absolute_pose/CentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/NoncentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/methods.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::points_t;
using opengv::absolute_pose::CentralAbsoluteAdapter;
using opengv::absolute_pose::NoncentralAbsoluteAdapter;

// Least squares over the inliers' reprojection errors (see refinement.hpp) in normalized
// image units, in the rotation (exp(w) R) and the translation (t + u) of rig_from_world:
// 6 degrees of freedom. Observation i is made by camera camera_index[i] of the rig
// (x_cam = R_c (R X + t) + t_c); a single camera is a rig of one identity camera.
class ReprojectionRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  ReprojectionRefinement(const points_t& points, const std::vector<Eigen::Vector2d>& xy,
                         const std::vector<int>& camera_index, const Rig& rig,
                         const std::vector<int>& inliers, Pose* rig_from_world)
      : points_(points), xy_(xy), camera_index_(camera_index), rig_(rig), inliers_(inliers),
        pose_(*rig_from_world) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
      const Eigen::Vector3d RX = pose_.R * points_[i];
      const Eigen::Vector3d x = cam_from_rig.R * (RX + pose_.t) + cam_from_rig.t;
      const double inv_z = 1.0 / x.z();
      const Eigen::Vector2d r = x.head<2>() * inv_z - xy_[i];
      Eigen::Matrix<double, 2, 3> dproject;  // d(x/z, y/z)/dx
      dproject << inv_z, 0, -x.x() * inv_z * inv_z, 0, inv_z, -x.y() * inv_z * inv_z;
      const Eigen::Matrix<double, 2, 3> dproject_rig = dproject * cam_from_rig.R;
      Eigen::Matrix<double, 2, 6> J;
      J << dproject_rig * -skew(RX), dproject_rig;  // dx_rig/dw = -[R X]x, dx_rig/du = I
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
      const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
      const Eigen::Vector3d x = cam_from_rig.R * (pose.R * points_[i] + pose.t) + cam_from_rig.t;
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
  const std::vector<int>& camera_index_;
  const Rig& rig_;
  const std::vector<int>& inliers_;
  Pose& pose_;
};

// Whether cam_from_world sees world point X along unit ray f, to within kTolerance.
// OpenGV's P3P and GP3P also return poses from the real parts of complex roots (a third
// to half of their solutions): they fail this test on their own sample.
bool sees_along_ray(const Pose& cam_from_world, const Eigen::Vector3d& X, const Eigen::Vector3d& f) {
  constexpr double kTolerance = 1e-4;
  const Eigen::Vector3d x = cam_from_world.R * X + cam_from_world.t;
  return (x.normalized() - f.normalized()).norm() < kTolerance;
}

class AbsolutePoseEstimator {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  AbsolutePoseEstimator(const bearingVectors_t& rays, const points_t& points, P3PMethod method)
      : rays_(rays), points_(points), method_(method), xy_(normalized_coordinates(rays)),
        camera_index_(rays.size(), 0) {}

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
    ReprojectionRefinement problem(points_, xy_, camera_index_, kSingleCamera, inliers,
                                   cam_from_world);
    return levenberg_marquardt<6>(problem);
  }

 private:
  inline static const Rig kSingleCamera{{Pose()}};
  const bearingVectors_t& rays_;
  const points_t& points_;
  P3PMethod method_;
  std::vector<Eigen::Vector2d> xy_;  // normalized image coordinates; NaN if none
  std::vector<int> camera_index_;    // all 0: the one camera of kSingleCamera
};

// GP3P (OpenGV) inside LO-MSAC: rig_from_world from rays of several cameras of a rig.
class GeneralizedAbsolutePoseEstimator {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  GeneralizedAbsolutePoseEstimator(const bearingVectors_t& rays,
                                   const std::vector<int>& camera_index,
                                   const points_t& points, const Rig& rig)
      : rays_(rays), camera_index_(camera_index), points_(points), rig_(rig),
        xy_(normalized_coordinates(rays)) {}

  size_t num_data() const { return rays_.size(); }

  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    bearingVectors_t s_rays;
    std::vector<int> s_cameras;
    points_t s_points;
    for (int i : sample) {
      s_rays.push_back(rays_[i]);
      s_cameras.push_back(camera_index_[i]);
      s_points.push_back(points_[i]);
    }
    for (const Pose& pose : gp3p(s_rays, s_cameras, s_points, rig_)) models->push_back(pose);
  }

  // Reprojection error in the observing camera's normalized image units, as
  // AbsolutePoseEstimator's.
  double squared_error(const Model& rig_from_world, size_t i) const {
    const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
    const Eigen::Vector3d x =
        cam_from_rig.R * (rig_from_world.R * points_[i] + rig_from_world.t) + cam_from_rig.t;
    if (x.z() <= kMinRayZ) return std::numeric_limits<double>::infinity();
    return (x.head<2>() / x.z() - xy_[i]).squaredNorm();
  }

  bool refine(const std::vector<int>& inliers, Model* rig_from_world) const {
    ReprojectionRefinement problem(points_, xy_, camera_index_, rig_, inliers, rig_from_world);
    return levenberg_marquardt<6>(problem);
  }

 private:
  const bearingVectors_t& rays_;
  const std::vector<int>& camera_index_;
  const points_t& points_;
  const Rig& rig_;
  std::vector<Eigen::Vector2d> xy_;
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
    if (!T.allFinite()) continue;
    const Pose pose = from_opengv(T);
    bool fits = true;
    for (int i = 0; i < 3; ++i) fits &= sees_along_ray(pose, points[i], rays[i]);
    if (fits) poses.push_back(pose);
  }
  return poses;
}

std::vector<Pose> gp3p(const bearingVectors_t& rays, const std::vector<int>& camera_index,
                       const points_t& points, const Rig& rig) {
  const NoncentralAbsoluteAdapter adapter(rays, camera_index, points, rig.offsets, rig.rotations);
  std::vector<Pose> poses;
  for (const auto& T : opengv::absolute_pose::gp3p(adapter, {0, 1, 2})) {
    if (!T.allFinite()) continue;
    const Pose rig_from_world = from_opengv(T);
    bool fits = true;
    for (int i = 0; i < 3; ++i)
      fits &= sees_along_ray(compose(rig.cams_from_rig[camera_index[i]], rig_from_world),
                             points[i], rays[i]);
    if (fits) poses.push_back(rig_from_world);
  }
  return poses;
}

RansacResult<Pose> estimate_absolute_pose(const bearingVectors_t& rays, const points_t& points,
                                          P3PMethod method, const RansacOptions& options) {
  const AbsolutePoseEstimator estimator(rays, points, method);
  return ransac(estimator, options);
}

RansacResult<Pose> estimate_generalized_absolute_pose(const bearingVectors_t& rays,
                                                      const std::vector<int>& camera_index,
                                                      const points_t& points, const Rig& rig,
                                                      const RansacOptions& options) {
  const GeneralizedAbsolutePoseEstimator estimator(rays, camera_index, points, rig);
  return ransac(estimator, options);
}

}  // namespace colmap_ext
