#include "absolute_pose.hpp"

#include <limits>
#include <utility>

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

// The reprojection error of a point x (camera frame) seen along the unit ray f: the
// point's position on the plane tangent to the unit sphere at f, B^T x / (f . x), with B
// an orthonormal basis of that plane (two tangents of the angle between f and x). For
// rays in any direction; a point at 90 degrees or more from its ray never fits.
struct TangentFrame {
  Eigen::Vector3d f;
  Eigen::Matrix<double, 3, 2> B;
};

inline TangentFrame tangent_frame(const Eigen::Vector3d& f) {
  TangentFrame frame{f, {}};
  const Eigen::Vector3d a = f.unitOrthogonal();
  frame.B << a, f.cross(a);
  return frame;
}

// Depths along the ray at or below this never fit (the point is beside or behind it).
constexpr double kMinDepth = 1e-9;

// The point X of world observation i in its camera's frame: x_cam = R_c (R X + t) + t_c
// for rig_from_world (R, t) and the observing camera's cam_from_rig (R_c, t_c).
inline Eigen::Vector3d in_camera(const Pose& cam_from_rig, const Pose& rig_from_world,
                                 const Eigen::Vector3d& X) {
  return cam_from_rig.R * (rig_from_world.R * X + rig_from_world.t) + cam_from_rig.t;
}

// The squared tangent-plane reprojection error of x_cam, times weight^2; +inf beside or
// behind the ray.
inline double weighted_squared_error(const TangentFrame& frame, double weight,
                                     const Eigen::Vector3d& x_cam) {
  const double depth = frame.f.dot(x_cam);
  if (depth <= kMinDepth) return std::numeric_limits<double>::infinity();
  return weight * weight * (frame.B.transpose() * x_cam / depth).squaredNorm();
}

// Least squares over the inliers' tangent-plane reprojection errors (see refinement.hpp),
// each over its threshold, in the rotation (exp(w) R) and the translation (t + u) of
// rig_from_world: 6 degrees of freedom. Observation i is made by camera camera_index[i]
// of the rig; a single camera is a rig of one identity camera.
class ReprojectionRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  ReprojectionRefinement(const points_t& points, const std::vector<TangentFrame>& frames,
                         const std::vector<double>& weights, const std::vector<int>& camera_index,
                         const Rig& rig, const std::vector<int>& inliers, Pose* rig_from_world)
      : points_(points), frames_(frames), weights_(weights), camera_index_(camera_index),
        rig_(rig), inliers_(inliers), pose_(*rig_from_world) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      const TangentFrame& frame = frames_[i];
      const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
      const Eigen::Vector3d RX = pose_.R * points_[i];
      const Eigen::Vector3d x = cam_from_rig.R * (RX + pose_.t) + cam_from_rig.t;
      const double inv_depth = 1.0 / frame.f.dot(x);
      const Eigen::Vector2d r = frame.B.transpose() * x * inv_depth;
      // d(B^T x / f.x)/dx = (B^T - r f^T) / f.x, and dx = R_c dx_rig
      const Eigen::Matrix<double, 2, 3> dproject_rig =
          (frame.B.transpose() - r * frame.f.transpose()) * inv_depth * cam_from_rig.R;
      Eigen::Matrix<double, 2, 6> J;
      J << dproject_rig * -skew(RX), dproject_rig;  // dx_rig/dw = -[R X]x, dx_rig/du = I
      J *= weights_[i];
      *JtJ += J.transpose() * J;
      *Jtr += J.transpose() * (weights_[i] * r);
      cost += weights_[i] * weights_[i] * r.squaredNorm();
    }
    return cost;
  }

  double cost(const Vec& delta) const {
    const Pose pose = moved(delta);
    double cost = 0.0;
    for (int i : inliers_) {
      const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
      cost += weighted_squared_error(frames_[i], weights_[i],
                                     in_camera(cam_from_rig, pose, points_[i]));
    }
    return cost;
  }

  void commit(const Vec& delta) { pose_ = moved(delta); }

 private:
  Pose moved(const Vec& delta) const {
    return {rotate_by(delta.head<3>(), pose_.R), pose_.t + delta.tail<3>()};
  }

  const points_t& points_;
  const std::vector<TangentFrame>& frames_;
  const std::vector<double>& weights_;  // 1 / each observation's threshold
  const std::vector<int>& camera_index_;
  const Rig& rig_;
  const std::vector<int>& inliers_;
  Pose& pose_;
};

