// mapsim: simulation front end. `experiment` runs simulated passages through the estimation core
// in-process; `reproduce` runs the thesis's result grids; `fleet`, `export-passages` and `bench`
// drive a running mapd.
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <numeric>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include <glog/logging.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/common/cli.h"
#include "core/logging/log_format.h"
#include "client/mapsim/city_experiment.h"
#include "client/mapsim/experiment.h"
#include "client/mapsim/localize_experiment.h"
#include "client/mapsim/passage_consistency.h"
#include "client/mapsim/pose_bias.h"
#include "client/mapsim/reproduce.h"
#if CROWDMAP_MAPSIM_SERVICE
#include "client/common/client_flags.h"
#include "client/mapsim/bench.h"
#include "client/mapsim/fleet.h"
#endif

namespace crowdmap {
namespace {

constexpr char kExitCodes[] = R"(Exit codes: 0 success, 1 failure (unreachable server, failed run, unwritable output, ...),
2 usage error (unknown command or flag, missing value, bad value), reported before any work.)";

// --- Flags shared by several commands ---

// --camera-rate-hz, --gnss-rate-hz and --odometry-rate-hz of a scenario (the loop's or the city's).
template <typename Options>
void AddSensorRateFlags(CLI::App* command, Options* scenario) {
  command->add_option("--camera-rate-hz", scenario->camera_rate_hz, "camera frames per second")
      ->check(Positive())
      ->type_name("HZ");
  command
      ->add_option_function<double>(
          "--gnss-rate-hz",
          [scenario](double hz) {
            scenario->gnss_rate_hz = hz;
            // The AR(1) coefficient is per fix: the process keeps the 1 Hz receiver's correlation time.
            scenario->gnss_ar1_alpha = std::pow(Options().gnss_ar1_alpha, 1.0 / hz);
          },
          "GNSS fixes per second (AR(1) noise keeps its correlation time)")
      ->check(Positive())
      ->default_val(scenario->gnss_rate_hz)
      ->type_name("HZ");
  command->add_option("--odometry-rate-hz", scenario->odometry_rate_hz, "wheel and steering samples per second")
      ->check(Positive())
      ->type_name("HZ");
}

// --landmarks and --seed of the loop scenario, and --noise unless `with_noise` is false.
void AddScenarioFlags(CLI::App* command, ScenarioOptions* scenario, bool with_noise = true) {
  command->add_option("--landmarks", scenario->landmarks, "landmarks along the 2 km route")->type_name("N");
  command->add_option("--seed", scenario->seed, "noise seed; the route and landmarks do not depend on it")
      ->type_name("S");
  AddSensorRateFlags(command, scenario);
  if (with_noise) {
    AddParsedOption(command, "--noise", &scenario->noise, &ParseNoiseConfig,
                    "white | gnss-ar1 | yaw-bias | ar1+yaw")
        ->default_str(NoiseConfigName(scenario->noise))
        ->type_name("X");
  }
}

// Factors of the sensors' noise, each scaling it both as drawn and as declared in the passages;
// and factors by which the drawn noise exceeds the declared.
struct NoiseScales {
  double steering = 1.0;
  double speed = 1.0;
  double gnss = 1.0;
  double pixel = 1.0;
  UndeclaredNoiseScales undeclared;
};

void AddNoiseScaleFlags(CLI::App* command, NoiseScales* scales) {
  const std::tuple<const char*, double*, const char*> flags[] = {
      {"--steering-noise-scale", &scales->steering, "steering"},
      {"--speed-noise-scale", &scales->speed, "speed"},
      {"--gnss-noise-scale", &scales->gnss, "GNSS"},
      {"--pixel-noise-scale", &scales->pixel, "camera's pixel"}};
  for (const auto& [name, scale, sensor] : flags) {
    command->add_option(name, *scale, absl::StrCat("scale the ", sensor, " noise, drawn and modelled alike"))
        ->check(Positive())
        ->type_name("X");
  }
  const std::tuple<const char*, double*, const char*> undeclared[] = {
      {"--undeclared-steering-noise-scale", &scales->undeclared.steering, "steering"},
      {"--undeclared-speed-noise-scale", &scales->undeclared.speed, "wheel-speed"},
      {"--undeclared-pixel-noise-scale", &scales->undeclared.pixel, "pixel"},
      {"--undeclared-gnss-noise-scale", &scales->undeclared.gnss, "GNSS"}};
  for (const auto& [name, scale, sensor] : undeclared) {
    command
        ->add_option(name, *scale,
                     absl::StrCat("draw the ", sensor, " noise X times as large as the passages declare it"))
        ->check(Positive())
        ->type_name("X");
  }
}

void ScaleNoise(const NoiseScales& scales, NoiseModel* sensors, double* gnss_sigma_m) {
  sensors->steering_sigma_rad *= scales.steering;
  sensors->speed_sigma_mps *= scales.speed;
  *gnss_sigma_m *= scales.gnss;
  sensors->pixel_sigma_px *= scales.pixel;
}

void ScaleNoise(const NoiseScales& scales, ScenarioOptions* scenario) {
  ScaleNoise(scales, &scenario->noise_model, &scenario->gnss_sigma_m);
  scenario->undeclared_noise = scales.undeclared;
}

void ScaleNoise(const NoiseScales& scales, CityScenarioOptions* city) {
  ScaleNoise(scales, &city->noise_model, &city->gnss_sigma_m);
  city->undeclared_noise = scales.undeclared;
}

// --warmup-passages, --relinearize-until-passages, --window-hops, --retain-passages,
// --relinearize-sigmas and --relinearizations-per-passage, --max-subgraph-dim, --estimate-camera-yaw,
// --fleet-yaw-prior-vehicles,
// --max-landmark-shift-sigmas, --max-chi2-per-dof, --max-update-shift-sigmas and
// --max-new-landmark-bias-sigmas (experiment and
// city).
void AddMapUpdateFlags(CLI::App* command, MapUpdateOptions* update) {
  command->add_option("--window-hops", update->window_hops,
                      "recover the map's covariance and re-estimate it within H links of each passage's "
                      "landmarks (0 = whole map, exact; 2 at city scale)")
      ->type_name("H");
  command->add_option("--warmup-passages", update->warmup_passages,
                      "the map's first B passages are solved jointly, re-solved with each one (0 = off)")
      ->type_name("B");
  command->add_option("--relinearize-until-passages", update->relinearize_until_passages,
                      "after the warm-up, re-solve all the map's passages jointly each time their count\n"
                      "doubles (2B, 4B, ...) up to R passages (0 = off)")
      ->type_name("R");
  command->add_option("--retain-passages", update->retain_passages,
                      "keep the factors of the last N passages apart (removable, re-linearisable), as mapd's\n"
                      "flag of that name; older ones are folded into the base (0 = keep all)")
      ->type_name("N");
  command->add_option("--detections-per-landmark", update->detections_per_landmark,
                      "last K >= 3 detections per landmark and passage (a new landmark needs 3), 0 = all")
      ->type_name("K");
  command->add_flag("--spread-detections", update->spread_detections,
                    "the K detections spread evenly over each landmark's track (its first and last among\n"
                    "them) instead of the last K, as mapd's flag of that name");
  command->add_option("--detection-spacing-s", update->detection_spacing_s,
                      "the K detections kept at least S seconds apart (0: the last K frames)")
      ->check(NonNegative())
      ->type_name("S");
  command->add_option("--detection-spacing-m", update->detection_spacing_m,
                      "...and M metres of travel apart: none while the vehicle stands still (0: by time alone)")
      ->check(NonNegative())
      ->type_name("M");
  command->add_option("--max-subgraph-dim", update->max_subgraph_dim,
                      "cc-gsd: at most D state dimensions per subgraph (mapd's flag of that name)")
      ->type_name("D");
  command->add_option("--relinearize-sigmas", update->relinearize_sigmas,
                      "after each passage, take again (at today's estimate) the retained passage whose\n"
                      "landmarks moved furthest since its factors were taken, if more than X of their\n"
                      "current sigmas (0 = off)")
      ->type_name("X");
  command->add_option("--relinearizations-per-passage", update->relinearizations_per_passage,
                      "at most K such re-linearisations per passage")
      ->type_name("K");
  command->add_option("--relinearize-area-passages", update->relinearize_area_passages,
                      "take each such passage again together with up to N - 1 other stale passages on\n"
                      "its landmarks, in one joint solve against the rest of the map (1: the passage\n"
                      "alone, solved whole; 0: its subgraphs anew; docs/results.md, \"The per-area\n"
                      "joint solve\")")
      ->check(NonNegative())
      ->type_name("N");
  command->add_flag("--estimate-camera-yaw", update->estimate_camera_yaw,
                    "estimate each vehicle's camera yaw offset, its history the prior, as mapd does\n"
                    "(summary.json: vehicle_yaw, estimate against truth per vehicle)");
  command->add_option("--fleet-yaw-prior-vehicles", update->fleet_camera_yaw_prior_vehicles,
                      "with --estimate-camera-yaw: once the map has N vehicles' records, a new vehicle's\n"
                      "camera yaw prior is centred on the fleet's mean (width their spread, at least 1\n"
                      "degree) instead of 0, as mapd's flag of that name (mapd: 10; here 0 = off)")
      ->check(NonNegative())
      ->type_name("N");
  command->add_option("--speed-scale-prior-sigma", update->speed_scale_prior_sigma,
                      "estimate each passage's wheel-speed scale, prior mean 1 with this sigma (e.g. 0.03;\n"
                      "0 = off: the speeds taken as unbiased, as mapd by default)")
      ->check(NonNegative())
      ->type_name("X");
  command->add_option("--correlated-gnss-min-lag1", update->correlated_gnss_min_lag1,
                      "a passage declaring white GNSS noise whose fixes' residuals have a lag-1 correlation\n"
                      "above X is estimated with a Gauss-Markov process instead, as mapd (0 = off)")
      ->check(CLI::Range(0.0, 0.999))
      ->default_val(update->correlated_gnss_min_lag1)
      ->type_name("X");
  command->add_option("--max-detection-residual-sigmas", update->max_detection_residual_sigmas,
                      "a detection whose residual at a subgraph's solution exceeds X pixel sigmas is set aside\n"
                      "as an outlier, as mapd (0 = off)")
      ->check(NonNegative())
      ->default_val(update->max_detection_residual_sigmas)
      ->type_name("X");
  command->add_option("--max-unfit-detection-fraction", update->max_unfit_detection_fraction,
                      "a passage more than X of whose detections are set aside as outliers (10 at least) is\n"
                      "refused, as mapd (0 = off)")
      ->check(CLI::Range(0.0, 0.999))
      ->default_val(update->max_unfit_detection_fraction)
      ->type_name("X");
  command->add_option("--sensor-test-sigmas", update->sensor_test_sigmas,
                      "a sensor whose residuals' chi-square exceeds their redundancy by X sigmas has its\n"
                      "covariances scaled by their ratio, as mapd (0 = off)")
      ->check(NonNegative())
      ->default_val(update->sensor_test_sigmas)
      ->type_name("X");
  // Gates given in sigmas, kept as squared Mahalanobis distances.
  const auto add_sigmas = [command](const std::string& flag, double* mahalanobis2, const std::string& description) {
    command->add_option_function<double>(flag, [mahalanobis2](double sigmas) { *mahalanobis2 = sigmas * sigmas; },
                                         description)
        ->check(NonNegative())
        ->default_val(std::sqrt(*mahalanobis2))
        ->type_name("X");
  };
  add_sigmas("--max-landmark-shift-sigmas", &update->max_landmark_shift_mahalanobis2,
             "a map landmark a subgraph's solve would move further than X of the map's sigmas is set\n"
             "aside for that passage, as mapd's flag of that name (0 = off)");
  add_sigmas("--max-update-shift-sigmas", &update->max_update_shift_mahalanobis2,
             "a passage whose update would move a landmark seen by 10 or more passages further than X\n"
             "of its sigmas is refused (quarantined), as mapd's flag of that name (0 = off)");
  command->add_option("--max-chi2-per-dof", update->max_chi2_per_dof,
                      "refuse a passage when a solve leaves chi2 above X per degree of freedom before any\n"
                      "inflation, 0 = never")
      ->type_name("X");
  command->add_option("--max-new-landmark-bias-sigmas", update->max_new_landmark_bias_sigmas,
                      "a new landmark whose second-order bias correction moves it by more than X of its sigmas\n"
                      "is held back, as mapd's flag of that name (0 = no such test)")
      ->check(NonNegative())
      ->type_name("X");
}

void AddQuietFlag(CLI::App* command, bool* quiet) { command->add_flag("--quiet", *quiet, "no progress lines"); }

// --- experiment ---

struct ExperimentCommand {
  ExperimentOptions options;
  NoiseScales scales;
  int shuffle_window = 0;
  int shuffle_from = 0;
  uint64_t shuffle_seed = 1;
  std::string order_file;
  std::string out = "out/experiment";
  bool quiet = false;
};

void AddExperimentFlags(CLI::App* command, ExperimentCommand* c) {
  ExperimentOptions& o = c->options;
  AddScenarioFlags(command, &o.scenario);
  command->add_option("--passages", o.passages, "simulated passages, applied in order")->type_name("P");
  command->add_option("--strategy", o.strategy, "cc | dc | cc-gsd | triangulation")->type_name("S");
  command->add_option("--out", c->out, "output folder: passages.csv, summary.json, errors.svg")->type_name("DIR");
  AddMapUpdateFlags(command, &o.update);
  command->add_option("--edge-margin-sigmas", o.update.edge_margin_sigmas,
                      "do not use detections of map landmarks predicted within M pixel sigmas of the image\n"
                      "border, where the detector's cut biases them (0 = use all)")
      ->type_name("M");
  command->add_option("--inflation-test-sigmas", o.update.inflation_test_sigmas,
                      "inflate a passage's measurement covariances by chi2/dof when its chi2 exceeds dof\n"
                      "by K sigma, 0 = never")
      ->type_name("K");
  CLI::Option* shuffle_window =
      command
          ->add_option("--shuffle-window", c->shuffle_window,
                       "apply the passages shuffled within consecutive groups of W, as W concurrent vehicles\n"
                       "would deliver them (0: in order)")
          ->check(NonNegative())
          ->type_name("W");
  command->add_option("--shuffle-from", c->shuffle_from, "keep passages 0..F-1 in order, shuffle from F on")
      ->check(NonNegative())
      ->type_name("F");
  command->add_option("--shuffle-seed", c->shuffle_seed, "seed of the shuffle")->type_name("K");
  command->add_option("--order-file", c->order_file,
                      "apply the passages in this order: one scenario passage index per line, a permutation\n"
                      "of 0..P-1 (e.g. a fleet run's arrival_order.txt)")
      ->excludes(shuffle_window)
      ->type_name("FILE");
  AddNoiseScaleFlags(command, &c->scales);
  command->add_flag_callback("--no-bias-correction", [&o] { o.update.bias_correction = false; },
                             "skip the second-order bias correction of each solution");
  command->add_flag_callback("--no-crlb", [&o] { o.crlb = false; },
                             "skip the Cramer-Rao bound of the same passages (summary.json:\n"
                             "crlb_mean_dist_err_m, error_over_crlb)");
  command
      ->add_option_function<std::pair<double, double>>(
          "--piece-m",
          [scenario = &o.scenario](const std::pair<double, double>& piece_m) {
            scenario->piece_min_m = piece_m.first;
            scenario->piece_max_m = piece_m.second;
          },
          "partial drives: each passage keeps one piece of the route, MIN to MAX metres long\n"
          "(uniform), from a random start (default: whole)")
      ->delimiter(',')
      ->type_name("MIN,MAX");
  command->add_flag("--alternate-directions", o.scenario.alternate_directions,
                    "traffic both ways: odd passages drive the route backwards (not with --piece-m)");
  command->add_option("--vehicles", o.scenario.vehicles,
                      "a fleet: passage i is driven by vehicle i % V (sim-v0, ...), each with its own camera\n"
                      "yaw error (0: every passage its own vehicle)")
      ->check(NonNegative())
      ->type_name("V");
  command->add_option("--vehicle-yaw-bias-sigma-rad", o.scenario.vehicle_yaw_bias_sigma_rad,
                      "each fleet vehicle's own camera yaw error, Gaussian")
      ->check(NonNegative())
      ->type_name("X");
  command->add_flag("--assume-white-gnss", o.assume_white_gnss,
                    "the estimator ignores the coloured GNSS process the passages declare (gnss-ar1,\n"
                    "ar1+yaw) and assumes white noise, as before it modelled it; the bound still models it");
  AddQuietFlag(command, &c->quiet);
}

absl::Status RunExperimentCommand(ExperimentCommand& c) {
  ExperimentOptions& options = c.options;
  ScaleNoise(c.scales, &options.scenario);
  if (!c.order_file.empty()) {
    absl::StatusOr<std::vector<int>> order = ReadOrderFile(c.order_file);
    if (!order.ok()) return order.status();
    options.order = *std::move(order);
  } else if (c.shuffle_window > 1) {
    options.order = ShuffledOrder(options.passages, c.shuffle_window, c.shuffle_from, c.shuffle_seed);
  }
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);

