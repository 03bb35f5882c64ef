#include "absolute_pose.hpp"

#include <opengv/absolute_pose/CentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/methods.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::points_t;
using opengv::absolute_pose::CentralAbsoluteAdapter;

// The reprojection error of a world point seen along the unit ray f: the point's
// position on the plane tangent to the unit sphere at f, B^T x / (f . x), with B an
// orthonormal basis of that plane (two tangents of the angle between f and x). For rays
// in any direction; a point at 90 degrees or more from its ray never fits.
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

// Least squares over the inliers' reprojection errors (see refinement.hpp), each over its
// threshold, in the rotation (exp(w) R) and the translation (t + u): 6 degrees of freedom.
class ReprojectionRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  ReprojectionRefinement(const points_t& points, const std::vector<TangentFrame>& frames,
                         const std::vector<double>& weights, const std::vector<int>& inliers,
                         Pose* cam_from_world)
      : points_(points), frames_(frames), weights_(weights), inliers_(inliers),
        pose_(*cam_from_world) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      const TangentFrame& frame = frames_[i];
      const Eigen::Vector3d RX = pose_.R * points_[i];
      const Eigen::Vector3d x = RX + pose_.t;
      const double inv_depth = 1.0 / frame.f.dot(x);
      const Eigen::Vector2d r = frame.B.transpose() * x * inv_depth;
      // d(B^T x / f.x)/dx = (B^T - r f^T) / f.x
      const Eigen::Matrix<double, 2, 3> dproject =
          (frame.B.transpose() - r * frame.f.transpose()) * inv_depth;
      Eigen::Matrix<double, 2, 6> J;
      J << dproject * -skew(RX), dproject;  // dx/dw = -[R X]x, dx/du = I
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
      const Eigen::Vector3d x = pose.R * points_[i] + pose.t;
      const double depth = frames_[i].f.dot(x);
      if (depth <= kMinDepth) return std::numeric_limits<double>::infinity();
      cost += weights_[i] * weights_[i] * (frames_[i].B.transpose() * x / depth).squaredNorm();
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
  const std::vector<int>& inliers_;
  Pose& pose_;
};

class AbsolutePoseEstimator {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  AbsolutePoseEstimator(const bearingVectors_t& rays, const points_t& points,
                        const std::vector<double>& max_errors, P3PMethod method)
      : rays_(rays), points_(points), method_(method), weights_(max_errors.size()) {
    frames_.reserve(rays.size());
    for (const auto& f : rays) frames_.push_back(tangent_frame(f));
    for (size_t i = 0; i < max_errors.size(); ++i) weights_[i] = 1.0 / max_errors[i];
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

  // The reprojection error over the observation's threshold, squared (inlier below 1);
  // a point beside or behind its ray never fits.
  double squared_error(const Model& cam_from_world, size_t i) const {
    const Eigen::Vector3d x = cam_from_world.R * points_[i] + cam_from_world.t;
    const double depth = frames_[i].f.dot(x);
    if (depth <= kMinDepth) return std::numeric_limits<double>::infinity();
    return weights_[i] * weights_[i] * (frames_[i].B.transpose() * x / depth).squaredNorm();
  }

  // Levenberg-Marquardt on the inliers' reprojection errors (6 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* cam_from_world) const {
    ReprojectionRefinement problem(points_, frames_, weights_, inliers, cam_from_world);
    return levenberg_marquardt<6>(problem);
  }

 private:
  const bearingVectors_t& rays_;
  const points_t& points_;
  P3PMethod method_;
  std::vector<TangentFrame> frames_;
  std::vector<double> weights_;  // 1 / each observation's threshold
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
                                          const std::vector<double>& max_errors,
                                          P3PMethod method, RansacOptions options) {
  const AbsolutePoseEstimator estimator(rays, points, max_errors, method);
  options.max_error = 1.0;  // errors arrive divided by their thresholds
  return ransac(estimator, options);
}

}  // namespace colmap_ext
