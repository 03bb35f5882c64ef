#include "relative_pose.hpp"

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <algorithm>
#include <array>
#include <random>
#include <type_traits>
#include <opengv/relative_pose/NoncentralRelativeAdapter.hpp>
#include <opengv/relative_pose/methods.hpp>
#include <opengv/relative_pose/modules/main.hpp>

#include "refinement.hpp"

namespace colmap_ext {
namespace {

using opengv::bearingVectors_t;
using opengv::relative_pose::NoncentralRelativeAdapter;

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

// The angular Sampson error over its threshold, squared (inlier below 1).
inline double weighted_squared_sampson(const Eigen::Matrix3d& E, const Eigen::Vector3d& f1,
                                       const Eigen::Vector3d& f2, double weight) {
  const SampsonTerms s = sampson_terms(E, f1, f2);
  return weight * weight * s.c * s.c / s.d;
}

// E = [t]x R has two rotations, Ra and Rb, and the unit translation t up to its sign.
struct EssentialDecomposition {
  Eigen::Matrix3d Ra, Rb;
  Eigen::Vector3d t;
};

EssentialDecomposition decompose(const Eigen::Matrix3d& E) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(E, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d U = svd.matrixU();
  Eigen::Matrix3d V = svd.matrixV();
  if (U.determinant() < 0) U = -U;
  if (V.determinant() < 0) V = -V;
  Eigen::Matrix3d W;
  W << 0, 1, 0, -1, 0, 0, 0, 0, 1;
  return {U * W * V.transpose(), U * W.transpose() * V.transpose(), U.col(2).normalized()};
}

// The angular Sampson error r of one pair and its gradient G = dr/dE over E's entries.
double sampson_residual(const Eigen::Matrix3d& E, const Eigen::Vector3d& f1,
                        const Eigen::Vector3d& f2, Eigen::Matrix3d* G) {
  const SampsonTerms s = sampson_terms(E, f1, f2);
  const double inv_sqrt_d = 1.0 / std::sqrt(s.d);
  const double r = s.c * inv_sqrt_d;
  // dr/dE = f2 f1^T / sqrt(d) - (r / d) (g2 f1^T + f2 g1^T)
  const double k = r * inv_sqrt_d * inv_sqrt_d;
  *G = inv_sqrt_d * f2 * f1.transpose() - k * (s.g2 * f1.transpose() + f2 * s.g1.transpose());
  return r;
}

// Least squares over the inliers' angular Sampson errors, each over its threshold (see
// refinement.hpp), in the rotation (exp(w) R) and the direction of translation (t + B u,
// renormalized, with B a basis of the plane orthogonal to t): 5 degrees of freedom.
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
      Eigen::Matrix3d G;
      const double r = weights_[i] * sampson_residual(E, rays1_[i], rays2_[i], &G);
      Vec J;
      for (int p = 0; p < 5; ++p) J[p] = weights_[i] * G.cwiseProduct(dE[p]).sum();
      *JtJ += J * J.transpose();
      *Jtr += r * J;
      cost += r * r;
    }
    return cost;
  }

  double cost(const Vec& delta) const {
    const Eigen::Matrix3d E = essential_from_pose(moved(delta));
    double cost = 0.0;
    for (int i : inliers_) cost += weighted_squared_sampson(E, rays1_[i], rays2_[i], weights_[i]);
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
      : rays1_(rays1), rays2_(rays2), method_(method),
        weights_(weights_from_thresholds(max_errors)) {}

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

  // The angular Sampson errors over the pairs' thresholds, squared (inlier below 1).
  void squared_errors(const Model& model, size_t begin, size_t end, double* errors) const {
    for (size_t i = begin; i < end; ++i)
      *errors++ = weighted_squared_sampson(model.E, rays1_[i], rays2_[i], weights_[i]);
  }

  // Levenberg-Marquardt on the inliers' Sampson errors (5 degrees of freedom).
  RefinementStatus refine(const std::vector<int>& inliers, Model* model,
                          int max_iterations) const {
    if (!model->has_pose) {
      model->pose = decompose_essential(model->E, rays1_, rays2_, inliers);
      model->has_pose = true;
    }
    SampsonRefinement problem(rays1_, rays2_, weights_, inliers, &model->pose);
    const RefinementStatus status = levenberg_marquardt<5>(problem, max_iterations);
    if (status != RefinementStatus::kFailed) model->E = essential_from_pose(model->pose);
    return status;
  }

 private:
  const bearingVectors_t& rays1_;
  const bearingVectors_t& rays2_;
  FivePointMethod method_;
  std::vector<double> weights_;  // 1 / each pair's threshold
};

