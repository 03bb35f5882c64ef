// A small Levenberg-Marquardt for the few-parameter refinements of RANSAC models.
//
// The model is moved by a local update `delta` of D parameters (e.g. a rotation vector
// and a translation step). A problem provides, with analytic derivatives:
//   double linearize(Mat* JtJ, Vec* Jtr) const;  // at the current model: J^T J, J^T r and
//                                                // the cost, the sum of squared residuals
//   double cost(const Vec& delta) const;         // the cost at the model moved by delta
//   void commit(const Vec& delta);               // moves the model for good
// J^T J and J^T r are accumulated point by point, so no residual vector or Jacobian
// matrix is ever stored.
#pragma once

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace colmap_ext {

// Converged when a step lowers the cost by less than kRelativeDecrease of it (Ceres's
// function_tolerance is 1e-6): near the optimum each step's decrease is 1e-4 to 1e-6 of the
// one before, so the cost left above the optimum is about 1e-13 of it, far below any
// change in the inliers, and a step more would only confirm it.
constexpr double kRelativeDecrease = 1e-8;

// How a refinement ended: its cost was not finite at the start (kFailed); no step lowers
// it by kRelativeDecrease any more (kConverged); or max_iterations steps were taken, each
// lowering it (kIterationLimit).
enum class RefinementStatus { kFailed, kConverged, kIterationLimit };

// Each iteration linearizes at the model and takes the first damped step that lowers the
// cost, raising the damping tenfold after each one that does not.
template <int D, typename Problem>
RefinementStatus levenberg_marquardt(Problem& problem, int max_iterations = 20) {
  using Vec = Eigen::Matrix<double, D, 1>;
  using Mat = Eigen::Matrix<double, D, D>;
  Mat H;
  Vec g;
  double lambda = 1e-4;
  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    const double cost = problem.linearize(&H, &g);
    if (!std::isfinite(cost)) return RefinementStatus::kFailed;  // only at the start: each
                                                                 // step lowers a finite cost
    bool improved = false;
    for (int attempt = 0; attempt < 10 && !improved; ++attempt) {
      Mat damped = H;
      damped.diagonal() += lambda * H.diagonal().cwiseMax(1e-12);
      const Vec step = damped.ldlt().solve(-g);
      if (!step.allFinite()) return RefinementStatus::kConverged;
      const double new_cost = problem.cost(step);
      if (std::isfinite(new_cost) && new_cost < cost) {
        problem.commit(step);
        if (cost - new_cost < kRelativeDecrease * cost || step.norm() < 1e-12)
          return RefinementStatus::kConverged;
        lambda = std::max(lambda * 0.1, 1e-12);
        improved = true;
      } else {
        lambda *= 10;
      }
    }
    if (!improved) return RefinementStatus::kConverged;
  }
  return RefinementStatus::kIterationLimit;
}

// The rotation exp(w) R: a local update of a rotation by a rotation vector w.
inline Eigen::Matrix3d rotate_by(const Eigen::Vector3d& w, const Eigen::Matrix3d& R) {
  const double angle = w.norm();
  if (angle < 1e-16) return R;
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix() * R;
}

}  // namespace colmap_ext
