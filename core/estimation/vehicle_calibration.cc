#include "core/estimation/vehicle_calibration.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace crowdmap {

VehicleCalibration NewVehicleCalibration(const std::string& vehicle_id, double prior_sigma_rad) {
  VehicleCalibration v;
  v.vehicle_id = vehicle_id;
  v.camera_yaw_variance_rad2 = prior_sigma_rad * prior_sigma_rad;
  v.camera_yaw_information = 1.0 / v.camera_yaw_variance_rad2;
  return v;
}

std::optional<VehicleCalibration> FleetCameraYawPrior(const std::vector<VehicleCalibration>& fleet,
                                                      const std::string& vehicle_id, int min_vehicles,
                                                      double min_sigma_rad) {
  const int n = static_cast<int>(fleet.size());
  if (n < std::max(2, min_vehicles)) return std::nullopt;
  double weights = 0.0, weighted = 0.0, mean_variance = 0.0;
  for (const VehicleCalibration& v : fleet) {
    weights += 1.0 / v.camera_yaw_variance_rad2;
    weighted += v.camera_yaw_offset_rad / v.camera_yaw_variance_rad2;
    mean_variance += v.camera_yaw_variance_rad2 / n;
  }
  const double mean = weighted / weights;
  double sample_variance = 0.0;
  for (const VehicleCalibration& v : fleet) {
    sample_variance += (v.camera_yaw_offset_rad - mean) * (v.camera_yaw_offset_rad - mean) / (n - 1);
  }
  const double spread = (sample_variance + mean_variance) * (1.0 + 2.0 * std::sqrt(2.0 / (n - 1)));
  VehicleCalibration prior;
  prior.vehicle_id = vehicle_id;
  prior.camera_yaw_offset_rad = mean;
  prior.camera_yaw_variance_rad2 = std::max(min_sigma_rad * min_sigma_rad, spread + mean_variance / n);
  prior.camera_yaw_information = 1.0 / prior.camera_yaw_variance_rad2;
  return prior;
}

std::optional<VehicleCalibration> FleetCameraYawPrior(const MapReaderInterface& map, const std::string& vehicle_id,
                                                      int min_vehicles, double min_sigma_rad) {
  std::vector<VehicleCalibration> fleet;
  map.ForEachVehicle([&](const VehicleCalibration& v) { fleet.push_back(v); });
  return FleetCameraYawPrior(fleet, vehicle_id, min_vehicles, min_sigma_rad);
}

VehicleCalibration ConsiderCameraYawSolve(const VehicleCalibration& prior, double posterior_offset_rad,
                                          double given_landmarks_rad2, double from_landmarks_rad2) {
  VehicleCalibration v = prior;
  v.camera_yaw_offset_rad = posterior_offset_rad;
  const double prior_information = 1.0 / prior.camera_yaw_variance_rad2;
  const double own = 1.0 / given_landmarks_rad2 - prior_information;
  if (!(own > 0.0)) return v;  // the solve added nothing about the yaw (to rounding)
  const double landmarks_share = std::sqrt(std::max(0.0, from_landmarks_rad2)) * (own + prior_information) / own;
  // The new solve's pairs with every earlier one (and the first prior, conservatively) and itself.
  v.camera_yaw_map_term =
      prior.camera_yaw_map_term + own * landmarks_share * landmarks_share * (2.0 * prior.camera_yaw_information + own);
  v.camera_yaw_information = prior.camera_yaw_information + own;
  v.camera_yaw_variance_rad2 =
      (1.0 + v.camera_yaw_map_term / v.camera_yaw_information) / v.camera_yaw_information;
  return v;
}

Passage WithVehicleCameraYaw(const Passage& passage, const VehicleCalibration& vehicle) {
  Passage calibrated = passage;
  calibrated.calibration.camera_yaw_rad += vehicle.camera_yaw_offset_rad;
  return calibrated;
}

VehicleCalibration VehicleCameraYawPrior(const std::string& vehicle_id, const MapUpdateOptions& options,
                                         const MapReaderInterface& map) {
  if (const VehicleCalibration* known = map.FindVehicle(vehicle_id)) return *known;
  if (options.fleet_camera_yaw_prior_vehicles > 0) {
    if (std::optional<VehicleCalibration> fleet = FleetCameraYawPrior(
            map, vehicle_id, options.fleet_camera_yaw_prior_vehicles, options.camera_yaw_prior_sigma_rad)) {
      return *fleet;
    }
  }
  return NewVehicleCalibration(vehicle_id, options.camera_yaw_prior_sigma_rad);
}

}  // namespace crowdmap