  const int every = std::max(1, options.passages / 20);
  auto progress = [&](const PassageRecord& r) {
    if (c.quiet || (r.passage % every != 0 && r.passage != options.passages)) return;
    std::cerr << absl::StrFormat("\rpassage %d/%d  error %.3f m  nees %.2f  %.1f ms/passage   ", r.passage,
                                 options.passages, r.metrics.mean_dist_err_m, r.metrics.nees_per_dof, r.solve_ms)
              << std::flush;
  };
  absl::StatusOr<ExperimentResult> result = RunExperiment(options, progress);
  if (!c.quiet) std::cerr << "\n";
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteExperimentOutputs(options, *result, c.out); !s.ok()) return s;
  std::cout << absl::StrFormat(
      "strategy=%s noise=%s landmarks=%d passages=%d final_mean_dist_err_m=%.4f final_nees_per_dof=%.3f "
      "final_joint_nees_per_dof=%.3f median_passage_ms=%.2f failed=%d quarantined=%d inflated=%d joint_rejected=%d "
      "detections_used=%d detections_outliers=%d landmarks_disagreeing=%d vehicle_yaw_within_2sigma=%.3f "
      "vehicle_yaw_nees=%.3f out=%s\n",
      options.strategy, NoiseConfigName(options.scenario.noise), options.scenario.landmarks, options.passages,
      result->final_mean_dist_err_m, result->final_nees_per_dof, result->final_joint_nees_per_dof,
      result->median_passage_ms, result->failed_passages, result->quarantined_passages, result->inflated_passages,
      result->joint_rejected_passages, result->detections_used, result->detections_outliers,
      result->landmarks_disagreeing, result->vehicle_yaw.within_2sigma_fraction, result->vehicle_yaw.nees, c.out);
  return absl::OkStatus();
}

