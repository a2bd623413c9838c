#ifndef CROWDMAP_CORE_ESTIMATION_FACTORS_H_
#define CROWDMAP_CORE_ESTIMATION_FACTORS_H_

#include <cmath>
#include <vector>

#include <Eigen/Core>
#include <ceres/ceres.h>

#include "core/model/camera_model.h"
#include "core/model/motion_model.h"
#include "core/model/passage.h"

namespace crowdmap {

// Square-root information S of a covariance C (S^T S = C^-1), so that S r is whitened.
Eigen::MatrixXd SqrtInformation(const Eigen::MatrixXd& cov);

template <typename T>
T NormalizeAngle(const T& a) {
  using std::floor;
  return a - T(2.0 * M_PI) * floor((a + T(M_PI)) / T(2.0 * M_PI));
}

// Relative motion between consecutive poses a -> b from preintegrated odometry. Residual, in the
// frame of pose a: (R(theta_a)^T (p_b - p_a) - delta_xy, wrap(theta_b - theta_a - delta_theta)),
// whitened by the preintegration covariance. Blocks: pose a (3), pose b (3).
class OdometryFactor {
 public:
  OdometryFactor(const Pose2& delta, const Eigen::Matrix3d& sqrt_info) : delta_(delta), sqrt_info_(sqrt_info) {}

  template <typename T>
  bool operator()(const T* a, const T* b, T* residual) const {
    Residual(a, b, T(1.0), delta_, sqrt_info_, residual);
    return true;
  }

  static ceres::CostFunction* Create(const RelativeMotion& motion);

  // The residual with the displacement delta_xy taken `scale` times (ScaledOdometryFactor).
  template <typename T>
  static void Residual(const T* a, const T* b, const T& scale, const Pose2& delta, const Eigen::Matrix3d& sqrt_info,
                       T* residual) {
    const T c = cos(a[2]), s = sin(a[2]);
    const T dx = b[0] - a[0], dy = b[1] - a[1];
    Eigen::Matrix<T, 3, 1> r;
    r << c * dx + s * dy - scale * T(delta.x()), -s * dx + c * dy - scale * T(delta.y()),
        NormalizeAngle(b[2] - a[2] - T(delta.z()));
    Eigen::Map<Eigen::Matrix<T, 3, 1>> out(residual);
    out = sqrt_info.cast<T>() * r;
  }

 private:
  Pose2 delta_;
  Eigen::Matrix3d sqrt_info_;
};

// OdometryFactor with a scale s of the distance travelled as a third block: the preintegrated
// motion becomes (s delta_xy, delta_theta). The turn is left as measured: encoders that report
// the speed times 1/s also turn the bicycle model's heading by 1/s of the true turn, but letting s
// scale the turn too biased its estimate (measured on the loop: s drifted from +0.1% to -0.2%
// over 100 clean passages, the map shrank with it and its error grew by 37%); the heading noise
// absorbs what the turn's share leaves. The covariance is the preintegration's, at s = 1.
// Blocks: pose a (3), pose b (3), scale (1).
class ScaledOdometryFactor {
 public:
  ScaledOdometryFactor(const Pose2& delta, const Eigen::Matrix3d& sqrt_info) : delta_(delta), sqrt_info_(sqrt_info) {}

  template <typename T>
  bool operator()(const T* a, const T* b, const T* scale, T* residual) const {
    OdometryFactor::Residual(a, b, scale[0], delta_, sqrt_info_, residual);
    return true;
  }

  static ceres::CostFunction* Create(const RelativeMotion& motion);

 private:
  Pose2 delta_;
  Eigen::Matrix3d sqrt_info_;
};

// GNSS antenna position: residual p + R(theta) lever_arm - y, whitened by the fix covariance
// (expressed in the estimation frame). Block: pose (3).
class GnssFactor {
 public:
  GnssFactor(const Eigen::Vector2d& measured, const Eigen::Vector2d& lever_arm, const Eigen::Matrix2d& sqrt_info)
      : measured_(measured), lever_arm_(lever_arm), sqrt_info_(sqrt_info) {}

  template <typename T>
  bool operator()(const T* pose, T* residual) const {
    const T c = cos(pose[2]), s = sin(pose[2]);
    Eigen::Matrix<T, 2, 1> r;
    r << pose[0] + c * T(lever_arm_.x()) - s * T(lever_arm_.y()) - T(measured_.x()),
        pose[1] + s * T(lever_arm_.x()) + c * T(lever_arm_.y()) - T(measured_.y());
    Eigen::Map<Eigen::Matrix<T, 2, 1>> out(residual);
    out = sqrt_info_.cast<T>() * r;
    return true;
  }

  static ceres::CostFunction* Create(const Eigen::Vector2d& measured, const Eigen::Matrix2d& cov,
                                     const Eigen::Vector2d& lever_arm);

