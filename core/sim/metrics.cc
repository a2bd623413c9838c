#include "core/sim/metrics.h"

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>

#include "core/map/map_window.h"

namespace crowdmap {

VehicleYawMetrics EvaluateVehicleYaw(const MapReaderInterface& map,
                                     const std::vector<std::pair<std::string, double>>& truth) {
  VehicleYawMetrics m;
  int within = 0;
  double sum = 0.0, squared = 0.0, nees = 0.0, sigmas = 0.0;
  for (const auto& [vehicle_id, truth_rad] : truth) {
    VehicleYawError e;
    e.vehicle_id = vehicle_id;
    e.truth_rad = truth_rad;
    e.estimate_rad = std::numeric_limits<double>::quiet_NaN();
    if (const VehicleCalibration* v = map.FindVehicle(vehicle_id)) {
      e.estimate_rad = v->camera_yaw_offset_rad;
      e.sigma_rad = std::sqrt(v->camera_yaw_variance_rad2);
      e.passages = v->passages;
      const double error = e.estimate_rad - truth_rad;
      ++m.estimated;
      if (std::abs(error) <= 2.0 * e.sigma_rad) ++within;
      sum += error;
      sigmas += e.sigma_rad;
      squared += error * error;
      nees += error * error / (e.sigma_rad * e.sigma_rad);
    }
    m.vehicles.push_back(std::move(e));
  }
  if (m.estimated > 0) {
    m.within_2sigma_fraction = static_cast<double>(within) / m.estimated;
    m.rms_error_rad = std::sqrt(squared / m.estimated);
    m.mean_error_rad = sum / m.estimated;
    m.mean_sigma_rad = sigmas / m.estimated;
    m.nees = nees / m.estimated;
  }
  return m;
}

MapErrorMetrics EvaluateMap(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth) {
  MapErrorMetrics m;
  const StackedMapErrors stacked = StackMapErrors(map, truth);
  double nees_sum = 0.0;
  bool nees_defined = true;
  for (size_t i = 0; i < stacked.ids.size(); ++i) {
    const Eigen::Vector2d e = stacked.errors.segment<2>(2 * i);
    const Eigen::Matrix2d cov = stacked.cov.block<2, 2>(2 * i, 2 * i);
    m.mean_dist_err_m += e.norm();
    m.mean_east_err_m += e.x();
    m.mean_north_err_m += e.y();
    m.east_3sigma_m += 3.0 * std::sqrt(cov(0, 0));
    m.north_3sigma_m += 3.0 * std::sqrt(cov(1, 1));
    Eigen::LLT<Eigen::Matrix2d> llt(cov);
    if (!cov.allFinite() || llt.info() != Eigen::Success) {
      nees_defined = false;
    } else {
      nees_sum += e.dot(llt.solve(e));
    }
  }
  m.landmarks_evaluated = static_cast<int>(stacked.ids.size());
  if (m.landmarks_evaluated == 0) return m;
  const double n = m.landmarks_evaluated;
  m.mean_dist_err_m /= n;
  m.mean_east_err_m /= n;
  m.mean_north_err_m /= n;
  m.east_3sigma_m /= n;
  m.north_3sigma_m /= n;
  m.nees_per_dof = nees_defined ? nees_sum / n / 2.0 : std::numeric_limits<double>::quiet_NaN();
  // e^T Sigma^-1 e / (2N) with the full joint covariance of the mapped landmarks.
  Eigen::LLT<Eigen::MatrixXd> joint(stacked.cov);
  m.joint_nees_per_dof = nees_defined && stacked.cov.allFinite() && joint.info() == Eigen::Success
                             ? stacked.errors.dot(joint.solve(stacked.errors)) / (2.0 * n)
                             : std::numeric_limits<double>::quiet_NaN();
  return m;
}

StackedMapErrors StackMapErrors(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth) {
  StackedMapErrors out;
  std::vector<Eigen::Vector2d> errors;
  for (const TruthLandmark& t : truth) {
    const Landmark* lm = map.FindLandmark(t.id);
    if (!lm) continue;
    out.ids.push_back(t.id);
    errors.push_back(EastNorthOffset(t.position, lm->position));
  }
  out.errors.resize(2 * errors.size());
  for (size_t i = 0; i < errors.size(); ++i) out.errors.segment<2>(2 * i) = errors[i];
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, out.ids);
  const int n = static_cast<int>(2 * out.ids.size());
  out.cov = cov.ok() ? *cov : Eigen::MatrixXd::Constant(n, n, std::numeric_limits<double>::quiet_NaN());
  return out;
}

double NeesPerDofSdIfConsistent(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth) {
  const StackedMapErrors stacked = StackMapErrors(map, truth);
  if (stacked.ids.empty()) return std::numeric_limits<double>::quiet_NaN();
  const Eigen::MatrixXd& cov = stacked.cov;
  // nees_per_dof = e^T D e / 2N with D the block diagonal of the 2x2 marginal inverses; for
  // e ~ N(0, cov) its variance is 2 tr((D cov)^2) / (2N)^2.
  Eigen::MatrixXd d_cov(cov.rows(), cov.cols());
  for (size_t i = 0; i < stacked.ids.size(); ++i) {
    Eigen::LLT<Eigen::Matrix2d> llt(cov.block<2, 2>(2 * i, 2 * i));
    if (llt.info() != Eigen::Success) return std::numeric_limits<double>::quiet_NaN();
    d_cov.middleRows<2>(2 * i) = llt.solve(cov.middleRows<2>(2 * i));
  }
  if (!d_cov.allFinite()) return std::numeric_limits<double>::quiet_NaN();
  return std::sqrt(2.0 * (d_cov * d_cov).trace()) / (2.0 * stacked.ids.size());
}

}  // namespace crowdmap
