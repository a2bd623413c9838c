#include "client/mapsim/localize_experiment.h"

#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <string>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/mapsim/experiment.h"
#include "core/estimation/factors.h"
#include "core/estimation/map_updater.h"
#include "core/estimation/vehicle_calibration.h"
#include "core/map/map_state.h"
#include "core/sim/metrics.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Table 5.5 of the thesis: (without, with) map for 44 and for 500 landmarks, per case.
struct ThesisRow {
  double signs_without, signs_with, dense_without, dense_with;
};
constexpr ThesisRow kThesis[] = {
    {2.38, 1.89, 2.76, 0.72},   {12.74, 7.39, 12.39, 0.87}, {2.29, 1.87, 2.15, 0.79},
    {17.28, 9.53, 17.29, 0.94}, {17.28, 8.14, 17.29, 0.92},
};

// The thesis's map model (equations 5.12-5.17): every landmark off its truth by a draw of
// N(bias, diag(sigma^2)), declared with diag(sigma^2) or the inconsistent diag(declared^2).
LocalizationMap ThesisMap(const Scenario& scenario, const LocalizeExperimentOptions& o, bool inconsistent,
                          uint64_t seed) {
  NoiseSource noise(SplitMix64(seed));
  LocalizationMap map;
  const int n = static_cast<int>(scenario.landmarks().size());
  map.cov_en_m2 = Eigen::MatrixXd::Zero(2 * n, 2 * n);
  const Eigen::Vector2d declared = inconsistent ? Eigen::Vector2d(o.inconsistent_sigma_east_m, o.inconsistent_sigma_north_m)
                                                : Eigen::Vector2d(o.map_sigma_east_m, o.map_sigma_north_m);
  for (int k = 0; k < n; ++k) {
    const TruthLandmark& lm = scenario.landmarks()[k];
    const Eigen::Vector2d error(o.map_bias_east_m + o.map_sigma_east_m * noise.Normal(),
                                o.map_bias_north_m + o.map_sigma_north_m * noise.Normal());
    map.ids.push_back(lm.id);
    map.positions.push_back(scenario.frame().ToGeo(lm.position_m + error));
    map.cov_en_m2.block<2, 2>(2 * k, 2 * k) = declared.cwiseProduct(declared).asDiagonal();
  }
  return map;
}

// The first passage index of crowdmap's own map: none of its passages is a localised one.
constexpr int kOwnMapFirstPassage = 100000;

// mapd's default options, with the camera yaw of each vehicle estimated.
MapUpdateOptions OwnMapOptions() {
  MapUpdateOptions options;
  options.estimate_camera_yaw = true;
  return options;
}

// crowdmap's own map of the scenario after `passages` passages (indices kOwnMapFirstPassage + i),
// applied in order by the in-process updater with OwnMapOptions(): the localised passage i's
// vehicle (sim-<i % 1000>) drove map passage kOwnMapFirstPassage + i.
absl::StatusOr<MapState> OwnMap(const Scenario& scenario, int passages, const LocalizeProgress& progress) {
  MapState map;
  MapUpdater updater{OwnMapOptions()};
  for (int i = 0; i < passages; ++i) {
    const Passage passage = scenario.MakePassage(kOwnMapFirstPassage + i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    if (!update.ok()) {
      spdlog::warn("own map: passage {} not applied: {}", i, std::string(update.status().message()));
      continue;
    }
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
    if (progress) progress(absl::StrFormat("own map n=%d passage %d/%d", scenario.landmarks().size(), i + 1, passages));
  }
  return map;
}

struct RunErrors {
  double distance_sum_m = 0.0;
  double nees_sum = 0.0;
  int poses = 0;
};

void Accumulate(const Scenario& scenario, const PassageLocalization& result, RunErrors* errors) {
  for (const LocalizedPose& p : result.poses) {
    const Pose2 truth = scenario.TruePoseAt(p.t_s);
    Eigen::Vector3d e;
    e.head<2>() = scenario.frame().ToLocal(p.position) - truth.head<2>();
    e.z() = NormalizeAngle(p.pose_m.z() - truth.z());
    errors->distance_sum_m += e.head<2>().norm();
    errors->nees_sum += e.dot(p.cov.ldlt().solve(e)) / 3.0;
    ++errors->poses;
  }
}

}  // namespace