// --- city ---

struct CityCommand {
  CityExperimentOptions options;
  NoiseScales scales;
  std::string out = "out/city";
  std::string export_dir;
  std::string export_format = "json";
  bool quiet = false;
};

// Each city vehicle's own calibration (CityScenarioOptions::vary_calibration).
void AddVaryCalibrationFlag(CLI::App* command, CityScenarioOptions* city, CLI::Option* needs = nullptr) {
  CLI::Option* option = command->add_flag(
      "--vary-calibration", city->vary_calibration,
      "each vehicle declares its own calibration, as in a fleet of several car models:\n"
      "a 1280-2560 px image with a 50-110 degree field of view and its principal point\n"
      "up to 3% off centre, the camera 0.5-2.5 m ahead and up to 0.5 m aside, turned up to\n"
      "5 degrees, the GNSS antenna -0.5 to 2 m ahead and up to 0.5 m aside, a 2.4-3.2 m\n"
      "wheelbase (uniform draws)");
  if (needs != nullptr) option->needs(needs);
}

// A city fleet's traffic and GNSS outages (CityScenarioOptions), in group "Traffic".
void AddTrafficFlags(CLI::App* command, CityScenarioOptions* city, CLI::Option* needs = nullptr) {
  const std::string traffic = "Traffic";
  std::vector<CLI::Option*> options = {
      command->add_option("--stop-probability", city->stop_probability,
                          "before each intersection a vehicle stops (a red light) with probability X")
          ->type_name("X"),
      command->add_option("--stop-min-s", city->stop_min_s, "shortest wait at a stop, s")
          ->default_val(city->stop_min_s)
          ->type_name("S"),
      command->add_option("--stop-max-s", city->stop_max_s, "longest wait at a stop, s")
          ->default_val(city->stop_max_s)
          ->type_name("S"),
      command->add_option("--gnss-outage-probability", city->gnss_outage_probability,
                          "a passage loses its GNSS (an underpass, an urban canyon) for a while with\n"
                          "probability X; its first and last 10 s keep their fixes")
          ->type_name("X"),
      command->add_option("--gnss-outage-min-s", city->gnss_outage_min_s, "shortest outage, s")
          ->default_val(city->gnss_outage_min_s)
          ->type_name("S"),
      command->add_option("--gnss-outage-max-s", city->gnss_outage_max_s, "longest outage, s")
          ->default_val(city->gnss_outage_max_s)
          ->type_name("S"),
  };
  for (CLI::Option* option : options) {
    option->group(traffic);
    if (needs != nullptr) option->needs(needs);
  }
}

