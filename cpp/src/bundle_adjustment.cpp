#include "bundle_adjustment.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cmath>
#include <limits>
#include <thread>

namespace colmap_ext {
namespace {

using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Matrix63d = Eigen::Matrix<double, 6, 3>;
using Matrix26d = Eigen::Matrix<double, 2, 6>;
using Matrix23d = Eigen::Matrix<double, 2, 3>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

// The reduced camera system is dense up to this many free frames ...
constexpr int kMaxDenseFrames = 200;
// ... and beyond, up to this many (6n x 6n doubles a thread: 72 MB at 500), where at least
// this share of the frame pairs share a point (long tracks, as a turntable's): a sparse
// factorisation of a nearly full matrix takes longer than a dense one. Sparse elsewhere.
constexpr int kMaxFilledDenseFrames = 500;
constexpr double kMinDenseFill = 0.25;
// Ceres's Levenberg-Marquardt defaults (TrustRegionMinimizer, LevenbergMarquardtStrategy).
constexpr double kMaxRadius = 1e16;
constexpr double kMinRadius = 1e-32;
constexpr double kMinRelativeDecrease = 1e-3;
constexpr double kMinDiagonal = 1e-6;
constexpr double kMaxDiagonal = 1e32;
// The squared residual (px^2) an observation behind its ray's tangent plane counts as.
constexpr double kBehindSquaredResidual = 1e12;

// body(begin, end, thread) over [0, n) in `num_threads` contiguous chunks, the first
// on the calling thread. The chunks depend on n and num_threads alone, so sums taken
// per thread and added in thread order give the same result on every run.
template <typename Body>
void parallel_for(int num_threads, size_t n, const Body& body) {
  const size_t threads = std::max<size_t>(1, std::min<size_t>(num_threads, n));
  std::vector<std::thread> workers;
  for (size_t t = 1; t < threads; ++t)
    workers.emplace_back([&body, t, n, threads] { body(n * t / threads, n * (t + 1) / threads, t); });
  body(0, n / threads, 0);
  for (std::thread& worker : workers) worker.join();
}

// rho(s) and rho'(s) of the squared residual s, as Ceres's losses with scale a.
std::pair<double, double> loss_value(Loss loss, double a, double s) {
  const double a2 = a * a;
  switch (loss) {
    case Loss::kCauchy:
      return {a2 * std::log1p(s / a2), 1.0 / (1.0 + s / a2)};
    case Loss::kHuber:
      if (s <= a2) return {s, 1.0};
      return {2.0 * a * std::sqrt(s) - a2, a / std::sqrt(s)};
    case Loss::kSoftL1: {
      const double root = std::sqrt(1.0 + s / a2);
      return {2.0 * a2 * (root - 1.0), 1.0 / root};
    }
    case Loss::kTrivial:
      break;
  }
  return {s, 1.0};
}

Eigen::Matrix3d exp_rotation(const Eigen::Vector3d& w) {
  const double angle = w.norm();
  if (angle < 1e-300) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
}

// One observation linearised: its residual and the derivatives of it, weighted by the
// square root of rho' (Ceres's corrector where rho'' <= 0, as every loss here).
struct Linearised {
  Eigen::Vector2d residual = Eigen::Vector2d::Zero();
  Matrix26d frame_jacobian = Matrix26d::Zero();
  Matrix23d point_jacobian = Matrix23d::Zero();
};

class Adjuster {
 public:
  Adjuster(std::vector<Pose>& frames, const std::vector<Eigen::Matrix<bool, 6, 1>>& free,
           const std::vector<Pose>& sensors, const std::vector<int>& image_frame,
           std::vector<Eigen::Vector3d>& points, const std::vector<char>& point_variable,
           const std::vector<BundleObservation>& observations, const BundleOptions& options)
      : frames_(frames), free_(free), sensors_(sensors), image_frame_(image_frame),
        points_(points), point_variable_(point_variable), observations_(observations),
        options_(options), num_threads_(std::max(1, options.num_threads)) {
    frame_block_.assign(frames.size(), -1);
    for (size_t f = 0; f < frames.size(); ++f)
      if (free[f].any()) frame_block_[f] = num_blocks_++;
    // Each variable point's observations, contiguous (the Schur complement's loop).
    std::vector<int> counts(points.size() + 1, 0);
    for (const BundleObservation& obs : observations)
      if (point_variable[obs.point]) ++counts[obs.point + 1];
    for (size_t p = 0; p < points.size(); ++p) counts[p + 1] += counts[p];
    point_start_ = counts;
    point_observations_.resize(counts.back());
    for (size_t o = 0; o < observations.size(); ++o) {
      const int p = observations[o].point;
      if (point_variable[p]) point_observations_[counts[p]++] = static_cast<int>(o);
    }
    linearised_.resize(observations.size());
    if (num_blocks_ > kMaxDenseFrames) {
      pattern_ = BlockPattern(*this);
      const double pairs = 0.5 * num_blocks_ * (num_blocks_ + 1.0);
      dense_ = num_blocks_ <= kMaxFilledDenseFrames &&
               static_cast<double>(pattern_.columns.size()) >= kMinDenseFill * pairs;
      if (dense_) pattern_ = BlockPattern();
    }
  }

