#include "client/mapsim/city_experiment.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <filesystem>
#include <fstream>

#include <Eigen/Cholesky>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/mapsim/experiment.h"
#include "core/estimation/cramer_rao.h"

namespace crowdmap {
namespace {

// The q-quantile (nearest rank) of v; 0 when empty.
double Quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  const size_t k = std::min(v.size(), static_cast<size_t>(std::max(1.0, std::ceil(q * v.size())))) - 1;
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

double Mean(const std::vector<double>& v) {
  double sum = 0.0;
  for (double x : v) sum += x;
  return v.empty() ? 0.0 : sum / v.size();
}

std::vector<double> ErrorsM(const std::vector<CityLandmarkError>& errors) {
  std::vector<double> out;
  out.reserve(errors.size());
  for (const CityLandmarkError& e : errors) out.push_back(e.error_m());
  return out;
}

// The diffuse prior of every landmark in a city's Cramer-Rao bound (CityCramerRao).
constexpr double kCityCrlbLandmarkPriorSigmaM = 1000.0;

// Vehicle `v`'s true camera yaw offset from the calibration its passages declare.
double CameraYawOffsetRad(const CityScenario& city, int v) {
  const CityVehicle vehicle = city.Vehicle(v);
  return vehicle.true_camera.camera_yaw_rad - vehicle.calibration.camera_yaw_rad;
}

// `json` for a figure that may be NaN (not computed): null then.
nlohmann::ordered_json FiniteOrNull(double x) { return std::isfinite(x) ? nlohmann::ordered_json(x) : nullptr; }

// The bound of the `applied` passages beside each mapped landmark's error (result->errors), and its
// means; a log line instead where it is not computed (CityExperimentOptions::crlb).
void AddCityCramerRao(const CityScenario& city, const std::vector<int>& applied, const CityExperimentOptions& options,
                      CityExperimentResult* result) {
  if (city.landmark_count() > kCityCrlbMaxLandmarks) {
    spdlog::info("Cramer-Rao bound not computed: {} landmarks in the layout, over {} (the bound is dense)",
                 city.landmark_count(), kCityCrlbMaxLandmarks);
    return;
  }
  if (options.city.vehicle_speed_scale_sigma != 0.0) {
    spdlog::info("Cramer-Rao bound not computed: the estimator does not model the vehicles' wheel-speed scale errors");
    return;
  }
  spdlog::info("Cramer-Rao bound of the {} passages applied...", applied.size());
  absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> bound = CityCramerRao(city, applied, options.update);
  if (!bound.ok()) {
    spdlog::warn("Cramer-Rao bound not computed: {}", bound.status().ToString());
    return;
  }
  double error_sum = 0.0, bound_sum = 0.0, nees_sum = 0.0;
  int n = 0;
  for (CityLandmarkError& e : result->errors) {
    const auto it = bound->find(e.id);
    if (it == bound->end()) continue;  // none: every mapped landmark was seen by an applied passage
    e.crlb_cov_m2 = it->second;
    error_sum += e.error_m();
    bound_sum += e.crlb_error_m();
    nees_sum += 0.5 * e.crlb_mahalanobis2();
    ++n;
  }
  if (n == 0) return;
  result->crlb_mean_error_m = bound_sum / n;
  result->error_over_crlb = error_sum / bound_sum;
  result->crlb_nees_per_dof = nees_sum / n;
}

}  // namespace

double CityLandmarkError::crlb_error_m() const {
  return crlb_cov_m2 ? ExpectedDistance(*crlb_cov_m2) : std::nan("");
}

double CityLandmarkError::crlb_mahalanobis2() const {
  if (!crlb_cov_m2) return std::nan("");
  const Eigen::Vector2d error = estimate_m - truth_m;
  return error.dot(crlb_cov_m2->ldlt().solve(error));
}

absl::StatusOr<std::map<LandmarkId, Eigen::Matrix2d>> CityCramerRao(const CityScenario& city,
                                                                    const std::vector<int>& indices,
                                                                    const MapUpdateOptions& update) {
  GraphOptions graph = UpdateGraphOptions(update);
  graph.frame_origin = city.frame().origin();
  const auto true_landmark = [&](LandmarkId id) -> std::optional<Eigen::Vector2d> {
    if (id < 1 || id > static_cast<LandmarkId>(city.landmark_count())) return std::nullopt;
    return city.landmarks()[id - 1].position_m;
  };
  // A city's passages glimpse some landmark along one ray; the estimator holds it back, and the
  // bound's 1 km prior keeps it from making the others' bound singular.
  CramerRaoBound bound(update.estimate_camera_yaw ? update.camera_yaw_prior_sigma_rad : 0.0,
                       kCityCrlbLandmarkPriorSigmaM);
  for (int index : indices) {
    const auto [passage, drive] = city.MakePassageWithTruth(index);
    const std::optional<double> yaw =
        update.estimate_camera_yaw ? std::optional<double>(CameraYawOffsetRad(city, index % city.options().vehicles))
                                   : std::nullopt;
    absl::StatusOr<PassageFisherInformation> info = PassageLandmarkInformation(
        passage, graph, [&drive = drive](double t) { return drive.PoseAt(t); }, true_landmark, yaw);
    if (!info.ok()) {
      return absl::Status(info.status().code(), absl::StrCat("passage ", index, ": ", info.status().message()));
    }
    bound.Add(*info);
  }
  return bound.Covariances();
}

absl::Status CityExperimentOptions::Validate() const {
  if (passages < 1) return absl::InvalidArgumentError(absl::StrCat("passages: must be >= 1, got ", passages));
  if (progress_every_passages < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("progress_every_passages: must be >= 1, got ", progress_every_passages));
  }
  if (absl::Status s = city.Validate(); !s.ok()) return s;
  if (absl::Status s = faults.Validate(); !s.ok()) return s;
  return update.Validate();
}

