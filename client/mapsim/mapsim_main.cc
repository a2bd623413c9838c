// mapsim: simulation front end. `experiment` runs simulated passages through the estimation core
// in-process; `reproduce` runs the thesis's result grids; `fleet`, `export-passages` and `bench`
// drive a running mapd.
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <numeric>
#include <string>
#include <vector>

#include <glog/logging.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "client/common/flags.h"
#include "core/logging/log_format.h"
#include "client/mapsim/city_experiment.h"
#include "client/mapsim/experiment.h"
#include "client/mapsim/localize_experiment.h"
#include "client/mapsim/passage_consistency.h"
#include "client/mapsim/pose_bias.h"
#include "client/mapsim/reproduce.h"
#if CROWDMAP_MAPSIM_SERVICE
#include "client/mapsim/bench.h"
#include "client/mapsim/fleet.h"
#endif

namespace crowdmap {
namespace {

constexpr char kUsage[] = R"(mapsim: simulate crowdsourced landmark mapping (thesis scenario).

Usage:
  mapsim experiment [flags]   run passages through the estimation core in-process
  mapsim city       [flags]   the same on a city: a street grid with buildings, a fleet driving
                              random partial routes
  mapsim reproduce  [flags]   run the thesis's table 5.2 and robustness grids
  mapsim localize   [flags]   thesis Table 5.5: one ~4 km passage localised without and with the
                              map (the thesis's map model, then crowdmap's own maps)
  mapsim crlb       [flags]   the Cramer-Rao bound of the experiment's passages: the smallest mean
                              landmark error any unbiased map can reach from them (--landmarks,
                              --passages, --noise, --seed, --detections-per-landmark as for
                              experiment); printed after 1, 10, 100, ... passages and the last
  mapsim pose-bias  [flags]   mean pose error of single-passage odometry + GNSS solves along the
                              route (the bias of the MAP estimate), before and after the
                              second-order bias correction
  mapsim passage-consistency [flags]  whether one passage's covariance describes its own error:
                              independent passages, each mapped alone, joint NEES against the truth
  mapsim fleet      [flags]   upload simulated passages to a running mapd from concurrent vehicles,
                              wait until applied, read the map back, write the experiment outputs
  mapsim export-passages [flags]  write simulated passages as files for `mapctl upload`
  mapsim bench      [flags]   load-test a running mapd (use a scratch database)
  mapsim --version            print the version

Exit codes: 0 success, 1 failure (unreachable server, failed run, unwritable output, ...),
2 usage error (unknown command or flag, missing value, bad value), reported before any work.

experiment flags:
  --landmarks N               landmarks along the 2 km route (default 25)
  --passages P                simulated passages, applied in order (default 100)
  --strategy S                cc | dc | cc-gsd | triangulation (default cc-gsd)
  --noise X                   white | gnss-ar1 | yaw-bias | ar1+yaw (default white)
  --seed S                    noise seed; the route and landmarks do not depend on it (default 1)
  --out DIR                   output folder (default out/experiment): passages.csv, summary.json, errors.svg
  --max-subgraph-dim D        cc-gsd state-dimension bound per subgraph (default 500)
  --detections-per-landmark K last K >= 2 detections per landmark and passage, 0 = all (default 5)
  --window-hops H             re-estimate the map within H links of each graph (0 = whole map, exact)
  --relinearize-sigmas X      after each passage, take again (at today's estimate) the retained
                              passage whose landmarks moved furthest since its factors were
                              taken, if more than X of their current sigmas (default 0 = off)
  --relinearizations-per-passage K  at most K such re-linearisations per passage (default 1)
  --warmup-passages B         the map's first B passages are solved jointly, re-solved with
                              each one (default 8; 0 = off)
  --relinearize-until-passages R  after the warm-up, re-solve all the map's passages jointly each
                              time their count doubles (2B, 4B, ...) up to R passages (default 128;
                              0 = off)
  --edge-margin-sigmas M      do not use detections of map landmarks predicted within M pixel
                              sigmas of the image border, where the detector's cut biases them
                              (default 3; 0 = use all)
  --inflation-test-sigmas K   inflate a passage's measurement covariances by chi2/dof when its chi2
                              exceeds dof by K sigma, 0 = never (default 4)
  --max-chi2-per-dof X        refuse a passage when a solve leaves chi2 above X per degree of
                              freedom before any inflation, 0 = never
                              (default 0)
  --shuffle-window W          apply the passages shuffled within consecutive groups of W, as W
                              concurrent vehicles would deliver them (default 0: in order)
  --shuffle-from F            keep passages 0..F-1 in order, shuffle from F on (default 0)
  --shuffle-seed K            seed of the shuffle (default 1)
  --order-file FILE           apply the passages in this order: one scenario passage index per
                              line, a permutation of 0..P-1 (e.g. a fleet run's arrival_order.txt)
  --steering-noise-scale X, --speed-noise-scale X, --gnss-noise-scale X, --pixel-noise-scale X
                              scale a sensor's noise, drawn and modelled alike (default 1)
  --no-bias-correction        skip the second-order bias correction of each solution
  --no-crlb                   skip the Cramer-Rao bound of the same passages (summary.json:
                              crlb_mean_dist_err_m, error_over_crlb)
  --piece-m MIN,MAX           partial drives: each passage keeps one piece of the route, MIN to
                              MAX metres long (uniform), from a random start (default: whole)
  --assume-white-gnss         the estimator ignores the coloured GNSS process the passages declare
                              (gnss-ar1, ar1+yaw) and assumes white noise, as before it modelled
                              it; the bound still models it
  --vehicles V                a fleet: passage i is driven by vehicle i % V (sim-v0, ...), each
                              with its own camera yaw error (default 0: every passage its own)
  --vehicle-yaw-bias-sigma-rad X  each fleet vehicle's own camera yaw error, Gaussian (default 0)
  --estimate-camera-yaw       estimate each vehicle's camera yaw offset, its history the prior
                              (summary.json: vehicle_yaw, estimate against truth per vehicle)
  --quiet                     no progress line

city flags:
  --blocks-x N, --blocks-y N  street grid of N x N blocks (default 6 x 6)
  --block-m M                 distance between streets, m (default 150)
  --passages P                passages applied in order to an empty map (default 200)
  --route-m M                 distance driven per passage, m (default 2000)
  --vehicles V                fleet size; passage i is driven by vehicle i % V (default 20)
  --seed S                    routes and noise (default 1)
  --layout-seed S             street jitter and landmarks (default 1)
  --noise X                   white | gnss-ar1 | yaw-bias | ar1+yaw (default white)
  --vehicle-yaw-bias-sigma-rad X  each vehicle's own camera yaw error, Gaussian (default 0)
  --rate-variation X          each vehicle's sensor rates scaled by a factor in [1-X, 1+X] (default 0)
  --no-occlusion              buildings do not hide landmarks
  --steering-noise-scale X, --speed-noise-scale X, --gnss-noise-scale X, --pixel-noise-scale X
                              as for experiment
  --strategy S                cc | dc | cc-gsd (default cc-gsd)
  --window-hops H, --warmup-passages B, --relinearize-until-passages R, --relinearize-sigmas X,
  --relinearizations-per-passage K, --estimate-camera-yaw  as for experiment
  --mislabel-rate X           faults: each detection reported under a neighbouring landmark's id
                              with probability X (default 0)
  --multipath-rate X          faults: a passage has a GNSS multipath burst (20-60 s of fixes 30-80 m
                              off, declared as usual) with probability X
  --overconfident-rate X      faults: a passage declares GNSS sigmas 5 times too small
  --bad-calibration-rate X    faults: a passage declares a camera yaw 3 degrees off and a wheelbase
                              15% off
  --fault-seed S              draws of the faults (default 1); summary.json counts the faulty
                              passages and splits the refused ones into faulty and clean
  --progress-every P          progress line on stderr every P passages (default 10)
  --out DIR                   output folder (default out/city): summary.json, landmarks.csv
  --export-passages DIR2      also write passages 0..P-1 as files for `mapctl upload`
                              (DIR2/passage-00000.json, ... as export-passages does)
  --export-format F           json | binary (default json)
  --quiet                     no progress lines

fleet flags (and --landmarks, --noise, --seed, --quiet as for experiment):
  --server HOST:PORT          mapd address (default $MAPCTL_SERVER or 127.0.0.1:50051)
  --passages P                passages 0..P-1 of the scenario (default 40)
  --vehicles V                concurrent vehicles; vehicle v uploads passages v, v+V, ... (default 4)
  --strategy S                fail unless the server runs strategy S (default: accept the server's)
  --sample-ms MS              read the map back and evaluate it this often while applying (default 250)
  --no-replay                 skip the check below
  --city                      upload city passages (mapsim city's default grid, --seed its fleet
                              seed) instead of the loop's; errors against the city's landmarks; no
                              replay
  --route-m M                 with --city: distance driven per passage (default 2000)
  --out DIR                   output folder (default out/fleet): passages.csv (one row per sampled
                              map; the last row is the final map), summary.json, errors.svg, map.geojson,
                              arrival_order.txt (the scenario passage index of each applied passage,
                              in the order the server applied them; see experiment --order-file)
  After the run (on a server whose map started empty) the passages are applied in-process in the
  order the server received them; summary.json gets that run's error and the largest landmark
  difference from the server's map (arrival_order_experiment_final_mean_dist_err_m,
  max_position_diff_vs_arrival_order_experiment_m, max_cov_diff_vs_arrival_order_experiment_m2).

export-passages flags (and --landmarks, --noise, --seed):
  --passages P                passages 0..P-1 (default 40)
  --format F                  json | binary (default json)
  --out DIR                   output folder (default out/passages): passage-00000.json, ...

bench flags (and --landmarks, --seed):
  --server HOST:PORT          mapd address (default $MAPCTL_SERVER or 127.0.0.1:50051)
  --clients K                 concurrent uploading clients (default 8)
  --passages P                passages uploaded (default 400)
  --readers R                 concurrent QueryRegion / GetTile readers (default 8)
  --seconds S                 longest read phase (default 10); reads stop when the queue is
                              drained, so that every measured read competes with map updates
  --city                      upload city passages (mapsim city's default grid) instead of the
                              loop's; reads cover the whole city
  --route-m M                 with --city: distance driven per passage (default 2000)
  --upload-rate R             pace the uploads at R per second over all clients (default 0: as
                              fast as acknowledgements come back); a paced run measures the
                              acknowledgements while the worker commits map changes

fleet and bench also take mapd's TLS and token flags:
  --tls-ca PATH               TLS: the PEM CA that signed mapd's certificate (default plaintext)
  --tls-cert PATH --tls-key PATH  mTLS: this client's PEM certificate and key
  --tls-server-name NAME      the name in mapd's certificate, if not the --server host
  --token-file PATH           bearer token (default $CROWDMAP_TOKEN_FILE; none); uploading
                              simulated vehicles' passages needs an admin token

localize flags:
  --landmarks LIST            landmark counts, comma-separated (default 44,500)
  --runs R                    passages (and generated maps) averaged per cell (default 10)
  --duration-s S              passage duration, s (default 340: 4 km at 12 m/s)
  --gnss-fixes K              GNSS fixes per passage, as the thesis's 512 (rate and AR(1) coefficient
                              per fix adjusted; 0 = the scenario's 1 Hz) (default 512)
  --own-map-passages LIST     also localise (ar1+yaw) against crowdmap's own map built from P
                              passages, for each P (comma-separated; default none)
  --seed S                    noise seed (default 1)
  --out FILE                  markdown table (default out/localize.md)

pose-bias flags (and --seed):
  --passages P                independent passages, each solved alone (default 1000)
  --bin-s S                   time bin width, s (default 5)
  --steering-noise-scale X    scale the steering noise (drawn and modelled) by X (default 1)
  --speed-noise-scale X       scale the speed noise likewise (default 1)
  --gnss-noise-scale X        scale the GNSS noise likewise (default 1)
  --pixel-noise-scale X       scale the camera's pixel noise likewise (default 1)

passage-consistency flags (and --landmarks, --seed, --noise, --detections-per-landmark and the
--...-noise-scale flags as for experiment):
  --passages P                independent passages, each applied alone to an empty map (default 300)
  --strategy S                cc | cc-gsd (default cc)
  Prints the mean joint NEES per degree of freedom with each passage's own covariance (1 =
  consistent), the NEES of the errors' spread and of their mean against the covariance averaged
  over the passages, and the own-covariance NEES along the most and least precise fifth of the
  directions, and the NEES and mean error of the passages' maps combined by their information, each
  linearised at its own estimate.

reproduce flags:
  --out DIR                   output folder (default out/reproduce); writes DIR/reproduction.md
  --passages P                passages per experiment (default 1000)
  --jobs J                    experiments run in parallel (default 2)
  --seed S                    first noise seed (default 1)
  --seeds K                   run every experiment with seeds S..S+K-1 and report the means
                              (default 3; about 3 minutes per seed on 2 cores)
  --nees-sd-target X          the CC and CC+GSD cells of table 5.2 take further seeds until the
                              standard deviation of their mean NEES, were the maps consistent, is
                              at most X (default 0.2; 0 = no further seeds)
  --max-seeds M               at most M seeds per cell (default 20)
)";

// A mapsim command's flags; it takes no positional arguments. Errors are usage errors.
absl::StatusOr<Flags> ParseFlags(const std::vector<std::string>& args, const std::map<std::string, bool>& known) {
  absl::StatusOr<Flags> flags = Flags::Parse(args, known);
  if (flags.ok() && !flags->positional().empty()) {
    return UsageError(absl::StrCat("unexpected argument '", flags->positional()[0], "'"));
  }
  return flags;
}

// --steering-noise-scale, --speed-noise-scale, --gnss-noise-scale and --pixel-noise-scale scale
// a sensor's noise, both as drawn and as declared in the passages.
absl::Status ScaleNoise(const Flags& flags, NoiseModel* sensors, double* gnss_sigma_m) {
  const std::pair<const char*, double*> sigmas[] = {{"steering-noise-scale", &sensors->steering_sigma_rad},
                                                    {"speed-noise-scale", &sensors->speed_sigma_mps},
                                                    {"gnss-noise-scale", gnss_sigma_m},
                                                    {"pixel-noise-scale", &sensors->pixel_sigma_px}};
  for (const auto& [name, sigma] : sigmas) {
    absl::StatusOr<double> scale = flags.GetDouble(name, 1.0);
    if (!scale.ok()) return scale.status();
    if (!(*scale > 0.0)) return UsageError(absl::StrCat(name, ": must be > 0, got ", *scale));
    *sigma *= *scale;
  }
  return absl::OkStatus();
}

absl::Status ScaleNoise(const Flags& flags, ScenarioOptions* scenario) {
  return ScaleNoise(flags, &scenario->noise_model, &scenario->gnss_sigma_m);
}

// --relinearize-sigmas and --relinearizations-per-passage (experiment and city).
absl::Status ParseLocalRelinearization(const Flags& flags, MapUpdateOptions* update) {
  absl::StatusOr<double> sigmas = flags.GetDouble("relinearize-sigmas", update->relinearize_sigmas);
  if (!sigmas.ok()) return sigmas.status();
  absl::StatusOr<long long> per_passage =
      flags.GetInt("relinearizations-per-passage", update->relinearizations_per_passage);
  if (!per_passage.ok()) return per_passage.status();
  update->relinearize_sigmas = *sigmas;
  update->relinearizations_per_passage = static_cast<int>(*per_passage);
  return absl::OkStatus();
}

// --mislabel-rate, --multipath-rate, --overconfident-rate, --bad-calibration-rate, --fault-seed.
absl::Status ParseFaults(const Flags& flags, FaultOptions* faults) {
  absl::StatusOr<double> mislabel = flags.GetDouble("mislabel-rate", faults->mislabel_rate),
                         multipath = flags.GetDouble("multipath-rate", faults->multipath_rate),
                         overconfident = flags.GetDouble("overconfident-rate", faults->overconfident_rate),
                         bad_calibration = flags.GetDouble("bad-calibration-rate", faults->bad_calibration_rate);
  absl::StatusOr<long long> seed = flags.GetInt("fault-seed", static_cast<long long>(faults->seed));
  for (const absl::Status& s :
       {mislabel.status(), multipath.status(), overconfident.status(), bad_calibration.status(), seed.status()}) {
    if (!s.ok()) return s;
  }
  faults->mislabel_rate = *mislabel;
  faults->multipath_rate = *multipath;
  faults->overconfident_rate = *overconfident;
  faults->bad_calibration_rate = *bad_calibration;
  faults->seed = static_cast<uint64_t>(*seed);
  return AsUsageError(faults->Validate());
}

absl::Status RunExperimentCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(args, {{"landmarks", true}, {"passages", true}, {"strategy", true},
                                                    {"noise", true}, {"seed", true}, {"out", true},
                                                    {"max-subgraph-dim", true}, {"detections-per-landmark", true},
                                                    {"window-hops", true}, {"warmup-passages", true},
                                                    {"relinearize-until-passages", true}, {"max-chi2-per-dof", true},
                                                    {"relinearize-sigmas", true}, {"relinearizations-per-passage", true},
                                                    {"inflation-test-sigmas", true}, {"edge-margin-sigmas", true},
                                                    {"shuffle-window", true}, {"shuffle-from", true}, {"shuffle-seed", true},
                                                    {"order-file", true}, {"steering-noise-scale", true},
                                                    {"speed-noise-scale", true}, {"gnss-noise-scale", true},
                                                    {"pixel-noise-scale", true}, {"no-bias-correction", false},
                                                    {"no-crlb", false}, {"assume-white-gnss", false},
                                                    {"piece-m", true}, {"quiet", false}, {"vehicles", true},
                                                    {"vehicle-yaw-bias-sigma-rad", true},
                                                    {"estimate-camera-yaw", false}});
  if (!flags.ok()) return flags.status();
  ExperimentOptions options;
  absl::StatusOr<long long> landmarks = flags->GetInt("landmarks", 25), passages = flags->GetInt("passages", 100),
                            seed = flags->GetInt("seed", 1), dim = flags->GetInt("max-subgraph-dim", 500),
                            per_landmark = flags->GetInt("detections-per-landmark", 5),
                            warmup = flags->GetInt("warmup-passages", options.update.warmup_passages),
                            relinearize =
                                flags->GetInt("relinearize-until-passages", options.update.relinearize_until_passages),
                            shuffle_window = flags->GetInt("shuffle-window", 0),
                            shuffle_from = flags->GetInt("shuffle-from", 0), shuffle_seed = flags->GetInt("shuffle-seed", 1),
                            window_hops = flags->GetInt("window-hops", options.update.window_hops),
                            vehicles = flags->GetInt("vehicles", 0);
  absl::StatusOr<double> chi2 = flags->GetDouble("max-chi2-per-dof", options.update.max_chi2_per_dof),
                         inflation = flags->GetDouble("inflation-test-sigmas", options.update.inflation_test_sigmas),
                         edge_margin = flags->GetDouble("edge-margin-sigmas", options.update.edge_margin_sigmas),
                         yaw_sigma = flags->GetDouble("vehicle-yaw-bias-sigma-rad", 0.0);
  for (const absl::Status& s : {vehicles.status(), yaw_sigma.status(), landmarks.status(), passages.status(),
                                seed.status(), dim.status(),
                                per_landmark.status(), warmup.status(), relinearize.status(), window_hops.status(),
                                chi2.status(), inflation.status(), edge_margin.status(), shuffle_window.status(),
                                shuffle_from.status(), shuffle_seed.status()}) {
    if (!s.ok()) return s;
  }
  absl::StatusOr<NoiseConfig> noise = ParseNoiseConfig(flags->GetString("noise", "white"));
  if (!noise.ok()) return AsUsageError(noise.status());
  options.scenario.landmarks = static_cast<int>(*landmarks);
  options.scenario.noise = *noise;
  options.scenario.seed = static_cast<uint64_t>(*seed);
  options.scenario.vehicles = static_cast<int>(*vehicles);
  options.scenario.vehicle_yaw_bias_sigma_rad = *yaw_sigma;
  if (absl::Status s = ScaleNoise(*flags, &options.scenario); !s.ok()) return s;
  options.passages = static_cast<int>(*passages);
  options.update.estimate_camera_yaw = flags->Has("estimate-camera-yaw");
  options.strategy = flags->GetString("strategy", "cc-gsd");
  options.update.max_subgraph_dim = static_cast<int>(*dim);
  options.update.detections_per_landmark = static_cast<int>(*per_landmark);
  options.update.warmup_passages = static_cast<int>(*warmup);
  options.update.relinearize_until_passages = static_cast<int>(*relinearize);
  options.update.window_hops = static_cast<int>(*window_hops);
  options.update.max_chi2_per_dof = *chi2;
  options.update.inflation_test_sigmas = *inflation;
  options.update.edge_margin_sigmas = *edge_margin;
  options.update.bias_correction = !flags->Has("no-bias-correction");
  options.crlb = !flags->Has("no-crlb");
  options.assume_white_gnss = flags->Has("assume-white-gnss");
  if (flags->Has("piece-m")) {
    const std::vector<std::string> parts = absl::StrSplit(flags->GetString("piece-m", ""), ',');
    if (parts.size() != 2 || !absl::SimpleAtod(parts[0], &options.scenario.piece_min_m) ||
        !absl::SimpleAtod(parts[1], &options.scenario.piece_max_m)) {
      return UsageError("piece-m: expected MIN,MAX in metres, e.g. 300,1500");
    }
    if (absl::Status s = options.scenario.Validate(); !s.ok()) return AsUsageError(s);
  }
  if (absl::Status s = ParseLocalRelinearization(*flags, &options.update); !s.ok()) return s;
  if (*shuffle_window < 0) return UsageError("shuffle-window: must be >= 0");
  if (*shuffle_from < 0) return UsageError("shuffle-from: must be >= 0");
  if (flags->Has("order-file")) {
    if (flags->Has("shuffle-window")) {
      return UsageError("order-file: cannot be used with --shuffle-window");
    }
    absl::StatusOr<std::vector<int>> order = ReadOrderFile(flags->GetString("order-file", ""));
    if (!order.ok()) return order.status();
    options.order = *std::move(order);
  } else if (*shuffle_window > 1) {
    options.order = ShuffledOrder(options.passages, static_cast<int>(*shuffle_window), static_cast<int>(*shuffle_from),
                                  static_cast<uint64_t>(*shuffle_seed));
  }
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  const std::string out = flags->GetString("out", "out/experiment");
  const bool quiet = flags->Has("quiet");

  const int every = std::max(1, options.passages / 20);
  auto progress = [&](const PassageRecord& r) {
    if (quiet || (r.passage % every != 0 && r.passage != options.passages)) return;
    std::cerr << absl::StrFormat("\rpassage %d/%d  error %.3f m  nees %.2f  %.1f ms/passage   ", r.passage,
                                 options.passages, r.metrics.mean_dist_err_m, r.metrics.nees_per_dof, r.solve_ms)
              << std::flush;
  };
  absl::StatusOr<ExperimentResult> result = RunExperiment(options, progress);
  if (!quiet) std::cerr << "\n";
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteExperimentOutputs(options, *result, out); !s.ok()) return s;
  std::cout << absl::StrFormat(
      "strategy=%s noise=%s landmarks=%d passages=%d final_mean_dist_err_m=%.4f final_nees_per_dof=%.3f "
      "final_joint_nees_per_dof=%.3f median_passage_ms=%.2f failed=%d quarantined=%d inflated=%d joint_rejected=%d "
      "detections_used=%d detections_outliers=%d landmarks_disagreeing=%d vehicle_yaw_within_2sigma=%.3f "
      "vehicle_yaw_nees=%.3f out=%s\n",
      options.strategy, NoiseConfigName(options.scenario.noise), options.scenario.landmarks, options.passages,
      result->final_mean_dist_err_m, result->final_nees_per_dof, result->final_joint_nees_per_dof,
      result->median_passage_ms, result->failed_passages, result->quarantined_passages, result->inflated_passages,
      result->joint_rejected_passages, result->detections_used, result->detections_outliers,
      result->landmarks_disagreeing, result->vehicle_yaw.within_2sigma_fraction, result->vehicle_yaw.nees, out);
  return absl::OkStatus();
}

absl::Status RunCityCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(
      args, {{"blocks-x", true}, {"blocks-y", true}, {"block-m", true}, {"passages", true}, {"route-m", true},
             {"vehicles", true}, {"seed", true}, {"layout-seed", true}, {"noise", true},
             {"vehicle-yaw-bias-sigma-rad", true}, {"rate-variation", true}, {"no-occlusion", false},
             {"strategy", true}, {"window-hops", true}, {"warmup-passages", true},
             {"relinearize-until-passages", true}, {"progress-every", true}, {"out", true},
             {"relinearize-sigmas", true}, {"relinearizations-per-passage", true},
             {"mislabel-rate", true}, {"multipath-rate", true}, {"overconfident-rate", true},
             {"bad-calibration-rate", true}, {"fault-seed", true},
             {"export-passages", true}, {"export-format", true}, {"steering-noise-scale", true},
             {"speed-noise-scale", true}, {"gnss-noise-scale", true}, {"pixel-noise-scale", true}, {"quiet", false},
             {"estimate-camera-yaw", false}});
  if (!flags.ok()) return flags.status();
  CityExperimentOptions options;
  CityScenarioOptions& city = options.city;
  absl::StatusOr<long long> blocks_x = flags->GetInt("blocks-x", city.blocks_x),
                            blocks_y = flags->GetInt("blocks-y", city.blocks_y),
                            passages = flags->GetInt("passages", options.passages),
                            vehicles = flags->GetInt("vehicles", city.vehicles), seed = flags->GetInt("seed", 1),
                            layout_seed = flags->GetInt("layout-seed", 1),
                            warmup = flags->GetInt("warmup-passages", options.update.warmup_passages),
                            relinearize =
                                flags->GetInt("relinearize-until-passages", options.update.relinearize_until_passages),
                            every = flags->GetInt("progress-every", options.progress_every_passages),
                            window_hops = flags->GetInt("window-hops", options.update.window_hops);
  absl::StatusOr<double> block_m = flags->GetDouble("block-m", city.block_m),
                         route_m = flags->GetDouble("route-m", city.route_length_m),
                         yaw_sigma = flags->GetDouble("vehicle-yaw-bias-sigma-rad", city.vehicle_yaw_bias_sigma_rad),
                         rate_variation = flags->GetDouble("rate-variation", city.rate_variation);
  for (const absl::Status& s : {blocks_x.status(), blocks_y.status(), passages.status(), vehicles.status(),
                                seed.status(), layout_seed.status(), warmup.status(), relinearize.status(),
                                every.status(), block_m.status(), route_m.status(), yaw_sigma.status(),
                                rate_variation.status(), window_hops.status()}) {
    if (!s.ok()) return s;
  }
  absl::StatusOr<NoiseConfig> noise = ParseNoiseConfig(flags->GetString("noise", "white"));
  if (!noise.ok()) return AsUsageError(noise.status());
  absl::StatusOr<UpdateStrategy> strategy = ParseUpdateStrategy(flags->GetString("strategy", "cc-gsd"));
  if (!strategy.ok()) return AsUsageError(strategy.status());
  city.blocks_x = static_cast<int>(*blocks_x);
  city.blocks_y = static_cast<int>(*blocks_y);
  city.block_m = *block_m;
  city.route_length_m = *route_m;
  city.vehicles = static_cast<int>(*vehicles);
  city.seed = static_cast<uint64_t>(*seed);
  city.layout_seed = static_cast<uint64_t>(*layout_seed);
  city.noise = *noise;
  city.vehicle_yaw_bias_sigma_rad = *yaw_sigma;
  city.rate_variation = *rate_variation;
  city.occlusion = !flags->Has("no-occlusion");
  if (absl::Status s = ScaleNoise(*flags, &city.noise_model, &city.gnss_sigma_m); !s.ok()) return s;
  options.passages = static_cast<int>(*passages);
  options.progress_every_passages = static_cast<int>(*every);
  options.update.strategy = *strategy;
  options.update.window_hops = static_cast<int>(*window_hops);
  if (absl::Status s = ParseLocalRelinearization(*flags, &options.update); !s.ok()) return s;
  if (absl::Status s = ParseFaults(*flags, &options.faults); !s.ok()) return s;
  options.update.warmup_passages = static_cast<int>(*warmup);
  options.update.relinearize_until_passages = static_cast<int>(*relinearize);
  options.update.estimate_camera_yaw = flags->Has("estimate-camera-yaw");
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  const std::string out = flags->GetString("out", "out/city");
  const bool quiet = flags->Has("quiet");

