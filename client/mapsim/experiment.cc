#include "client/mapsim/experiment.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <optional>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <random>

#include <Eigen/Cholesky>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/mapsim/svg_plot.h"
#include "core/estimation/cramer_rao.h"
#include "core/estimation/triangulation.h"

namespace crowdmap {
namespace {

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}


}  // namespace

absl::Status ExperimentOptions::Validate() const {
  if (passages < 1) return absl::InvalidArgumentError(absl::StrCat("passages: must be >= 1, got ", passages));
  if (strategy != "triangulation") {
    absl::StatusOr<UpdateStrategy> s = ParseUpdateStrategy(strategy);
    if (!s.ok()) return s.status();
  }
  if (absl::Status s = scenario.Validate(); !s.ok()) return s;
  if (!order.empty()) {
    if (static_cast<int>(order.size()) != passages) {
      return absl::InvalidArgumentError(absl::StrCat("order: has ", order.size(), " entries for ", passages, " passages"));
    }
    std::vector<bool> seen(passages, false);
    for (size_t k = 0; k < order.size(); ++k) {
      if (order[k] < 0 || order[k] >= passages || seen[order[k]]) {
        return absl::InvalidArgumentError(
            absl::StrCat("order[", k, "]: ", order[k], " is out of range or repeated (need a permutation of 0..",
                         passages - 1, ")"));
      }
      seen[order[k]] = true;
    }
  }
  return update.Validate();
}

std::vector<int> ShuffledOrder(int passages, int window, int from, uint64_t seed) {
  std::vector<int> order(std::max(0, passages));
  std::iota(order.begin(), order.end(), 0);
  if (window <= 1) return order;
  std::mt19937_64 rng(seed);
  for (int begin = std::max(0, from); begin < passages; begin += window) {
    std::shuffle(order.begin() + begin, order.begin() + std::min(passages, begin + window), rng);
  }
  return order;
}

