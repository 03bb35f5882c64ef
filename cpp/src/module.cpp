// pybind11 face of the solvers. Inputs arrive checked and normalised by the Python
// package `solvers` (unit rays, float64, C-contiguous); the RANSAC loops run with
// the GIL released.
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <stdexcept>
#include <string>

#include "absolute_pose.hpp"
#include "bundle_adjustment.hpp"
#include "largest.hpp"
#include "relative_pose.hpp"
#include "triangulation.hpp"

namespace py = pybind11;
using namespace colmap_ext;

namespace {

using RowsX3 = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
using RowsX12 = Eigen::Matrix<double, Eigen::Dynamic, 12, Eigen::RowMajor>;

opengv::bearingVectors_t to_vectors(const Eigen::Ref<const RowsX3>& rows) {
  opengv::bearingVectors_t out(rows.rows());
  for (Eigen::Index i = 0; i < rows.rows(); ++i) out[i] = rows.row(i).transpose();
  return out;
}

FivePointMethod five_point_method(const std::string& name) {
  if (name == "nister") return FivePointMethod::kNister;
  if (name == "stewenius") return FivePointMethod::kStewenius;
  throw std::invalid_argument("unknown 5-point method '" + name + "' (nister, stewenius)");
}

GeneralizedRelativeMethod generalized_relative_method(const std::string& name) {
  if (name == "sixpt") return GeneralizedRelativeMethod::kSixPoint;
  if (name == "fivept_plus_one") return GeneralizedRelativeMethod::kFivePlusOne;
  if (name == "seventeenpt") return GeneralizedRelativeMethod::kSeventeenPoint;
  throw std::invalid_argument("unknown generalized relative pose method '" + name +
                              "' (sixpt, fivept_plus_one, seventeenpt)");
}

// Poses from rows of their row-major 3x4 matrices [R | t].
std::vector<Pose> to_poses(const Eigen::Ref<const RowsX12>& rows) {
  std::vector<Pose> poses(rows.rows());
  for (Eigen::Index v = 0; v < rows.rows(); ++v) {
    Eigen::Map<const Eigen::Matrix<double, 3, 4, Eigen::RowMajor>> T(rows.row(v).data());
    poses[v] = {T.leftCols<3>(), T.col(3)};
  }
  return poses;
}

std::vector<int> to_indices(const Eigen::Ref<const Eigen::VectorXi>& values) {
  return std::vector<int>(values.data(), values.data() + values.size());
}

P3PMethod p3p_method(const std::string& name) {
  if (name == "kneip") return P3PMethod::kKneip;
  if (name == "gao") return P3PMethod::kGao;
  throw std::invalid_argument("unknown P3P method '" + name + "' (kneip, gao)");
}

std::vector<double> to_thresholds(const Eigen::Ref<const Eigen::VectorXd>& max_errors,
                                  Eigen::Index num_data) {
  if (max_errors.size() != num_data)
    throw std::invalid_argument("max_errors must hold one threshold per correspondence");
  return std::vector<double>(max_errors.data(), max_errors.data() + max_errors.size());
}

RansacOptions ransac_options(int max_iterations, int min_iterations, double confidence,
                             uint64_t seed) {
  RansacOptions options;
  options.max_iterations = max_iterations;
  options.min_iterations = min_iterations;
  options.confidence = confidence;
  options.seed = seed;
  return options;
}

py::dict ransac_dict(const RansacResult<Pose>& r) {
  py::array_t<bool> mask(static_cast<py::ssize_t>(r.inlier_mask.size()));
  auto m = mask.mutable_unchecked<1>();
  for (size_t i = 0; i < r.inlier_mask.size(); ++i) m(i) = r.inlier_mask[i] != 0;
  py::dict d;
  d["success"] = r.success;
  d["R"] = r.model.R;
  d["t"] = r.model.t;
  d["inlier_mask"] = mask;
  d["num_inliers"] = r.num_inliers;
  d["num_iterations"] = r.num_iterations;
  return d;
}

py::dict relative_pose(const Eigen::Ref<const RowsX3>& rays1, const Eigen::Ref<const RowsX3>& rays2,
                       const std::string& method,
                       const Eigen::Ref<const Eigen::VectorXd>& max_errors, int max_iterations,
                       int min_iterations, double confidence, uint64_t seed) {
  const FivePointMethod m = five_point_method(method);
  const opengv::bearingVectors_t f1 = to_vectors(rays1), f2 = to_vectors(rays2);
  const std::vector<double> thresholds = to_thresholds(max_errors, rays1.rows());
  RelativePoseResult result;
  {
    py::gil_scoped_release release;
    result = estimate_relative_pose(
        f1, f2, thresholds, m,
        ransac_options(max_iterations, min_iterations, confidence, seed));
  }
  py::dict d = ransac_dict(result.ransac);
  d["E"] = result.E;
  return d;
}

py::dict absolute_pose(const Eigen::Ref<const RowsX3>& rays, const Eigen::Ref<const RowsX3>& points,
                       const std::string& method,
                       const Eigen::Ref<const Eigen::VectorXd>& max_errors, int max_iterations,
                       int min_iterations, double confidence, uint64_t seed) {
  const P3PMethod m = p3p_method(method);
  const opengv::bearingVectors_t f = to_vectors(rays);
  const opengv::points_t X = to_vectors(points);
  const std::vector<double> thresholds = to_thresholds(max_errors, rays.rows());
  RansacResult<Pose> result;
  {
    py::gil_scoped_release release;
    result = estimate_absolute_pose(
        f, X, thresholds, m, ransac_options(max_iterations, min_iterations, confidence, seed));
  }
  return ransac_dict(result);
}

py::dict generalized_relative_pose(const Eigen::Ref<const RowsX3>& rays1,
                                   const Eigen::Ref<const Eigen::VectorXi>& camera_index1,
                                   const Eigen::Ref<const RowsX3>& rays2,
                                   const Eigen::Ref<const Eigen::VectorXi>& camera_index2,
                                   const Eigen::Ref<const RowsX12>& cams_from_rig,
                                   const std::string& method,
                                   const Eigen::Ref<const Eigen::VectorXd>& max_errors,
                                   int max_iterations, int min_iterations, double confidence,
                                   uint64_t seed) {
  const GeneralizedRelativeMethod m = generalized_relative_method(method);
  const opengv::bearingVectors_t f1 = to_vectors(rays1), f2 = to_vectors(rays2);
  const std::vector<int> c1 = to_indices(camera_index1), c2 = to_indices(camera_index2);
  const Rig rig(to_poses(cams_from_rig));
  const std::vector<double> thresholds = to_thresholds(max_errors, rays1.rows());
  RansacResult<Pose> result;
  {
    py::gil_scoped_release release;
    result = estimate_generalized_relative_pose(
        f1, c1, f2, c2, rig, thresholds, m,
        ransac_options(max_iterations, min_iterations, confidence, seed));
  }
  return ransac_dict(result);
}

py::dict generalized_absolute_pose(const Eigen::Ref<const RowsX3>& rays,
                                   const Eigen::Ref<const Eigen::VectorXi>& camera_index,
                                   const Eigen::Ref<const RowsX3>& points,
                                   const Eigen::Ref<const RowsX12>& cams_from_rig,
                                   const Eigen::Ref<const Eigen::VectorXd>& max_errors,
                                   int max_iterations, int min_iterations, double confidence,
                                   uint64_t seed) {
  const opengv::bearingVectors_t f = to_vectors(rays);
  const opengv::points_t X = to_vectors(points);
  const std::vector<int> cameras = to_indices(camera_index);
  const Rig rig(to_poses(cams_from_rig));
  const std::vector<double> thresholds = to_thresholds(max_errors, rays.rows());
  RansacResult<Pose> result;
  {
    py::gil_scoped_release release;
    result = estimate_generalized_absolute_pose(
        f, cameras, X, rig, thresholds,
        ransac_options(max_iterations, min_iterations, confidence, seed));
  }
  return ransac_dict(result);
}

std::vector<Eigen::Matrix3d> five_point_py(const Eigen::Ref<const RowsX3>& rays1,
                                           const Eigen::Ref<const RowsX3>& rays2,
                                           const std::string& method) {
  if (rays1.rows() != 5 || rays2.rows() != 5)
    throw std::invalid_argument("five_point takes exactly 5 ray pairs");
  return five_point(to_vectors(rays1), to_vectors(rays2), five_point_method(method));
}

std::vector<Eigen::Matrix<double, 3, 4>> p3p_py(const Eigen::Ref<const RowsX3>& rays,
                                                const Eigen::Ref<const RowsX3>& points,
                                                const std::string& method) {
  if (rays.rows() != 3 || points.rows() != 3)
    throw std::invalid_argument("p3p takes exactly 3 ray/point pairs");
  std::vector<Eigen::Matrix<double, 3, 4>> out;
  for (const Pose& pose : p3p(to_vectors(rays), to_vectors(points), p3p_method(method))) {
    Eigen::Matrix<double, 3, 4> T;
    T << pose.R, pose.t;
    out.push_back(T);
  }
  return out;
}

py::tuple triangulate_tracks_py(const Eigen::Ref<const RowsX12>& cams_from_world,
                                const Eigen::Ref<const Eigen::VectorXi>& view_index,
                                const Eigen::Ref<const Eigen::VectorXi>& point_index,
                                const Eigen::Ref<const RowsX3>& rays, int num_points,
                                double min_angle_deg) {
  const std::vector<Pose> poses = to_poses(cams_from_world);
  std::vector<Observation> observations(rays.rows());
  for (Eigen::Index k = 0; k < rays.rows(); ++k)
    observations[k] = {view_index[k], point_index[k], rays.row(k).transpose()};
  TriangulationResult result;
  {
    py::gil_scoped_release release;
    result = triangulate_tracks(poses, observations, num_points, min_angle_deg * M_PI / 180.0);
  }
  py::array_t<double> points({static_cast<py::ssize_t>(num_points), py::ssize_t{3}});
  py::array_t<bool> valid(num_points);
  auto p = points.mutable_unchecked<2>();
  auto v = valid.mutable_unchecked<1>();
  for (int i = 0; i < num_points; ++i) {
    for (int j = 0; j < 3; ++j) p(i, j) = result.points[i][j];
    v(i) = result.valid[i] != 0;
  }
  return py::make_tuple(points, valid);
}


using RowsX6 = Eigen::Matrix<double, Eigen::Dynamic, 6, Eigen::RowMajor>;
using BoolRowsX6 = Eigen::Matrix<bool, Eigen::Dynamic, 6, Eigen::RowMajor>;

Loss loss_type(const std::string& name) {
  if (name == "trivial") return Loss::kTrivial;
  if (name == "cauchy") return Loss::kCauchy;
  if (name == "huber") return Loss::kHuber;
  if (name == "soft_l1") return Loss::kSoftL1;
  throw std::invalid_argument("unknown loss '" + name + "' (trivial, cauchy, huber, soft_l1)");
}

py::tuple bundle_adjust_py(const Eigen::Ref<const RowsX12>& rigs_from_world,
                           const Eigen::Ref<const BoolRowsX6>& free_parameters,
                           const Eigen::Ref<const RowsX12>& sensors_from_rig,
                           const Eigen::Ref<const Eigen::VectorXi>& image_frame,
                           const Eigen::Ref<const RowsX3>& points,
                           const Eigen::Ref<const Eigen::Matrix<bool, Eigen::Dynamic, 1>>& point_variable,
                           const Eigen::Ref<const Eigen::VectorXi>& observation_image,
                           const Eigen::Ref<const Eigen::VectorXi>& observation_point,
                           const Eigen::Ref<const RowsX3>& rays,
                           const Eigen::Ref<const RowsX6>& pixels_from_tangent,
                           const std::string& loss, double loss_scale, int max_iterations,
                           double gradient_tolerance, double function_tolerance,
                           double max_step_scale, double initial_trust_region_radius,
                           int num_threads) {
  const Eigen::Index num_frames = rigs_from_world.rows(), num_images = sensors_from_rig.rows();
  const Eigen::Index num_points = points.rows(), num_observations = rays.rows();
  if (free_parameters.rows() != num_frames || image_frame.size() != num_images ||
      point_variable.size() != num_points || observation_image.size() != num_observations ||
      observation_point.size() != num_observations ||
      pixels_from_tangent.rows() != num_observations)
    throw std::invalid_argument("bundle_adjust: inconsistent array lengths");
  for (Eigen::Index i = 0; i < num_images; ++i)
    if (image_frame[i] < 0 || image_frame[i] >= num_frames)
      throw std::invalid_argument("bundle_adjust: image_frame out of range");
  std::vector<BundleObservation> observations(num_observations);
  for (Eigen::Index k = 0; k < num_observations; ++k) {
    if (observation_image[k] < 0 || observation_image[k] >= num_images ||
        observation_point[k] < 0 || observation_point[k] >= num_points)
      throw std::invalid_argument("bundle_adjust: observation index out of range");
    observations[k].image = observation_image[k];
    observations[k].point = observation_point[k];
    observations[k].ray = rays.row(k).transpose();
    observations[k].pixels_from_tangent =
        Eigen::Map<const Eigen::Matrix<double, 2, 3, Eigen::RowMajor>>(pixels_from_tangent.row(k).data());
  }
  std::vector<Pose> frames = to_poses(rigs_from_world);
  const std::vector<Pose> sensors = to_poses(sensors_from_rig);
  std::vector<Eigen::Matrix<bool, 6, 1>> free(num_frames);
  for (Eigen::Index f = 0; f < num_frames; ++f) free[f] = free_parameters.row(f).transpose();
  std::vector<Eigen::Vector3d> xyz(num_points);
  std::vector<char> variable(num_points);
  for (Eigen::Index p = 0; p < num_points; ++p) {
    xyz[p] = points.row(p).transpose();
    variable[p] = point_variable[p];
  }
  BundleOptions options;
  options.loss = loss_type(loss);
  options.loss_scale = loss_scale;
  options.max_iterations = max_iterations;
  options.gradient_tolerance = gradient_tolerance;
  options.function_tolerance = function_tolerance;
  options.max_step_scale = max_step_scale;
  options.initial_trust_region_radius = initial_trust_region_radius;
  options.num_threads = num_threads;
  BundleSummary summary;
  {
    py::gil_scoped_release release;
    summary = bundle_adjust(frames, free, sensors, to_indices(image_frame), xyz, variable,
                            observations, options);
  }
  py::array_t<double> frames_out({static_cast<py::ssize_t>(num_frames), py::ssize_t{12}});
  auto fo = frames_out.mutable_unchecked<2>();
  for (Eigen::Index f = 0; f < num_frames; ++f)
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) fo(f, 4 * r + c) = frames[f].R(r, c);
      fo(f, 4 * r + 3) = frames[f].t(r);
    }
  py::array_t<double> points_out({static_cast<py::ssize_t>(num_points), py::ssize_t{3}});
  auto po = points_out.mutable_unchecked<2>();
  for (Eigen::Index p = 0; p < num_points; ++p)
    for (int j = 0; j < 3; ++j) po(p, j) = xyz[p][j];
  py::dict info;
  info["iterations"] = summary.iterations;
  info["initial_cost"] = summary.initial_cost;
  info["final_cost"] = summary.final_cost;
  info["usable"] = summary.usable;
  return py::make_tuple(frames_out, points_out, info);
}

