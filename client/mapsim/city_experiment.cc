#include "client/mapsim/city_experiment.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <filesystem>
#include <fstream>

#include <Eigen/Cholesky>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

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

std::string JsonNumber(double v) { return std::isfinite(v) ? absl::StrFormat("%.6g", v) : "null"; }

}  // namespace

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
      "p95_error_m=%.4f nees_per_dof=%.3f p50_ms=%.1f p95_ms=%.1f vehicle_yaw_within_2sigma=%.3f "
      "vehicle_yaw_nees=%.3f",
      layout_landmarks, errors.size(), passages, failed_passages, failed_faulty_passages, failed_clean_passages,
      faulty_passages, quarantined_passages, relinearized_passages, inflated_passages, landmarks_held_back,
      landmarks_disagreeing, detections_used, detections_outliers,
      mean_error_m, median_error_m, p95_error_m, nees_per_dof, p50_ms, p95_ms, vehicle_yaw.within_2sigma_fraction,
      vehicle_yaw.nees);
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
      result.landmarks_held_back += update->summary.landmarks_held_back;
      result.landmarks_disagreeing += update->summary.landmarks_disagreeing;
      result.inflated_passages += update->summary.max_variance_factor > 1.0 ? 1 : 0;
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
      progress(p);
    }
  }
  result.errors = CityMapErrors(map, *city);
  const std::vector<double> errors_m = ErrorsM(result.errors);
  result.mean_error_m = Mean(errors_m);
  result.median_error_m = Quantile(errors_m, 0.5);
  result.p95_error_m = Quantile(errors_m, 0.95);
  for (const CityLandmarkError& e : result.errors) result.nees_per_dof += 0.5 * e.mahalanobis2 / result.errors.size();
  result.p50_ms = Quantile(result.passage_ms, 0.5);
  result.p95_ms = Quantile(result.passage_ms, 0.95);
  std::vector<std::pair<std::string, double>> yaw_truth;
  for (int v = 0; v < options.city.vehicles; ++v) {
    const CityVehicle vehicle = city->Vehicle(v);
    yaw_truth.emplace_back(vehicle.vehicle_id,
                           vehicle.true_camera.camera_yaw_rad - options.city.calibration.camera_yaw_rad);
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
  csv << "landmark,true_east_m,true_north_m,est_east_m,est_north_m,error_m,sigma_east_m,sigma_north_m\n";
  for (const CityLandmarkError& e : result.errors) {
    csv << absl::StrFormat("%d,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f\n", e.id, e.truth_m.x(), e.truth_m.y(),
                           e.estimate_m.x(), e.estimate_m.y(), e.error_m(), e.sigma_east_m, e.sigma_north_m);
  }
  csv.close();
  if (!csv) return absl::InternalError(absl::StrCat("cannot write ", dir, "/landmarks.csv"));

  const CityScenarioOptions& c = options.city;
  std::ofstream json(std::filesystem::path(dir) / "summary.json");
  json << "{\n"
       << absl::StrFormat("  \"blocks_x\": %d,\n  \"blocks_y\": %d,\n", c.blocks_x, c.blocks_y)
       << "  \"block_m\": " << JsonNumber(c.block_m) << ",\n"
       << "  \"route_length_m\": " << JsonNumber(c.route_length_m) << ",\n"
       << absl::StrFormat("  \"vehicles\": %d,\n  \"seed\": %d,\n  \"layout_seed\": %d,\n", c.vehicles, c.seed,
                          c.layout_seed)
       << absl::StrFormat("  \"noise\": \"%s\",\n", NoiseConfigName(c.noise))
       << absl::StrFormat("  \"strategy\": \"%s\",\n", UpdateStrategyName(options.update.strategy))
       << absl::StrFormat("  \"passages\": %d,\n", result.passages)
       << absl::StrFormat("  \"passages_failed\": %d,\n", result.failed_passages)
       << absl::StrFormat("  \"passages_relinearized\": %d,\n", result.relinearized_passages)
       << absl::StrFormat("  \"passages_inflated\": %d,\n", result.inflated_passages)
       << absl::StrFormat("  \"landmarks_held_back\": %d,\n", result.landmarks_held_back)
       << absl::StrFormat("  \"landmarks_disagreeing\": %d,\n", result.landmarks_disagreeing)
       << absl::StrFormat("  \"passages_quarantined\": %d,\n", result.quarantined_passages)
       << absl::StrFormat("  \"detections_used\": %d,\n", result.detections_used)
       << absl::StrFormat("  \"detections_outliers\": %d,\n", result.detections_outliers)
       << absl::StrFormat("  \"faults\": {\"seed\": %d, \"mislabel_rate\": %g, \"multipath_rate\": %g, "
                          "\"overconfident_rate\": %g, \"bad_calibration_rate\": %g,\n", options.faults.seed,
                          options.faults.mislabel_rate, options.faults.multipath_rate, options.faults.overconfident_rate,
                          options.faults.bad_calibration_rate)
       << absl::StrFormat("    \"faulty_passages\": %d, \"mislabelled_detections\": %d, \"multipath_passages\": %d, "
                          "\"overconfident_passages\": %d, \"bad_calibration_passages\": %d,\n",
                          result.faulty_passages, result.mislabelled_detections, result.multipath_passages,
                          result.overconfident_passages, result.bad_calibration_passages)
       << absl::StrFormat("    \"failed_faulty_passages\": %d, \"failed_clean_passages\": %d},\n",
                          result.failed_faulty_passages, result.failed_clean_passages)
       << absl::StrFormat("  \"relinearize_sigmas\": %g,\n", options.update.relinearize_sigmas)
       << "  \"nees_per_dof\": " << JsonNumber(result.nees_per_dof) << ",\n"
       << absl::StrFormat("  \"landmarks_in_layout\": %d,\n", result.layout_landmarks)
       << absl::StrFormat("  \"landmarks_mapped\": %d,\n", result.errors.size())
       << "  \"layout_s\": " << JsonNumber(result.layout_s) << ",\n"
       << "  \"mean_error_m\": " << JsonNumber(result.mean_error_m) << ",\n"
       << "  \"median_error_m\": " << JsonNumber(result.median_error_m) << ",\n"
       << "  \"p95_error_m\": " << JsonNumber(result.p95_error_m) << ",\n"
       << "  \"p50_ms_per_passage\": " << JsonNumber(result.p50_ms) << ",\n"
       << "  \"p95_ms_per_passage\": " << JsonNumber(result.p95_ms) << ",\n"
       << absl::StrFormat("  \"estimate_camera_yaw\": %s,\n", options.update.estimate_camera_yaw ? "true" : "false")
       << "  \"vehicle_yaw_bias_sigma_rad\": " << JsonNumber(c.vehicle_yaw_bias_sigma_rad) << ",\n"
       << "  \"vehicle_yaw_within_2sigma\": " << JsonNumber(result.vehicle_yaw.within_2sigma_fraction) << ",\n"
       << "  \"vehicle_yaw_nees\": " << JsonNumber(result.vehicle_yaw.nees) << ",\n"
       << "  \"vehicle_yaw_rms_error_rad\": " << JsonNumber(result.vehicle_yaw.rms_error_rad) << "\n}\n";
  json.close();
  if (!json) return absl::InternalError(absl::StrCat("cannot write ", dir, "/summary.json"));
  return absl::OkStatus();
}

}  // namespace crowdmap
