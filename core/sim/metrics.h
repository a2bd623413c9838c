#ifndef CROWDMAP_CORE_SIM_METRICS_H_
#define CROWDMAP_CORE_SIM_METRICS_H_

#include <vector>

#include "core/map/map_state.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Accuracy and consistency of a map against the true landmarks (DESIGN section 8). Errors are
// East/North at the true position; landmarks missing from the map are not counted.
struct MapErrorMetrics {
  int landmarks_evaluated = 0;
  double mean_dist_err_m = 0.0;   // mean horizontal distance error
  double mean_east_err_m = 0.0;   // signed means (errors can cancel: a bias indicator)
  double mean_north_err_m = 0.0;
  double east_3sigma_m = 0.0;     // 3 x mean of the East standard deviations
  double north_3sigma_m = 0.0;
  double nees_per_dof = 0.0;      // mean of e^T Sigma^-1 e over landmarks, divided by 2 (NaN
                                  // when the map has no covariance); 1 for a consistent map
  double joint_nees_per_dof = 0.0;  // e^T Sigma^-1 e over all landmarks with the cross-covariances,
                                    // divided by 2N: chi2(2N)/2N when consistent, so a steadier
                                    // test than the per-landmark mean when errors are correlated
};

MapErrorMetrics EvaluateMap(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_METRICS_H_