using FloatMatrix = py::array_t<float, py::array::c_style | py::array::forcecast>;
using Int64Vector = py::array_t<int64_t, py::array::c_style | py::array::forcecast>;

py::tuple largest_per_row_py(const FloatMatrix& values, int k, const Int64Vector& subset,
                             int k_subset) {
  if (values.ndim() != 2) throw std::invalid_argument("values must be a 2-D array");
  const py::ssize_t rows = values.shape(0), cols = values.shape(1), num_subset = subset.size();
  if (k < 0 || k_subset < 0) throw std::invalid_argument("k and k_subset must be >= 0");
  const int64_t* columns = subset.data();
  for (py::ssize_t s = 0; s < num_subset; ++s)
    if (columns[s] < 0 || columns[s] >= cols) throw std::invalid_argument("subset out of range");
  py::array_t<int64_t> index({rows, static_cast<py::ssize_t>(k)});
  py::array_t<float> best({rows, static_cast<py::ssize_t>(k)});
  py::array_t<int64_t> sub_index({rows, static_cast<py::ssize_t>(k_subset)});
  py::array_t<float> sub_best({rows, static_cast<py::ssize_t>(k_subset)});
  const float* data = values.data();
  int64_t* index_out = index.mutable_data();
  float* best_out = best.mutable_data();
  int64_t* sub_index_out = sub_index.mutable_data();
  float* sub_best_out = sub_best.mutable_data();
  {
    py::gil_scoped_release release;
    largest_per_row(data, rows, cols, k, columns, num_subset, k_subset, index_out, best_out,
                    sub_index_out, sub_best_out);
  }
  return py::make_tuple(index, best, sub_index, sub_best);
}

