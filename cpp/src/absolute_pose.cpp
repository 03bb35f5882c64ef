#include "absolute_pose.hpp"

#include <limits>
#include <utility>

#include <opengv/absolute_pose/CentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/NoncentralAbsoluteAdapter.hpp>
#include <opengv/absolute_pose/methods.hpp>
#include <opengv/absolute_pose/modules/main.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::points_t;
using opengv::absolute_pose::NoncentralAbsoluteAdapter;

// The reprojection error of a point x seen along the unit ray f: the point's offset on
// the plane tangent to the unit sphere at f, |f x x| / (f . x) (the tangent of the angle
// between f and x). For rays in any direction; a point at 90 degrees or more from its ray
// never fits. The error turns with the frame, so that of x_cam = R_c x_rig + t_c along a
// rig camera's ray f is that of x_rig - o along R_c^T f, o the camera's centre in the rig:
// every observation is scored in the rig's frame, against rig_from_world alone.
//
// The observations in the rig's frame are held a column per coordinate (each contiguous,
// so that scoring vectorises): world point, ray, an orthonormal basis of the tangent plane
// (the refinement's residual), centre of the observing camera, and the weight 1 / threshold.
enum Column { kX, kRay = 3, kTangent1 = 6, kTangent2 = 9, kCentre = 12, kWeight = 15, kColumns };

// Depths along the ray at or below this never fit (the point is beside or behind it).
constexpr double kMinDepth = 1e-9;

// The squared errors over their thresholds of observations begin..end-1, into errors[0..]
// (+inf beside or behind the ray), from the columns of `rows` observations in `data`
// (column-major), given rig_from_world's R (row-major) and t in pose[0..8], pose[9..11].
// kOffCentre: some camera's centre is not the rig's (a single camera's always is). Compiled for
// AVX2 as well, chosen where the processor has it: four points an instruction instead of
// SSE2's two, and no FMA, so that the errors are the same to the bit on every processor.
template <bool kOffCentre>
__attribute__((target_clones("avx2", "default")))
void tangent_squared_errors(const double* data, size_t rows, const double* pose, size_t begin,
                            size_t end, double* __restrict errors) {
  const double *X = data + kX * rows, *Y = X + rows, *Z = Y + rows, *fx = data + kRay * rows,
               *fy = fx + rows, *fz = fy + rows, *ox = data + kCentre * rows, *oy = ox + rows,
               *oz = oy + rows, *weight = data + kWeight * rows;
  const double r00 = pose[0], r01 = pose[1], r02 = pose[2], r10 = pose[3], r11 = pose[4],
               r12 = pose[5], r20 = pose[6], r21 = pose[7], r22 = pose[8], t0 = pose[9],
               t1 = pose[10], t2 = pose[11];
  for (size_t i = begin; i < end; ++i) {
    double x = r00 * X[i] + r01 * Y[i] + r02 * Z[i] + t0;
    double y = r10 * X[i] + r11 * Y[i] + r12 * Z[i] + t1;
    double z = r20 * X[i] + r21 * Y[i] + r22 * Z[i] + t2;
    if constexpr (kOffCentre) {
      x -= ox[i];
      y -= oy[i];
      z -= oz[i];
    }
    const double depth = fx[i] * x + fy[i] * y + fz[i] * z;
    const double cx = fy[i] * z - fz[i] * y, cy = fz[i] * x - fx[i] * z, cz = fx[i] * y - fy[i] * x;
    const double error = weight[i] * weight[i] * (cx * cx + cy * cy + cz * cz) / (depth * depth);
    errors[i - begin] = depth > kMinDepth ? error : std::numeric_limits<double>::infinity();
  }
}

