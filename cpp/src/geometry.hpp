// Conventions, written down once.
//
// Poses follow COLMAP: a Pose {R, t} maps x_to = R x_from + t (cam_from_world,
// cam2_from_cam1). The essential matrix is COLMAP's: x2^T E x1 = 0 for normalized
// homogeneous points, E = [t]_x R with (R, t) = cam2_from_cam1.
//
// OpenGV differs: its relative pose [R12|t12] maps camera 2 into camera 1
// (X1 = R12 X2 + t12), its absolute pose [R|t] is world_from_camera, and its
// essential matrices satisfy f1^T E f2 = 0, i.e. E_colmap = E_opengv^T.
// The functions below are the only places that translate between the two.
#pragma once

#include <Eigen/Core>
#include <opengv/types.hpp>
#include <utility>
#include <vector>

namespace colmap_ext {

struct Pose {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

// COLMAP cam2_from_cam1 <-> OpenGV [R12|t12] (cam1_from_cam2); the same inversion
// maps COLMAP cam_from_world <-> OpenGV world_from_camera.
inline Pose inverse(const Pose& pose) {
  return {pose.R.transpose(), -pose.R.transpose() * pose.t};
}

inline Pose from_opengv(const opengv::transformation_t& T) {
  return inverse(Pose{T.leftCols<3>(), T.col(3)});
}

// a_from_c = a_from_b * b_from_c.
inline Pose compose(const Pose& a_from_b, const Pose& b_from_c) {
  return {a_from_b.R * b_from_c.R, a_from_b.R * b_from_c.t + a_from_b.t};
}

// A calibrated camera rig (COLMAP's cam_from_rig per camera) and, per observation, the
// index of the camera that made it. OpenGV's non-central adapters take the inverse,
// rig_from_cam, as "camera offsets" (centres) and "camera rotations".
struct Rig {
  std::vector<Pose> cams_from_rig;
  opengv::translations_t offsets;  // camera centres in the rig frame
  opengv::rotations_t rotations;   // rig_from_cam rotations

  explicit Rig(std::vector<Pose> cams) : cams_from_rig(std::move(cams)) {
    for (const Pose& cam_from_rig : cams_from_rig) {
      const Pose rig_from_cam = inverse(cam_from_rig);
      offsets.push_back(rig_from_cam.t);
      rotations.push_back(rig_from_cam.R);
    }
  }
  int num_cameras() const { return static_cast<int>(cams_from_rig.size()); }
};

inline Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d S;
  S << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return S;
}

inline Eigen::Matrix3d essential_from_pose(const Pose& cam2_from_cam1) {
  return skew(cam2_from_cam1.t) * cam2_from_cam1.R;
}

}  // namespace colmap_ext
