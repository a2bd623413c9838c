#ifndef CROWDMAP_CORE_MODEL_CAMERA_MODEL_H_
#define CROWDMAP_CORE_MODEL_CAMERA_MODEL_H_

#include <cmath>

#include <Eigen/Core>

#include "core/model/passage.h"

namespace crowdmap {

// Smallest depth (m along the optical axis) at which a landmark counts as in front of the camera.
constexpr double kMinCameraDepthM = 0.1;

// Landmark in the camera frame for a vehicle pose (DESIGN section 4): v = R(theta)^T (L - p),
// c = R(yaw)^T (v - t_cam). Templated for automatic differentiation.
template <typename T>
Eigen::Matrix<T, 2, 1> LandmarkInCamera(const T* pose, const T* landmark, const Calibration& calib) {
  using std::cos;
  using std::sin;
  const T c = cos(pose[2]), s = sin(pose[2]);
  const T dx = landmark[0] - pose[0], dy = landmark[1] - pose[1];
  const T vx = c * dx + s * dy - T(calib.camera_position_m.x());
  const T vy = -s * dx + c * dy - T(calib.camera_position_m.y());
  const T cy = T(std::cos(calib.camera_yaw_rad)), sy = T(std::sin(calib.camera_yaw_rad));
  return {cy * vx + sy * vy, -sy * vx + cy * vy};
}

// The same with the camera turned by a further `yaw_offset_rad` (an estimated calibration error,
// added to calib.camera_yaw_rad).
template <typename T>
Eigen::Matrix<T, 2, 1> LandmarkInCamera(const T* pose, const T* landmark, const Calibration& calib,
                                        const T& yaw_offset_rad) {
  using std::cos;
  using std::sin;
  Calibration straight = calib;
  straight.camera_yaw_rad = 0.0;
  const Eigen::Matrix<T, 2, 1> v = LandmarkInCamera(pose, landmark, straight);
  const T yaw = T(calib.camera_yaw_rad) + yaw_offset_rad;
  const T cy = cos(yaw), sy = sin(yaw);
  return {cy * v.x() + sy * v.y(), -sy * v.x() + cy * v.y()};
}

// Horizontal pixel of a point in the camera frame (2D pinhole): u = -fx c_y / c_x + cx. False
// when it is not in front of the camera.
template <typename T>
bool ProjectCameraPoint(const Eigen::Matrix<T, 2, 1>& cam, const Calibration& calib, T* u_px) {
  if (!(cam.x() > T(kMinCameraDepthM))) return false;
  *u_px = -T(calib.fx_px) * cam.y() / cam.x() + T(calib.cx_px);
  return true;
}

// Horizontal pixel of a landmark. False when the landmark is not in front of the camera.
template <typename T>
bool ProjectLandmark(const T* pose, const T* landmark, const Calibration& calib, T* u_px) {
  return ProjectCameraPoint(LandmarkInCamera(pose, landmark, calib), calib, u_px);
}

inline Eigen::Vector2d LandmarkInCameraFrame(const Eigen::Vector3d& pose, const Eigen::Vector2d& landmark,
                                             const Calibration& calib) {
  return LandmarkInCamera(pose.data(), landmark.data(), calib);
}

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MODEL_CAMERA_MODEL_H_
