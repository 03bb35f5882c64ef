// One generic LO-MSAC loop over an estimator (in the spirit of PoseLib's ransac.h).
//
// An Estimator provides:
//   using Model = ...;
//   static constexpr int kSampleSize;
//   size_t num_data() const;
//   void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const;
//   // The squared errors of data begin..end-1 into errors[0..]; +inf or NaN: never fits.
//   // Scored a block at a time, so that an estimator's loop over the block can vectorise.
//   void squared_errors(const Model& model, size_t begin, size_t end, double* errors) const;
//   // Least squares on the inliers, at most max_iterations steps (refinement.hpp).
//   RefinementStatus refine(const std::vector<int>& inliers, Model* model,
//                           int max_iterations) const;
// and may provide, to draw samples other than uniformly:
//   void draw_sample(std::mt19937_64& rng, std::vector<int>* sample) const;
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <random>
#include <type_traits>
#include <utility>
#include <vector>

#include "refinement.hpp"

namespace colmap_ext {

struct RansacOptions {
  double max_error = 1e-3;  // inlier threshold on the estimator's error (not squared)
  int max_iterations = 10000;
  int min_iterations = 10;
  double confidence = 0.9999;
  uint64_t seed = 0;
};

// 1 / each correspondence's threshold: estimators with one threshold per correspondence
// score errors times their weight and run with max_error 1.
inline std::vector<double> weights_from_thresholds(const std::vector<double>& max_errors) {
  std::vector<double> weights(max_errors.size());
  for (size_t i = 0; i < max_errors.size(); ++i) weights[i] = 1.0 / max_errors[i];
  return weights;
}

template <typename Estimator, typename = void>
struct draws_own_samples : std::false_type {};

template <typename Estimator>
struct draws_own_samples<Estimator, std::void_t<decltype(std::declval<const Estimator&>().draw_sample(
                                         std::declval<std::mt19937_64&>(),
                                         std::declval<std::vector<int>*>()))>> : std::true_type {};

template <typename Model>
struct RansacResult {
  bool success = false;
  Model model{};
  std::vector<char> inlier_mask;
  int num_inliers = 0;
  int num_iterations = 0;
};

// Number of iterations after which an all-inlier sample has been drawn with `confidence`.
inline int required_iterations(int num_inliers, int num_data, int sample_size, double confidence) {
  const double inlier_ratio = static_cast<double>(num_inliers) / num_data;
  const double p_good_sample = std::pow(inlier_ratio, sample_size);
  if (p_good_sample >= 1.0 - 1e-12) return 0;
  if (p_good_sample <= std::numeric_limits<double>::min()) return std::numeric_limits<int>::max();
  const double n = std::log(1.0 - confidence) / std::log1p(-p_good_sample);
  return n > std::numeric_limits<int>::max() ? std::numeric_limits<int>::max()
                                               : static_cast<int>(std::ceil(n));
}

// Data scored at once by squared_errors: small, so that scoring a model that cannot win
// stops soon after its score passes the bound.
constexpr size_t kScoreBlock = 64;

// The local optimisation of a new best model: least squares on its inliers, to
// convergence. A single step instead finds the same inliers on benchmarks/solvers.py's
// problems, but moves the mapper's models (docs/experiments/speed.md, "P3P").
constexpr int kLocalOptimizationSteps = 20;
// The final refinement's steps at most: ten rounds of refinement to convergence (20
// steps), each followed by finding the inliers again.
constexpr int kFinalRefinementSteps = 200;

// MSAC score of one model (lower is better). Scoring stops early once the score passes
// `bound`: such a model cannot become the best one.
template <typename Estimator>
double score_model(const Estimator& estimator, const typename Estimator::Model& model,
                   double max_sq_error, double bound = std::numeric_limits<double>::infinity()) {
  double score = 0.0;
  double errors[kScoreBlock];
  const size_t n = estimator.num_data();
  for (size_t begin = 0; begin < n; begin += kScoreBlock) {
    const size_t count = std::min(kScoreBlock, n - begin);
    estimator.squared_errors(model, begin, begin + count, errors);
    for (size_t k = 0; k < count; ++k) score += errors[k] < max_sq_error ? errors[k] : max_sq_error;
    if (score > bound) return score;
  }
  return score;
}

template <typename Estimator>
void find_inliers(const Estimator& estimator, const typename Estimator::Model& model,
                  double max_sq_error, std::vector<int>* inliers) {
  inliers->clear();
  double errors[kScoreBlock];
  const size_t n = estimator.num_data();
  for (size_t begin = 0; begin < n; begin += kScoreBlock) {
    const size_t count = std::min(kScoreBlock, n - begin);
    estimator.squared_errors(model, begin, begin + count, errors);
    for (size_t k = 0; k < count; ++k)
      if (errors[k] < max_sq_error) inliers->push_back(static_cast<int>(begin + k));
  }
}

template <typename Estimator>
RansacResult<typename Estimator::Model> ransac(const Estimator& estimator,
                                               const RansacOptions& options) {
  using Model = typename Estimator::Model;
  constexpr int kSampleSize = Estimator::kSampleSize;
  RansacResult<Model> result;
  const int num_data = static_cast<int>(estimator.num_data());
  if (num_data < kSampleSize) return result;

  const double max_sq_error = options.max_error * options.max_error;
  std::mt19937_64 rng(options.seed);
  std::vector<int> indices(num_data);
  std::iota(indices.begin(), indices.end(), 0);
  std::vector<int> sample(kSampleSize), best_inliers;
  std::vector<Model> models;
  double best_score = std::numeric_limits<double>::infinity();
  int max_iterations = options.max_iterations;

  int iteration = 0;
  for (; iteration < max_iterations; ++iteration) {
    if constexpr (draws_own_samples<Estimator>::value) {
      estimator.draw_sample(rng, &sample);
    } else {
      // Partial Fisher-Yates: kSampleSize distinct indices.
      for (int k = 0; k < kSampleSize; ++k) {
        std::uniform_int_distribution<int> pick(k, num_data - 1);
        std::swap(indices[k], indices[pick(rng)]);
        sample[k] = indices[k];
      }
    }
    models.clear();
    estimator.minimal_solve(sample, &models);
    for (const Model& model : models) {
      const double score = score_model(estimator, model, max_sq_error, best_score);
      if (score >= best_score) continue;
      best_score = score;
      result.model = model;
      find_inliers(estimator, model, max_sq_error, &best_inliers);
      // Local optimisation: a least-squares fit on the inliers often finds more of them.
      Model refined = result.model;
      if (static_cast<int>(best_inliers.size()) > kSampleSize &&
          estimator.refine(best_inliers, &refined, kLocalOptimizationSteps) !=
              RefinementStatus::kFailed) {
        const double refined_score = score_model(estimator, refined, max_sq_error, best_score);
        if (refined_score < best_score) {
          best_score = refined_score;
          result.model = refined;
          find_inliers(estimator, refined, max_sq_error, &best_inliers);
        }
      }
      const int needed = required_iterations(static_cast<int>(best_inliers.size()), num_data,
                                             kSampleSize, options.confidence);
      max_iterations = std::min(options.max_iterations, std::max(options.min_iterations, needed));
    }
  }
  result.num_iterations = iteration;
  if (static_cast<int>(best_inliers.size()) < kSampleSize) return result;

  // Final least-squares refinement on the inliers, a step at a time, the inliers found
  // again after each step, until a step converges on inliers that its result keeps: the
  // least-squares fit of its own inliers, as refining to convergence between findings
  // reaches, without converging on each set of inliers on the way. Kept even where it
  // raises the MSAC score a little (inliers near the threshold cross it): a least-squares
  // fit of the inliers is the more accurate estimate, and the descent cannot leave the
  // RANSAC model's basin.
  for (int step = 0; step < kFinalRefinementSteps; ++step) {
    Model refined = result.model;
    const RefinementStatus status = estimator.refine(best_inliers, &refined, 1);
    if (status == RefinementStatus::kFailed) break;
    result.model = refined;
    std::vector<int> inliers;
    find_inliers(estimator, refined, max_sq_error, &inliers);
    const bool unchanged = inliers == best_inliers;
    best_inliers.swap(inliers);
    if (static_cast<int>(best_inliers.size()) < kSampleSize) break;
    if (unchanged && status == RefinementStatus::kConverged) break;
  }
  result.success = true;
  result.num_inliers = static_cast<int>(best_inliers.size());
  result.inlier_mask.assign(num_data, 0);
  for (int i : best_inliers) result.inlier_mask[i] = 1;
  return result;
}

}  // namespace colmap_ext
