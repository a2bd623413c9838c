#ifndef CROWDMAP_CLIENT_MAPSIM_LOCALIZE_EXPERIMENT_H_
#define CROWDMAP_CLIENT_MAPSIM_LOCALIZE_EXPERIMENT_H_

#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/estimation/map_update_options.h"
#include "core/localization/passage_localizer.h"
#include "core/sim/scenario.h"

namespace crowdmap {

// Thesis section 5.4 (Table 5.5): one passage of a ~4 km route localised without the map
// (odometry + GNSS) and with it, for two landmark distributions and five noise configurations.
// The map is either the thesis's model (Table 5.4: truth + N(bias, diag(sigma^2)), declared with
// that covariance, or with the over-confident one of field tests) or crowdmap's own, built from P
// simulated passages of the same route by the in-process update (MapUpdater).
struct LocalizeExperimentOptions {
  std::vector<int> landmark_counts = {44, 500};  // "traffic signs" and "dense" (1 every 8 m)
  double duration_s = 340.0;                     // 4.0 km at the route's 12 m/s
  // GNSS fixes per passage: the thesis's graph had 512 on its loop (a slower vehicle); the rate is
  // set to give as many, and the AR(1) coefficient per fix so that the noise's correlation time
  // stays that of the scenario's 1 Hz receiver. 0 = the scenario's 1 Hz.
  int gnss_fixes = 512;
  int runs = 10;                                 // passages (and maps) per cell, averaged
  uint64_t seed = 1;
  // Table 5.4: map error bias and sigma (East, North), and the declared sigma of the
  // inconsistent map.
  double map_bias_east_m = 0.15;
  double map_bias_north_m = -0.08;
  double map_sigma_east_m = 0.78;
  double map_sigma_north_m = 1.77;
  double inconsistent_sigma_east_m = 0.40;
  double inconsistent_sigma_north_m = 0.42;
  // Crowdmap's own maps: built from this many passages each (empty: not run), noise ar1+yaw.
  std::vector<int> own_map_passages;
  // The localiser, with the camera's yaw offset estimated (the map update's 1 degree prior; for an
  // own map, the vehicle's record's uncertainty), as LocalizePassage does.
  PassageLocalizerOptions localizer = [] {
    PassageLocalizerOptions o;
    o.camera_yaw_sigma_rad = MapUpdateOptions().camera_yaw_prior_sigma_rad;
    return o;
  }();

  absl::Status Validate() const;
};

// One configuration of Table 5.5: a noise configuration and which map.
struct LocalizeCase {
  std::string name;
  NoiseConfig noise = NoiseConfig::kWhite;
  bool inconsistent_map = false;
  int own_map_passages = 0;  // > 0: crowdmap's map from that many passages instead of the thesis model
};

struct LocalizeCell {
  int landmarks = 0;
  double without_map_m = 0.0;   // mean pose distance error over the runs' poses
  double with_map_m = 0.0;
  double with_map_nees_per_dof = 0.0;  // pose NEES / 3, mean over poses and runs
  double thesis_without_m = 0.0;       // NaN when the thesis has no such cell
  double thesis_with_m = 0.0;
  int rejected_detections = 0;         // summed over the runs
  // crowdmap's own map against the truth (NaN for the thesis's map model), and the Cramer-Rao bound
  // on its mean landmark error from the same passages (LoopCramerRaoMeanError).
  double map_error_m = 0.0;
  double map_nees_per_dof = 0.0;
  double map_crlb_m = 0.0;
};

struct LocalizeRow {
  LocalizeCase config;
  std::vector<LocalizeCell> cells;  // one per landmark count
};

// The five cases of Table 5.5, then one ar1+yaw case per own-map passage count.
std::vector<LocalizeCase> LocalizeCases(const LocalizeExperimentOptions& options);

using LocalizeProgress = std::function<void(const std::string& what)>;

absl::StatusOr<std::vector<LocalizeRow>> RunLocalizeExperiment(const LocalizeExperimentOptions& options,
                                                                const LocalizeProgress& progress = nullptr);

// The rows as a markdown table, the thesis's values beside ours.
std::string LocalizeMarkdown(const LocalizeExperimentOptions& options, const std::vector<LocalizeRow>& rows);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPSIM_LOCALIZE_EXPERIMENT_H_