// cam2_from_cam1 for camera c1 of a rig in frame 1 and camera c2 in frame 2.
Pose camera_pair_pose(const Rig& rig, const Pose& rig2_from_rig1, int c1, int c2) {
  return compose(compose(rig.cams_from_rig[c2], rig2_from_rig1), inverse(rig.cams_from_rig[c1]));
}

// The essential matrix (COLMAP's) of every camera pair of a rig, given rig2_from_rig1:
// index c1 * K + c2 for a ray of camera c1 in the first frame and of c2 in the second.
std::vector<Eigen::Matrix3d> pair_essentials(const Rig& rig, const Pose& rig2_from_rig1) {
  const int K = rig.num_cameras();
  std::vector<Eigen::Matrix3d> essentials(K * K);
  for (int c1 = 0; c1 < K; ++c1)
    for (int c2 = 0; c2 < K; ++c2)
      essentials[c1 * K + c2] = essential_from_pose(camera_pair_pose(rig, rig2_from_rig1, c1, c2));
  return essentials;
}

// Least squares over the inliers' angular Sampson errors, each in its camera pair and
// over its threshold (see refinement.hpp), in the rotation (exp(w) R) and the translation
// (t + u) of rig2_from_rig1: 6 degrees of freedom, the rig's baseline fixing the scale.
class GeneralizedSampsonRefinement {
 public:
  using Vec = Eigen::Matrix<double, 6, 1>;
  using Mat = Eigen::Matrix<double, 6, 6>;

  GeneralizedSampsonRefinement(const bearingVectors_t& rays1, const bearingVectors_t& rays2,
                               const std::vector<double>& weights, const std::vector<int>& pair,
                               const Rig& rig, const std::vector<int>& inliers,
                               Pose* rig2_from_rig1)
      : rays1_(rays1), rays2_(rays2), weights_(weights), pair_(pair), rig_(rig),
        inliers_(inliers), pose_(*rig2_from_rig1) {}

  double linearize(Mat* JtJ, Vec* Jtr) const {
    // Per camera pair: E = [t_p]x R_p with R_p = R2 R R1^T and t_p = R2 (t + R o1) + t2
    // (cam_from_rig = (R1, t1), (R2, t2); o1 camera 1's centre in the rig).
    const int K = rig_.num_cameras();
    std::vector<Eigen::Matrix3d> E(K * K);
    std::vector<std::array<Eigen::Matrix3d, 6>> dE(K * K);
    for (int c1 = 0; c1 < K; ++c1) {
      const Pose& cam1_from_rig = rig_.cams_from_rig[c1];
      const Eigen::Vector3d R_o1 = pose_.R * rig_.offsets[c1];
      for (int c2 = 0; c2 < K; ++c2) {
        const Pose& cam2_from_rig = rig_.cams_from_rig[c2];
        const Pose p = camera_pair_pose(rig_, pose_, c1, c2);
        const int k = c1 * K + c2;
        E[k] = essential_from_pose(p);
        for (int j = 0; j < 3; ++j) {
          const Eigen::Vector3d axis = Eigen::Vector3d::Unit(j);
          const Eigen::Matrix3d dR = cam2_from_rig.R * skew(axis) * pose_.R * cam1_from_rig.R.transpose();
          const Eigen::Vector3d dt = cam2_from_rig.R * axis.cross(R_o1);
          dE[k][j] = skew(dt) * p.R + skew(p.t) * dR;
          dE[k][3 + j] = skew(cam2_from_rig.R.col(j)) * p.R;
        }
      }
    }
    JtJ->setZero();
    Jtr->setZero();
    double cost = 0.0;
    for (int i : inliers_) {
      Eigen::Matrix3d G;
      const double r = weights_[i] * sampson_residual(E[pair_[i]], rays1_[i], rays2_[i], &G);
      Vec J;
      for (int p = 0; p < 6; ++p) J[p] = weights_[i] * G.cwiseProduct(dE[pair_[i]][p]).sum();
      *JtJ += J * J.transpose();
      *Jtr += r * J;
      cost += r * r;
    }
    return cost;
  }