void AddCityFlags(CLI::App* command, CityCommand* c) {
  CityExperimentOptions& o = c->options;
  CityScenarioOptions& city = o.city;
  command->add_option("--blocks-x", city.blocks_x, "street grid: blocks from west to east")->type_name("N");
  command->add_option("--blocks-y", city.blocks_y, "street grid: blocks from south to north")->type_name("N");
  command->add_option("--block-m", city.block_m, "distance between streets, m")->type_name("M");
  command->add_option("--passages", o.passages, "passages applied in order to an empty map")->type_name("P");
  command->add_option("--route-m", city.route_length_m, "distance driven per passage, m")->type_name("M");
  command->add_option("--vehicles", city.vehicles, "fleet size; passage i is driven by vehicle i % V")
      ->type_name("V");
  command->add_option("--late-blocks-x", city.late_blocks_x,
                      "a district mapped late: the eastern N blocks are driven only from passage\n"
                      "--late-from-passage on (landmarks.csv gives each landmark's east position)")
      ->type_name("N");
  command->add_option("--late-from-passage", city.late_from_passage, "see --late-blocks-x")->type_name("P");
  command->add_option("--seed", city.seed, "routes and noise")->type_name("S");
  command->add_option("--layout-seed", city.layout_seed, "street jitter and landmarks")->type_name("S");
  AddParsedOption(command, "--noise", &city.noise, &ParseNoiseConfig, "white | gnss-ar1 | yaw-bias | ar1+yaw")
      ->default_str(NoiseConfigName(city.noise))
      ->type_name("X");
  command->add_option("--vehicle-yaw-bias-sigma-rad", city.vehicle_yaw_bias_sigma_rad,
                      "each vehicle's own camera yaw error, Gaussian")
      ->type_name("X");
  command->add_option("--vehicle-speed-scale-sigma", city.vehicle_speed_scale_sigma,
                      "each vehicle's own wheel-speed scale error: its encoders report the speed times\n"
                      "1 + X times a Gaussian draw (e.g. 0.02 for 2%)")
      ->type_name("X");
  AddVaryCalibrationFlag(command, &city);
  AddSensorRateFlags(command, &city);
  command->add_flag_callback("--no-crlb", [&o] { o.crlb = false; },
                             "skip the Cramer-Rao bound of the passages applied (summary.json:\n"
                             "crlb_mean_error_m, error_over_crlb, crlb_nees_per_dof; landmarks.csv: each\n"
                             "landmark's crlb_error_m, crlb_mahalanobis2). Not computed over 4,000 landmarks\n"
                             "(it is dense) or with wheel-speed scale errors, which are not modelled");
  command->add_option("--rate-variation", city.rate_variation,
                      "each vehicle's sensor rates scaled by a factor in [1-X, 1+X]")
      ->type_name("X");
  AddTrafficFlags(command, &city);
  command->add_flag_callback("--no-occlusion", [&city] { city.occlusion = false; }, "buildings do not hide landmarks");
  AddNoiseScaleFlags(command, &c->scales);
  AddParsedOption(command, "--strategy", &o.update.strategy, &ParseUpdateStrategy, "cc | dc | cc-gsd")
      ->default_str(UpdateStrategyName(o.update.strategy))
      ->type_name("S");
  AddMapUpdateFlags(command, &o.update);
  const std::string faults = "Faults";
  command->add_option("--mislabel-rate", o.faults.mislabel_rate,
                      "each detection reported under a neighbouring landmark's id with probability X")
      ->type_name("X")
      ->group(faults);
  command->add_option("--multipath-rate", o.faults.multipath_rate,
                      "a passage has a GNSS multipath burst (20-60 s of fixes 30-80 m off, declared as\n"
                      "usual) with probability X")
      ->type_name("X")
      ->group(faults);
  command->add_option("--overconfident-rate", o.faults.overconfident_rate,
                      "a passage declares GNSS sigmas 5 times too small")
      ->type_name("X")
      ->group(faults);
  command->add_option("--bad-calibration-rate", o.faults.bad_calibration_rate,
                      "a passage declares a camera yaw 3 degrees off and a wheelbase 15% off")
      ->type_name("X")
      ->group(faults);
  command->add_option("--fault-seed", o.faults.seed,
                      "draws of the faults; summary.json counts the faulty passages and splits the refused\n"
                      "ones into faulty and clean")
      ->type_name("S")
      ->group(faults);
  command->add_option("--progress-every", o.progress_every_passages, "progress line on stderr every P passages")
      ->type_name("P");
  command->add_option("--out", c->out, "output folder: summary.json, landmarks.csv")->type_name("DIR");
  command->add_option("--export-passages", c->export_dir,
                      "also write passages 0..P-1 as files for `mapctl upload` (DIR2/passage-00000.json, ...\n"
                      "as export-passages does)")
      ->type_name("DIR2");
  command->add_option("--export-format", c->export_format, "json | binary")
      ->check(CLI::IsMember({"json", "binary"}))
      ->type_name("F");
  AddQuietFlag(command, &c->quiet);
}

