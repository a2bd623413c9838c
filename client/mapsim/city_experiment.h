#ifndef CROWDMAP_CLIENT_MAPSIM_CITY_EXPERIMENT_H_
#define CROWDMAP_CLIENT_MAPSIM_CITY_EXPERIMENT_H_

#include <cmath>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "client/mapsim/experiment.h"
#include "core/estimation/map_updater.h"
#include "core/sim/city_scenario.h"
#include "core/sim/faults.h"
#include "core/sim/metrics.h"

namespace crowdmap {

// `mapsim city`: passages 0..P-1 of a city scenario applied in order to an empty map in-process.
struct CityExperimentOptions {
  CityScenarioOptions city;
  int passages = 200;
  MapUpdateOptions update;
  FaultOptions faults;               // injected into the passages (none by default)
  int progress_every_passages = 10;  // progress callback period
  // The Cramer-Rao bound of the passages applied (CityCramerRao), beside each landmark's error.
  // Skipped, with a log line, for a layout of more than kCityCrlbMaxLandmarks landmarks (the bound
  // is dense) and with wheel-speed scale errors (CityScenarioOptions::vehicle_speed_scale_sigma),
  // which the estimator does not model.
  bool crlb = true;

  absl::Status Validate() const;
};

// One mapped landmark against the truth, in the city frame (m).
struct CityLandmarkError {
  LandmarkId id = 0;
  Eigen::Vector2d truth_m = Eigen::Vector2d::Zero();
  Eigen::Vector2d estimate_m = Eigen::Vector2d::Zero();
  double sigma_east_m = 0.0;
  double sigma_north_m = 0.0;
  double mahalanobis2 = 0.0;  // of the error, in the landmark's marginal covariance
  // The Cramer-Rao bound's marginal covariance of the landmark (city frame, m^2); none when the
  // bound was not computed.
  std::optional<Eigen::Matrix2d> crlb_cov_m2;
  // The bound's expected distance error, and the error's squared Mahalanobis distance in the
  // bound's covariance; NaN without the bound.
  double crlb_error_m() const;
  double crlb_mahalanobis2() const;
  double error_m() const { return (estimate_m - truth_m).norm(); }
};

// Where the run is, for progress output.
struct CityProgress {
  int passages_done = 0;
  int passages_total = 0;
  size_t landmarks_mapped = 0;
  double mean_error_m = 0.0;  // over the mapped landmarks
  double median_error_m = 0.0;
  double p50_ms = 0.0;        // per passage, so far
  double p95_ms = 0.0;
  double recent_p50_ms = 0.0;  // per passage, over those since the last progress report
  double recent_p95_ms = 0.0;
};

struct CityExperimentResult {
  size_t layout_landmarks = 0;
  double layout_s = 0.0;  // time to build the layout
  int passages = 0;
  int failed_passages = 0;  // refused by the estimator (the map is unchanged by them)
  int relinearized_passages = 0;  // re-linearisations applied (MapUpdateOptions::relinearize_sigmas)
  // Injected faults (FaultOptions) and what the estimator made of them.
  int faulty_passages = 0;       // with at least one fault
  int failed_faulty_passages = 0;
  int failed_clean_passages = 0;  // refused although nothing was injected: false refusals
  int mislabelled_detections = 0;
  int multipath_passages = 0;
  int overconfident_passages = 0;
  int bad_calibration_passages = 0;
  int landmarks_held_back = 0;   // summed over the passages (PassageUpdateSummary)
  int landmarks_disagreeing = 0;
  int inflated_passages = 0;     // whose consistency test scaled their covariances
  // As ExperimentResult's.
  int correlated_gnss_passages = 0;
  std::vector<double> gnss_residual_lag1;
  SensorInflations sensor_inflations;
  int quarantined_passages = 0;  // refused by the map's checks (FailedPrecondition; also in failed_passages)
  int64_t detections_used = 0;
  int64_t detections_outliers = 0;  // set aside by the residual test
  std::vector<double> passage_ms;         // wall time of each passage: simulation excluded
  std::vector<CityLandmarkError> errors;  // the final map's landmarks, by id
  double mean_error_m = 0.0;
  double median_error_m = 0.0;
  double p95_error_m = 0.0;
  double nees_per_dof = 0.0;  // marginal NEES per degree of freedom, mean over the mapped landmarks
  // Over the mapped landmarks, with the bound: its mean expected distance error, the map's mean
  // error over it, and the mean of crlb_mahalanobis2 / 2 (1 for an efficient unbiased map). NaN
  // without the bound.
  double crlb_mean_error_m = std::nan("");
  double error_over_crlb = std::nan("");
  double crlb_nees_per_dof = std::nan("");
  double p50_ms = 0.0;
  double p95_ms = 0.0;
  // Each vehicle's estimated camera yaw offset against its true one (no estimates without
  // MapUpdateOptions::estimate_camera_yaw).
  VehicleYawMetrics vehicle_yaw;

  // One key=value line.
  std::string Brief() const;
};

// The mapped landmarks of `map` against the scenario's truth, by id.
std::vector<CityLandmarkError> CityMapErrors(const MapState& map, const CityScenario& city);

// Largest layout whose Cramer-Rao bound RunCityExperiment computes: the bound inverts the dense
// information of every landmark seen (4,000 landmarks: 8,000 x 8,000, 0.5 GB).
inline constexpr size_t kCityCrlbMaxLandmarks = 4000;

// The Cramer-Rao bound (core/estimation/cramer_rao.h) of the city passages `indices`, as simulated
// before any injected fault, each landmark's marginal covariance in the city frame. With
// update.estimate_camera_yaw each vehicle's camera yaw offset is a state of the bound, with the
// estimator's prior. Every landmark has a diffuse prior (1 km), so that one seen along a single
// ray, which the estimator holds back, leaves the others' bound finite; its own is then of the
// prior's size.
absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> CityCramerRao(const CityScenario& city,
                                                                    const std::vector<int>& indices,
                                                                    const MapUpdateOptions& update);

absl::StatusOr<CityExperimentResult> RunCityExperiment(const CityExperimentOptions& options,
                                                       const std::function<void(const CityProgress&)>& progress = nullptr);

// Writes DIR/summary.json and DIR/landmarks.csv (id, truth and estimate East/North, error, sigmas).
absl::Status WriteCityOutputs(const CityExperimentOptions& options, const CityExperimentResult& result,
                              const std::string& dir);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_CITY_EXPERIMENT_H_