  BundleSummary solve() {
    BundleSummary summary;
    double cost = linearise();
    summary.initial_cost = cost;
    double radius = options_.initial_trust_region_radius, decrease_factor = 2.0;
    while (summary.iterations < options_.max_iterations) {
      if (gradient_max_norm() <= options_.gradient_tolerance) break;
      Step step;
      const bool solved = solve_step(1.0 / radius, step);
      ++summary.iterations;
      const std::vector<Pose> frames_before = frames_;
      const std::vector<Eigen::Vector3d> points_before = points_;
      double new_cost = std::numeric_limits<double>::infinity();
      if (solved) {
        apply(step, 1.0, frames_before, points_before);
        new_cost = evaluate_cost();
      }
      const double ratio = solved && step.predicted_decrease > 0
                               ? (cost - new_cost) / step.predicted_decrease
                               : -1.0;
      if (!std::isfinite(new_cost) || ratio < kMinRelativeDecrease) {
        frames_ = frames_before;
        points_ = points_before;
        radius /= decrease_factor;
        decrease_factor *= 2.0;
        if (radius < kMinRadius) break;
        continue;
      }
      // Under a robust loss the reweighted step falls short of the minimum along it:
      // take it at twice, four times ... its length while the cost keeps falling.
      for (double scale = 2.0; scale <= options_.max_step_scale; scale *= 2.0) {
        const std::vector<Pose> frames_accepted = frames_;
        const std::vector<Eigen::Vector3d> points_accepted = points_;
        apply(step, scale, frames_before, points_before);
        const double longer_cost = evaluate_cost();
        if (!(longer_cost < new_cost)) {
          frames_ = frames_accepted;
          points_ = points_accepted;
          break;
        }
        new_cost = longer_cost;
      }
      radius = std::min(kMaxRadius,
                        radius / std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * ratio - 1.0, 3)));
      decrease_factor = 2.0;
      const double decrease = cost - new_cost;
      cost = linearise();
      if (decrease <= options_.function_tolerance * (cost + decrease)) break;
    }
    summary.final_cost = cost;
    summary.usable = std::isfinite(cost);
    return summary;
  }

 private:
  struct Step {
    std::vector<Vector6d> frames;
    std::vector<Eigen::Vector3d> points;
    double predicted_decrease = 0.0;
  };

  // Every image's cam_from_world at the current frame poses.
  std::vector<Pose> cameras_from_world() const {
    std::vector<Pose> cameras(sensors_.size());
    for (size_t i = 0; i < sensors_.size(); ++i)
      cameras[i] = compose(sensors_[i], frames_[image_frame_[i]]);
    return cameras;
  }