absl::Status RunCityCommand(CityCommand& c) {
  CityExperimentOptions& options = c.options;
  ScaleNoise(c.scales, &options.city);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);

  if (!c.export_dir.empty()) {
#if CROWDMAP_MAPSIM_SERVICE
    absl::StatusOr<CityScenario> scenario = CityScenario::Create(options.city);
    if (!scenario.ok()) return scenario.status();
    if (absl::Status s = ExportPassages([&](int i) { return scenario->MakePassage(i); }, options.passages,
                                        c.export_format == "binary", c.export_dir);
        !s.ok()) {
      return s;
    }
    std::cout << absl::StrFormat("wrote %d passages to %s\n", options.passages, c.export_dir);
#else
    return absl::UnimplementedError("--export-passages: this mapsim was built without the service (gRPC)");
#endif
  }

  auto progress = [&](const CityProgress& p) {
    if (c.quiet) return;
    std::cerr << absl::StrFormat(
        "passage %d/%d  landmarks mapped %d  error mean %.3f m median %.3f m  per passage: p50 %.1f ms p95 %.1f ms "
        "(last %d: p50 %.1f ms p95 %.1f ms)\n",
        p.passages_done, p.passages_total, p.landmarks_mapped, p.mean_error_m, p.median_error_m, p.p50_ms, p.p95_ms,
        std::min(p.passages_done, options.progress_every_passages), p.recent_p50_ms, p.recent_p95_ms);
  };
  absl::StatusOr<CityExperimentResult> result = RunCityExperiment(options, progress);
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteCityOutputs(options, *result, c.out); !s.ok()) return s;
  std::cout << result->Brief() << absl::StrFormat(" layout_s=%.3f out=%s\n", result->layout_s, c.out);
  return absl::OkStatus();
}

// --- crlb ---

struct CrlbCommand {
  ScenarioOptions scenario;
  int passages = 100;
  GraphOptions graph;
};

void AddCrlbFlags(CLI::App* command, CrlbCommand* c) {
  AddScenarioFlags(command, &c->scenario);
  command->add_option("--passages", c->passages, "passages; the bound is printed after 1, 10, 100, ... and the last")
      ->type_name("P");
  command->add_option("--detections-per-landmark", c->graph.detections_per_landmark,
                      "last K >= 2 detections per landmark and passage, 0 = all")
      ->type_name("K");
}

absl::Status RunCrlbCommand(const CrlbCommand& c) {
  if (c.passages < 1) return UsageError("passages: must be >= 1");
  absl::StatusOr<Scenario> scenario = Scenario::Create(c.scenario);
  if (!scenario.ok()) return scenario.status();
  std::vector<int> indices(c.passages);
  std::iota(indices.begin(), indices.end(), 0);
  int next_report = 1;
  absl::StatusOr<double> bound =
      LoopCramerRaoMeanError(*scenario, indices, c.graph, 0.0, [&](int done, double mean_error_m) {
        if (done != next_report && done != c.passages) return;
        if (done == next_report) next_report *= 10;
        std::cout << absl::StrFormat("passages=%d crlb_mean_dist_err_m=%.4f\n", done, mean_error_m);
      });
  return bound.status();
}

// --- pose-bias ---

struct PoseBiasCommand {
  PoseBiasOptions options;
  NoiseScales scales;
  bool quiet = false;
};

void AddPoseBiasFlags(CLI::App* command, PoseBiasCommand* c) {
  command->add_option("--passages", c->options.passages, "independent passages, each solved alone")->type_name("P");
  command->add_option("--seed", c->options.scenario.seed, "noise seed")->type_name("S");
  command->add_option("--bin-s", c->options.bin_s, "time bin width, s")->type_name("S");
  AddNoiseScaleFlags(command, &c->scales);
  AddQuietFlag(command, &c->quiet);
}

absl::Status RunPoseBiasCommand(PoseBiasCommand& c) {
  PoseBiasOptions& options = c.options;
  ScaleNoise(c.scales, &options.scenario);
  const int every = std::max(1, options.passages / 20);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<std::vector<PoseBiasBin>> bins = RunPoseBias(options, [&](int done) {
    if (!c.quiet && (done % every == 0 || done == options.passages)) {
      std::cerr << absl::StrFormat("\rpassage %d/%d   ", done, options.passages) << std::flush;
    }
  });
  if (!c.quiet) std::cerr << "\n";
  if (!bins.ok()) return bins.status();
  std::cout << "mean pose error (standard error), MAP | after the second-order bias correction\n";
  std::cout << absl::StrFormat("%6s %7s | %15s %15s %13s | %15s %15s %13s\n", "t (s)", "nodes", "along-track m",
                               "cross-track m", "heading mrad", "along-track m", "cross-track m", "heading mrad");
  double worst = 0.0, worst_corrected = 0.0;
  for (const PoseBiasBin& b : *bins) {
    std::cout << absl::StrFormat(
        "%6.0f %7d | %+7.3f (%5.3f) %+7.3f (%5.3f) %+5.1f (%4.1f) | %+7.3f (%5.3f) %+7.3f (%5.3f) %+5.1f (%4.1f)\n",
        b.start_s, b.samples, b.mean.x(), b.mean_se.x(), b.mean.y(), b.mean_se.y(), 1e3 * b.mean.z(),
        1e3 * b.mean_se.z(), b.corrected_mean.x(), b.corrected_se.x(), b.corrected_mean.y(), b.corrected_se.y(),
        1e3 * b.corrected_mean.z(), 1e3 * b.corrected_se.z());
    worst = std::max(worst, b.mean.head<2>().norm());
    worst_corrected = std::max(worst_corrected, b.corrected_mean.head<2>().norm());
  }
  std::cout << absl::StrFormat("passages=%d largest_position_bias_m=%.3f corrected_largest_position_bias_m=%.3f\n",
                               options.passages, worst, worst_corrected);
  return absl::OkStatus();
}

// --- passage-consistency ---

struct PassageConsistencyCommand {
  PassageConsistencyCommand() { options.update.strategy = UpdateStrategy::kCorrelated; }

  PassageConsistencyOptions options;
  NoiseScales scales;
  bool quiet = false;
};

