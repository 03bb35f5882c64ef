#include "relative_pose.hpp"

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <opengv/relative_pose/CentralRelativeAdapter.hpp>
#include <opengv/relative_pose/methods.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::relative_pose::CentralRelativeAdapter;

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
      : rays1_(rays1), rays2_(rays2), method_(method) {
    x1_.reserve(rays1.size());
    x2_.reserve(rays2.size());
    for (size_t i = 0; i < rays1.size(); ++i) {
      x1_.push_back(rays1[i] / rays1[i].z());
      x2_.push_back(rays2[i] / rays2[i].z());
      valid_.push_back(rays1[i].z() > kMinRayZ && rays2[i].z() > kMinRayZ);
    }
  }

  size_t num_data() const { return rays1_.size(); }

  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    bearingVectors_t s1, s2;
    for (int i : sample) {
      s1.push_back(rays1_[i]);
      s2.push_back(rays2_[i]);
    }
    for (const Eigen::Matrix3d& E : five_point(s1, s2, method_)) models->push_back({E, {}, false});
  }

  // Sampson error: first-order geometric error in normalized image units.
  double squared_error(const Model& model, size_t i) const {
    if (!valid_[i]) return std::numeric_limits<double>::infinity();
    const Eigen::Vector3d Ex1 = model.E * x1_[i];
    const Eigen::Vector3d Etx2 = model.E.transpose() * x2_[i];
    const double c = x2_[i].dot(Ex1);
    const double d = Ex1.head<2>().squaredNorm() + Etx2.head<2>().squaredNorm();
    return d > 0 ? c * c / d : std::numeric_limits<double>::infinity();
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
  std::vector<Eigen::Vector3d> x1_, x2_;  // normalized image points (x/z, y/z, 1)
  std::vector<bool> valid_;
};

}  // namespace

std::vector<Eigen::Matrix3d> five_point(const bearingVectors_t& rays1,
                                        const bearingVectors_t& rays2, FivePointMethod method) {
  CentralRelativeAdapter adapter(rays1, rays2);
  std::vector<Eigen::Matrix3d> essentials;
  if (method == FivePointMethod::kNister) {
    for (const auto& E : opengv::relative_pose::fivept_nister(adapter)) {
      if (E.allFinite()) essentials.push_back(E.transpose());
    }
  } else {
    for (const auto& E : opengv::relative_pose::fivept_stewenius(adapter)) {
      if (E.imag().norm() > 1e-8 * E.real().norm()) continue;  // complex root
      if (E.real().allFinite()) essentials.push_back(E.real().transpose());
    }
  }
  for (Eigen::Matrix3d& E : essentials) E /= E.norm();
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