  if (flags->Has("export-passages")) {
#if CROWDMAP_MAPSIM_SERVICE
    const std::string format = flags->GetString("export-format", "json");
    if (format != "json" && format != "binary") {
      return UsageError(absl::StrCat("--export-format: '", format, "' is not json or binary"));
    }
    absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
    if (!scenario.ok()) return scenario.status();
    const std::string dir = flags->GetString("export-passages", "");
    if (absl::Status s = ExportPassages([&](int i) { return scenario->MakePassage(i); }, options.passages,
                                        format == "binary", dir);
        !s.ok()) {
      return s;
    }
    std::cout << absl::StrFormat("wrote %d passages to %s\n", options.passages, dir);
#else
    return absl::UnimplementedError("--export-passages: this mapsim was built without the service (gRPC)");
#endif
  }

  auto progress = [&](const CityProgress& p) {
    if (quiet) return;
    std::cerr << absl::StrFormat(
        "passage %d/%d  landmarks mapped %d  error mean %.3f m median %.3f m  p50 %.1f ms  p95 %.1f ms per passage\n",
        p.passages_done, p.passages_total, p.landmarks_mapped, p.mean_error_m, p.median_error_m, p.p50_ms, p.p95_ms);
  };
  absl::StatusOr<CityExperimentResult> result = RunCityExperiment(options, progress);
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteCityOutputs(options, *result, out); !s.ok()) return s;
  std::cout << result->Brief() << absl::StrFormat(" layout_s=%.3f out=%s\n", result->layout_s, out);
  return absl::OkStatus();
}