absl::Status WriteOrderFile(const std::vector<int>& order, const std::string& path) {
  std::ofstream out(path, std::ios::trunc);
  for (int i : order) out << i << "\n";
  out.close();
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": write failed"));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<int>> ReadOrderFile(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open"));
  std::vector<int> order;
  std::string line;
  for (int line_no = 1; std::getline(in, line); ++line_no) {
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    size_t used = 0;
    int value = -1;
    try {
      value = std::stoi(line, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    if (used == 0 || line.find_first_not_of(" \t\r", used) != std::string::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ":", line_no, ": expected one passage index per line, got \"", line, "\""));
    }
    order.push_back(value);
  }
  if (order.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no passage indices"));
  return order;
}

absl::StatusOr<double> LoopCramerRaoMeanError(const Scenario& scenario, const std::vector<int>& indices,
                                              const GraphOptions& graph, double camera_yaw_prior_sigma_rad,
                                              const std::function<void(int, double)>& progress,
                                              CramerRaoBound* bound_out) {
  GraphOptions options = graph;
  options.frame_origin = scenario.options().origin;
  const auto true_landmark = [&](LandmarkId id) -> std::optional<Eigen::Vector2d> {
    if (id < 1 || id > static_cast<LandmarkId>(scenario.landmarks().size())) return std::nullopt;
    return scenario.landmarks()[id - 1].position_m;
  };
  CramerRaoBound bound(camera_yaw_prior_sigma_rad);
  const auto mean_error = [&]() -> absl::StatusOr<double> {
    absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> cov = bound.Covariances();
    if (!cov.ok()) return cov.status();
    double sum = 0.0;
    for (const auto& [id, c] : *cov) sum += ExpectedDistance(c);
    return cov->empty() ? 0.0 : sum / cov->size();
  };
  for (size_t k = 0; k < indices.size(); ++k) {
    absl::StatusOr<PassageFisherInformation> info =
        PassageLandmarkInformation(scenario.MakePassage(indices[k]), options,
                                   [&](double t) { return scenario.TruePoseAt(indices[k], t); }, true_landmark,
                                   camera_yaw_prior_sigma_rad > 0.0
                                       ? std::optional<double>(scenario.CameraYawErrorRad(indices[k]))
                                       : std::nullopt);
    if (!info.ok()) return info.status();
    bound.Add(*info);
    if (progress) {
      absl::StatusOr<double> now = mean_error();
      if (!now.ok()) return now.status();
      progress(static_cast<int>(k) + 1, *now);
    }
  }
  absl::StatusOr<double> mean = mean_error();
  if (bound_out != nullptr) *bound_out = std::move(bound);
  return mean;
}

absl::StatusOr<ExperimentResult> RunExperiment(const ExperimentOptions& options, const ExperimentProgress& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options.scenario);
  if (!scenario.ok()) return scenario.status();

  const bool triangulation = options.strategy == "triangulation";
  MapUpdateOptions update = options.update;
  if (!triangulation) update.strategy = *ParseUpdateStrategy(options.strategy);
  TriangulationMapper triangulation_mapper;
  MapUpdater updater(update);
  std::map<MapUpdater::PassageKey, int> index_of;
  const auto make_passage = [&](int index) {
    Passage passage = scenario->MakePassage(index);
    if (options.assume_white_gnss) passage.noise.gnss_correlation_time_s = 0.0;
    return passage;
  };
  const auto passage_of = [&](const MapUpdater::PassageKey& key) -> absl::StatusOr<Passage> {
    const auto it = index_of.find(key);
    if (it == index_of.end()) return absl::NotFoundError("passage not applied");
    return make_passage(it->second);
  };

  ExperimentResult result;
  std::vector<double> times;
  for (int i = 0; i < options.passages; ++i) {
    const Passage passage = make_passage(options.order.empty() ? i : options.order[i]);
    PassageRecord record;
    record.passage = i + 1;
    const auto start = std::chrono::steady_clock::now();
    if (triangulation) {
      if (absl::Status s = triangulation_mapper.AddPassage(passage); !s.ok()) {
        ++result.failed_passages;
        spdlog::warn("passage={} rejected: {}", passage.passage_id, s.ToString());
      }
      record.subgraphs = 1;
    } else {
      absl::StatusOr<PassageUpdate> u = updater.Compute(passage, result.final_map);
      if (u.ok()) {
        result.final_map.Apply(u->delta);
        updater.Applied(passage, u->delta);
        index_of[{passage.vehicle_id, passage.passage_id}] = options.order.empty() ? i : options.order[i];
        result.relinearized_passages += RelinearizeStaleInMemory(passage_of, &updater, &result.final_map);
        record.subgraphs = u->summary.subgraphs;
        if (u->summary.max_variance_factor > 1.0) ++result.inflated_passages;
        CountGnssCheck(u->summary, &result.correlated_gnss_passages, &result.gnss_residual_lag1);
        CountSensorInflations(u->summary, &result.sensor_inflations);
        if (u->summary.joint_rejected) ++result.joint_rejected_passages;
        result.detections_used += u->summary.detections_used;
        result.detections_outliers += u->summary.detections_outliers;
        result.landmarks_disagreeing += u->summary.landmarks_disagreeing;
      } else {
        ++result.failed_passages;
        if (absl::IsFailedPrecondition(u.status())) ++result.quarantined_passages;
        spdlog::warn("passage={} rejected: {}", passage.passage_id, u.status().ToString());
      }
    }
    record.solve_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    record.metrics = EvaluateMap(triangulation ? triangulation_mapper.map() : result.final_map, scenario->landmarks());
    times.push_back(record.solve_ms);
    result.records.push_back(record);
    if (progress) progress(record);
  }
  if (triangulation) result.final_map = triangulation_mapper.map();

  const size_t tail = std::max<size_t>(1, result.records.size() / 10);
  double nees = 0.0, joint = 0.0;
  for (size_t k = result.records.size() - tail; k < result.records.size(); ++k) {
    nees += result.records[k].metrics.nees_per_dof;
    joint += result.records[k].metrics.joint_nees_per_dof;
  }
  result.final_nees_per_dof = nees / tail;
  result.final_joint_nees_per_dof = joint / tail;
  result.final_mean_dist_err_m = result.records.back().metrics.mean_dist_err_m;
  result.nees_per_dof_sd_if_consistent = NeesPerDofSdIfConsistent(result.final_map, scenario->landmarks());
  result.median_passage_ms = Median(times);
  result.vehicle_yaw = EvaluateVehicleYaw(result.final_map, FleetYawTruth(*scenario));
  if (options.crlb) {
    std::vector<int> indices(options.passages);
    for (int i = 0; i < options.passages; ++i) indices[i] = options.order.empty() ? i : options.order[i];
    const GraphOptions graph = UpdateGraphOptions(update);
    // With the camera yaw estimated, the bound has each vehicle's yaw offset as a state too.
    CramerRaoBound information;
    absl::StatusOr<double> bound =
        LoopCramerRaoMeanError(*scenario, indices, graph,
                               update.estimate_camera_yaw ? update.camera_yaw_prior_sigma_rad : 0.0, nullptr, &information);
    if (!bound.ok()) return bound.status();
    result.crlb_mean_dist_err_m = *bound;
    // The map's errors are East/North at each landmark, the bound's in the scenario's frame: over
    // a few kilometres the two differ by a rotation of about 1e-4 rad.
    const StackedMapErrors errors = StackMapErrors(result.final_map, scenario->landmarks());
    if (absl::StatusOr<Eigen::MatrixXd> cov = information.JointCovariance(errors.ids); cov.ok() && cov->size() > 0) {
      const Eigen::LLT<Eigen::MatrixXd> llt(*cov);
      if (llt.info() == Eigen::Success) {
        result.crlb_joint_nees_per_dof = errors.errors.dot(llt.solve(errors.errors)) / errors.errors.size();
      }
    }
  }
  return result;
}

