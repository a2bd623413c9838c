#ifndef CROWDMAP_CORE_ESTIMATION_VEHICLE_CALIBRATION_H_
#define CROWDMAP_CORE_ESTIMATION_VEHICLE_CALIBRATION_H_

// A vehicle's camera yaw offset across its passages (docs/estimation.md, "Per-vehicle camera
// calibration"). Every solve of one of its (sub)graphs estimates the offset with the vehicle's
// record as prior; these functions turn the solve's result into the vehicle's new record.

#include <optional>
#include <string>
#include <vector>

#include "core/estimation/map_update_options.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"

namespace crowdmap {

// The record a vehicle without one starts from: offset 0 with variance prior_sigma_rad^2.
VehicleCalibration NewVehicleCalibration(const std::string& vehicle_id, double prior_sigma_rad);

// The prior of the camera yaw offset of a vehicle without a record, from the records of the fleet
// (`map`'s vehicles) once it has at least `min_vehicles` of them; nullopt before.
//
// An empirical-Bayes prior: the vehicles' offsets taken as draws of one distribution, whose mean
// is the records' mean m (weighted by their precisions 1/v_i: a vehicle seen once on a young map
// counts less than one the map knows well) and whose variance is that of the true offsets around
// it. Each record is a posterior mean x_i with variance v_i, so the true offsets vary by about
//   tau^2 = s^2 + mean(v)   (s^2 the records' sample variance about m; total variance: a posterior
//                            mean varies less than what it estimates, by its own variance),
// which is never below the records' own uncertainty: a fleet whose cameras share one error is
// not taken as known better than one passage measures it. The prior's variance is tau^2 at about
// its 95% upper bound from n records, tau^2 (1 + 2 sqrt(2 / (n - 1))), plus the uncertainty of m,
// mean(v) / n, and never below min_sigma_rad^2 (the fixed prior's): the records' variances hold
// the priors they were made with, so a prior narrowed to the fleet's would count the fleet again
// in every new record, and narrow itself further with each generation (measured: over-confident
// maps under AR(1) GNSS noise). When every vehicle's camera has the same error (a fleet of one
// model and mount), a new vehicle then starts from that error instead of 0, and its record comes
// closer to it. (A sequential update's factor leaves the passage's yaw prior out, so this prior
// does not steer the map; the young map's joint solves keep the fixed prior, see joint_solve.cc.)
std::optional<VehicleCalibration> FleetCameraYawPrior(const std::vector<VehicleCalibration>& fleet,
                                                      const std::string& vehicle_id, int min_vehicles,
                                                      double min_sigma_rad);
// The same over `map`'s vehicles.
std::optional<VehicleCalibration> FleetCameraYawPrior(const MapReaderInterface& map, const std::string& vehicle_id,
                                                      int min_vehicles, double min_sigma_rad);

// The vehicle's record after a solve that took `prior` as its yaw prior and found the offset
// `posterior_offset_rad`, with marginal variance given_landmarks_rad2 + from_landmarks_rad2
// (GraphLinearization::ScalarMarginal: the variance with the solve's landmarks known, and what
// their uncertainty adds).
//
// The solves of one vehicle all measure its yaw against the same map, so the parts of their errors
// that come from the map's landmarks are not independent: a map error that turns a street by a
// little turns every yaw estimated along it the same way. Chaining the solves' posteriors would
// count that part as if it shrank with every passage and make the record over-confident. Instead
// the record is a consider estimate, the solves weighted by their own information J_k (pixels,
// odometry, GNSS: independent from solve to solve, J = 1/given - 1/prior) with the map-borne
// errors kept apart. Solve k's map-borne error has standard deviation s_k (its posterior share
// sqrt(from) undone from the prior's weight: s = sqrt(from) (J + 1/prior) / J). The map only
// gains information, and the error of a better estimate is shared by every poorer one, so two
// solves' map-borne errors are taken to covary by the later one's variance; where the later one
// looked at other landmarks they covary less, so this errs on the safe side. The record keeps
//   camera_yaw_information  I = sum J_k (the first prior counted as a solve without map error),
//   camera_yaw_map_term     U = sum_i sum_j J_i J_j s_later(i,j)^2,
// and its variance is 1/I + U / I^2. The mean is the solve's posterior mean.
VehicleCalibration ConsiderCameraYawSolve(const VehicleCalibration& prior, double posterior_offset_rad,
                                          double given_landmarks_rad2, double from_landmarks_rad2);

// `passage` with the vehicle's estimated offset added to the camera yaw it declares: how the map
// update solves it and how LocalizePassage localises it.
Passage WithVehicleCameraYaw(const Passage& passage, const VehicleCalibration& vehicle);

// The prior of a passage's camera yaw offset, as the map update takes it: the vehicle's record in
// `map`, or for a new vehicle the fleet's prior (options.fleet_camera_yaw_prior_vehicles, when the
// fleet is large enough), else mean 0 with options.camera_yaw_prior_sigma_rad. A localisation
// applies its offset (WithVehicleCameraYaw) and estimates the offset again with its standard
// deviation (PassageLocalizerOptions::camera_yaw_sigma_rad).
VehicleCalibration VehicleCameraYawPrior(const std::string& vehicle_id, const MapUpdateOptions& options,
                                         const MapReaderInterface& map);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_VEHICLE_CALIBRATION_H_