absl::StatusOr<ScenarioOptions> ScenarioFromFlags(const Flags& flags) {
  ScenarioOptions scenario;
  absl::StatusOr<long long> landmarks = flags.GetInt("landmarks", 25), seed = flags.GetInt("seed", 1);
  if (!landmarks.ok()) return landmarks.status();
  if (!seed.ok()) return seed.status();
  absl::StatusOr<NoiseConfig> noise = ParseNoiseConfig(flags.GetString("noise", "white"));
  if (!noise.ok()) return AsUsageError(noise.status());
  scenario.landmarks = static_cast<int>(*landmarks);
  scenario.seed = static_cast<uint64_t>(*seed);
  scenario.noise = *noise;
  return scenario;
}

#if CROWDMAP_MAPSIM_SERVICE
// --server's default: $MAPCTL_SERVER when set (as for mapctl), else `fallback`.
std::string ServerDefault(const std::string& fallback) {
  const char* env = std::getenv("MAPCTL_SERVER");
  return env != nullptr && *env != '\0' ? env : fallback;
}

// The command's flags and the client security flags (--tls-ca, --token-file, ...).
std::map<std::string, bool> WithSecurityFlags(std::map<std::string, bool> known) {
  for (const auto& flag : ClientSecurityFlags()) known.insert(flag);
  return known;
}