  // Squared residual (px^2) of an observation whose point lies at y in its camera's frame.
  static double squared_residual(const BundleObservation& obs, const Eigen::Vector3d& y,
                                 Eigen::Vector2d* residual) {
    const double along = obs.ray.dot(y);
    if (!(along > 1e-12 * y.norm())) {
      residual->setZero();
      return kBehindSquaredResidual;
    }
    *residual = obs.pixels_from_tangent * (y / along - obs.ray);
    return residual->squaredNorm();
  }

  double evaluate_cost() const {
    const std::vector<Pose> cameras = cameras_from_world();
    std::vector<double> partial_cost(num_threads_, 0.0);
    parallel_for(num_threads_, observations_.size(), [&](size_t begin, size_t end, size_t t) {
      double cost = 0.0;
      Eigen::Vector2d residual;
      for (size_t o = begin; o < end; ++o) {
        const BundleObservation& obs = observations_[o];
        const Pose& cam = cameras[obs.image];
        cost += loss_value(options_.loss, options_.loss_scale,
                           squared_residual(obs, cam.R * points_[obs.point] + cam.t,
                                            &residual)).first;
      }
      partial_cost[t] = cost;
    });
    double cost = 0.0;
    for (const double c : partial_cost) cost += c;
    return 0.5 * cost;
  }

  // Residuals and Jacobians at the current parameters, and the gradient. Returns the cost.
  double linearise() {
    const std::vector<Pose> cameras = cameras_from_world();
    std::vector<double> partial_cost(num_threads_, 0.0);
    std::vector<std::vector<Vector6d>> partial_gradient(
        num_threads_, std::vector<Vector6d>(num_blocks_, Vector6d::Zero()));
    parallel_for(num_threads_, observations_.size(), [&](size_t begin, size_t end, size_t t) {
      double cost = 0.0;
      std::vector<Vector6d>& frame_gradient = partial_gradient[t];
      for (size_t o = begin; o < end; ++o) cost += linearise(o, cameras, frame_gradient);
      partial_cost[t] = cost;
    });
    frame_gradient_ = std::move(partial_gradient[0]);
    for (int t = 1; t < num_threads_; ++t)
      for (int b = 0; b < num_blocks_; ++b) frame_gradient_[b] += partial_gradient[t][b];
    // Each point's gradient from its observations (in their order), point by point.
    point_gradient_.assign(points_.size(), Eigen::Vector3d::Zero());
    parallel_for(num_threads_, points_.size(), [&](size_t begin, size_t end, size_t) {
      for (size_t p = begin; p < end; ++p)
        for (int k = point_start_[p]; k < point_start_[p + 1]; ++k) {
          const Linearised& lin = linearised_[point_observations_[k]];
          point_gradient_[p] += lin.point_jacobian.transpose() * lin.residual;
        }
    });
    double cost = 0.0;
    for (const double c : partial_cost) cost += c;
    return 0.5 * cost;
  }