absl::Status LocalizeExperimentOptions::Validate() const {
  if (landmark_counts.empty()) return absl::InvalidArgumentError("landmarks: at least one count");
  for (int n : landmark_counts) {
    if (n < 1) return absl::InvalidArgumentError("landmarks: counts must be >= 1");
  }
  if (runs < 1) return absl::InvalidArgumentError("runs: must be >= 1");
  if (gnss_fixes == 1 || gnss_fixes < 0) return absl::InvalidArgumentError("gnss_fixes: 0 or >= 2");
  if (!(duration_s > 10.0)) return absl::InvalidArgumentError("duration_s: must be > 10");
  for (int p : own_map_passages) {
    if (p < 1) return absl::InvalidArgumentError("own-map-passages: counts must be >= 1");
  }
  return localizer.Validate();
}

std::vector<LocalizeCase> LocalizeCases(const LocalizeExperimentOptions& options) {
  std::vector<LocalizeCase> cases = {
      {"white", NoiseConfig::kWhite, false, 0},
      {"gnss-ar1", NoiseConfig::kGnssAr1, false, 0},
      {"yaw-bias", NoiseConfig::kYawBias, false, 0},
      {"ar1+yaw", NoiseConfig::kGnssAr1YawBias, false, 0},
      {"ar1+yaw, inconsistent map", NoiseConfig::kGnssAr1YawBias, true, 0},
  };
  for (int p : options.own_map_passages) {
    cases.push_back({absl::StrCat("ar1+yaw, crowdmap map P=", p), NoiseConfig::kGnssAr1YawBias, false, p});
  }
  return cases;
}

absl::StatusOr<std::vector<LocalizeRow>> RunLocalizeExperiment(const LocalizeExperimentOptions& options,
                                                                const LocalizeProgress& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  const std::vector<LocalizeCase> cases = LocalizeCases(options);
  std::vector<LocalizeRow> rows;
  for (size_t c = 0; c < cases.size(); ++c) {
    LocalizeRow row;
    row.config = cases[c];
    for (size_t l = 0; l < options.landmark_counts.size(); ++l) {
      const int landmarks = options.landmark_counts[l];
      ScenarioOptions so;
      so.landmarks = landmarks;
      so.noise = cases[c].noise;
      so.seed = options.seed;
      so.duration_s = options.duration_s;
      so.repeat_route = true;
      if (options.gnss_fixes > 0) {
        so.gnss_rate_hz = (options.gnss_fixes - 1) / options.duration_s;
        so.gnss_ar1_alpha = std::pow(so.gnss_ar1_alpha, 1.0 / so.gnss_rate_hz);
      }
      absl::StatusOr<Scenario> scenario = Scenario::Create(so);
      if (!scenario.ok()) return scenario.status();
      std::optional<MapState> own;
      if (cases[c].own_map_passages > 0) {
        absl::StatusOr<MapState> built = OwnMap(*scenario, cases[c].own_map_passages, progress);
        if (!built.ok()) return built.status();
        own = std::move(*built);
      }
      RunErrors without, with;
      LocalizeCell cell;
      cell.landmarks = landmarks;
      cell.map_error_m = cell.map_nees_per_dof = cell.map_crlb_m = kNaN;
      if (own) {
        const MapErrorMetrics metrics = EvaluateMap(*own, scenario->landmarks());
        cell.map_error_m = metrics.mean_dist_err_m;
        cell.map_nees_per_dof = metrics.nees_per_dof;
        std::vector<int> indices(cases[c].own_map_passages);
        for (size_t i = 0; i < indices.size(); ++i) indices[i] = kOwnMapFirstPassage + static_cast<int>(i);
        const MapUpdateOptions update = OwnMapOptions();
        const GraphOptions graph = UpdateGraphOptions(update);
        absl::StatusOr<double> bound =
            LoopCramerRaoMeanError(*scenario, indices, graph, update.camera_yaw_prior_sigma_rad);
        if (!bound.ok()) return bound.status();
        cell.map_crlb_m = *bound;
      }
      for (int run = 0; run < options.runs; ++run) {
        const Passage passage = scenario->MakePassage(run);
        // With crowdmap's map, as LocalizePassage: the vehicle's estimated camera yaw applied, and
        // estimated again with the record's uncertainty as its prior.
        Passage with_map = passage;
        PassageLocalizerOptions localizer = options.localizer;
        if (own) {
          const VehicleCalibration vehicle = VehicleCameraYawPrior(passage.vehicle_id, OwnMapOptions(), *own);
          with_map = WithVehicleCameraYaw(passage, vehicle);
          if (localizer.camera_yaw_sigma_rad > 0.0) localizer.camera_yaw_sigma_rad = std::sqrt(vehicle.camera_yaw_variance_rad2);
        }
        absl::StatusOr<LocalizationMap> map =
            own ? ReadLocalizationMap(*own, passage)
                : absl::StatusOr<LocalizationMap>(ThesisMap(*scenario, options, cases[c].inconsistent_map,
                                                            options.seed * 1000003ull + run * 7919ull + landmarks));
        if (!map.ok()) return map.status();
        absl::StatusOr<PassageLocalization> alone = LocalizePassage(passage, LocalizationMap{}, options.localizer);
        if (!alone.ok()) return alone.status();
        absl::StatusOr<PassageLocalization> located = LocalizePassage(with_map, *map, localizer);
        if (!located.ok()) return located.status();
        Accumulate(*scenario, *alone, &without);
        Accumulate(*scenario, *located, &with);
        cell.rejected_detections += static_cast<int>(located->rejected.size());
        spdlog::debug("localize case=\"{}\" landmarks={} run={} {}", cases[c].name, landmarks, run, located->Brief());
        if (progress) progress(absl::StrFormat("%s n=%d run %d/%d", cases[c].name, landmarks, run + 1, options.runs));
      }
      cell.without_map_m = without.distance_sum_m / without.poses;
      cell.with_map_m = with.distance_sum_m / with.poses;
      cell.with_map_nees_per_dof = with.nees_sum / with.poses;
      const bool thesis_cell = c < std::size(kThesis) && (landmarks == 44 || landmarks == 500);
      cell.thesis_without_m = thesis_cell ? (landmarks == 44 ? kThesis[c].signs_without : kThesis[c].dense_without) : kNaN;
      cell.thesis_with_m = thesis_cell ? (landmarks == 44 ? kThesis[c].signs_with : kThesis[c].dense_with) : kNaN;
      row.cells.push_back(cell);
    }
    rows.push_back(std::move(row));
  }
  return rows;
}