absl::Status RunFleetCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(args, WithSecurityFlags({{"server", true}, {"landmarks", true}, {"passages", true},
                                                    {"noise", true}, {"seed", true}, {"vehicles", true},
                                                    {"strategy", true}, {"sample-ms", true}, {"out", true},
                                                    {"quiet", false}, {"no-replay", false}, {"city", false},
                                                    {"route-m", true}}));
  if (!flags.ok()) return flags.status();
  absl::StatusOr<ScenarioOptions> scenario = ScenarioFromFlags(*flags);
  if (!scenario.ok()) return scenario.status();
  FleetOptions options;
  absl::StatusOr<long long> passages = flags->GetInt("passages", 40), vehicles = flags->GetInt("vehicles", 4),
                            sample_ms = flags->GetInt("sample-ms", 250);
  absl::StatusOr<double> route_m = flags->GetDouble("route-m", options.city_scenario.route_length_m);
  for (const absl::Status& s : {passages.status(), vehicles.status(), sample_ms.status(), route_m.status()}) {
    if (!s.ok()) return s;
  }
  if (flags->Has("route-m") && !flags->Has("city")) return UsageError("route-m: only with --city");
  options.city = flags->Has("city");
  options.city_scenario.seed = scenario->seed;
  options.city_scenario.noise = scenario->noise;
  options.city_scenario.route_length_m = *route_m;
  options.server = flags->GetString("server", ServerDefault(options.server));
  if (absl::Status s = ApplyClientSecurityFlags(*flags, &options.client.security); !s.ok()) return AsUsageError(s);
  options.scenario = *scenario;
  options.passages = static_cast<int>(*passages);
  options.vehicles = static_cast<int>(*vehicles);
  options.strategy = flags->GetString("strategy", "");
  options.sample_interval = std::chrono::milliseconds(*sample_ms);
  options.replay = !flags->Has("no-replay") && !options.city;
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  const std::string out = flags->GetString("out", "out/fleet");
  const bool quiet = flags->Has("quiet");
  auto progress = [&](const FleetProgress& p) {
    if (quiet) return;
    // A joint solve holds the count for seconds: say so, so that the pause does not look like a hang.
    const std::string joint =
        p.joint_solve_of > 0 ? absl::StrFormat("  (server: joint solve of %d passages)", p.joint_solve_of) : "";
    std::cerr << absl::StrFormat("\ruploaded %d/%d  applied %d/%d  error %s%s   ", p.uploaded, p.total, p.applied,
                                 p.total, p.mean_dist_err_m < 0 ? std::string("-") : absl::StrFormat("%.3f m", p.mean_dist_err_m),
                                 joint)
              << std::flush;
  };
  absl::StatusOr<FleetResult> result = RunFleet(options, progress);
  if (!quiet) std::cerr << "\n";
  if (!result.ok()) return result.status();
  if (absl::Status s = WriteFleetOutputs(options, *result, out); !s.ok()) return s;
  std::cout << result->Brief() << " vehicles=" << options.vehicles << " out=" << out << "\n";
  return absl::OkStatus();
}