  // Observation o linearised into linearised_[o] (its camera's pose among `cameras`), its
  // frame's gradient added to `frame_gradient`. Returns rho of its squared residual.
  double linearise(size_t o, const std::vector<Pose>& cameras,
                   std::vector<Vector6d>& frame_gradient) {
    const BundleObservation& obs = observations_[o];
    Linearised& lin = linearised_[o];
    const int frame = image_frame_[obs.image];
    const Pose& cam = cameras[obs.image];
    const Eigen::Vector3d y = cam.R * points_[obs.point] + cam.t;
    Eigen::Vector2d residual;
    const double s = squared_residual(obs, y, &residual);
    const auto [rho, rho1] = loss_value(options_.loss, options_.loss_scale, s);
    lin = Linearised();
    if (s >= kBehindSquaredResidual) return rho;
    const double weight = std::sqrt(rho1);
    const double along = obs.ray.dot(y);
    // d residual / d y of r = P (y / (ray . y) - ray).
    const Matrix23d dr_dy =
        weight * (obs.pixels_from_tangent - (obs.pixels_from_tangent * y / along) *
                                                obs.ray.transpose()) / along;
    lin.residual = weight * residual;
    if (frame_block_[frame] >= 0) {
      const Pose& sensor = sensors_[obs.image];
      const Matrix23d dr_drig = dr_dy * sensor.R;  // y = R_s (R w X + t + dt) + t_s
      lin.frame_jacobian.leftCols<3>() = -dr_drig * skew(frames_[frame].R * points_[obs.point]);
      lin.frame_jacobian.rightCols<3>() = dr_drig;
      for (int k = 0; k < 6; ++k)
        if (!free_[frame](k)) lin.frame_jacobian.col(k).setZero();
      frame_gradient[frame_block_[frame]] += lin.frame_jacobian.transpose() * lin.residual;
    }
    if (point_variable_[obs.point]) lin.point_jacobian = dr_dy * cam.R;
    return rho;
  }

  // Ceres's gradient check, max |x - Plus(x, -g)|: on a rotation the change of its unit
  // quaternion (tangent: half the angle), which stays below 2 however large the gradient,
  // so that COLMAP's tolerances stop where they stop Ceres.
  double gradient_max_norm() const {
    double norm = 0.0;
    for (size_t f = 0; f < frames_.size(); ++f) {
      const int block = frame_block_[f];
      if (block < 0) continue;
      const Vector6d& g = frame_gradient_[block];
      const Eigen::Vector3d step = -2.0 * g.head<3>();
      const double angle = step.norm();
      const Eigen::Quaterniond q(frames_[f].R);
      Eigen::Quaterniond change(1.0, 0.0, 0.0, 0.0);
      if (angle > 0) {
        change.w() = std::cos(angle);
        change.vec() = std::sin(angle) / angle * step;
      }
      const Eigen::Quaterniond moved = change * q;
      norm = std::max({norm, (q.coeffs() - moved.coeffs()).cwiseAbs().maxCoeff(),
                       g.tail<3>().cwiseAbs().maxCoeff()});
    }
    for (size_t p = 0; p < points_.size(); ++p)
      if (point_variable_[p]) norm = std::max(norm, point_gradient_[p].cwiseAbs().maxCoeff());
    return norm;
  }

  // The frame pairs (a <= b) that share a variable point: the reduced camera system's
  // upper block triangle, row by row (each row's columns ascending). Fixed for a problem,
  // so found once; a block's place in it is then a search in its row, not a hash lookup.
  struct BlockPattern {
    BlockPattern() = default;
    explicit BlockPattern(const Adjuster& adjuster) {
      const int n = adjuster.num_blocks_;
      std::vector<std::vector<int>> block_points(n);  // the variable points of each block
      for (size_t p = 0; p + 1 < adjuster.point_start_.size(); ++p)
        for (int k = adjuster.point_start_[p]; k < adjuster.point_start_[p + 1]; ++k) {
          const int block = adjuster.block_of(adjuster.point_observations_[k]);
          if (block >= 0) block_points[block].push_back(static_cast<int>(p));
        }
      std::vector<int> seen(n, -1);  // the row that last took each column
      row_start.assign(1, 0);
      for (int a = 0; a < n; ++a) {
        const size_t first = columns.size();
        seen[a] = a;
        columns.push_back(a);
        for (int p : block_points[a])
          for (int k = adjuster.point_start_[p]; k < adjuster.point_start_[p + 1]; ++k) {
            const int b = adjuster.block_of(adjuster.point_observations_[k]);
            if (b > a && seen[b] != a) {
              seen[b] = a;
              columns.push_back(b);
            }
          }
        std::sort(columns.begin() + first, columns.end());
        row_start.push_back(static_cast<int>(columns.size()));
      }
    }
    int place(int a, int b) const {
      return static_cast<int>(
          std::lower_bound(columns.begin() + row_start[a], columns.begin() + row_start[a + 1], b) -
          columns.begin());
    }
    std::vector<int> row_start, columns;
  };

