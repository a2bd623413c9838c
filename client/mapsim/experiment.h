#ifndef CROWDMAP_CLIENT_MAPSIM_EXPERIMENT_H_
#define CROWDMAP_CLIENT_MAPSIM_EXPERIMENT_H_

#include <functional>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/status/statusor.h"
#include "core/estimation/graph_builder.h"
#include "core/estimation/map_updater.h"
#include "core/map/map_state.h"
#include "core/sim/metrics.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Per sensor (odometry, GNSS, camera), the passages whose own test found the sensor noisier than
// declared (MapUpdateOptions::sensor_test_sigmas), and the variance factors found.
struct SensorInflations {
  int passages[kPassageSensors] = {0, 0, 0};
  std::vector<double> factors[kPassageSensors];
};

class CramerRaoBound;

// One simulated crowdsourcing run: P passages of the thesis scenario applied in order to an
// initially empty map with one strategy (cc, dc, cc-gsd, or the triangulation baseline).
struct ExperimentOptions {
  ScenarioOptions scenario;
  int passages = 100;
  std::string strategy = "cc-gsd";  // cc | dc | cc-gsd | triangulation
  MapUpdateOptions update;          // strategy field is set from `strategy`
  // Scenario passage indices in the order they are applied (a permutation of 0..passages-1,
  // e.g. the order in which a server received them); empty = 0, 1, ..., passages-1.
  std::vector<int> order;
  // Compute the Cramer-Rao bound of the same passages (LoopCramerRaoMeanError) for summary.json.
  bool crlb = true;
  // Clear the GNSS process the simulated passages declare (NoiseModel::gnss_correlation_time_s)
  // before the estimator sees them: the estimator then assumes white GNSS noise, as it did before
  // it modelled coloured noise. The bound still models the process that was simulated.
  bool assume_white_gnss = false;

  absl::Status Validate() const;
};

// Map quality after one passage, and what the passage cost.
struct PassageRecord {
  int passage = 0;  // 1-based
  MapErrorMetrics metrics;
  double solve_ms = 0.0;  // wall time to apply the passage (graph, solves, covariance, update)
  int subgraphs = 0;
};

struct ExperimentResult {
  std::vector<PassageRecord> records;
  MapState final_map;
  double final_mean_dist_err_m = 0.0;
  double final_nees_per_dof = 0.0;        // mean over the last 10% of passages
  double final_joint_nees_per_dof = 0.0;  // likewise, joint NEES with the cross-covariances
  // The run-to-run standard deviation of final_nees_per_dof for a consistent map with the final
  // map's covariance (NeesPerDofSdIfConsistent).
  double nees_per_dof_sd_if_consistent = 0.0;
  double median_passage_ms = 0.0;
  int failed_passages = 0;          // passages the estimator rejected (the map is unchanged by them)
  int relinearized_passages = 0;    // re-linearisations applied (MapUpdateOptions::relinearize_sigmas)
  int inflated_passages = 0;        // passages whose measurement covariances the consistency test inflated
  // Passages declaring white GNSS noise estimated with a Gauss-Markov process their residuals
  // showed (MapUpdateOptions::correlated_gnss_min_lag1), and every checked passage's residual lag-1
  // correlation.
  int correlated_gnss_passages = 0;
  std::vector<double> gnss_residual_lag1;
  SensorInflations sensor_inflations;  // MapUpdateOptions::sensor_test_sigmas
  int joint_rejected_passages = 0;  // warm-up passages applied sequentially: the joint solve was not usable
  // What the map's gates set aside (as mapd would): passages quarantined (FailedPrecondition, the
  // map's checks refused them; counted in failed_passages too), detections used and set aside as
  // outliers, map landmarks a passage disagreed with (not used for it).
  int quarantined_passages = 0;
  int64_t detections_used = 0;
  int64_t detections_outliers = 0;
  int landmarks_disagreeing = 0;
  // The Cramer-Rao bound on the mean distance error after the last passage (NaN when not computed
  // or not defined), with white noise the floor of final_mean_dist_err_m.
  double crlb_mean_dist_err_m = std::numeric_limits<double>::quiet_NaN();
  // The final map's errors against the bound's joint covariance instead of its own, e^T C^-1 e /
  // 2N: about 1 when the map's error is what an efficient estimator's would be (NaN as above).
  // Beside the final map's own joint NEES (the last record's), it tells an error larger than the
  // bound from a covariance smaller than it.
  double crlb_joint_nees_per_dof = std::numeric_limits<double>::quiet_NaN();
  // With a fleet (ScenarioOptions::vehicles): each vehicle's estimated camera yaw offset against
  // its true one (empty estimates without MapUpdateOptions::estimate_camera_yaw).
  VehicleYawMetrics vehicle_yaw;
};