absl::Status RunExportPassagesCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(args, {{"landmarks", true}, {"passages", true}, {"noise", true},
                                                    {"seed", true}, {"format", true}, {"out", true}});
  if (!flags.ok()) return flags.status();
  absl::StatusOr<ScenarioOptions> scenario = ScenarioFromFlags(*flags);
  if (!scenario.ok()) return scenario.status();
  absl::StatusOr<long long> passages = flags->GetInt("passages", 40);
  if (!passages.ok()) return passages.status();
  const std::string format = flags->GetString("format", "json");
  if (format != "json" && format != "binary") {
    return UsageError(absl::StrCat("--format: '", format, "' is not json or binary"));
  }
  const std::string out = flags->GetString("out", "out/passages");
  if (absl::Status s = ExportPassages(*scenario, static_cast<int>(*passages), format == "binary", out); !s.ok()) return s;
  std::cout << absl::StrFormat("wrote %d passages to %s\n", *passages, out);
  return absl::OkStatus();
}

absl::Status RunBenchCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(args, WithSecurityFlags({{"server", true}, {"landmarks", true}, {"seed", true},
                                                    {"clients", true}, {"passages", true}, {"readers", true},
                                                    {"seconds", true}, {"city", false}, {"route-m", true},
                                                    {"upload-rate", true}}));
  if (!flags.ok()) return flags.status();
  absl::StatusOr<ScenarioOptions> scenario = ScenarioFromFlags(*flags);
  if (!scenario.ok()) return scenario.status();
  BenchOptions options;
  absl::StatusOr<long long> clients = flags->GetInt("clients", options.clients),
                            passages = flags->GetInt("passages", options.passages),
                            readers = flags->GetInt("readers", options.readers);
  absl::StatusOr<double> seconds = flags->GetDouble("seconds", options.read_seconds),
                         route_m = flags->GetDouble("route-m", options.city_scenario.route_length_m),
                         upload_rate = flags->GetDouble("upload-rate", options.upload_rate_per_s);
  for (const absl::Status& s : {clients.status(), passages.status(), readers.status(), seconds.status(),
                                route_m.status(), upload_rate.status()}) {
    if (!s.ok()) return s;
  }
  options.city = flags->Has("city");
  options.city_scenario.seed = scenario->seed;
  options.city_scenario.route_length_m = *route_m;
  options.upload_rate_per_s = *upload_rate;
  options.server = flags->GetString("server", ServerDefault(options.server));
  if (absl::Status s = ApplyClientSecurityFlags(*flags, &options.security); !s.ok()) return AsUsageError(s);
  options.scenario = *scenario;
  options.clients = static_cast<int>(*clients);
  options.passages = static_cast<int>(*passages);
  options.readers = static_cast<int>(*readers);
  options.read_seconds = *seconds;
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

