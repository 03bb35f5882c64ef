// A small Levenberg-Marquardt for the few-parameter refinements of RANSAC models.
//
// The model is moved by a local update `delta` (e.g. a rotation vector and a
// translation step); `residuals(delta, &r)` evaluates the residuals at the moved
// model and `commit(delta)` moves it for good. The Jacobian is by central
// differences: D is 5 or 6 here, so 2D residual passes per iteration are cheap next
// to the sampling loop, and no model needs hand-derived derivatives.
#pragma once

#include <Eigen/Dense>

namespace colmap_ext {

template <int D, typename Residuals, typename Commit>
bool levenberg_marquardt(const Residuals& residuals, const Commit& commit,
                         int max_iterations = 20) {
  using Vec = Eigen::Matrix<double, D, 1>;
  using Mat = Eigen::Matrix<double, D, D>;
  constexpr double kStep = 1e-6;
  Eigen::VectorXd r, r_plus, r_minus, r_new;
  residuals(Vec::Zero(), &r);
  double cost = r.squaredNorm();
  if (!std::isfinite(cost)) return false;
  double lambda = 1e-4;
  Eigen::MatrixXd J(r.size(), D);
  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    for (int j = 0; j < D; ++j) {
      const Vec h = Vec::Unit(j) * kStep;
      residuals(h, &r_plus);
      residuals(-h, &r_minus);
      J.col(j) = (r_plus - r_minus) / (2 * kStep);
    }
    const Mat H = J.transpose() * J;
    const Vec g = J.transpose() * r;
    bool improved = false;
    for (int attempt = 0; attempt < 10 && !improved; ++attempt) {
      Mat damped = H;
      damped.diagonal() += lambda * H.diagonal().cwiseMax(1e-12);
      const Vec step = damped.ldlt().solve(-g);
      if (!step.allFinite()) break;
      residuals(step, &r_new);
      const double new_cost = r_new.squaredNorm();
      if (std::isfinite(new_cost) && new_cost < cost) {
        commit(step);
        const bool converged = cost - new_cost < 1e-12 * cost || step.norm() < 1e-12;
        cost = new_cost;
        r.swap(r_new);
        lambda = std::max(lambda * 0.1, 1e-12);
        improved = true;
        if (converged) return true;
      } else {
        lambda *= 10;
      }
    }
    if (!improved) break;
  }
  return true;
}

// The rotation exp(w) R: a local update of a rotation by a rotation vector w.
inline Eigen::Matrix3d rotate_by(const Eigen::Vector3d& w, const Eigen::Matrix3d& R) {
  const double angle = w.norm();
  if (angle < 1e-16) return R;
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix() * R;
}

}  // namespace colmap_ext
