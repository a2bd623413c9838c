#include "core/sim/metrics.h"

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>

namespace crowdmap {

MapErrorMetrics EvaluateMap(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth) {
  MapErrorMetrics m;
  double nees_sum = 0.0;
  bool nees_defined = true;
  for (const TruthLandmark& t : truth) {
    const Landmark* lm = map.FindLandmark(t.id);
    if (!lm) continue;
    const Eigen::Vector2d e = EastNorthOffset(t.position, lm->position);
    ++m.landmarks_evaluated;
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
  return m;
}

}  // namespace crowdmap
