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
  const Eigen::Matrix<double, 9, 9> Q = qr.householderQ();
  return Q.rightCols<4>();
}

// Essential matrices in COLMAP's convention, unit Frobenius norm, from the null space.
void five_point_from_null_space(const Eigen::Matrix<double, 9, 4>& null_space,
                                FivePointMethod method, std::vector<Eigen::Matrix3d>* essentials) {
  if (method == FivePointMethod::kNister) {
    opengv::essentials_t solutions;
    opengv::relative_pose::modules::fivept_nister_main(null_space, solutions);
    for (const auto& E : solutions) {
      if (E.allFinite()) essentials->push_back(E.transpose() / E.norm());
    }
  } else {
    opengv::complexEssentials_t solutions;
    opengv::relative_pose::modules::fivept_stewenius_main(null_space, solutions);
    for (const auto& E : solutions) {
      if (E.imag().norm() > 1e-8 * E.real().norm()) continue;  // complex root
      if (E.real().allFinite()) essentials->push_back(E.real().transpose() / E.real().norm());
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

// Depths of a ray pair's midpoint triangulation along each ray.
Eigen::Vector2d midpoint_depths(const Pose& cam2_from_cam1, const Eigen::Vector3d& f1,
                                const Eigen::Vector3d& f2) {
  const Eigen::Vector3d c2 = -cam2_from_cam1.R.transpose() * cam2_from_cam1.t;
  const Eigen::Vector3d g = cam2_from_cam1.R.transpose() * f2;
  Eigen::Matrix<double, 3, 2> A;
  A << f1, -g;
  return (A.transpose() * A).ldlt().solve(A.transpose() * c2);
}

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
                        FivePointMethod method)
      : rays1_(rays1), rays2_(rays2), method_(method), x1_(rays1.size()), x2_(rays2.size()) {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    for (size_t i = 0; i < rays1.size(); ++i) {
      const bool valid = rays1[i].z() > kMinRayZ && rays2[i].z() > kMinRayZ;
      x1_[i] = valid ? Eigen::Vector2d(rays1[i].head<2>() / rays1[i].z()) : Eigen::Vector2d(kNaN, kNaN);
      x2_[i] = valid ? Eigen::Vector2d(rays2[i].head<2>() / rays2[i].z()) : Eigen::Vector2d(kNaN, kNaN);
    }
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

  // Sampson error: first-order geometric error in normalized image units. NaN (never an
  // inlier) for rays without normalized coordinates.
  double squared_error(const Model& model, size_t i) const {
    const Eigen::Matrix3d& E = model.E;
    const double x1 = x1_[i].x(), y1 = x1_[i].y(), x2 = x2_[i].x(), y2 = x2_[i].y();
    const double Ex1_0 = E(0, 0) * x1 + E(0, 1) * y1 + E(0, 2);
    const double Ex1_1 = E(1, 0) * x1 + E(1, 1) * y1 + E(1, 2);
    const double Ex1_2 = E(2, 0) * x1 + E(2, 1) * y1 + E(2, 2);
    const double Etx2_0 = E(0, 0) * x2 + E(1, 0) * y2 + E(2, 0);
    const double Etx2_1 = E(0, 1) * x2 + E(1, 1) * y2 + E(2, 1);
    const double c = x2 * Ex1_0 + y2 * Ex1_1 + Ex1_2;
    return c * c / (Ex1_0 * Ex1_0 + Ex1_1 * Ex1_1 + Etx2_0 * Etx2_0 + Etx2_1 * Etx2_1);
  }

  // Levenberg-Marquardt on the inliers' Sampson errors over rotation and the
  // direction of translation (5 degrees of freedom).
  bool refine(const std::vector<int>& inliers, Model* model) const {
    if (!model->has_pose) {
      model->pose = decompose_essential(model->E, rays1_, rays2_, inliers);
      model->has_pose = true;
    }
    Pose& pose = model->pose;
    Eigen::Matrix<double, 3, 2> tangent;  // basis of the translation's tangent plane
    const auto moved = [&](const Eigen::Matrix<double, 5, 1>& delta) {
      return Pose{rotate_by(delta.head<3>(), pose.R), (pose.t + tangent * delta.tail<2>()).normalized()};
    };
    const auto update_tangent = [&]() {
      Eigen::JacobiSVD<Eigen::Matrix<double, 3, 1>> svd(pose.t, Eigen::ComputeFullU);
      tangent = svd.matrixU().rightCols<2>();
    };
    update_tangent();
    const auto residuals = [&](const Eigen::Matrix<double, 5, 1>& delta, Eigen::VectorXd* r) {
      const Model candidate{essential_from_pose(moved(delta)), {}, false};
      r->resize(inliers.size());
      for (size_t k = 0; k < inliers.size(); ++k)
        (*r)[k] = std::sqrt(squared_error(candidate, inliers[k]));
    };
    const auto commit = [&](const Eigen::Matrix<double, 5, 1>& delta) {
      pose = moved(delta);
      update_tangent();
    };
    if (!levenberg_marquardt<5>(residuals, commit)) return false;
    model->E = essential_from_pose(pose);
    return true;
  }

 private:
  const bearingVectors_t& rays1_;
  const bearingVectors_t& rays2_;
  FivePointMethod method_;
  std::vector<Eigen::Vector2d> x1_, x2_;  // normalized image points (x/z, y/z); NaN if none
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
      const Eigen::Vector2d d = midpoint_depths(candidate, rays1[i], rays2[i]);
      count += d.x() > 0 && d.y() > 0;
    }
    if (count > best_count) {
      best_count = count;
      best = candidate;
    }
  }
  return best;
}

RelativePoseResult estimate_relative_pose(const bearingVectors_t& rays1,
                                          const bearingVectors_t& rays2, FivePointMethod method,
                                          const RansacOptions& options) {
  const RelativePoseEstimator estimator(rays1, rays2, method);
  RansacResult<RelativeModel> found = ransac(estimator, options);
  RelativePoseResult result;
  result.ransac.success = found.success;
  result.ransac.inlier_mask = std::move(found.inlier_mask);
  result.ransac.num_inliers = found.num_inliers;
  result.ransac.num_iterations = found.num_iterations;
  if (!found.success) return result;
  if (!found.model.has_pose) {
    std::vector<int> inliers;
    for (size_t i = 0; i < rays1.size(); ++i)
      if (result.ransac.inlier_mask[i]) inliers.push_back(static_cast<int>(i));
    found.model.pose = decompose_essential(found.model.E, rays1, rays2, inliers);
  }
  result.ransac.model = found.model.pose;
  result.E = essential_from_pose(found.model.pose);
  return result;
}

}  // namespace colmap_ext