std::string CityExperimentResult::Brief() const {
  return absl::StrFormat(
      "layout_landmarks=%d landmarks_mapped=%d passages=%d failed=%d (faulty %d, clean %d) faulty=%d "
      "quarantined=%d relinearized=%d inflated=%d held_back=%d disagreeing=%d detections_used=%d "
      "detections_outliers=%d mean_error_m=%.4f median_error_m=%.4f "
      "p95_error_m=%.4f nees_per_dof=%.3f crlb_mean_error_m=%.4f error_over_crlb=%.3f crlb_nees_per_dof=%.3f "
      "p50_ms=%.1f p95_ms=%.1f vehicle_yaw_within_2sigma=%.3f vehicle_yaw_nees=%.3f",
      layout_landmarks, errors.size(), passages, failed_passages, failed_faulty_passages, failed_clean_passages,
      faulty_passages, quarantined_passages, relinearized_passages, inflated_passages, landmarks_held_back,
      landmarks_disagreeing, detections_used, detections_outliers, mean_error_m, median_error_m, p95_error_m,
      nees_per_dof, crlb_mean_error_m, error_over_crlb, crlb_nees_per_dof, p50_ms, p95_ms,
      vehicle_yaw.within_2sigma_fraction, vehicle_yaw.nees);
}