void largest_per_column_py(const FloatMatrix& values, int k, int64_t first_row,
                           py::array_t<int64_t, py::array::c_style> index,
                           py::array_t<float, py::array::c_style> best) {
  if (values.ndim() != 2) throw std::invalid_argument("values must be a 2-D array");
  const py::ssize_t rows = values.shape(0), cols = values.shape(1);
  if (k < 0) throw std::invalid_argument("k must be >= 0");
  for (const py::array* state : {static_cast<py::array*>(&index), static_cast<py::array*>(&best)})
    if (state->ndim() != 2 || state->shape(0) != cols || state->shape(1) != k)
      throw std::invalid_argument("index and best must be (columns, k) arrays");
  const float* data = values.data();
  int64_t* index_inout = index.mutable_data();
  float* best_inout = best.mutable_data();
  py::gil_scoped_release release;
  largest_per_column(data, rows, cols, k, first_row, index_inout, best_inout);
}

}  // namespace

PYBIND11_MODULE(_opengv, m) {
  m.doc() =
      "OpenGV minimal solvers and RANSAC in COLMAP's conventions (see geometry.hpp), and the "
      "mapper's bundle adjuster (bundle_adjustment.hpp) and its search kernels (largest.hpp).";
  m.def("relative_pose", &relative_pose, py::arg("rays1"), py::arg("rays2"), py::arg("method"),
        py::arg("max_errors"), py::arg("max_iterations"), py::arg("min_iterations"),
        py::arg("confidence"), py::arg("seed"));
  m.def("absolute_pose", &absolute_pose, py::arg("rays"), py::arg("points3D"), py::arg("method"),
        py::arg("max_errors"), py::arg("max_iterations"), py::arg("min_iterations"),
        py::arg("confidence"), py::arg("seed"));
  m.def("generalized_relative_pose", &generalized_relative_pose, py::arg("rays1"),
        py::arg("camera_index1"), py::arg("rays2"), py::arg("camera_index2"),
        py::arg("cams_from_rig"), py::arg("method"), py::arg("max_errors"),
        py::arg("max_iterations"), py::arg("min_iterations"), py::arg("confidence"),
        py::arg("seed"));
  m.def("generalized_absolute_pose", &generalized_absolute_pose, py::arg("rays"),
        py::arg("camera_index"), py::arg("points3D"), py::arg("cams_from_rig"),
        py::arg("max_errors"), py::arg("max_iterations"), py::arg("min_iterations"),
        py::arg("confidence"), py::arg("seed"));
  m.def("five_point", &five_point_py, py::arg("rays1"), py::arg("rays2"), py::arg("method"));
  m.def("p3p", &p3p_py, py::arg("rays"), py::arg("points3D"), py::arg("method"));
  m.def("triangulate_tracks", &triangulate_tracks_py, py::arg("cams_from_world"),
        py::arg("view_index"), py::arg("point_index"), py::arg("rays"), py::arg("num_points"),
        py::arg("min_angle_deg"));
  m.def("bundle_adjust", &bundle_adjust_py, py::arg("rigs_from_world"),
        py::arg("free_parameters"), py::arg("sensors_from_rig"), py::arg("image_frame"),
        py::arg("points"), py::arg("point_variable"), py::arg("observation_image"),
        py::arg("observation_point"), py::arg("rays"), py::arg("pixels_from_tangent"),
        py::arg("loss"), py::arg("loss_scale"), py::arg("max_iterations"),
        py::arg("gradient_tolerance"), py::arg("function_tolerance"),
        py::arg("max_step_scale"), py::arg("initial_trust_region_radius"),
        py::arg("num_threads"));
  m.def("largest_per_row", &largest_per_row_py, py::arg("values"), py::arg("k"),
        py::arg("subset"), py::arg("k_subset"));
  m.def("largest_per_column", &largest_per_column_py, py::arg("values"), py::arg("k"),
        py::arg("first_row"), py::arg("index").noconvert(), py::arg("best").noconvert());
}