class RigFrameObservations {
 public:
  RigFrameObservations(const bearingVectors_t& rays, const std::vector<int>& camera_index,
                       const points_t& points, const Rig& rig,
                       const std::vector<double>& max_errors)
      : data_(rays.size(), kColumns), centred_(true) {
    for (size_t i = 0; i < rays.size(); ++i) {
      const Pose rig_from_cam = inverse(rig.cams_from_rig[camera_index[i]]);
      centred_ &= rig_from_cam.t.isZero(0.0);
      const Eigen::Vector3d ray = rig_from_cam.R * rays[i];
      const Eigen::Vector3d tangent = ray.unitOrthogonal();
      data_.row(i) << points[i].transpose(), ray.transpose(), tangent.transpose(),
          ray.cross(tangent).transpose(), rig_from_cam.t.transpose(), 1.0 / max_errors[i];
    }
  }

  size_t size() const { return static_cast<size_t>(data_.rows()); }

  // The squared errors over their thresholds of observations begin..end-1 given
  // rig_from_world, into errors[0..]: +inf beside or behind the ray.
  void squared_errors(const Pose& rig_from_world, size_t begin, size_t end,
                      double* errors) const {
    if (centred_) {
      squared_errors<false>(rig_from_world, begin, end, errors);
    } else {
      squared_errors<true>(rig_from_world, begin, end, errors);
    }
  }

  Eigen::Vector3d point(int i) const { return data_.row(i).segment<3>(kX); }
  Eigen::Vector3d ray(int i) const { return data_.row(i).segment<3>(kRay); }
  Eigen::Matrix<double, 2, 3> tangents(int i) const {  // the basis as rows
    Eigen::Matrix<double, 2, 3> B;
    B << data_.row(i).segment<3>(kTangent1), data_.row(i).segment<3>(kTangent2);
    return B;
  }
  Eigen::Vector3d centre(int i) const { return data_.row(i).segment<3>(kCentre); }
  double weight(int i) const { return data_(i, kWeight); }

 private:
  template <bool kOffCentre>
  void squared_errors(const Pose& rig_from_world, size_t begin, size_t end,
                      double* errors) const {
    const Eigen::Matrix3d& R = rig_from_world.R;
    const Eigen::Vector3d& t = rig_from_world.t;
    const double pose[12] = {R(0, 0), R(0, 1), R(0, 2), R(1, 0), R(1, 1), R(1, 2),
                             R(2, 0), R(2, 1), R(2, 2), t.x(),   t.y(),   t.z()};
    tangent_squared_errors<kOffCentre>(data_.data(), static_cast<size_t>(data_.rows()), pose,
                                       begin, end, errors);
  }

  Eigen::Matrix<double, Eigen::Dynamic, kColumns> data_;  // column-major
  bool centred_;  // every camera's centre is the rig's
};