  // The reduced camera system S x = rhs (its upper block triangle), one per thread:
  // dense, or the blocks of `pattern` (nullptr: dense).
  struct ReducedSystem {
    ReducedSystem(int n, const BlockPattern* pattern)
        : n(n), pattern(pattern), rhs(Eigen::VectorXd::Zero(6 * n)) {
      if (pattern == nullptr)
        matrix = Eigen::MatrixXd::Zero(6 * n, 6 * n);
      else
        blocks.assign(pattern->columns.size(), Matrix6d::Zero());
    }
    void add_block(int a, int b, const Matrix6d& block) {
      if (a > b) return;
      if (pattern == nullptr)
        matrix.block<6, 6>(6 * a, 6 * b) += block;
      else
        blocks[pattern->place(a, b)] += block;
    }
    void add(const ReducedSystem& other) {
      rhs += other.rhs;
      if (pattern == nullptr) {
        matrix.triangularView<Eigen::Upper>() += other.matrix;
      } else {
        for (size_t k = 0; k < blocks.size(); ++k) blocks[k] += other.blocks[k];
      }
    }
    int n;
    const BlockPattern* pattern;
    Eigen::VectorXd rhs;
    Eigen::MatrixXd matrix;
    std::vector<Matrix6d> blocks;
  };

  // The block of the frame of observation o (-1: not free).
  int block_of(int o) const { return frame_block_[image_frame_[observations_[o].image]]; }