 private:
  Eigen::Vector2d measured_;
  Eigen::Vector2d lever_arm_;
  Eigen::Matrix2d sqrt_info_;
};

// Two consecutive GNSS fixes whose errors follow a first-order Gauss-Markov process (see
// NoiseModel::gnss_correlation_time_s): with z = S (antenna(pose) - y) the normalised error of a
// fix (S its stationary square-root information), the process's white innovation
//   r = (z_k - alpha z_(k-1)) / sqrt(1 - alpha^2),
// unit-variance and independent of every other innovation and of the first fix's z_0 (a plain
// GnssFactor), so a chain of these whitens the correlated sequence exactly. Blocks: the pose of
// fix k-1 (3), the pose of fix k (3); CreateAtOneNode when both fixes share a pose node.
class GnssAr1Factor {
 public:
  GnssAr1Factor(const Eigen::Vector2d& previous_measured, const Eigen::Matrix2d& previous_sqrt_info,
                const Eigen::Vector2d& measured, const Eigen::Matrix2d& sqrt_info, const Eigen::Vector2d& lever_arm,
                double alpha)
      : previous_measured_(previous_measured),
        previous_sqrt_info_(previous_sqrt_info),
        measured_(measured),
        sqrt_info_(sqrt_info),
        lever_arm_(lever_arm),
        alpha_(alpha),
        inv_beta_(1.0 / std::sqrt(1.0 - alpha * alpha)) {}

  template <typename T>
  bool operator()(const T* previous_pose, const T* pose, T* residual) const {
    const Eigen::Matrix<T, 2, 1> z_previous = previous_sqrt_info_.cast<T>() * (Antenna(previous_pose) - previous_measured_.cast<T>());
    const Eigen::Matrix<T, 2, 1> z = sqrt_info_.cast<T>() * (Antenna(pose) - measured_.cast<T>());
    Eigen::Map<Eigen::Matrix<T, 2, 1>> out(residual);
    out = (z - T(alpha_) * z_previous) * T(inv_beta_);
    return true;
  }

  // The innovation between fixes `dt_s` apart, each with its stationary covariance.
  static ceres::CostFunction* Create(const Eigen::Vector2d& previous_measured, const Eigen::Matrix2d& previous_cov,
                                     const Eigen::Vector2d& measured, const Eigen::Matrix2d& cov,
                                     const Eigen::Vector2d& lever_arm, double dt_s, double correlation_time_s);
  static ceres::CostFunction* CreateAtOneNode(const Eigen::Vector2d& previous_measured,
                                              const Eigen::Matrix2d& previous_cov, const Eigen::Vector2d& measured,
                                              const Eigen::Matrix2d& cov, const Eigen::Vector2d& lever_arm, double dt_s,
                                              double correlation_time_s);
  // alpha = exp(-dt / tau).
  static double Alpha(double dt_s, double correlation_time_s);

 private:
  template <typename T>
  Eigen::Matrix<T, 2, 1> Antenna(const T* pose) const {
    const T c = cos(pose[2]), s = sin(pose[2]);
    return Eigen::Matrix<T, 2, 1>(pose[0] + c * T(lever_arm_.x()) - s * T(lever_arm_.y()),
                                  pose[1] + s * T(lever_arm_.x()) + c * T(lever_arm_.y()));
  }

  Eigen::Vector2d previous_measured_;
  Eigen::Matrix2d previous_sqrt_info_;
  Eigen::Vector2d measured_;
  Eigen::Matrix2d sqrt_info_;
  Eigen::Vector2d lever_arm_;
  double alpha_;
  double inv_beta_;
};

// One detection: residual (u_predicted - u_measured) / sigma_px. Blocks: pose (3), landmark (2).
class CameraFactor {
 public:
  CameraFactor(double u_px, double sigma_px, const Calibration& calib)
      : u_px_(u_px), inv_sigma_(1.0 / sigma_px), calib_(calib) {}

  template <typename T>
  bool operator()(const T* pose, const T* landmark, T* residual) const {
    return Residual(LandmarkInCamera(pose, landmark, calib_), residual);
  }

  static ceres::CostFunction* Create(double u_px, double sigma_px, const Calibration& calib);

 protected:
  // The whitened pixel residual of a landmark at `cam` in the camera frame.
  template <typename T>
  bool Residual(const Eigen::Matrix<T, 2, 1>& cam, T* residual) const {
    T u;
    if (!ProjectCameraPoint(cam, calib_, &u)) return false;
    residual[0] = (u - T(u_px_)) * T(inv_sigma_);
    return true;
  }

  double u_px_;
  double inv_sigma_;
  Calibration calib_;
};

// One detection by a camera whose yaw is off its declared calibration by an estimated offset
// (shared by every detection of the vehicle's passage): residual (u_predicted - u_measured) /
// sigma_px with the camera turned by calib.camera_yaw_rad + offset. Blocks: pose (3), landmark
// (2), camera yaw offset (1, rad).
class CameraYawFactor : public CameraFactor {
 public:
  using CameraFactor::CameraFactor;

  template <typename T>
  bool operator()(const T* pose, const T* landmark, const T* yaw_offset, T* residual) const {
    return Residual(LandmarkInCamera(pose, landmark, calib_, yaw_offset[0]), residual);
  }

