#include "core/estimation/factors.h"

#include <cmath>

#include <Eigen/Cholesky>

namespace crowdmap {

Eigen::MatrixXd SqrtInformation(const Eigen::MatrixXd& cov) {
  // cov = L L^T  =>  cov^-1 = L^-T L^-1, so S = L^-1.
  Eigen::LLT<Eigen::MatrixXd> llt(cov);
  const Eigen::MatrixXd identity = Eigen::MatrixXd::Identity(cov.rows(), cov.cols());
  return llt.matrixL().solve(identity);
}

ceres::CostFunction* OdometryFactor::Create(const RelativeMotion& motion) {
  return new ceres::AutoDiffCostFunction<OdometryFactor, 3, 3, 3>(
      new OdometryFactor(motion.delta, SqrtInformation(motion.cov)));
}

ceres::CostFunction* ScaledOdometryFactor::Create(const RelativeMotion& motion) {
  return new ceres::AutoDiffCostFunction<ScaledOdometryFactor, 3, 3, 3, 1>(
      new ScaledOdometryFactor(motion.delta, SqrtInformation(motion.cov)));
}

ceres::CostFunction* GnssFactor::Create(const Eigen::Vector2d& measured, const Eigen::Matrix2d& cov,
                                        const Eigen::Vector2d& lever_arm) {
  return new ceres::AutoDiffCostFunction<GnssFactor, 2, 3>(new GnssFactor(measured, lever_arm, SqrtInformation(cov)));
}

namespace {

// Both fixes of a GnssAr1Factor at one pose node (fixes less than the node merge tolerance apart).
struct GnssAr1AtOneNode {
  template <typename T>
  bool operator()(const T* pose, T* residual) const {
    return factor(pose, pose, residual);
  }
  GnssAr1Factor factor;
};

}  // namespace

double GnssAr1Factor::Alpha(double dt_s, double correlation_time_s) { return std::exp(-dt_s / correlation_time_s); }

ceres::CostFunction* GnssAr1Factor::Create(const Eigen::Vector2d& previous_measured, const Eigen::Matrix2d& previous_cov,
                                           const Eigen::Vector2d& measured, const Eigen::Matrix2d& cov,
                                           const Eigen::Vector2d& lever_arm, double dt_s, double correlation_time_s) {
  return new ceres::AutoDiffCostFunction<GnssAr1Factor, 2, 3, 3>(
      new GnssAr1Factor(previous_measured, SqrtInformation(previous_cov), measured, SqrtInformation(cov), lever_arm,
                        Alpha(dt_s, correlation_time_s)));
}

ceres::CostFunction* GnssAr1Factor::CreateAtOneNode(const Eigen::Vector2d& previous_measured,
                                                    const Eigen::Matrix2d& previous_cov, const Eigen::Vector2d& measured,
                                                    const Eigen::Matrix2d& cov, const Eigen::Vector2d& lever_arm,
                                                    double dt_s, double correlation_time_s) {
  return new ceres::AutoDiffCostFunction<GnssAr1AtOneNode, 2, 3>(new GnssAr1AtOneNode{
      GnssAr1Factor(previous_measured, SqrtInformation(previous_cov), measured, SqrtInformation(cov), lever_arm,
                    Alpha(dt_s, correlation_time_s))});
}

ceres::CostFunction* CameraFactor::Create(double u_px, double sigma_px, const Calibration& calib) {
  return new ceres::AutoDiffCostFunction<CameraFactor, 1, 3, 2>(new CameraFactor(u_px, sigma_px, calib));
}

ceres::CostFunction* CameraYawFactor::Create(double u_px, double sigma_px, const Calibration& calib) {
  return new ceres::AutoDiffCostFunction<CameraYawFactor, 1, 3, 2, 1>(new CameraYawFactor(u_px, sigma_px, calib));
}

ceres::ResidualBlockId AddCameraResidual(double u_px, double sigma_px, const Calibration& calib,
                                         ceres::LossFunction* loss, double* pose, double* landmark,
                                         double* yaw_offset_rad, ceres::Problem* problem) {
  if (yaw_offset_rad == nullptr) {
    return problem->AddResidualBlock(CameraFactor::Create(u_px, sigma_px, calib), loss, pose, landmark);
  }
  return problem->AddResidualBlock(CameraYawFactor::Create(u_px, sigma_px, calib), loss, pose, landmark,
                                   yaw_offset_rad);
}

ceres::CostFunction* ScalarPriorFactor::Create(double mean, double sigma) {
  return new ceres::AutoDiffCostFunction<ScalarPriorFactor, 1, 1>(new ScalarPriorFactor(mean, sigma));
}

BearingFactor::BearingFactor(double u_px, double sigma_px, const Calibration& calib)
    : bearing_rad_(std::atan2(calib.cx_px - u_px, calib.fx_px)), calib_(calib) {
  // du/db = -fx / cos^2(b) = -(fx^2 + (u - cx)^2) / fx.
  const double du_db = (calib.fx_px * calib.fx_px + (u_px - calib.cx_px) * (u_px - calib.cx_px)) / calib.fx_px;
  inv_sigma_rad_ = du_db / sigma_px;
}

ceres::CostFunction* BearingFactor::Create(double u_px, double sigma_px, const Calibration& calib) {
  return new ceres::AutoDiffCostFunction<BearingFactor, 1, 3, 2>(new BearingFactor(u_px, sigma_px, calib));
}

ceres::CostFunction* ShiftedBearingFactor::Create(const Pose2& pose, const Eigen::Vector2d& landmark, double w,
                                                  double u_px, double sigma_px, const Calibration& calib) {
  return new ceres::AutoDiffCostFunction<ShiftedBearingFactor, 1, 2, 2>(
      new ShiftedBearingFactor(pose, landmark, w, u_px, sigma_px, calib));
}

ceres::CostFunction* Ar1StepFactor::Create(double alpha, double sigma) {
  return new ceres::AutoDiffCostFunction<Ar1StepFactor, 2, 2, 2>(new Ar1StepFactor(alpha, sigma));
}

LandmarkPriorFactor::LandmarkPriorFactor(const Eigen::VectorXd& mean, const Eigen::MatrixXd& sqrt_info)
    : mean_(mean), sqrt_info_(sqrt_info) {
  set_num_residuals(static_cast<int>(mean.size()));
  for (int i = 0; i < mean.size() / 2; ++i) mutable_parameter_block_sizes()->push_back(2);
}

bool LandmarkPriorFactor::Evaluate(double const* const* parameters, double* residuals, double** jacobians) const {
  const int n = static_cast<int>(mean_.size());
  Eigen::VectorXd x(n);
  for (int i = 0; i < n / 2; ++i) x.segment<2>(2 * i) = Eigen::Map<const Eigen::Vector2d>(parameters[i]);
  Eigen::Map<Eigen::VectorXd>(residuals, n) = sqrt_info_ * (x - mean_);
  if (jacobians) {
    for (int i = 0; i < n / 2; ++i) {
      if (!jacobians[i]) continue;
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, 2, Eigen::RowMajor>>(jacobians[i], n, 2) =
          sqrt_info_.middleCols<2>(2 * i);
    }
  }
  return true;
}

}  // namespace crowdmap