absl::StatusOr<std::vector<int>> ParseIntList(const std::string& flag, const std::string& text) {
  std::vector<int> out;
  for (absl::string_view part : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    int value = 0;
    if (!absl::SimpleAtoi(part, &value)) {
      return UsageError(absl::StrCat(flag, ": '", text, "' is not a comma-separated list of integers"));
    }
    out.push_back(value);
  }
  return out;
}

absl::Status RunLocalizeCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags =
      ParseFlags(args, {{"landmarks", true}, {"runs", true}, {"duration-s", true}, {"own-map-passages", true}, {"gnss-fixes", true},
                          {"seed", true}, {"out", true}, {"quiet", false}});
  if (!flags.ok()) return flags.status();
  LocalizeExperimentOptions options;
  absl::StatusOr<std::vector<int>> landmarks = ParseIntList("landmarks", flags->GetString("landmarks", "44,500"));
  absl::StatusOr<std::vector<int>> own = ParseIntList("own-map-passages", flags->GetString("own-map-passages", ""));
  absl::StatusOr<long long> runs = flags->GetInt("runs", options.runs), seed = flags->GetInt("seed", 1),
                            gnss_fixes = flags->GetInt("gnss-fixes", options.gnss_fixes);
  absl::StatusOr<double> duration = flags->GetDouble("duration-s", options.duration_s);
  for (const absl::Status& s :
       {landmarks.status(), own.status(), runs.status(), seed.status(), duration.status(), gnss_fixes.status()}) {
    if (!s.ok()) return s;
  }
  options.landmark_counts = *landmarks;
  options.own_map_passages = *own;
  options.runs = static_cast<int>(*runs);
  options.seed = static_cast<uint64_t>(*seed);
  options.duration_s = *duration;
  options.gnss_fixes = static_cast<int>(*gnss_fixes);
  const bool quiet = flags->Has("quiet");
  if (quiet) spdlog::set_level(spdlog::level::warn);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<std::vector<LocalizeRow>> rows = RunLocalizeExperiment(options, [&](const std::string& what) {
    if (!quiet) std::cerr << "\r" << what << "        " << std::flush;
  });
  if (!quiet) std::cerr << "\n";
  if (!rows.ok()) return rows.status();
  const std::string table = LocalizeMarkdown(options, *rows);
  std::cout << table;
  const std::string out = flags->GetString("out", "out/localize.md");
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(out).parent_path(), ec);
  std::ofstream file(out);
  file << table;
  if (!file) return absl::InternalError(absl::StrCat("out: cannot write ", out));
  return absl::OkStatus();
}

