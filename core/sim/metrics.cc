#include "core/sim/metrics.h"

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>

namespace crowdmap {

namespace {

// e^T Sigma^-1 e / (2N) with the full joint covariance of the mapped landmarks.
double JointNeesPerDof(const MapReaderInterface& map, const std::vector<const TruthLandmark*>& mapped,
                       const Eigen::VectorXd& errors) {
  const int n = static_cast<int>(mapped.size());
  Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  for (int i = 0; i < n; ++i) {
    cov.block<2, 2>(2 * i, 2 * i) = map.FindLandmark(mapped[i]->id)->cov_en_m2;
    for (int j = i + 1; j < n; ++j) {
      Eigen::Matrix2d c;
      if (!map.CrossCovariance(mapped[i]->id, mapped[j]->id, &c)) continue;
      cov.block<2, 2>(2 * i, 2 * j) = c;
      cov.block<2, 2>(2 * j, 2 * i) = c.transpose();
    }
  }
  Eigen::LLT<Eigen::MatrixXd> llt(cov);
  if (!cov.allFinite() || llt.info() != Eigen::Success) return std::numeric_limits<double>::quiet_NaN();
  return errors.dot(llt.solve(errors)) / (2.0 * n);
}

}  // namespace

MapErrorMetrics EvaluateMap(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth) {
  MapErrorMetrics m;
  std::vector<const TruthLandmark*> mapped;
  std::vector<Eigen::Vector2d> errors;
  double nees_sum = 0.0;
  bool nees_defined = true;
  for (const TruthLandmark& t : truth) {
    const Landmark* lm = map.FindLandmark(t.id);
    if (!lm) continue;
    const Eigen::Vector2d e = EastNorthOffset(t.position, lm->position);
    ++m.landmarks_evaluated;
    mapped.push_back(&t);
    errors.push_back(e);
    m.mean_dist_err_m += e.norm();
    m.mean_east_err_m += e.x();
    m.mean_north_err_m += e.y();
    m.east_3sigma_m += 3.0 * std::sqrt(lm->cov_en_m2(0, 0));
    m.north_3sigma_m += 3.0 * std::sqrt(lm->cov_en_m2(1, 1));
    Eigen::LLT<Eigen::Matrix2d> llt(lm->cov_en_m2);
    if (!lm->cov_en_m2.allFinite() || llt.info() != Eigen::Success) {
      nees_defined = false;
    } else {
      nees_sum += e.dot(llt.solve(e));
    }
  }
  if (m.landmarks_evaluated == 0) return m;
  const double n = m.landmarks_evaluated;
  m.mean_dist_err_m /= n;
  m.mean_east_err_m /= n;
  m.mean_north_err_m /= n;
  m.east_3sigma_m /= n;
  m.north_3sigma_m /= n;
  m.nees_per_dof = nees_defined ? nees_sum / n / 2.0 : std::numeric_limits<double>::quiet_NaN();
  Eigen::VectorXd stacked(2 * errors.size());
  for (size_t i = 0; i < errors.size(); ++i) stacked.segment<2>(2 * i) = errors[i];
  m.joint_nees_per_dof = nees_defined ? JointNeesPerDof(map, mapped, stacked) : std::numeric_limits<double>::quiet_NaN();
  return m;
}

}  // namespace crowdmap
