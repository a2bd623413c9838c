#ifndef CROWDMAP_CORE_SIM_METRICS_H_
#define CROWDMAP_CORE_SIM_METRICS_H_

#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>

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

// The errors (East/North at the truth, two rows per landmark) and the joint covariance of the
// truth landmarks that are in the map, in the order of `truth`.
struct StackedMapErrors {
  std::vector<LandmarkId> ids;
  Eigen::VectorXd errors;
  Eigen::MatrixXd cov;
};
StackedMapErrors StackMapErrors(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth);

// The standard deviation that nees_per_dof would have from run to run if the map were consistent
// (its errors drawn from its own joint covariance). Errors common to many landmarks make it large:
// one run's nees_per_dof is then one draw of a few degrees of freedom, and only an average over
// runs (seeds) tests consistency. NaN without a usable covariance.
double NeesPerDofSdIfConsistent(const MapReaderInterface& map, const std::vector<TruthLandmark>& truth);

// One vehicle's estimated camera yaw offset (VehicleCalibration) against its true one.
struct VehicleYawError {
  std::string vehicle_id;
  double truth_rad = 0.0;
  double estimate_rad = 0.0;  // NaN when the map holds no estimate for it
  double sigma_rad = 0.0;
  int64_t passages = 0;
};

struct VehicleYawMetrics {
  std::vector<VehicleYawError> vehicles;  // in the order of the truth
  int estimated = 0;                      // vehicles with an estimate
  double within_2sigma_fraction = 0.0;    // of those estimated: |error| <= 2 sigma (95.4% if consistent)
  double rms_error_rad = 0.0;
  // The mean of the errors, with their signs: what the vehicles' records share. Independent
  // records put it near 0 (within rms_error_rad / sqrt(estimated)); on a road every vehicle drives
  // the same way it is the map's own bias seen through the camera (docs/results.md, "All
  // detections on the thesis loop").
  double mean_error_rad = 0.0;
  double mean_sigma_rad = 0.0;            // of the estimated vehicles' records
  double nees = 0.0;                      // mean of (error / sigma)^2; 1 when consistent
};

// `truth`: vehicle_id and true offset from the declared camera yaw, per vehicle.
VehicleYawMetrics EvaluateVehicleYaw(const MapReaderInterface& map,
                                     const std::vector<std::pair<std::string, double>>& truth);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_SIM_METRICS_H_