absl::Status RunCrlbCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags = ParseFlags(args, {{"landmarks", true}, {"passages", true}, {"noise", true},
                                                    {"seed", true}, {"detections-per-landmark", true}});
  if (!flags.ok()) return flags.status();
  absl::StatusOr<ScenarioOptions> options = ScenarioFromFlags(*flags);
  if (!options.ok()) return options.status();
  absl::StatusOr<long long> passages = flags->GetInt("passages", 100),
                            per_landmark = flags->GetInt("detections-per-landmark", 5);
  if (!passages.ok()) return passages.status();
  if (!per_landmark.ok()) return per_landmark.status();
  if (*passages < 1) return UsageError("passages: must be >= 1");
  absl::StatusOr<Scenario> scenario = Scenario::Create(*options);
  if (!scenario.ok()) return scenario.status();
  std::vector<int> indices(*passages);
  std::iota(indices.begin(), indices.end(), 0);
  GraphOptions graph;
  graph.detections_per_landmark = static_cast<int>(*per_landmark);
  int next_report = 1;
  absl::StatusOr<double> bound =
      LoopCramerRaoMeanError(*scenario, indices, graph, 0.0, [&](int done, double mean_error_m) {
        if (done != next_report && done != *passages) return;
        if (done == next_report) next_report *= 10;
        std::cout << absl::StrFormat("passages=%d crlb_mean_dist_err_m=%.4f\n", done, mean_error_m);
      });
  return bound.status();
}

absl::Status RunPoseBiasCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags =
      ParseFlags(args, {{"passages", true}, {"seed", true}, {"bin-s", true}, {"steering-noise-scale", true},
                          {"speed-noise-scale", true}, {"gnss-noise-scale", true}, {"pixel-noise-scale", true},
                          {"quiet", false}});
  if (!flags.ok()) return flags.status();
  PoseBiasOptions options;
  absl::StatusOr<long long> passages = flags->GetInt("passages", options.passages), seed = flags->GetInt("seed", 1);
  absl::StatusOr<double> bin = flags->GetDouble("bin-s", options.bin_s);
  for (const absl::Status& s : {passages.status(), seed.status(), bin.status()}) {
    if (!s.ok()) return s;
  }
  if (absl::Status s = ScaleNoise(*flags, &options.scenario); !s.ok()) return s;
  options.passages = static_cast<int>(*passages);
  options.bin_s = *bin;
  options.scenario.seed = static_cast<uint64_t>(*seed);
  const bool quiet = flags->Has("quiet");
  const int every = std::max(1, options.passages / 20);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<std::vector<PoseBiasBin>> bins = RunPoseBias(options, [&](int done) {
    if (!quiet && (done % every == 0 || done == options.passages)) {
      std::cerr << absl::StrFormat("\rpassage %d/%d   ", done, options.passages) << std::flush;
    }
  });
  if (!quiet) std::cerr << "\n";
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