// Vehicle id and true camera yaw offset (its own error and the noise configuration's common
// bias) of each vehicle of a fleet scenario; empty without a fleet.
std::vector<std::pair<std::string, double>> FleetYawTruth(const Scenario& scenario);

// Called after each passage with the record; used for progress output.
using ExperimentProgress = std::function<void(const PassageRecord&)>;

// The Cramer-Rao bound on the mean distance error of the map built from `scenario`'s passages
// `indices` (mean over the landmarks seen of the bound's expected distance; see cramer_rao.h), and
// `progress` called with the bound after each passage's information is added, if given.
// `camera_yaw_prior_sigma_rad` > 0: the estimator estimates each vehicle's camera yaw offset with
// this prior, and the bound holds these offsets as states (0: the calibration taken as known).
// `bound_out`, if given, receives the summed information (for the bound's joint covariance).
absl::StatusOr<double> LoopCramerRaoMeanError(const Scenario& scenario, const std::vector<int>& indices,
                                              const GraphOptions& graph, double camera_yaw_prior_sigma_rad = 0.0,
                                              const std::function<void(int, double)>& progress = nullptr,
                                              CramerRaoBound* bound_out = nullptr);

// 0..passages-1 with the passages from `from` on shuffled within consecutive groups of `window`
// (as concurrent vehicles would reorder them); deterministic for a given seed. window <= 1 keeps
// the order.
std::vector<int> ShuffledOrder(int passages, int window, int from, uint64_t seed);

// An order file holds one scenario passage index per line (e.g. the arrival order of a
// `mapsim fleet` run, so that the run can be replayed with `mapsim experiment --order-file`).
absl::Status WriteOrderFile(const std::vector<int>& order, const std::string& path);
absl::StatusOr<std::vector<int>> ReadOrderFile(const std::string& path);

absl::StatusOr<ExperimentResult> RunExperiment(const ExperimentOptions& options,
                                               const ExperimentProgress& progress = nullptr);

// Writes DIR/passages.csv, DIR/summary.json (plus the `extra_summary` figures) and DIR/errors.svg.
absl::Status WriteExperimentOutputs(const ExperimentOptions& options, const ExperimentResult& result,
                                    const std::string& dir,
                                    const std::vector<std::pair<std::string, double>>& extra_summary = {});

// Counts a passage that was estimated with the GNSS process its residuals showed, and keeps the
// residuals' lag-1 correlation of one that was checked (PassageUpdateSummary).
void CountGnssCheck(const PassageUpdateSummary& summary, int* correlated_passages, std::vector<double>* lag1);
// "p50", "p95" and "max" of `values` (empty: none), for summary.json.
std::map<std::string, double> Percentiles(std::vector<double> values);

void CountSensorInflations(const PassageUpdateSummary& summary, SensorInflations* inflations);
// {"odometry": {"passages": N, "factor": Percentiles}, "gnss": ..., "camera": ...}, for summary.json.
nlohmann::ordered_json SensorInflationsJson(const SensorInflations& inflations);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_EXPERIMENT_H_