  double cost(const Vec& delta) const {
    const std::vector<Eigen::Matrix3d> E = pair_essentials(rig_, moved(delta));
    double cost = 0.0;
    for (int i : inliers_)
      cost += weighted_squared_sampson(E[pair_[i]], rays1_[i], rays2_[i], weights_[i]);
    return cost;
  }

  void commit(const Vec& delta) { pose_ = moved(delta); }

 private:
  Pose moved(const Vec& delta) const {
    return {rotate_by(delta.head<3>(), pose_.R), pose_.t + delta.tail<3>()};
  }

  const bearingVectors_t& rays1_;
  const bearingVectors_t& rays2_;
  const std::vector<double>& weights_;  // 1 / each pair's threshold
  const std::vector<int>& pair_;
  const Rig& rig_;
  const std::vector<int>& inliers_;
  Pose& pose_;
};

// rig2_from_rig1 with the essential matrices of its camera pairs (pair_essentials).
struct GeneralizedRelativeModel {
  Pose pose;
  std::vector<Eigen::Matrix3d> essentials;
};

// Generalized relative pose (see GeneralizedRelativeMethod) inside LO-MSAC.
template <GeneralizedRelativeMethod kMethod>
class GeneralizedRelativePoseEstimator {
 public:
  using Model = GeneralizedRelativeModel;
  static constexpr int kSampleSize =
      kMethod == GeneralizedRelativeMethod::kSeventeenPoint ? 17 : 6;

  GeneralizedRelativePoseEstimator(const bearingVectors_t& rays1, const std::vector<int>& cameras1,
                                   const bearingVectors_t& rays2, const std::vector<int>& cameras2,
                                   const Rig& rig, const std::vector<double>& max_errors)
      : rays1_(rays1), cameras1_(cameras1), rays2_(rays2), cameras2_(cameras2), rig_(rig),
        adapter_(rays1, rays2, cameras1, cameras2, rig.offsets, rig.rotations),
        weights_(weights_from_thresholds(max_errors)) {
    members_of_pair_.resize(rig.num_cameras() * rig.num_cameras());
    for (size_t i = 0; i < rays1.size(); ++i) {
      pair_.push_back(cameras1[i] * rig.num_cameras() + cameras2[i]);
      members_of_pair_[pair_.back()].push_back(static_cast<int>(i));
      origin1_.push_back(rig.offsets[cameras1[i]]);
      origin2_.push_back(rig.offsets[cameras2[i]]);
      direction1_.push_back(rig.rotations[cameras1[i]] * rays1[i]);
      direction2_.push_back(rig.rotations[cameras2[i]] * rays2[i]);
    }
  }

  size_t num_data() const { return pair_.size(); }

  // 5+1: five pairs of one camera pair (the camera pair of a pair drawn at random) and
  // one of another; uniform where the data has no such sample.
  template <GeneralizedRelativeMethod M = kMethod,
            std::enable_if_t<M == GeneralizedRelativeMethod::kFivePlusOne, int> = 0>
  void draw_sample(std::mt19937_64& rng, std::vector<int>* sample) const {
    const int n = static_cast<int>(num_data());
    std::uniform_int_distribution<int> any(0, n - 1);
    const int anchor = any(rng);
    const std::vector<int>& same = members_of_pair_[pair_[anchor]];
    const int num_same = static_cast<int>(same.size());
    const auto distinct = [&](int k, const auto& draw) {  // draw() until new to the sample
      do (*sample)[k] = draw();
      while (std::find(sample->begin(), sample->begin() + k, (*sample)[k]) != sample->begin() + k);
    };
    if (num_same < 5 || num_same == n) {
      for (int k = 0; k < kSampleSize; ++k) distinct(k, [&] { return any(rng); });
      return;
    }
    std::uniform_int_distribution<int> member(0, num_same - 1);
    (*sample)[0] = anchor;
    for (int k = 1; k < 5; ++k) distinct(k, [&] { return same[member(rng)]; });
    int other;
    do other = any(rng);
    while (pair_[other] == pair_[anchor]);
    (*sample)[5] = other;
  }