std::vector<CityLandmarkError> CityMapErrors(const MapState& map, const CityScenario& city) {
  std::vector<CityLandmarkError> errors;
  errors.reserve(map.landmark_count());
  const LocalFrame& frame = city.frame();
  map.ForEachLandmark([&](const Landmark& lm) {
    if (lm.id < 1 || lm.id > static_cast<LandmarkId>(city.landmark_count())) return;
    CityLandmarkError e;
    e.id = lm.id;
    e.truth_m = city.landmarks()[lm.id - 1].position_m;
    e.estimate_m = frame.ToLocal(lm.position);
    // The covariance is East/North at the landmark; rotate it into the city frame's axes.
    const Eigen::Matrix2d j = frame.EnToLocal(lm.position);
    const Eigen::Matrix2d cov = j * lm.cov_en_m2 * j.transpose();
    e.sigma_east_m = std::sqrt(std::max(0.0, cov(0, 0)));
    e.sigma_north_m = std::sqrt(std::max(0.0, cov(1, 1)));
    const Eigen::Vector2d error = e.estimate_m - e.truth_m;
    e.mahalanobis2 = error.dot(cov.ldlt().solve(error));
    errors.push_back(e);
  });
  std::sort(errors.begin(), errors.end(), [](const auto& a, const auto& b) { return a.id < b.id; });
  return errors;
}

absl::StatusOr<CityExperimentResult> RunCityExperiment(const CityExperimentOptions& options,
                                                       const std::function<void(const CityProgress&)>& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const auto layout_start = std::chrono::steady_clock::now();
  absl::StatusOr<CityScenario> city = CityScenario::Create(options.city);
  if (!city.ok()) return city.status();
  CityExperimentResult result;
  result.layout_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - layout_start).count();
  result.layout_landmarks = city->landmark_count();
  result.passages = options.passages;

  MapState map;
  MapUpdater updater(options.update);
  std::map<MapUpdater::PassageKey, int> index_of;
  std::vector<int> applied;  // passage indices, in order
  const auto make_passage = [&](int index, InjectedFaults* faults) {
    Passage passage = city->MakePassage(index);
    const InjectedFaults injected = InjectFaults(options.faults, index, city->frame(), &passage);
    if (faults != nullptr) *faults = injected;
    return passage;
  };
  const auto passage_of = [&](const MapUpdater::PassageKey& key) -> absl::StatusOr<Passage> {
    const auto it = index_of.find(key);
    if (it == index_of.end()) return absl::NotFoundError("passage not applied");
    return make_passage(it->second, nullptr);
  };
  for (int i = 0; i < options.passages; ++i) {
    InjectedFaults faults;
    const Passage passage = make_passage(i, &faults);
    result.faulty_passages += faults.any() ? 1 : 0;
    result.mislabelled_detections += faults.mislabelled_detections;
    result.multipath_passages += faults.multipath ? 1 : 0;
    result.overconfident_passages += faults.overconfident ? 1 : 0;
    result.bad_calibration_passages += faults.bad_calibration ? 1 : 0;
    const auto start = std::chrono::steady_clock::now();
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    if (update.ok()) {
      map.Apply(update->delta);
      updater.Applied(passage, update->delta);
      index_of[{passage.vehicle_id, passage.passage_id}] = i;
      applied.push_back(i);
      result.landmarks_held_back += update->summary.landmarks_held_back;
      result.landmarks_disagreeing += update->summary.landmarks_disagreeing;
      result.inflated_passages += update->summary.max_variance_factor > 1.0 ? 1 : 0;
      CountGnssCheck(update->summary, &result.correlated_gnss_passages, &result.gnss_residual_lag1);
      CountSensorInflations(update->summary, &result.sensor_inflations);
      result.detections_used += update->summary.detections_used;
      result.detections_outliers += update->summary.detections_outliers;
      result.relinearized_passages += RelinearizeStaleInMemory(passage_of, &updater, &map);
    } else {
      ++result.failed_passages;
      if (absl::IsFailedPrecondition(update.status())) ++result.quarantined_passages;
      ++(faults.any() ? result.failed_faulty_passages : result.failed_clean_passages);
      spdlog::warn("passage={} rejected: {}", passage.passage_id, update.status().ToString());
    }
    result.passage_ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
    const int done = i + 1;
    if (progress && (done % options.progress_every_passages == 0 || done == options.passages)) {
      CityProgress p;
      p.passages_done = done;
      p.passages_total = options.passages;
      p.landmarks_mapped = map.landmark_count();
      const std::vector<double> errors_m = ErrorsM(CityMapErrors(map, *city));
      p.mean_error_m = Mean(errors_m);
      p.median_error_m = Quantile(errors_m, 0.5);
      p.p50_ms = Quantile(result.passage_ms, 0.5);
      p.p95_ms = Quantile(result.passage_ms, 0.95);
      const std::vector<double> recent(result.passage_ms.end() - std::min<size_t>(result.passage_ms.size(),
                                                                                  options.progress_every_passages),
                                       result.passage_ms.end());
      p.recent_p50_ms = Quantile(recent, 0.5);
      p.recent_p95_ms = Quantile(recent, 0.95);
      progress(p);
    }
  }
  result.errors = CityMapErrors(map, *city);
  if (options.crlb) AddCityCramerRao(*city, applied, options, &result);
  const std::vector<double> errors_m = ErrorsM(result.errors);
  result.mean_error_m = Mean(errors_m);
  result.median_error_m = Quantile(errors_m, 0.5);
  result.p95_error_m = Quantile(errors_m, 0.95);
  for (const CityLandmarkError& e : result.errors) result.nees_per_dof += 0.5 * e.mahalanobis2 / result.errors.size();
  result.p50_ms = Quantile(result.passage_ms, 0.5);
  result.p95_ms = Quantile(result.passage_ms, 0.95);
  std::vector<std::pair<std::string, double>> yaw_truth;
  for (int v = 0; v < options.city.vehicles; ++v) {
    yaw_truth.emplace_back(city->Vehicle(v).vehicle_id, CameraYawOffsetRad(*city, v));
  }
  result.vehicle_yaw = EvaluateVehicleYaw(map, yaw_truth);
  return result;
}