std::string LocalizeMarkdown(const LocalizeExperimentOptions& options, const std::vector<LocalizeRow>& rows) {
  auto value = [](double v) { return std::isnan(v) ? std::string("-") : absl::StrFormat("%.2f", v); };
  std::string out = absl::StrFormat(
      "Mean pose distance error (m) over all poses of %d passages of %.0f s (%s GNSS fixes) per cell (thesis: one "
      "passage), "
      "thesis / ours; ratio = ours / thesis with the map; NEES = pose NEES/dof with the map; rejected = "
      "detections rejected per passage.\n\n",
      options.runs, options.duration_s,
      options.gnss_fixes > 0 ? absl::StrCat(options.gnss_fixes) : absl::StrCat(static_cast<int>(options.duration_s) + 1));
  std::string header = "| configuration |", rule = "|---|";
  for (int n : options.landmark_counts) {
    header += absl::StrFormat(" N=%d without map | N=%d with map | ratio | NEES | rejected |", n, n);
    rule += "---|---|---|---|---|";
  }
  out += header + "\n" + rule + "\n";
  for (const LocalizeRow& row : rows) {
    std::string line = "| " + row.config.name + " |";
    for (const LocalizeCell& cell : row.cells) {
      line += absl::StrFormat(" %s / %.2f | %s / %.2f | %s | %.2f | %.1f |", value(cell.thesis_without_m),
                              cell.without_map_m, value(cell.thesis_with_m), cell.with_map_m,
                              value(cell.with_map_m / cell.thesis_with_m), cell.with_map_nees_per_dof,
                              static_cast<double>(cell.rejected_detections) / options.runs);
    }
    out += line + "\n";
  }
  for (const LocalizeRow& row : rows) {
    for (const LocalizeCell& cell : row.cells) {
      if (std::isnan(cell.map_error_m)) continue;
      out += absl::StrFormat(
          "\n%s, N=%d: the map's mean landmark error %.2f m (Cramer-Rao bound of its passages %.2f m), landmark "
          "NEES/dof %.2f.",
          row.config.name, cell.landmarks, cell.map_error_m, cell.map_crlb_m, cell.map_nees_per_dof);
    }
  }
  out += "\n";
  return out;
}

}  // namespace crowdmap