  // Samples from a single camera pair are skipped: one pair's essential matrix leaves the
  // translation's scale open (and OpenGV's 6-point solver takes 100x longer on them).
  void minimal_solve(const std::vector<int>& sample, std::vector<Model>* models) const {
    const auto same_pair = [&](int i) { return pair_[i] == pair_[sample[0]]; };
    if (std::all_of(sample.begin(), sample.end(), same_pair)) return;
    if constexpr (kMethod == GeneralizedRelativeMethod::kSixPoint) {
      // OpenGV's rotations map frame 2 into frame 1; each gets its translation. OpenGV
      // returns all 64 roots, complex ones by their real parts; scoring tells them apart.
      for (const auto& R12 : opengv::relative_pose::sixpt(adapter_, sample)) {
        if (!R12.allFinite()) continue;
        const Eigen::Matrix3d R = R12.transpose();
        const Pose rig2_from_rig1{R, translation_given_rotation(R, sample)};
        add_model({rig2_from_rig1, pair_essentials(rig_, rig2_from_rig1)}, sample, models);
      }
    } else if constexpr (kMethod == GeneralizedRelativeMethod::kFivePlusOne) {
      five_plus_one(sample, models);
    } else {
      const opengv::transformation_t T = opengv::relative_pose::seventeenpt(adapter_, sample);
      if (!T.allFinite()) return;
      const Pose rig2_from_rig1 = from_opengv(T);
      add_model({rig2_from_rig1, pair_essentials(rig_, rig2_from_rig1)}, sample, models);
    }
  }

  // The angular Sampson errors in the pairs' camera pairs over their thresholds, squared.
  void squared_errors(const Model& model, size_t begin, size_t end, double* errors) const {
    for (size_t i = begin; i < end; ++i)
      *errors++ = weighted_squared_sampson(model.essentials[pair_[i]], rays1_[i], rays2_[i],
                                           weights_[i]);
  }

  RefinementStatus refine(const std::vector<int>& inliers, Model* model,
                          int max_iterations) const {
    GeneralizedSampsonRefinement problem(rays1_, rays2_, weights_, pair_, rig_, inliers,
                                         &model->pose);
    const RefinementStatus status = levenberg_marquardt<6>(problem, max_iterations);
    if (status != RefinementStatus::kFailed) model->essentials = pair_essentials(rig_, model->pose);
    return status;
  }

 private:
  // Keeps a solution that puts every sample pair in front of its cameras. Sampson errors
  // cannot tell a solution from its twisted pair (turned 180 deg about the translation),
  // which the solvers also return, and which fits as well where the baseline dwarfs
  // the rig.
  void add_model(const Model& model, const std::vector<int>& sample,
                 std::vector<Model>* models) const {
    for (int i : sample) {
      const Pose cam2_from_cam1 = camera_pair_pose(rig_, model.pose, cameras1_[i], cameras2_[i]);
      if (!in_front(cam2_from_cam1, rays1_[i], rays2_[i])) return;
    }
    models->push_back(model);
  }

  // The 5-point solver (OpenGV's Stewenius) on the first five pairs, all of cameras
  // (c1, c2), gives R and the direction of t of cam2_from_cam1 = (R_p, l t_p); the
  // sixth pair, of other cameras, gives the scale l: rig2_from_rig1 = (R, a + l b) with
  // R = R2^T R_p R1, a = R2^T (R_p t1 - t2), b = R2^T t_p, and its rays must meet.
  void five_plus_one(const std::vector<int>& sample, std::vector<Model>* models) const {
    const auto first_pair = [&](int i) { return pair_[i] == pair_[sample[0]]; };
    if (!std::all_of(sample.begin(), sample.begin() + 5, first_pair) || first_pair(sample[5]))
      return;
    const Pose& cam1_from_rig = rig_.cams_from_rig[cameras1_[sample[0]]];
    const Pose& cam2_from_rig = rig_.cams_from_rig[cameras2_[sample[0]]];
    std::vector<Eigen::Matrix3d> essentials;
    five_point_from_null_space(epipolar_null_space(rays1_, rays2_, sample.data()),
                               FivePointMethod::kStewenius, &essentials);
    const int j = sample[5];
    for (const Eigen::Matrix3d& E : essentials) {
      const EssentialDecomposition d = decompose(E);
      for (const Eigen::Matrix3d& R_pair : {d.Ra, d.Rb}) {
        const Eigen::Matrix3d R = cam2_from_rig.R.transpose() * R_pair * cam1_from_rig.R;
        const Eigen::Vector3d a =
            cam2_from_rig.R.transpose() * (R_pair * cam1_from_rig.t - cam2_from_rig.t);
        const Eigen::Vector3d b = cam2_from_rig.R.transpose() * d.t;
        const Eigen::Vector3d n = (R * direction1_[j]).cross(direction2_[j]);
        const double denominator = n.dot(b);
        if (std::abs(denominator) < 1e-12) continue;
        const double scale = (n.dot(origin2_[j] - R * origin1_[j]) - n.dot(a)) / denominator;
        const Pose rig2_from_rig1{R, a + scale * b};
        add_model({rig2_from_rig1, pair_essentials(rig_, rig2_from_rig1)}, sample, models);
      }
    }
  }