  // The Levenberg-Marquardt step with damping mu: (H + mu D) x = -g, H = J^T J, D its
  // diagonal (clamped as Ceres's), points eliminated first.
  bool solve_step(double mu, Step& step) {
    const int n = num_blocks_;
    std::vector<std::vector<Matrix6d>> partial_hessian(
        num_threads_, std::vector<Matrix6d>(n, Matrix6d::Zero()));
    parallel_for(num_threads_, observations_.size(), [&](size_t begin, size_t end, size_t t) {
      std::vector<Matrix6d>& hessian = partial_hessian[t];
      for (size_t o = begin; o < end; ++o) {
        const int block = block_of(o);
        if (block >= 0)
          hessian[block] += linearised_[o].frame_jacobian.transpose() *
                            linearised_[o].frame_jacobian;
      }
    });
    std::vector<Matrix6d>& frame_hessian = partial_hessian[0];
    for (int t = 1; t < num_threads_; ++t)
      for (int b = 0; b < n; ++b) frame_hessian[b] += partial_hessian[t][b];
    std::vector<Vector6d> frame_diagonal(n);
    for (int b = 0; b < n; ++b) {
      frame_diagonal[b] = frame_hessian[b].diagonal().cwiseMax(kMinDiagonal).cwiseMin(kMaxDiagonal);
      frame_hessian[b].diagonal() += mu * frame_diagonal[b];
    }
    const bool dense = dense_;
    std::vector<ReducedSystem> systems;
    for (int t = 0; t < num_threads_; ++t) systems.emplace_back(n, dense ? nullptr : &pattern_);
    for (int b = 0; b < n; ++b) {
      systems[0].add_block(b, b, frame_hessian[b]);
      systems[0].rhs.segment<6>(6 * b) = -frame_gradient_[b];
    }

    // Each point eliminated into its thread's system.
    std::vector<Eigen::Matrix3d> point_inverse(points_.size());
    std::vector<Eigen::Vector3d> point_diagonal(points_.size());
    std::vector<char> singular(num_threads_, 0);
    parallel_for(num_threads_, points_.size(), [&](size_t begin, size_t end, size_t t) {
      ReducedSystem& system = systems[t];
      std::vector<Matrix63d> coupling;  // frame-point blocks of the point's observations
      std::vector<int> coupling_block;
      for (size_t p = begin; p < end; ++p) {
        if (!point_variable_[p]) continue;
        Eigen::Matrix3d hessian = Eigen::Matrix3d::Zero();
        coupling.clear();
        coupling_block.clear();
        for (int k = point_start_[p]; k < point_start_[p + 1]; ++k) {
          const int o = point_observations_[k];
          const Linearised& lin = linearised_[o];
          hessian += lin.point_jacobian.transpose() * lin.point_jacobian;
          const int block = block_of(o);
          if (block >= 0) {
            coupling.push_back(lin.frame_jacobian.transpose() * lin.point_jacobian);
            coupling_block.push_back(block);
          }
        }
        point_diagonal[p] = hessian.diagonal().cwiseMax(kMinDiagonal).cwiseMin(kMaxDiagonal);
        hessian.diagonal() += mu * point_diagonal[p];
        bool invertible = false;
        hessian.computeInverseWithCheck(point_inverse[p], invertible);
        if (!invertible) {
          singular[t] = 1;
          return;
        }
        for (size_t i = 0; i < coupling.size(); ++i) {
          const Matrix63d left = coupling[i] * point_inverse[p];
          system.rhs.segment<6>(6 * coupling_block[i]) += left * point_gradient_[p];
          for (size_t j = 0; j < coupling.size(); ++j) {
            if (coupling_block[i] <= coupling_block[j])
              system.add_block(coupling_block[i], coupling_block[j],
                               -left * coupling[j].transpose());
          }
        }
      }
    });
    for (int t = 0; t < num_threads_; ++t)
      if (singular[t]) return false;
    ReducedSystem& system = systems[0];
    for (int t = 1; t < num_threads_; ++t) system.add(systems[t]);
    Eigen::VectorXd& rhs = system.rhs;

    // Fixed parameters of free frames (the gauge): x = 0 there.
    std::vector<char> fixed(6 * n, 0);
    for (size_t f = 0; f < frames_.size(); ++f)
      if (frame_block_[f] >= 0)
        for (int k = 0; k < 6; ++k)
          if (!free_[f](k)) fixed[6 * frame_block_[f] + k] = 1;
    Eigen::VectorXd x;
    if (dense) {
      for (int i = 0; i < 6 * n; ++i)
        if (fixed[i]) {
          rhs(i) = 0.0;
          system.matrix.row(i).setZero();
          system.matrix.col(i).setZero();
          system.matrix(i, i) = 1.0;
        }
      Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> llt(system.matrix);
      if (llt.info() != Eigen::Success) return false;
      x = llt.solve(rhs);
    } else {
      std::vector<Eigen::Triplet<double>> triplets;
      triplets.reserve(system.blocks.size() * 36);
      for (int a = 0; a < n; ++a)
        for (int k = pattern_.row_start[a]; k < pattern_.row_start[a + 1]; ++k) {
          const int b = pattern_.columns[k];
          const Matrix6d& block = system.blocks[k];
          for (int r = 0; r < 6; ++r)
            for (int c = 0; c < 6; ++c) {
              const int row = 6 * a + r, col = 6 * b + c;
              if (row > col || fixed[row] || fixed[col]) continue;
              triplets.emplace_back(row, col, block(r, c));
            }
        }
      for (int i = 0; i < 6 * n; ++i)
        if (fixed[i]) {
          triplets.emplace_back(i, i, 1.0);
          rhs(i) = 0.0;
        }
      Eigen::SparseMatrix<double> sparse(6 * n, 6 * n);
      sparse.setFromTriplets(triplets.begin(), triplets.end());
      Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Upper> ldlt(sparse);
      if (ldlt.info() != Eigen::Success) return false;
      x = ldlt.solve(rhs);
    }
    if (!x.allFinite()) return false;

    step.frames.assign(frames_.size(), Vector6d::Zero());
    // The model's decrease, -g.x - x^T H x / 2 with (H + mu D) x = -g: its terms g.x
    // and x^T D x, the frames' first, then each thread's points.
    std::vector<double> gradient_term(num_threads_, 0.0), damping_term(num_threads_, 0.0);
    for (size_t f = 0; f < frames_.size(); ++f) {
      const int block = frame_block_[f];
      if (block < 0) continue;
      step.frames[f] = x.segment<6>(6 * block);
      gradient_term[0] += frame_gradient_[block].dot(step.frames[f]);
      damping_term[0] += step.frames[f].dot(frame_diagonal[block].cwiseProduct(step.frames[f]));
    }
    step.points.assign(points_.size(), Eigen::Vector3d::Zero());
    parallel_for(num_threads_, points_.size(), [&](size_t begin, size_t end, size_t t) {
      for (size_t p = begin; p < end; ++p) {
        if (!point_variable_[p]) continue;
        Eigen::Vector3d b = -point_gradient_[p];
        for (int k = point_start_[p]; k < point_start_[p + 1]; ++k) {
          const int o = point_observations_[k];
          const Linearised& lin = linearised_[o];
          const int frame = image_frame_[observations_[o].image];
          if (frame_block_[frame] >= 0)
            b -= (lin.frame_jacobian.transpose() * lin.point_jacobian).transpose() *
                 step.frames[frame];
        }
        step.points[p] = point_inverse[p] * b;
        gradient_term[t] += point_gradient_[p].dot(step.points[p]);
        damping_term[t] += step.points[p].dot(point_diagonal[p].cwiseProduct(step.points[p]));
      }
    });
    double gradient = 0.0, damping = 0.0;
    for (int t = 0; t < num_threads_; ++t) {
      gradient += gradient_term[t];
      damping += damping_term[t];
    }
    step.predicted_decrease = 0.5 * (-gradient + mu * damping);
    return std::isfinite(step.predicted_decrease);
  }

