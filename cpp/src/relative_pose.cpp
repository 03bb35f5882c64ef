#include "relative_pose.hpp"

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <opengv/relative_pose/modules/main.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;

// The null space of the five epipolar constraints f1^T E f2 = 0 (OpenGV's E, row-major
// in 9-vectors): the input of OpenGV's 5-point solvers. A fixed-size QR here instead of
// the dynamic-size SVD inside opengv::relative_pose::fivept_nister/_stewenius.
Eigen::Matrix<double, 9, 4> epipolar_null_space(const bearingVectors_t& rays1,
                                                const bearingVectors_t& rays2, const int* indices) {
  Eigen::Matrix<double, 9, 5> constraints;
  for (int k = 0; k < 5; ++k) {
    const Eigen::Vector3d& f1 = rays1[indices[k]];
    const Eigen::Vector3d& f2 = rays2[indices[k]];
    for (int r = 0; r < 3; ++r) constraints.col(k).segment<3>(3 * r) = f1[r] * f2;
  }
  const Eigen::HouseholderQR<Eigen::Matrix<double, 9, 5>> qr(constraints);
  Eigen::Matrix<double, 9, 4> last_columns = Eigen::Matrix<double, 9, 4>::Zero();
  last_columns.bottomRows<4>().setIdentity();
  return qr.householderQ() * last_columns;  // Q's last 4 columns: orthogonal to the constraints
}

// Whether a unit-norm E satisfies the essential-matrix constraint 2 E E^T E = tr(E E^T) E.
// OpenGV's Nister solver returns an inaccurate root in a few percent of cases (its
// Sturm bracketing and polishing); such matrices are not essential and are dropped.
bool is_essential(const Eigen::Matrix3d& E) {
  constexpr double kTolerance = 1e-3;
  const Eigen::Matrix3d EEt = E * E.transpose();
  return (2 * EEt * E - EEt.trace() * E).cwiseAbs().maxCoeff() < kTolerance;
}

// Essential matrices in COLMAP's convention, unit Frobenius norm, from the null space.
void five_point_from_null_space(const Eigen::Matrix<double, 9, 4>& null_space,
                                FivePointMethod method, std::vector<Eigen::Matrix3d>* essentials) {
  const auto add = [&](const Eigen::Matrix3d& E_opengv) {
    const Eigen::Matrix3d E = E_opengv.transpose() / E_opengv.norm();
    if (E.allFinite() && is_essential(E)) essentials->push_back(E);
  };
  if (method == FivePointMethod::kNister) {
    opengv::essentials_t solutions;
    opengv::relative_pose::modules::fivept_nister_main(null_space, solutions);
    for (const auto& E : solutions) add(E);
  } else {
    opengv::complexEssentials_t solutions;
    opengv::relative_pose::modules::fivept_stewenius_main(null_space, solutions);
    for (const auto& E : solutions) {
      if (E.imag().norm() <= 1e-8 * E.real().norm()) add(E.real());  // else a complex root
    }
  }
}

// Whether one of E's decompositions can put every sample pair in front of both cameras
// (a necessary condition). For E = [t]x R and a pair at depths l1, l2 (l2 f2 = l1 R f1 + t),
// (t x f2) . (E f1) = (l1 / l2) |t x R f1|^2 up to a sign shared by all pairs: pairs whose
// depths differ in sign, which no decomposition puts in front together, differ in sign
// here. Needs no decomposition, and unlike a triangulated depth it stays reliable for
// distant points (l1 / l2 near 1).
bool twisted_pair_consistent(const Eigen::Matrix3d& E, const bearingVectors_t& rays1,
                             const bearingVectors_t& rays2, const int* indices, int count) {
  // The epipole t (t^T E = 0) is orthogonal to every column of E.
  const Eigen::Vector3d candidates[3] = {E.col(0).cross(E.col(1)), E.col(1).cross(E.col(2)),
                                         E.col(2).cross(E.col(0))};
  const Eigen::Vector3d* t = &candidates[0];
  for (const Eigen::Vector3d& c : candidates)
    if (c.squaredNorm() > t->squaredNorm()) t = &c;
  bool positive = false, negative = false;
  for (int k = 0; k < count; ++k) {
    const double s = t->cross(rays2[indices[k]]).dot(E * rays1[indices[k]]);
    positive |= s > 0;
    negative |= s < 0;
  }
  return !(positive && negative);
}

// Whether the midpoint triangulation of a ray pair lies in front of both cameras: the
// depths (l1, l2) minimising |l1 f1 - (l2 g + c2)| in camera 1's frame (g = R^T f2, c2 the
// centre of camera 2), by Cramer's rule on the 2x2 normal equations.
bool in_front(const Pose& cam2_from_cam1, const Eigen::Vector3d& f1, const Eigen::Vector3d& f2) {
  const Eigen::Vector3d c2 = -cam2_from_cam1.R.transpose() * cam2_from_cam1.t;
  const Eigen::Vector3d g = cam2_from_cam1.R.transpose() * f2;
  const double ff = f1.squaredNorm(), gg = g.squaredNorm(), fg = f1.dot(g);
  const double fc = f1.dot(c2), gc = g.dot(c2);
  const double det = ff * gg - fg * fg;  // >= 0; 0 for parallel rays
  return det > 0 && gg * fc - fg * gc > 0 && fg * fc - ff * gc > 0;
}