// Least squares over the inliers' reprojection errors over their thresholds (see
// refinement.hpp), the residual B^T x / (f . x) in the rig's frame (B the tangent basis: the
// error's two components), in the rotation (exp(w) R) and the translation (t + u) of
// rig_from_world: 6 degrees of freedom.
class ReprojectionRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  ReprojectionRefinement(const RigFrameObservations& observations,
                         const std::vector<int>& inliers, Pose* rig_from_world)
      : observations_(observations), inliers_(inliers), pose_(*rig_from_world) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    Mat H = Mat::Zero();  // locals: kept in registers, not stored point by point
    Vec g = Vec::Zero();
    double cost = 0.0;
    for (int i : inliers_) {
      const Eigen::Vector3d RX = pose_.R * observations_.point(i);
      const Eigen::Vector3d x = RX + pose_.t - observations_.centre(i);
      const Eigen::Vector3d f = observations_.ray(i);
      const Eigen::Matrix<double, 2, 3> B = observations_.tangents(i);
      const double inv_depth = 1.0 / f.dot(x);
      const double scale = observations_.weight(i) * inv_depth;
      const Eigen::Vector2d r = scale * (B * x);  // weighted residual
      // d(w B^T x / f.x)/dx = (w B^T - r f^T) / f.x; dx/dw = -[R X]x, dx/du = I, and
      // a^T (-[v]x) = (v x a)^T.
      const Eigen::Matrix<double, 2, 3> A = scale * B - (inv_depth * r) * f.transpose();
      Eigen::Matrix<double, 6, 2> Jt;  // J^T
      Jt << RX.cross(A.row(0).transpose()), RX.cross(A.row(1).transpose()), A.transpose();
      H.noalias() += Jt * Jt.transpose();
      g.noalias() += Jt * r;
      cost += r.squaredNorm();
    }
    *JtJ = H;
    *Jtr = g;
    return cost;
  }

  double cost(const Vec& delta) const {
    const Pose pose = moved(delta);
    double cost = 0.0;
    for (int i : inliers_) cost += residual(i, pose.R * observations_.point(i) + pose.t).squaredNorm();
    return cost;
  }

  void commit(const Vec& delta) { pose_ = moved(delta); }

 private:
  Pose moved(const Vec& delta) const {
    return {rotate_by(delta.head<3>(), pose_.R), pose_.t + delta.tail<3>()};
  }

  // Observation i's weighted residual, x_rig its point in the rig's frame: +inf beside or
  // behind the ray.
  Eigen::Vector2d residual(int i, const Eigen::Vector3d& x_rig) const {
    const Eigen::Vector3d x = x_rig - observations_.centre(i);
    const double depth = observations_.ray(i).dot(x);
    if (depth <= kMinDepth)
      return Eigen::Vector2d::Constant(std::numeric_limits<double>::infinity());
    return observations_.weight(i) / depth * (observations_.tangents(i) * x);
  }

  const RigFrameObservations& observations_;
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

// What the P3P and GP3P estimators share: each observation's reprojection error over its
// threshold, in the rig's frame, and its refinement. Subclasses add minimal_solve.
class RigReprojectionErrors {
 public:
  using Model = Pose;
  static constexpr int kSampleSize = 3;

  RigReprojectionErrors(const bearingVectors_t& rays, std::vector<int> camera_index,
                        const points_t& points, const Rig& rig,
                        const std::vector<double>& max_errors)
      : rays_(rays), camera_index_(std::move(camera_index)), points_(points), rig_(rig),
        observations_(rays, camera_index_, points, rig, max_errors) {}

  size_t num_data() const { return rays_.size(); }

  // The reprojection errors over the observations' thresholds, squared (inlier below 1);
  // a point beside or behind its ray never fits.
  void squared_errors(const Model& rig_from_world, size_t begin, size_t end,
                      double* errors) const {
    observations_.squared_errors(rig_from_world, begin, end, errors);
  }

  // Levenberg-Marquardt on the inliers' reprojection errors (6 degrees of freedom).
  RefinementStatus refine(const std::vector<int>& inliers, Model* rig_from_world,
                          int max_iterations) const {
    ReprojectionRefinement problem(observations_, inliers, rig_from_world);
    return levenberg_marquardt<6>(problem, max_iterations);
  }

 protected:
  const bearingVectors_t& rays_;
  std::vector<int> camera_index_;  // the rig camera of each observation
  const points_t& points_;
  const Rig& rig_;
  RigFrameObservations observations_;
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
    bearingVectors_t s_rays(kSampleSize);
    points_t s_points(kSampleSize);
    for (int k = 0; k < kSampleSize; ++k) {
      s_rays[k] = rays_[sample[k]];
      s_points[k] = points_[sample[k]];
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
  // OpenGV's solvers themselves: its p3p_kneip and p3p_gao only copy three rays and points
  // out of an adapter into new vectors first.
  opengv::transformations_t solutions;
  if (method == P3PMethod::kKneip) {
    opengv::absolute_pose::modules::p3p_kneip_main(rays, points, solutions);
  } else {
    opengv::absolute_pose::modules::p3p_gao_main(rays, points, solutions);
  }
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