  void apply(const Step& step, double scale, const std::vector<Pose>& frames,
             const std::vector<Eigen::Vector3d>& points) {
    for (size_t f = 0; f < frames_.size(); ++f) {
      if (frame_block_[f] < 0) continue;
      frames_[f].R = exp_rotation(scale * step.frames[f].head<3>()) * frames[f].R;
      frames_[f].t = frames[f].t + scale * step.frames[f].tail<3>();
    }
    for (size_t p = 0; p < points_.size(); ++p)
      if (point_variable_[p]) points_[p] = points[p] + scale * step.points[p];
  }

  std::vector<Pose>& frames_;
  const std::vector<Eigen::Matrix<bool, 6, 1>>& free_;
  const std::vector<Pose>& sensors_;
  const std::vector<int>& image_frame_;
  std::vector<Eigen::Vector3d>& points_;
  const std::vector<char>& point_variable_;
  const std::vector<BundleObservation>& observations_;
  const BundleOptions& options_;
  const int num_threads_;
  std::vector<int> frame_block_;
  int num_blocks_ = 0;
  std::vector<int> point_start_, point_observations_;
  bool dense_ = true;     // whether the reduced camera system is dense
  BlockPattern pattern_;  // its blocks where it is not
  std::vector<Linearised> linearised_;
  std::vector<Vector6d> frame_gradient_;
  std::vector<Eigen::Vector3d> point_gradient_;
};

}  // namespace

BundleSummary bundle_adjust(std::vector<Pose>& rigs_from_world,
                            const std::vector<Eigen::Matrix<bool, 6, 1>>& free_parameters,
                            const std::vector<Pose>& sensors_from_rig,
                            const std::vector<int>& image_frame,
                            std::vector<Eigen::Vector3d>& points,
                            const std::vector<char>& point_variable,
                            const std::vector<BundleObservation>& observations,
                            const BundleOptions& options) {
  Adjuster adjuster(rigs_from_world, free_parameters, sensors_from_rig, image_frame, points,
                    point_variable, observations, options);
  return adjuster.solve();
}

}  // namespace colmap_ext