// The angular Sampson error of a pair of unit rays is c / sqrt(d): c = f2^T E f1, and
// d = |g1|^2 + |g2|^2 with g1 = E^T f2 - c f1 and g2 = E f1 - c f2 the gradients of c
// within the tangent planes of f1 and f2. To first order, the angle (radians) by which the
// rays must turn to meet; it holds for rays in any direction, behind the image plane too.
struct SampsonTerms {
  Eigen::Vector3d g1, g2;
  double c, d;
};

inline SampsonTerms sampson_terms(const Eigen::Matrix3d& E, const Eigen::Vector3d& f1,
                                  const Eigen::Vector3d& f2) {
  SampsonTerms s;
  s.g2 = E * f1;
  s.g1 = E.transpose() * f2;
  s.c = f2.dot(s.g2);
  s.g2 -= s.c * f2;
  s.g1 -= s.c * f1;
  s.d = s.g1.squaredNorm() + s.g2.squaredNorm();
  return s;
}

// Least squares over the inliers' Sampson errors (see refinement.hpp), in the rotation
// (exp(w) R) and the direction of translation (t + B u, renormalized, with B a basis
// of the plane orthogonal to t): 5 degrees of freedom.
class SampsonRefinement {
 public:
  using Vec = Eigen::Matrix<double, 5, 1>;
  using Mat = Eigen::Matrix<double, 5, 5>;

  SampsonRefinement(const bearingVectors_t& rays1, const bearingVectors_t& rays2,
                    const std::vector<double>& weights, const std::vector<int>& inliers,
                    Pose* cam2_from_cam1)
      : rays1_(rays1), rays2_(rays2), weights_(weights), inliers_(inliers), pose_(*cam2_from_cam1) {
    update_tangent();
  }

  double linearize(Mat* JtJ, Vec* Jtr) const {
    const Eigen::Matrix3d E = essential_from_pose(pose_);
    Eigen::Matrix3d dE[5];  // derivatives of E = [t]x R along the 5 parameters
    for (int k = 0; k < 3; ++k) dE[k] = skew(pose_.t) * skew(Eigen::Vector3d::Unit(k)) * pose_.R;
    for (int k = 0; k < 2; ++k) dE[3 + k] = skew(tangent_.col(k)) * pose_.R;
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      const Eigen::Vector3d& f1 = rays1_[i];
      const Eigen::Vector3d& f2 = rays2_[i];
      const SampsonTerms s = sampson_terms(E, f1, f2);
      const double inv_sqrt_d = 1.0 / std::sqrt(s.d);
      const double r = s.c * inv_sqrt_d;
      // dr/dE = f2 f1^T / sqrt(d) - (r / d) (g2 f1^T + f2 g1^T)
      const double k = r * inv_sqrt_d * inv_sqrt_d;
      const Eigen::Matrix3d G = inv_sqrt_d * f2 * f1.transpose() -
                                k * (s.g2 * f1.transpose() + f2 * s.g1.transpose());
      Vec J;
      for (int p = 0; p < 5; ++p) J[p] = weights_[i] * G.cwiseProduct(dE[p]).sum();
      *JtJ += J * J.transpose();
      *Jtr += weights_[i] * r * J;
      cost += weights_[i] * weights_[i] * r * r;
    }
    return cost;
  }

  double cost(const Vec& delta) const {
    const Eigen::Matrix3d E = essential_from_pose(moved(delta));
    double cost = 0.0;
    for (int i : inliers_) {
      const SampsonTerms s = sampson_terms(E, rays1_[i], rays2_[i]);
      cost += weights_[i] * weights_[i] * s.c * s.c / s.d;
    }
    return cost;
  }

  void commit(const Vec& delta) {
    pose_ = moved(delta);
    update_tangent();
  }

 private:
  Pose moved(const Vec& delta) const {
    return {rotate_by(delta.head<3>(), pose_.R), (pose_.t + tangent_ * delta.tail<2>()).normalized()};
  }

  void update_tangent() {
    const Eigen::Vector3d a = pose_.t.unitOrthogonal();
    tangent_ << a, pose_.t.cross(a);
  }

  const bearingVectors_t& rays1_;
  const bearingVectors_t& rays2_;
  const std::vector<double>& weights_;  // 1 / each pair's threshold
  const std::vector<int>& inliers_;
  Pose& pose_;
  Eigen::Matrix<double, 3, 2> tangent_;
};

// E with a pose: during sampling only E is known; refine() decomposes it once.
struct RelativeModel {
  Eigen::Matrix3d E = Eigen::Matrix3d::Zero();
  Pose pose;
  bool has_pose = false;
};