  // The least-squares t of rig2_from_rig1 = (R, t) that makes each sample's two rays
  // meet: (R d1 x d2) . t = (R d1 x d2) . (o2 - R o1) for rays o + l d in the rig frames.
  Eigen::Vector3d translation_given_rotation(const Eigen::Matrix3d& R,
                                             const std::vector<int>& sample) const {
    Eigen::Matrix3d AtA = Eigen::Matrix3d::Zero();
    Eigen::Vector3d Atb = Eigen::Vector3d::Zero();
    for (int i : sample) {
      const Eigen::Vector3d n = (R * direction1_[i]).cross(direction2_[i]);
      AtA += n * n.transpose();
      Atb += n * n.dot(origin2_[i] - R * origin1_[i]);
    }
    return AtA.ldlt().solve(Atb);
  }

  const bearingVectors_t& rays1_;
  const std::vector<int>& cameras1_;
  const bearingVectors_t& rays2_;
  const std::vector<int>& cameras2_;
  const Rig& rig_;
  const NoncentralRelativeAdapter adapter_;
  std::vector<double> weights_;           // 1 / each pair's threshold
  std::vector<int> pair_;                 // camera pair of each correspondence (pair_essentials)
  std::vector<std::vector<int>> members_of_pair_;  // correspondences by camera pair
  opengv::translations_t origin1_, origin2_;     // camera centres in the rig frames
  opengv::bearingVectors_t direction1_, direction2_;  // rays in the rig frames
};

template <GeneralizedRelativeMethod kMethod>
RansacResult<Pose> run_generalized_relative(const bearingVectors_t& rays1,
                                            const std::vector<int>& cameras1,
                                            const bearingVectors_t& rays2,
                                            const std::vector<int>& cameras2, const Rig& rig,
                                            const std::vector<double>& max_errors,
                                            RansacOptions options) {
  const GeneralizedRelativePoseEstimator<kMethod> estimator(rays1, cameras1, rays2, cameras2, rig,
                                                            max_errors);
  options.max_error = 1.0;  // errors arrive divided by their thresholds
  RansacResult<GeneralizedRelativeModel> found = ransac(estimator, options);
  RansacResult<Pose> result;
  result.success = found.success;
  result.model = found.model.pose;
  result.inlier_mask = std::move(found.inlier_mask);
  result.num_inliers = found.num_inliers;
  result.num_iterations = found.num_iterations;
  return result;
}

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
  const EssentialDecomposition d = decompose(E);
  const Pose candidates[4] = {{d.Ra, d.t}, {d.Ra, -d.t}, {d.Rb, d.t}, {d.Rb, -d.t}};
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

RansacResult<Pose> estimate_generalized_relative_pose(const bearingVectors_t& rays1,
                                                      const std::vector<int>& cameras1,
                                                      const bearingVectors_t& rays2,
                                                      const std::vector<int>& cameras2,
                                                      const Rig& rig,
                                                      const std::vector<double>& max_errors,
                                                      GeneralizedRelativeMethod method,
                                                      const RansacOptions& options) {
  switch (method) {
    case GeneralizedRelativeMethod::kSixPoint:
      return run_generalized_relative<GeneralizedRelativeMethod::kSixPoint>(
          rays1, cameras1, rays2, cameras2, rig, max_errors, options);
    case GeneralizedRelativeMethod::kFivePlusOne:
      return run_generalized_relative<GeneralizedRelativeMethod::kFivePlusOne>(
          rays1, cameras1, rays2, cameras2, rig, max_errors, options);
    default:
      return run_generalized_relative<GeneralizedRelativeMethod::kSeventeenPoint>(
          rays1, cameras1, rays2, cameras2, rig, max_errors, options);
  }
}

}  // namespace colmap_ext