std::vector<std::pair<std::string, double>> FleetYawTruth(const Scenario& scenario) {
  std::vector<std::pair<std::string, double>> truth;
  for (int v = 0; v < scenario.options().vehicles; ++v) {
    // Passage v is the vehicle's first.
    truth.emplace_back(scenario.MakePassage(v).vehicle_id, scenario.CameraYawErrorRad(v));
  }
  return truth;
}

absl::Status WriteExperimentOutputs(const ExperimentOptions& options, const ExperimentResult& result,
                                    const std::string& dir,
                                    const std::vector<std::pair<std::string, double>>& extra_summary) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", dir, ": ", ec.message()));

  std::ofstream csv(std::filesystem::path(dir) / "passages.csv");
  csv << "passage,mean_dist_err_m,mean_east_err_m,mean_north_err_m,east_3sigma_m,north_3sigma_m,nees_per_dof,"
         "solve_ms,subgraphs,joint_nees_per_dof\n";
  for (const PassageRecord& r : result.records) {
    const MapErrorMetrics& m = r.metrics;
    csv << absl::StrFormat("%d,%.6f,%.6f,%.6f,%.6f,%.6f,%.6f,%.3f,%d,%.6f\n", r.passage, m.mean_dist_err_m,
                           m.mean_east_err_m, m.mean_north_err_m, m.east_3sigma_m, m.north_3sigma_m, m.nees_per_dof,
                           r.solve_ms, r.subgraphs, m.joint_nees_per_dof);
  }
  if (!csv) return absl::InternalError(absl::StrCat("cannot write ", dir, "/passages.csv"));

  absl::StatusOr<Scenario> scenario = Scenario::Create(options.scenario);
  if (!scenario.ok()) return scenario.status();
  const StackedMapErrors stacked = StackMapErrors(result.final_map, scenario->landmarks());
  std::ofstream landmarks(std::filesystem::path(dir) / "landmarks.csv");
  landmarks << "landmark,true_east_m,true_north_m,east_err_m,north_err_m,cov_ee_m2,cov_en_m2,cov_nn_m2\n";
  size_t k = 0;  // stacked holds the mapped landmarks in the order of the truth
  for (const TruthLandmark& t : scenario->landmarks()) {
    if (k == stacked.ids.size() || stacked.ids[k] != t.id) continue;
    const Eigen::Vector2d e = stacked.errors.segment<2>(2 * k);
    const Eigen::Matrix2d c = stacked.cov.block<2, 2>(2 * k, 2 * k);
    landmarks << absl::StrFormat("%d,%.4f,%.4f,%.6f,%.6f,%.9g,%.9g,%.9g\n", t.id, t.position_m.x(), t.position_m.y(),
                                 e.x(), e.y(), c(0, 0), c(0, 1), c(1, 1));
    ++k;
  }
  if (!landmarks) return absl::InternalError(absl::StrCat("cannot write ", dir, "/landmarks.csv"));
  std::ofstream cross(std::filesystem::path(dir) / "cross_covariances.csv");
  cross << "landmark_a,landmark_b,cov_ee_m2,cov_en_m2,cov_ne_m2,cov_nn_m2\n";
  for (size_t i = 0; i < stacked.ids.size(); ++i) {
    for (size_t j = i + 1; j < stacked.ids.size(); ++j) {
      const Eigen::Matrix2d c = stacked.cov.block<2, 2>(2 * i, 2 * j);
      if (c.isZero(0.0)) continue;
      cross << absl::StrFormat("%d,%d,%.9g,%.9g,%.9g,%.9g\n", stacked.ids[i], stacked.ids[j], c(0, 0), c(0, 1), c(1, 0),
                               c(1, 1));
    }
  }
  if (!cross) return absl::InternalError(absl::StrCat("cannot write ", dir, "/cross_covariances.csv"));

  // Non-finite figures (no bound computed) are written as null.
  nlohmann::ordered_json summary = {
      {"strategy", options.strategy},
      {"noise", NoiseConfigName(options.scenario.noise)},
      {"seed", options.scenario.seed},
      {"landmarks", options.scenario.landmarks},
      {"piece_min_m", options.scenario.piece_min_m},
      {"piece_max_m", options.scenario.piece_max_m},
      {"passages", options.passages},
      {"failed_passages", result.failed_passages},
      {"relinearized_passages", result.relinearized_passages},
      {"relinearize_sigmas", options.update.relinearize_sigmas},
      {"relinearize_area_passages", options.update.relinearize_area_passages},
      {"inflated_passages", result.inflated_passages},
      {"correlated_gnss_passages", result.correlated_gnss_passages},
      {"gnss_residual_lag1", Percentiles(result.gnss_residual_lag1)},
      {"sensor_test_sigmas", options.update.sensor_test_sigmas},
      {"max_detection_residual_sigmas", options.update.max_detection_residual_sigmas},
      {"max_unfit_detection_fraction", options.update.max_unfit_detection_fraction},
      {"sensor_inflated", SensorInflationsJson(result.sensor_inflations)},
      {"max_subgraph_dim", options.update.max_subgraph_dim},
      {"detections_per_landmark", options.update.detections_per_landmark},
      {"spread_detections", options.update.spread_detections},
      {"warmup_passages", options.update.warmup_passages},
      {"relinearize_until_passages", options.update.relinearize_until_passages},
      {"edge_margin_sigmas", options.update.edge_margin_sigmas},
      {"joint_rejected_passages", result.joint_rejected_passages},
      {"quarantined_passages", result.quarantined_passages},
      {"detections_used", result.detections_used},
      {"detections_outliers", result.detections_outliers},
      {"landmarks_disagreeing", result.landmarks_disagreeing},
      {"final_mean_dist_err_m", result.final_mean_dist_err_m},
      {"final_nees_per_dof", result.final_nees_per_dof},
      {"final_joint_nees_per_dof", result.final_joint_nees_per_dof},
      {"nees_per_dof_sd_if_consistent", result.nees_per_dof_sd_if_consistent},
      {"crlb_mean_dist_err_m", result.crlb_mean_dist_err_m},
      {"error_over_crlb", result.final_mean_dist_err_m / result.crlb_mean_dist_err_m},
      {"last_joint_nees_per_dof", result.records.empty() ? std::nan("") : result.records.back().metrics.joint_nees_per_dof},
      {"crlb_joint_nees_per_dof", result.crlb_joint_nees_per_dof},
      {"median_passage_ms", result.median_passage_ms},
      {"estimate_camera_yaw", options.update.estimate_camera_yaw},
      {"fleet_camera_yaw_prior_vehicles", options.update.fleet_camera_yaw_prior_vehicles},
      {"vehicles", options.scenario.vehicles},
      {"vehicle_yaw_bias_sigma_rad", options.scenario.vehicle_yaw_bias_sigma_rad},
      {"vehicle_yaw_within_2sigma", result.vehicle_yaw.within_2sigma_fraction},
      {"vehicle_yaw_nees", result.vehicle_yaw.nees},
      {"vehicle_yaw_rms_error_rad", result.vehicle_yaw.rms_error_rad},
      {"vehicle_yaw_mean_error_rad", result.vehicle_yaw.mean_error_rad},
      {"vehicle_yaw_mean_sigma_rad", result.vehicle_yaw.mean_sigma_rad},
  };
  nlohmann::ordered_json& vehicle_yaw = summary["vehicle_yaw"] = nlohmann::ordered_json::array();
  for (const VehicleYawError& e : result.vehicle_yaw.vehicles) {
    vehicle_yaw.push_back({{"vehicle_id", e.vehicle_id},
                           {"truth_rad", e.truth_rad},
                           {"estimate_rad", e.estimate_rad},
                           {"sigma_rad", e.sigma_rad},
                           {"passages", e.passages}});
  }
  for (const auto& [key, value] : extra_summary) summary[key] = value;
  std::ofstream json(std::filesystem::path(dir) / "summary.json");
  json << summary.dump(2) << "\n";
  if (!json) return absl::InternalError(absl::StrCat("cannot write ", dir, "/summary.json"));

  return WriteErrorPlot(result.records,
                        absl::StrFormat("%s, N=%d, %s noise, seed %d", options.strategy, options.scenario.landmarks,
                                        NoiseConfigName(options.scenario.noise), options.scenario.seed),
                        (std::filesystem::path(dir) / "errors.svg").string());
}