class RelativePoseEstimator {
 public:
  using Model = RelativeModel;
  static constexpr int kSampleSize = 5;

  RelativePoseEstimator(const bearingVectors_t& rays1, const bearingVectors_t& rays2,
                        const std::vector<double>& max_errors, FivePointMethod method)
      : rays1_(rays1), rays2_(rays2), method_(method), weights_(max_errors.size()) {
    for (size_t i = 0; i < max_errors.size(); ++i) weights_[i] = 1.0 / max_errors[i];
  }

  size_t num_data() const { return rays1_.size(); }

  // OpenGV's 5-point solutions, less those that cannot put all five pairs in front.
  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    std::vector<Eigen::Matrix3d> essentials;
    five_point_from_null_space(epipolar_null_space(rays1_, rays2_, sample.data()), method_,
                               &essentials);
    for (const Eigen::Matrix3d& E : essentials) {
      if (twisted_pair_consistent(E, rays1_, rays2_, sample.data(), kSampleSize))
        models->push_back({E, {}, false});
    }
  }

  // The angular Sampson error over the pair's threshold, squared (inlier below 1).
  double squared_error(const Model& model, size_t i) const {
    const SampsonTerms s = sampson_terms(model.E, rays1_[i], rays2_[i]);
    return weights_[i] * weights_[i] * s.c * s.c / s.d;
  }

  // Levenberg-Marquardt on the inliers' Sampson errors (5 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* model) const {
    if (!model->has_pose) {
      model->pose = decompose_essential(model->E, rays1_, rays2_, inliers);
      model->has_pose = true;
    }
    SampsonRefinement problem(rays1_, rays2_, weights_, inliers, &model->pose);
    if (!levenberg_marquardt<5>(problem)) return false;
    model->E = essential_from_pose(model->pose);
    return true;
  }

 private:
  const bearingVectors_t& rays1_;
  const bearingVectors_t& rays2_;
  FivePointMethod method_;
  std::vector<double> weights_;  // 1 / each pair's threshold
};

}  // namespace

std::vector<Eigen::Matrix3d> five_point(const bearingVectors_t& rays1,
                                        const bearingVectors_t& rays2, FivePointMethod method) {
  const int indices[5] = {0, 1, 2, 3, 4};
  std::vector<Eigen::Matrix3d> essentials;
  five_point_from_null_space(epipolar_null_space(rays1, rays2, indices), method, &essentials);
  return essentials;
}

Pose decompose_essential(const Eigen::Matrix3d& E, const bearingVectors_t& rays1,
                         const bearingVectors_t& rays2, const std::vector<int>& indices) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(E, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d U = svd.matrixU();
  Eigen::Matrix3d V = svd.matrixV();
  if (U.determinant() < 0) U = -U;
  if (V.determinant() < 0) V = -V;
  Eigen::Matrix3d W;
  W << 0, 1, 0, -1, 0, 0, 0, 0, 1;
  const Eigen::Matrix3d Ra = U * W * V.transpose();
  const Eigen::Matrix3d Rb = U * W.transpose() * V.transpose();
  const Eigen::Vector3d t = U.col(2).normalized();
  const Pose candidates[4] = {{Ra, t}, {Ra, -t}, {Rb, t}, {Rb, -t}};
  Pose best;
  int best_count = -1;
  for (const Pose& candidate : candidates) {
    int count = 0;
    for (int i : indices) {
      count += in_front(candidate, rays1[i], rays2[i]);
    }
    if (count > best_count) {
      best_count = count;
      best = candidate;
    }
  }
  return best;
}

RelativePoseResult estimate_relative_pose(const bearingVectors_t& rays1,
                                          const bearingVectors_t& rays2,
                                          const std::vector<double>& max_errors,
                                          FivePointMethod method, RansacOptions options) {
  const RelativePoseEstimator estimator(rays1, rays2, max_errors, method);
  options.max_error = 1.0;  // errors arrive divided by their thresholds
  RansacResult<RelativeModel> found = ransac(estimator, options);
  RelativePoseResult result;
  result.ransac.success = found.success;
  result.ransac.inlier_mask = std::move(found.inlier_mask);
  result.ransac.num_inliers = found.num_inliers;
  result.ransac.num_iterations = found.num_iterations;
  if (!found.success) return result;
  // The cheirality check on the final inliers: refinement cannot see the sign of t
  // (E is the same for t and -t), so a sign chosen on an earlier, smaller inlier set
  // must not survive.
  std::vector<int> inliers;
  for (size_t i = 0; i < rays1.size(); ++i)
    if (result.ransac.inlier_mask[i]) inliers.push_back(static_cast<int>(i));
  found.model.pose = decompose_essential(found.model.E, rays1, rays2, inliers);
  result.ransac.model = found.model.pose;
  result.E = essential_from_pose(found.model.pose);
  return result;
}

}  // namespace colmap_ext