void AddPassageConsistencyFlags(CLI::App* command, PassageConsistencyCommand* c) {
  PassageConsistencyOptions& o = c->options;
  AddScenarioFlags(command, &o.scenario);
  command->add_option("--passages", o.passages, "independent passages, each applied alone to an empty map")
      ->type_name("P");
  AddParsedOption(command, "--strategy", &o.update.strategy, &ParseUpdateStrategy, "cc | cc-gsd")
      ->default_str(UpdateStrategyName(o.update.strategy))
      ->type_name("S");
  command->add_option("--detections-per-landmark", o.update.detections_per_landmark,
                      "last K >= 3 detections per landmark and passage (a new landmark needs 3), 0 = all")
      ->type_name("K");
  AddNoiseScaleFlags(command, &c->scales);
  AddQuietFlag(command, &c->quiet);
}

absl::Status RunPassageConsistencyCommand(PassageConsistencyCommand& c) {
  PassageConsistencyOptions& options = c.options;
  ScaleNoise(c.scales, &options.scenario);
  const int every = std::max(1, options.passages / 20);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<PassageConsistency> result = RunPassageConsistency(options, [&](int done) {
    if (!c.quiet && (done % every == 0 || done == options.passages)) {
      std::cerr << absl::StrFormat("\rpassage %d/%d   ", done, options.passages) << std::flush;
    }
  });
  if (!c.quiet) std::cerr << "\n";
  if (!result.ok()) return result.status();
  std::cout << absl::StrFormat(
      "passages_used=%d dof=%d own_nees_per_dof=%.3f spread_nees_per_dof=%.3f bias_nees_per_dof=%.4f "
      "(unbiased: about %.4f) own_nees_most_precise_fifth=%.3f own_nees_least_precise_fifth=%.3f "
      "fused_nees_per_dof=%.3f fused_mean_error_en_m=%.3f,%.3f\n",
      result->passages_used, result->dof, result->own_nees_per_dof, result->spread_nees_per_dof,
      result->bias_nees_per_dof, 1.0 / result->passages_used, result->own_nees_most_precise_fifth,
      result->own_nees_least_precise_fifth, result->fused_nees_per_dof, result->fused_mean_error_en_m.x(),
      result->fused_mean_error_en_m.y());
  return absl::OkStatus();
}

// --- localize ---

struct LocalizeCommand {
  LocalizeExperimentOptions options;
  std::string out = "out/localize.md";
  bool quiet = false;
};

void AddLocalizeFlags(CLI::App* command, LocalizeCommand* c) {
  LocalizeExperimentOptions& o = c->options;
  command->add_option("--landmarks", o.landmark_counts, "landmark counts, comma-separated")
      ->delimiter(',')
      ->type_name("LIST");
  command->add_option("--runs", o.runs, "passages (and generated maps) averaged per cell")->type_name("R");
  command->add_option("--duration-s", o.duration_s, "passage duration, s (340: 4 km at 12 m/s)")->type_name("S");
  command->add_option("--gnss-fixes", o.gnss_fixes,
                      "GNSS fixes per passage, as the thesis's 512 (rate and AR(1) coefficient per fix\n"
                      "adjusted; 0 = the scenario's 1 Hz)")
      ->type_name("K");
  command->add_option("--own-map-passages", o.own_map_passages,
                      "also localise (ar1+yaw) against crowdmap's own map built from P passages, for each P\n"
                      "(comma-separated; default none)")
      ->delimiter(',')
      ->type_name("LIST");
  command->add_option("--camera-yaw-sigma-rad", o.localizer.camera_yaw_sigma_rad,
                      "estimate the camera's yaw offset in each localisation with this prior sigma (own maps:\n"
                      "the vehicle's record's, as LocalizePassage; 0 = take the calibration as exact)")
      ->check(NonNegative())
      ->type_name("X");
  command->add_option("--seed", o.seed, "noise seed")->type_name("S");
  command->add_option("--out", c->out, "markdown table")->type_name("FILE");
  AddQuietFlag(command, &c->quiet);
}

absl::Status RunLocalizeCommand(const LocalizeCommand& c) {
  const LocalizeExperimentOptions& options = c.options;
  if (c.quiet) spdlog::set_level(spdlog::level::warn);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<std::vector<LocalizeRow>> rows = RunLocalizeExperiment(options, [&](const std::string& what) {
    if (!c.quiet) std::cerr << "\r" << what << "        " << std::flush;
  });
  if (!c.quiet) std::cerr << "\n";
  if (!rows.ok()) return rows.status();
  const std::string table = LocalizeMarkdown(options, *rows);
  std::cout << table;
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(c.out).parent_path(), ec);
  std::ofstream file(c.out);
  file << table;
  if (!file) return absl::InternalError(absl::StrCat("out: cannot write ", c.out));
  return absl::OkStatus();
}

// --- reproduce ---

void AddReproduceFlags(CLI::App* command, ReproduceOptions* o) {
  command->add_option("--out", o->out_dir, "output folder; writes DIR/reproduction.md")->type_name("DIR");
  command->add_option("--passages", o->passages, "passages per experiment")->type_name("P");
  command->add_option("--jobs", o->jobs, "experiments run in parallel")->type_name("J");
  command->add_option("--seed", o->seed, "first noise seed")->type_name("S");
  command->add_option("--seeds", o->seeds,
                      "run every experiment with seeds S..S+K-1 and report the means (about 3 minutes per\n"
                      "seed on 2 cores)")
      ->type_name("K");
  command->add_option("--nees-sd-target", o->nees_sd_target,
                      "the CC and CC+GSD cells of table 5.2 take further seeds until the standard deviation\n"
                      "of their mean NEES, were the maps consistent, is at most X (0 = no further seeds)")
      ->type_name("X");
  command->add_option("--max-seeds", o->max_seeds, "at most M seeds per cell")->type_name("M");
  command->add_option("--detections-per-landmark", o->detections_per_landmark,
                      "every experiment uses the last K >= 3 detections per landmark and passage, 0 = all")
      ->type_name("K");
}

#if CROWDMAP_MAPSIM_SERVICE

// --- fleet ---

struct FleetCommand {
  FleetOptions options;
  ClientSecurityFlags security;
  int64_t sample_ms = 250;
  bool no_replay = false;
  std::string out = "out/fleet";
  bool quiet = false;
};