void CountGnssCheck(const PassageUpdateSummary& summary, int* correlated_passages, std::vector<double>* lag1) {
  if (summary.gnss_correlation_time_s > 0.0) ++*correlated_passages;
  if (summary.gnss_residual_lag1 != 0.0) lag1->push_back(summary.gnss_residual_lag1);
}

void CountSensorInflations(const PassageUpdateSummary& summary, SensorInflations* inflations) {
  for (int s = 0; s < kPassageSensors; ++s) {
    if (summary.sensor_test_factors[s] <= 1.0) continue;
    ++inflations->passages[s];
    inflations->factors[s].push_back(summary.sensor_test_factors[s]);
  }
}

nlohmann::ordered_json SensorInflationsJson(const SensorInflations& inflations) {
  nlohmann::ordered_json out;
  for (int s = 0; s < kPassageSensors; ++s) {
    out[PassageSensorName(s)] = {{"passages", inflations.passages[s]}, {"factor", Percentiles(inflations.factors[s])}};
  }
  return out;
}

std::map<std::string, double> Percentiles(std::vector<double> values) {
  if (values.empty()) return {};
  std::sort(values.begin(), values.end());
  auto at = [&](double q) { return values[static_cast<size_t>(std::lround(q * static_cast<double>(values.size() - 1)))]; };
  return {{"p50", at(0.5)}, {"p95", at(0.95)}, {"max", values.back()}};
}

}  // namespace crowdmap