absl::Status RunPassageConsistencyCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags =
      ParseFlags(args, {{"landmarks", true}, {"passages", true}, {"strategy", true}, {"seed", true},
                          {"detections-per-landmark", true}, {"steering-noise-scale", true},
                          {"speed-noise-scale", true}, {"gnss-noise-scale", true}, {"pixel-noise-scale", true},
                          {"noise", true}, {"quiet", false}});
  if (!flags.ok()) return flags.status();
  PassageConsistencyOptions options;
  absl::StatusOr<NoiseConfig> noise = ParseNoiseConfig(flags->GetString("noise", "white"));
  if (!noise.ok()) return AsUsageError(noise.status());
  options.scenario.noise = *noise;
  absl::StatusOr<long long> landmarks = flags->GetInt("landmarks", 25),
                            passages = flags->GetInt("passages", options.passages), seed = flags->GetInt("seed", 1),
                            per_landmark = flags->GetInt("detections-per-landmark", 5);
  for (const absl::Status& s : {landmarks.status(), passages.status(), seed.status(), per_landmark.status()}) {
    if (!s.ok()) return s;
  }
  absl::StatusOr<UpdateStrategy> strategy = ParseUpdateStrategy(flags->GetString("strategy", "cc"));
  if (!strategy.ok()) return AsUsageError(strategy.status());
  if (absl::Status s = ScaleNoise(*flags, &options.scenario); !s.ok()) return s;
  options.scenario.landmarks = static_cast<int>(*landmarks);
  options.scenario.seed = static_cast<uint64_t>(*seed);
  options.passages = static_cast<int>(*passages);
  options.update.strategy = *strategy;
  options.update.detections_per_landmark = static_cast<int>(*per_landmark);
  const bool quiet = flags->Has("quiet");
  const int every = std::max(1, options.passages / 20);
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  absl::StatusOr<PassageConsistency> result = RunPassageConsistency(options, [&](int done) {
    if (!quiet && (done % every == 0 || done == options.passages)) {
      std::cerr << absl::StrFormat("\rpassage %d/%d   ", done, options.passages) << std::flush;
    }
  });
  if (!quiet) std::cerr << "\n";
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

absl::Status RunReproduceCommand(const std::vector<std::string>& args) {
  absl::StatusOr<Flags> flags =
      ParseFlags(args, {{"out", true},
                          {"passages", true},
                          {"jobs", true},
                          {"seed", true},
                          {"seeds", true},
                          {"nees-sd-target", true},
                          {"max-seeds", true}});
  if (!flags.ok()) return flags.status();
  ReproduceOptions options;
  absl::StatusOr<long long> passages = flags->GetInt("passages", options.passages),
                            jobs = flags->GetInt("jobs", options.jobs), seed = flags->GetInt("seed", 1),
                            seeds = flags->GetInt("seeds", options.seeds),
                            max_seeds = flags->GetInt("max-seeds", options.max_seeds);
  absl::StatusOr<double> sd_target = flags->GetDouble("nees-sd-target", options.nees_sd_target);
  for (const absl::Status& s :
       {passages.status(), jobs.status(), seed.status(), seeds.status(), max_seeds.status(), sd_target.status()}) {
    if (!s.ok()) return s;
  }
  options.out_dir = flags->GetString("out", options.out_dir);
  options.passages = static_cast<int>(*passages);
  options.jobs = static_cast<int>(*jobs);
  options.seed = static_cast<uint64_t>(*seed);
  options.seeds = static_cast<int>(*seeds);
  options.max_seeds = static_cast<int>(*max_seeds);
  options.nees_sd_target = *sd_target;
  return RunReproduction(options);
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
  std::vector<std::string> args(argv + 1, argv + argc);
  if (!args.empty() && args[0] == "--version") {
    std::cout << "mapsim (crowdmap) " << CROWDMAP_VERSION << "\n";
    return 0;
  }
  if (args.empty()) {
    std::cerr << crowdmap::kUsage;
    return crowdmap::kExitUsage;
  }
  if (args[0] == "--help" || args[0] == "-h" || args[0] == "help") {
    std::cout << crowdmap::kUsage;
    return crowdmap::kExitOk;
  }
  const std::string command = args[0];
  args.erase(args.begin());
  for (const std::string& a : args) {
    if (a == "--help" || a == "-h") {
      std::cout << crowdmap::kUsage;
      return 0;
    }
  }
  absl::Status status;
  if (command == "experiment") {
    status = crowdmap::RunExperimentCommand(args);
  } else if (command == "city") {
    status = crowdmap::RunCityCommand(args);
  } else if (command == "reproduce") {
    status = crowdmap::RunReproduceCommand(args);
  } else if (command == "localize") {
    status = crowdmap::RunLocalizeCommand(args);
  } else if (command == "crlb") {
    status = crowdmap::RunCrlbCommand(args);
  } else if (command == "pose-bias") {
    status = crowdmap::RunPoseBiasCommand(args);
  } else if (command == "passage-consistency") {
    status = crowdmap::RunPassageConsistencyCommand(args);
#if CROWDMAP_MAPSIM_SERVICE
  } else if (command == "fleet") {
    status = crowdmap::RunFleetCommand(args);
  } else if (command == "export-passages") {
    status = crowdmap::RunExportPassagesCommand(args);
  } else if (command == "bench") {
    status = crowdmap::RunBenchCommand(args);
#endif
  } else {
    std::cerr << "mapsim: unknown command '" << command << "' (see mapsim --help)\n";
    return crowdmap::kExitUsage;
  }
  if (crowdmap::IsUsageError(status)) {
    std::cerr << "mapsim " << command << ": " << status.message() << " (see mapsim --help)\n";
  } else if (!status.ok()) {
    std::cerr << "mapsim " << command << ": " << status.message() << "\n";
  }
  return crowdmap::ExitCodeFor(status);
}