void AddFleetFlags(CLI::App* command, FleetCommand* c) {
  FleetOptions& o = c->options;
  AddServerFlag(command, &o.server);
  AddScenarioFlags(command, &o.scenario);
  command->add_option("--passages", o.passages, "passages 0..P-1 of the scenario")->type_name("P");
  command->add_option("--vehicles", o.vehicles, "concurrent vehicles; vehicle v uploads passages v, v+V, ...")
      ->type_name("V");
  command->add_option("--strategy", o.strategy, "fail unless the server runs strategy S (default: accept the server's)")
      ->type_name("S");
  command->add_option("--sample-ms", c->sample_ms, "read the map back and evaluate it this often while applying")
      ->type_name("MS");
  command->add_flag("--no-replay", c->no_replay, "skip the check of the server's map against an in-process replay");
  CLI::Option* city = command->add_flag("--city", o.city,
                                        "upload city passages (mapsim city's default grid, --seed its fleet seed)\n"
                                        "instead of the loop's; errors against the city's landmarks; no replay");
  command->add_option("--route-m", o.city_scenario.route_length_m, "distance driven per passage, m")
      ->needs(city)
      ->type_name("M");
  AddVaryCalibrationFlag(command, &o.city_scenario, city);
  AddTrafficFlags(command, &o.city_scenario, city);
  command->add_option("--out", c->out,
                      "output folder: passages.csv (one row per sampled map; the last row is the final map),\n"
                      "summary.json, errors.svg, map.geojson, arrival_order.txt (the scenario passage index of\n"
                      "each applied passage, in the order the server applied them; see experiment --order-file)")
      ->type_name("DIR");
  AddQuietFlag(command, &c->quiet);
  AddClientSecurityFlags(command, &c->security);
}

absl::Status RunFleetCommand(FleetCommand& c) {
  FleetOptions& options = c.options;
  options.city_scenario.seed = options.scenario.seed;
  options.city_scenario.noise = options.scenario.noise;
  absl::StatusOr<ClientSecurityOptions> security = ClientSecurityFromFlags(c.security);
  if (!security.ok()) return security.status();
  options.client.security = *std::move(security);
  options.sample_interval = std::chrono::milliseconds(c.sample_ms);
  options.replay = !c.no_replay && !options.city;
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  std::string shown;  // the progress line on screen: written again only when it changes
  auto progress = [&](const FleetProgress& p) {
    if (c.quiet) return;
    // A joint solve holds the count for seconds: say so, so that the pause does not look like a hang.
    const std::string joint =
        p.joint_solve_of > 0 ? absl::StrFormat("  (server: joint solve of %d passages)", p.joint_solve_of) : "";
    std::string line = absl::StrFormat("\ruploaded %d/%d  applied %d/%d  error %s%s   ", p.uploaded, p.total, p.applied,
                                       p.total,
                                       p.mean_dist_err_m < 0 ? std::string("-") : absl::StrFormat("%.3f m", p.mean_dist_err_m),
                                       joint);
    if (line == shown) return;
    std::cerr << line << std::flush;
    shown = std::move(line);
  };
  absl::StatusOr<FleetResult> result = RunFleet(options, progress);
  if (!c.quiet) std::cerr << "\n";
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteFleetOutputs(options, *result, c.out); !s.ok()) return s;
  std::cout << result->Brief() << " vehicles=" << options.vehicles << " out=" << c.out << "\n";
  return absl::OkStatus();
}

// --- export-passages ---

struct ExportPassagesCommand {
  ScenarioOptions scenario;
  int passages = 40;
  std::string format = "json";
  std::string out = "out/passages";
};

void AddExportPassagesFlags(CLI::App* command, ExportPassagesCommand* c) {
  AddScenarioFlags(command, &c->scenario);
  command->add_option("--passages", c->passages, "passages 0..P-1")->type_name("P");
  command->add_option("--format", c->format, "json | binary")->check(CLI::IsMember({"json", "binary"}))->type_name("F");
  command->add_option("--out", c->out, "output folder: passage-00000.json, ...")->type_name("DIR");
}

absl::Status RunExportPassagesCommand(const ExportPassagesCommand& c) {
  if (absl::Status s = ExportPassages(c.scenario, c.passages, c.format == "binary", c.out); !s.ok()) return s;
  std::cout << absl::StrFormat("wrote %d passages to %s\n", c.passages, c.out);
  return absl::OkStatus();
}

// --- bench ---

struct BenchCommand {
  BenchOptions options;
  ClientSecurityFlags security;
};

void AddBenchFlags(CLI::App* command, BenchCommand* c) {
  BenchOptions& o = c->options;
  AddServerFlag(command, &o.server);
  AddScenarioFlags(command, &o.scenario, /*with_noise=*/false);
  command->add_option("--clients", o.clients, "concurrent uploading clients")->type_name("K");
  command->add_option("--passages", o.passages, "passages uploaded")->type_name("P");
  command->add_option("--readers", o.readers, "concurrent QueryRegion / GetTile readers")->type_name("R");
  command->add_option("--seconds", o.read_seconds,
                      "longest read phase; reads stop when the queue is drained, so that every measured read\n"
                      "competes with map updates")
      ->type_name("S");
  command->add_flag("--city", o.city,
                    "upload city passages (mapsim city's default grid) instead of the loop's; reads cover the\n"
                    "whole city");
  command->add_option("--route-m", o.city_scenario.route_length_m, "with --city: distance driven per passage, m")
      ->type_name("M");
  command->add_option("--upload-rate", o.upload_rate_per_s,
                      "pace the uploads at R per second over all clients (0: as fast as acknowledgements come\n"
                      "back); a paced run measures the acknowledgements while the worker commits map changes")
      ->type_name("R");
  AddClientSecurityFlags(command, &c->security);
}

absl::Status RunBenchCommand(BenchCommand& c) {
  BenchOptions& options = c.options;
  options.city_scenario.seed = options.scenario.seed;
  absl::StatusOr<ClientSecurityOptions> security = ClientSecurityFromFlags(c.security);
  if (!security.ok()) return security.status();
  options.security = *std::move(security);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<BenchResult> result = RunBench(options);
  if (!result.ok()) return result.status();
  std::cout << absl::StrFormat(
      "durable uploads:  %.1f passages/s (%d clients, %d passages in %.2f s), ack p50 %.2f ms  p99 %.2f ms  max %.2f ms\n"
      "applied:          %.1f passages/s (first upload to queue drained, %.2f s)\n"
      "QueryRegion:      p50 %.2f ms  p99 %.2f ms  (%d calls, %d landmarks, %d readers, %.1f s while the worker applied)\n"
      "GetTile:          p50 %.2f ms  p99 %.2f ms  (%d calls)\n",
      result->uploads_per_s, options.clients, result->passages, result->upload_s, result->ack.p50_ms,
      result->ack.p99_ms, result->ack.max_ms, result->applied_per_s,
      result->apply_s, result->query_region.p50_ms, result->query_region.p99_ms, result->query_region.calls,
      result->landmarks_in_box, options.readers, result->read_s, result->get_tile.p50_ms, result->get_tile.p99_ms,
      result->get_tile.calls);
  std::cout << result->Brief() << "\n";
  return absl::OkStatus();
}