absl::Status WriteCityOutputs(const CityExperimentOptions& options, const CityExperimentResult& result,
                              const std::string& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", dir, ": ", ec.message()));

  std::ofstream csv(std::filesystem::path(dir) / "landmarks.csv");
  csv << "landmark,true_east_m,true_north_m,est_east_m,est_north_m,error_m,sigma_east_m,sigma_north_m,mahalanobis2,"
         "crlb_error_m,crlb_mahalanobis2\n";
  for (const CityLandmarkError& e : result.errors) {
    csv << absl::StrFormat("%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,", e.id, e.truth_m.x(), e.truth_m.y(),
                           e.estimate_m.x(), e.estimate_m.y(), e.error_m(), e.sigma_east_m, e.sigma_north_m,
                           e.mahalanobis2)
        << (e.crlb_cov_m2 ? absl::StrFormat("%.4f,%.4f\n", e.crlb_error_m(), e.crlb_mahalanobis2()) : ",\n");
  }
  csv.close();
  if (!csv) return absl::InternalError(absl::StrCat("cannot write ", dir, "/landmarks.csv"));

  const CityScenarioOptions& c = options.city;
  const FaultOptions& f = options.faults;
  // Non-finite figures are written as null.
  const nlohmann::ordered_json summary = {
      {"blocks_x", c.blocks_x},
      {"blocks_y", c.blocks_y},
      {"block_m", c.block_m},
      {"route_length_m", c.route_length_m},
      {"late_blocks_x", c.late_blocks_x},
      {"late_from_passage", c.late_from_passage},
      {"vehicles", c.vehicles},
      {"seed", c.seed},
      {"layout_seed", c.layout_seed},
      {"noise", NoiseConfigName(c.noise)},
      {"rate_variation", c.rate_variation},
      {"vary_calibration", c.vary_calibration},
      {"traffic",
       {{"stop_probability", c.stop_probability},
        {"stop_s", {c.stop_min_s, c.stop_max_s}},
        {"gnss_outage_probability", c.gnss_outage_probability},
        {"gnss_outage_s", {c.gnss_outage_min_s, c.gnss_outage_max_s}}}},
      {"strategy", UpdateStrategyName(options.update.strategy)},
      {"detections_per_landmark", options.update.detections_per_landmark},
      {"spread_detections", options.update.spread_detections},
      {"passages", result.passages},
      {"passages_failed", result.failed_passages},
      {"passages_relinearized", result.relinearized_passages},
      {"passages_inflated", result.inflated_passages},
      {"passages_correlated_gnss", result.correlated_gnss_passages},
      {"gnss_residual_lag1", Percentiles(result.gnss_residual_lag1)},
      {"sensor_test_sigmas", options.update.sensor_test_sigmas},
      {"max_detection_residual_sigmas", options.update.max_detection_residual_sigmas},
      {"max_unfit_detection_fraction", options.update.max_unfit_detection_fraction},
      {"sensor_inflated", SensorInflationsJson(result.sensor_inflations)},
      {"landmarks_held_back", result.landmarks_held_back},
      {"landmarks_disagreeing", result.landmarks_disagreeing},
      {"passages_quarantined", result.quarantined_passages},
      {"detections_used", result.detections_used},
      {"detections_outliers", result.detections_outliers},
      {"faults",
       {{"seed", f.seed},
        {"mislabel_rate", f.mislabel_rate},
        {"multipath_rate", f.multipath_rate},
        {"overconfident_rate", f.overconfident_rate},
        {"bad_calibration_rate", f.bad_calibration_rate},
        {"faulty_passages", result.faulty_passages},
        {"mislabelled_detections", result.mislabelled_detections},
        {"multipath_passages", result.multipath_passages},
        {"overconfident_passages", result.overconfident_passages},
        {"bad_calibration_passages", result.bad_calibration_passages},
        {"failed_faulty_passages", result.failed_faulty_passages},
        {"failed_clean_passages", result.failed_clean_passages}}},
      {"relinearize_sigmas", options.update.relinearize_sigmas},
      {"relinearize_area_passages", options.update.relinearize_area_passages},
      {"nees_per_dof", result.nees_per_dof},
      {"landmarks_in_layout", result.layout_landmarks},
      {"landmarks_mapped", result.errors.size()},
      {"layout_s", result.layout_s},
      {"mean_error_m", result.mean_error_m},
      {"median_error_m", result.median_error_m},
      {"p95_error_m", result.p95_error_m},
      {"crlb_mean_error_m", FiniteOrNull(result.crlb_mean_error_m)},
      {"error_over_crlb", FiniteOrNull(result.error_over_crlb)},
      {"crlb_nees_per_dof", FiniteOrNull(result.crlb_nees_per_dof)},
      {"p50_ms_per_passage", result.p50_ms},
      {"p95_ms_per_passage", result.p95_ms},
      {"estimate_camera_yaw", options.update.estimate_camera_yaw},
      {"fleet_camera_yaw_prior_vehicles", options.update.fleet_camera_yaw_prior_vehicles},
      {"vehicle_yaw_bias_sigma_rad", options.city.vehicle_yaw_bias_sigma_rad},
      {"vehicle_yaw_within_2sigma", result.vehicle_yaw.within_2sigma_fraction},
      {"vehicle_yaw_nees", result.vehicle_yaw.nees},
      {"vehicle_yaw_rms_error_rad", result.vehicle_yaw.rms_error_rad},
      {"vehicle_yaw_mean_error_rad", result.vehicle_yaw.mean_error_rad},
      {"vehicle_yaw_mean_sigma_rad", result.vehicle_yaw.mean_sigma_rad},
  };
  std::ofstream json(std::filesystem::path(dir) / "summary.json");
  json << summary.dump(2) << "\n";
  json.close();
  if (!json) return absl::InternalError(absl::StrCat("cannot write ", dir, "/summary.json"));
  return absl::OkStatus();
}

}  // namespace crowdmap