  static ceres::CostFunction* Create(double u_px, double sigma_px, const Calibration& calib);
};

// Adds one detection's pixel residual to `problem`: a CameraFactor, or with `yaw_offset_rad` (a
// camera yaw offset state, or nullptr) a CameraYawFactor on it.
ceres::ResidualBlockId AddCameraResidual(double u_px, double sigma_px, const Calibration& calib,
                                         ceres::LossFunction* loss, double* pose, double* landmark,
                                         double* yaw_offset_rad, ceres::Problem* problem);

// Gaussian prior on a scalar state (a camera yaw offset): residual (x - mean) / sigma. Block: x (1).
class ScalarPriorFactor {
 public:
  ScalarPriorFactor(double mean, double sigma) : mean_(mean), inv_sigma_(1.0 / sigma) {}

  template <typename T>
  bool operator()(const T* x, T* residual) const {
    residual[0] = (x[0] - T(mean_)) * T(inv_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double mean, double sigma);

 private:
  double mean_;
  double inv_sigma_;
};

// Bearing form of a detection, used to localise a passage against the map before the pixel
// model is solved: residual wrap(atan2(c_y, c_x) - b) / sigma_b, with b = atan2(cx - u, fx) and
// sigma_b the pixel sigma mapped through the projection at u (first order). Unlike the pixel
// residual it is bounded and defined for landmarks behind the camera, so it converges from
// initial guesses tens of metres off. Blocks: pose (3), landmark (2).
class BearingFactor {
 public:
  BearingFactor(double u_px, double sigma_px, const Calibration& calib);

  template <typename T>
  bool operator()(const T* pose, const T* landmark, T* residual) const {
    using std::atan2;
    const Eigen::Matrix<T, 2, 1> cam = LandmarkInCamera(pose, landmark, calib_);
    residual[0] = NormalizeAngle(atan2(cam.y(), cam.x()) - T(bearing_rad_)) * T(inv_sigma_rad_);
    return true;
  }

  static ceres::CostFunction* Create(double u_px, double sigma_px, const Calibration& calib);

 private:
  double bearing_rad_;
  double inv_sigma_rad_;
  Calibration calib_;
};

// A bearing (BearingFactor) from a pose held fixed but for a translation, interpolated between two
// knots of a piecewise-linear offset, (1 - w) a + w b, to a landmark held fixed: it aligns a
// trajectory to the map before the trajectory itself is solved. Blocks: knot a (2), knot b (2).
class ShiftedBearingFactor {
 public:
  ShiftedBearingFactor(const Pose2& pose, const Eigen::Vector2d& landmark, double w, double u_px, double sigma_px,
                       const Calibration& calib)
      : pose_(pose), landmark_(landmark), w_(w), bearing_(u_px, sigma_px, calib) {}

  template <typename T>
  bool operator()(const T* a, const T* b, T* residual) const {
    const T pose[3] = {T(pose_.x()) + T(1.0 - w_) * a[0] + T(w_) * b[0],
                       T(pose_.y()) + T(1.0 - w_) * a[1] + T(w_) * b[1], T(pose_.z())};
    const T landmark[2] = {T(landmark_.x()), T(landmark_.y())};
    return bearing_(pose, landmark, residual);
  }

  static ceres::CostFunction* Create(const Pose2& pose, const Eigen::Vector2d& landmark, double w, double u_px,
                                     double sigma_px, const Calibration& calib);

 private:
  Pose2 pose_;
  Eigen::Vector2d landmark_;
  double w_;
  BearingFactor bearing_;
};

// Two consecutive values of a first-order Gauss-Markov process in the plane, each axis with
// stationary deviation sigma and correlation alpha between them: the white innovation
// (b - alpha a) / (sigma sqrt(1 - alpha^2)). Blocks: a (2), b (2).
class Ar1StepFactor {
 public:
  Ar1StepFactor(double alpha, double sigma) : alpha_(alpha), inv_scale_(1.0 / (sigma * std::sqrt(1.0 - alpha * alpha))) {}

  template <typename T>
  bool operator()(const T* a, const T* b, T* residual) const {
    for (int i = 0; i < 2; ++i) residual[i] = (b[i] - T(alpha_) * a[i]) * T(inv_scale_);
    return true;
  }

  static ceres::CostFunction* Create(double alpha, double sigma);

 private:
  double alpha_;
  double inv_scale_;
};

// Gaussian prior on k landmarks jointly: residual S (x - mean), x the stacked landmark positions,
// S the square-root information of their joint covariance. With k = 1 this is one DC prior; with
// all map landmarks of a graph it is the CC prior. Blocks: k landmarks (2 each). Linear, so the
// Jacobian is exact: the column block of S for each landmark.
class LandmarkPriorFactor : public ceres::CostFunction {
 public:
  LandmarkPriorFactor(const Eigen::VectorXd& mean, const Eigen::MatrixXd& sqrt_info);

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override;

  const Eigen::VectorXd& mean() const { return mean_; }
  const Eigen::MatrixXd& sqrt_info() const { return sqrt_info_; }

 private:
  Eigen::VectorXd mean_;
  Eigen::MatrixXd sqrt_info_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_FACTORS_H_