#endif  // CROWDMAP_MAPSIM_SERVICE

// Every command's flags; the one parsed is run.
struct Commands {
  ExperimentCommand experiment;
  CityCommand city;
  ReproduceOptions reproduce;
  LocalizeCommand localize;
  CrlbCommand crlb;
  PoseBiasCommand pose_bias;
  PassageConsistencyCommand passage_consistency;
#if CROWDMAP_MAPSIM_SERVICE
  FleetCommand fleet;
  ExportPassagesCommand export_passages;
  BenchCommand bench;
#endif
};

// mapsim's command line, its flags bound to `c`; `run` maps each command's name to what it runs.
std::unique_ptr<CLI::App> NewMapsimCommandLine(Commands* c, std::map<std::string, std::function<absl::Status()>>* run) {
  std::unique_ptr<CLI::App> app = NewCommandLine(
      "mapsim",
      "mapsim: simulate crowdsourced landmark mapping (thesis scenario). `mapsim COMMAND --help` lists a\n"
      "command's flags.",
      kExitCodes);
  // `details`: more on what the command does, in its --help only.
  auto add = [&](const char* name, const char* description, std::function<absl::Status()> command,
                 const std::string& details = "") {
    (*run)[name] = std::move(command);
    CLI::App* subcommand = app->add_subcommand(name, description);
    if (!details.empty()) subcommand->footer(details + "\n\n" + kExitCodes);
    return subcommand;
  };
  AddExperimentFlags(add("experiment", "run passages through the estimation core in-process",
                         [c] { return RunExperimentCommand(c->experiment); }),
                     &c->experiment);
  AddCityFlags(add("city",
                   "the same on a city: a street grid with buildings, a fleet driving random partial\n"
                   "routes",
                   [c] { return RunCityCommand(c->city); }),
               &c->city);
  AddReproduceFlags(add("reproduce", "run the thesis's table 5.2 and robustness grids",
                        [c] {
                          if (absl::Status s = c->reproduce.Validate(); !s.ok()) return AsUsageError(s);
                          return RunReproduction(c->reproduce);
                        }),
                    &c->reproduce);
  AddLocalizeFlags(add("localize",
                       "thesis Table 5.5: one ~4 km passage localised without and with the map (the thesis's\n"
                       "map model, then crowdmap's own maps)",
                       [c] { return RunLocalizeCommand(c->localize); }),
                   &c->localize);
  AddCrlbFlags(add("crlb",
                   "the Cramer-Rao bound of the experiment's passages: the smallest mean landmark error any\n"
                   "unbiased map can reach from them",
                   [c] { return RunCrlbCommand(c->crlb); }),
               &c->crlb);
  AddPoseBiasFlags(add("pose-bias",
                       "mean pose error of single-passage odometry + GNSS solves along the route (the bias of\n"
                       "the MAP estimate), before and after the second-order bias correction",
                       [c] { return RunPoseBiasCommand(c->pose_bias); }),
                   &c->pose_bias);
  AddPassageConsistencyFlags(
      add("passage-consistency",
          "whether one passage's covariance describes its own error: independent passages, each\n"
          "mapped alone, joint NEES against the truth",
          [c] { return RunPassageConsistencyCommand(c->passage_consistency); },
          "Prints the mean joint NEES per degree of freedom with each passage's own covariance (1 =\n"
          "consistent), the NEES of the errors' spread and of their mean against the covariance averaged\n"
          "over the passages, the own-covariance NEES along the most and least precise fifth of the\n"
          "directions, and the NEES and mean error of the passages' maps combined by their information,\n"
          "each linearised at its own estimate."),
      &c->passage_consistency);
#if CROWDMAP_MAPSIM_SERVICE
  AddFleetFlags(add("fleet",
                    "upload simulated passages to a running mapd from concurrent vehicles, wait until\n"
                    "applied, read the map back, write the experiment outputs",
                    [c] { return RunFleetCommand(c->fleet); },
                    "After the run (on a server whose map started empty) the passages are applied in-process\n"
                    "in the order the server received them; summary.json gets that run's error and the\n"
                    "largest landmark difference from the server's map\n"
                    "(arrival_order_experiment_final_mean_dist_err_m,\n"
                    "max_position_diff_vs_arrival_order_experiment_m,\n"
                    "max_cov_diff_vs_arrival_order_experiment_m2). Uploading simulated vehicles' passages\n"
                    "needs an admin token."),
                &c->fleet);
  AddExportPassagesFlags(add("export-passages", "write simulated passages as files for `mapctl upload`",
                             [c] { return RunExportPassagesCommand(c->export_passages); }),
                         &c->export_passages);
  AddBenchFlags(add("bench", "load-test a running mapd (use a scratch database)",
                    [c] { return RunBenchCommand(c->bench); }),
                &c->bench);
#endif
  return app;
}

}  // namespace
}  // namespace crowdmap

int main(int argc, char** argv) {
  // Ceres reports rejected trial steps through glog; only errors are worth an operator's eye.
  google::InitGoogleLogging(argv[0]);
  FLAGS_minloglevel = google::GLOG_ERROR;
  // Log lines go to stderr (stdout carries the results), in the tools' common format.
  auto logger = spdlog::stderr_color_mt("mapsim");
  crowdmap::UseTextLogFormat(*logger);
  spdlog::set_default_logger(logger);

  crowdmap::Commands commands;
  std::map<std::string, std::function<absl::Status()>> run;
  std::unique_ptr<CLI::App> app = crowdmap::NewMapsimCommandLine(&commands, &run);
  const std::vector<std::string> args(argv + 1, argv + argc);
  if (args.empty()) {
    std::cerr << app->help();
    return crowdmap::kExitUsage;
  }
  absl::StatusOr<crowdmap::ParsedCommandLine> parsed = crowdmap::ParseCommandLine(*app, args, std::cout);
  if (parsed.ok() && *parsed == crowdmap::ParsedCommandLine::kPrintedHelpOrVersion) return crowdmap::kExitOk;
  const std::string command = crowdmap::ParsedCommand(*app);
  const absl::Status status = parsed.ok() ? run.at(command)() : parsed.status();
  const std::string where = command.empty() ? "mapsim" : "mapsim " + command;
  if (crowdmap::IsUsageError(status)) {
    std::cerr << where << ": " << status.message() << " (see mapsim --help)\n";
  } else if (!status.ok()) {
    std::cerr << where << ": " << status.message() << "\n";
  }
  return crowdmap::ExitCodeFor(status);
}