// Whether cam_from_world sees world point X along unit ray f, to within kTolerance.
// OpenGV's P3P and GP3P also return poses from the real parts of complex roots (a third
// to half of their solutions): they do not fit their own sample, or put points behind
// the camera.
bool sees_along_ray(const Pose& cam_from_world, const Eigen::Vector3d& X,
                    const Eigen::Vector3d& f) {
  constexpr double kTolerance = 1e-4;
  const Eigen::Vector3d x = cam_from_world.R * X + cam_from_world.t;
  return (x.normalized() - f.normalized()).norm() < kTolerance;
}

// What the P3P and GP3P estimators share: each observation's tangent-plane reprojection
// error through its rig camera, over its threshold, and its refinement. Subclasses add
// minimal_solve.
class RigReprojectionErrors {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  RigReprojectionErrors(const bearingVectors_t& rays, std::vector<int> camera_index,
                        const points_t& points, const Rig& rig,
                        const std::vector<double>& max_errors)
      : rays_(rays), camera_index_(std::move(camera_index)), points_(points), rig_(rig),
        weights_(weights_from_thresholds(max_errors)) {
    frames_.reserve(rays.size());
    for (const auto& f : rays) frames_.push_back(tangent_frame(f));
  }

  size_t num_data() const { return rays_.size(); }

  // The reprojection error over the observation's threshold, squared (inlier below 1);
  // a point beside or behind its ray never fits.
  double squared_error(const Model& rig_from_world, size_t i) const {
    const Pose& cam_from_rig = rig_.cams_from_rig[camera_index_[i]];
    return weighted_squared_error(frames_[i], weights_[i],
                                  in_camera(cam_from_rig, rig_from_world, points_[i]));
  }

  // Levenberg-Marquardt on the inliers' reprojection errors (6 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* rig_from_world) const {
    ReprojectionRefinement problem(points_, frames_, weights_, camera_index_, rig_, inliers,
                                   rig_from_world);
    return levenberg_marquardt<6>(problem);
  }

 protected:
  const bearingVectors_t& rays_;
  std::vector<int> camera_index_;  // the rig camera of each observation
  const points_t& points_;
  const Rig& rig_;
  std::vector<TangentFrame> frames_;
  std::vector<double> weights_;  // 1 / each observation's threshold
};

// P3P (OpenGV) inside LO-MSAC: cam_from_world of a single camera, a rig of one identity
// camera.
class AbsolutePoseEstimator : public RigReprojectionErrors {
 public:
  AbsolutePoseEstimator(const bearingVectors_t& rays, const points_t& points,
                        const std::vector<double>& max_errors, P3PMethod method)
      : RigReprojectionErrors(rays, std::vector<int>(rays.size(), 0), points, kSingleCamera,
                              max_errors),
        method_(method) {}

  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    bearingVectors_t s_rays;
    points_t s_points;
    for (int i : sample) {
      s_rays.push_back(rays_[i]);
      s_points.push_back(points_[i]);
    }
    for (const Pose& pose : p3p(s_rays, s_points, method_)) models->push_back(pose);
  }

 private:
  inline static const Rig kSingleCamera{{Pose()}};
  P3PMethod method_;
};

// GP3P (OpenGV) inside LO-MSAC: rig_from_world from rays of several cameras of a rig.
class GeneralizedAbsolutePoseEstimator : public RigReprojectionErrors {
 public:
  using RigReprojectionErrors::RigReprojectionErrors;

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
                                          const std::vector<double>& max_errors,
                                          P3PMethod method, RansacOptions options) {
  const AbsolutePoseEstimator estimator(rays, points, max_errors, method);
  options.max_error = 1.0;  // errors arrive divided by their thresholds
  return ransac(estimator, options);
}

RansacResult<Pose> estimate_generalized_absolute_pose(const bearingVectors_t& rays,
                                                      const std::vector<int>& camera_index,
                                                      const points_t& points, const Rig& rig,
                                                      const std::vector<double>& max_errors,
                                                      RansacOptions options) {
  const GeneralizedAbsolutePoseEstimator estimator(rays, camera_index, points, rig, max_errors);
  options.max_error = 1.0;  // errors arrive divided by their thresholds
  return ransac(estimator, options);
}

}  // namespace colmap_ext
