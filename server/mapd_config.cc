#include "server/mapd_config.h"

#include <cmath>
#include <cstdlib>
#include <istream>
#include <memory>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/strip.h"
#include "server/request_log.h"
#include "server/security_config.h"

namespace crowdmap {
namespace {

constexpr char kFooter[] = R"(Every setting also reads the environment (MAPD_LISTEN, MAPD_DB, MAPD_MAX_QUEUE, ...; MAPD_CONFIG for
the file). Precedence: flag, environment, config file, default.
SIGTERM / SIGINT: health turns NOT_SERVING, uploads are refused (UNAVAILABLE), the passage being
applied is finished, and mapd exits 0. SIGHUP: the --auth-file is read again.)";

// mapd's config file, read by CLI11: "name = value" or "name: value" lines, '#' comments, names as
// the flags without "--" ('_' for '-' too), the value taken as it is. CLI11 reads the file before
// the environment, and the environment only into settings still unset (book, "CLI11 Internals":
// _process_ini, then _process_env), so the file would win; a setting whose environment variable
// is set is therefore left out here, for mapd's order is flag, environment, file.
class MapdConfigFile : public CLI::Config {
 public:
  explicit MapdConfigFile(const CLI::App* mapd) : mapd_(mapd) {}

  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override {
    std::vector<CLI::ConfigItem> items;
    std::string line;
    for (int number = 1; std::getline(input, line); ++number) {
      absl::string_view text = line;
      if (const size_t hash = text.find('#'); hash != absl::string_view::npos) text = text.substr(0, hash);
      text = absl::StripAsciiWhitespace(text);
      if (text.empty()) continue;
      const std::string where = absl::StrCat(mapd_->get_config_ptr()->as<std::string>(), ":", number, ": ");
      const size_t eq = text.find_first_of("=:");
      if (eq == absl::string_view::npos) throw CLI::ConfigError(where + "expected \"name = value\"");
      CLI::ConfigItem item;
      item.name = absl::StrReplaceAll(absl::StripAsciiWhitespace(text.substr(0, eq)), {{"_", "-"}});
      item.inputs = {std::string(absl::StripAsciiWhitespace(text.substr(eq + 1)))};
      const CLI::Option* setting = mapd_->get_option_no_throw("--" + item.name);
      if (setting == nullptr || !setting->get_configurable()) {
        throw CLI::ConfigError(where + "unknown setting " + item.name);
      }
      const char* env = std::getenv(setting->get_envname().c_str());
      if (env != nullptr && *env != '\0') continue;
      items.push_back(std::move(item));
    }
    return items;
  }

  // mapd reads config files only.
  std::string to_config(const CLI::App*, bool, bool, std::string) const override { return ""; }

 private:
  const CLI::App* mapd_;
};

// A setting given in sigmas and kept as the squared Mahalanobis distance `*mahalanobis2`.
void AddSigmasSetting(CLI::App* app, const std::string& name, double* mahalanobis2, const std::string& description) {
  app->add_option_function<double>(
         "--" + name, [mahalanobis2](double sigmas) { *mahalanobis2 = sigmas * sigmas; }, description)
      ->envname(MapdEnvName(name))
      ->check(CLI::NonNegativeNumber)
      ->default_val(std::sqrt(*mahalanobis2))
      ->type_name("X");
}

// mapd's command line, its settings bound to `config`.
std::unique_ptr<CLI::App> NewMapdCommandLine(MapdConfig* config) {
  auto mapd = std::make_unique<CLI::App>("mapd: the crowdsourced landmark map service (gRPC, mapservice.v1).", "mapd");
  mapd->option_defaults()->always_capture_default()->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  mapd->get_formatter()->column_width(34);
  mapd->footer(kFooter);
  CLI::App* app = mapd.get();
  MapServerOptions& o = config->server;
  MapUpdateOptions& u = o.worker.update;
  u = MapdDefaultUpdateOptions();
  o.create_db = false;  // mapd creates a map only when told to (--create)
  AddMapdSetting(app, "listen", &o.listen, "host:port to serve on")->type_name("ADDR");
  AddMapdSetting(app, "db", &o.db_path,
                 "SQLite map database, created on first start; the passage queue is kept beside it in\n"
                 "PATH.queue")
      ->type_name("PATH");
  app->add_option_function<std::string>(
         "--strategy",
         [&u](const std::string& name) {
           absl::StatusOr<UpdateStrategy> strategy = ParseUpdateStrategy(name);
           if (!strategy.ok()) throw CLI::ValidationError("--strategy", std::string(strategy.status().message()));
           u.strategy = *strategy;
         },
         "map update strategy: cc | dc | cc-gsd")
      ->envname(MapdEnvName("strategy"))
      ->default_str(UpdateStrategyName(u.strategy))
      ->type_name("NAME");
  AddMapdSetting(app, "max-subgraph-dim", &u.max_subgraph_dim, "largest subgraph state dimension with cc-gsd")
      ->type_name("N");
  AddMapdSetting(app, "window-hops", &u.window_hops,
                 "covariances are recovered, and the map re-solved after each passage, within N links\n"
                 "(shared factors) of the passage's landmarks (of a read's, for reads); outside covariances\n"
                 "are conservative (0: whole map, exact; 2 at city scale)")
      ->type_name("N");
  AddMapdSetting(app, "read-window-hops", &o.read_window_hops,
                 "links of the window a read's covariances come from (-1: as --window-hops). Fewer make reads\n"
                 "faster and their sigmas wider, never narrower than exact: on a 10k-landmark city, a 500 m\n"
                 "box with cross-covariances took 54-58 ms with 2 links (sigmas 1% wider than exact) and 27-29\n"
                 "ms with 1 (6% wider on average, 34% at most; docs/results.md)")
      ->type_name("N");
  AddMapdSetting(app, "detections-per-landmark", &u.detections_per_landmark,
                 "detections used per landmark and passage: the last N of the frames 0.5 s and 1 m of travel\n"
                 "apart (0: all of them, >= 3 otherwise). All gave the simulator's city fleets 20% less\n"
                 "error over ten seeds with NEES/dof 0.94-0.99 against 0.89-0.90, an independent fleet 5%\n"
                 "less; but the vehicles' camera-yaw records grow over-confident on a road driven the same\n"
                 "way many times, and a camera error not estimated costs more, so the default stays the\n"
                 "thesis's 5 (docs/results.md, \"All detections on the thesis loop\")")
      ->type_name("N");
  AddMapdSetting(app, "spread-detections", &u.spread_detections,
                 "take the N detections spread evenly over each landmark's track (its first and last frames\n"
                 "among them) instead of the last N: more parallax where a narrow lens loses landmarks far\n"
                 "down the street (the simulator's city: 17% less error with 50-110 degree lenses, 13% with\n"
                 "the thesis camera, no gain with AR(1) GNSS; the thesis loop 6-15%, one seed's joint\n"
                 "NEES/dof 1.16 -> 1.44; 25% more with a camera yaw error left unestimated; docs/results.md)")
      ->type_name("BOOL");
  AddMapdSetting(app, "warmup-passages", &u.warmup_passages,
                 "a new map's first N passages are solved jointly, re-solved with each one, so their arrival\n"
                 "order does not stay in the map (0 = off; see README)")
      ->type_name("N");
  AddMapdSetting(app, "relinearize-until-passages", &u.relinearize_until_passages,
                 "after the warm-up, the map's passages are all re-solved jointly each time their count\n"
                 "doubles (16, 32, ...), up to N passages, so that none stays in the map as taken at a\n"
                 "young map's poor estimate (0 = off; see README)")
      ->type_name("N");
  AddMapdSetting(app, "relinearize-sigmas", &u.relinearize_sigmas,
                 "local re-linearisation: the retained passage whose landmarks moved furthest since its\n"
                 "factors were taken is taken again at today's estimate when that move exceeds X of their\n"
                 "current sigmas; a rule per street, not per map, so a street first mapped on day 300 gets\n"
                 "it too. Done while the queue is empty, so a backlog is applied at full speed (0 = off;\n"
                 "a district first driven at passage 150 had 13% less error with 6, 15% with 0.5, which\n"
                 "re-linearises twice as often: docs/results.md, \"A district mapped late\")")
      ->type_name("X");
  AddMapdSetting(app, "relinearizations-per-passage", &u.relinearizations_per_passage,
                 "N such re-linearisations owed for each passage applied (at most 256 owed; `mapctl info`\n"
                 "shows them)")
      ->type_name("N");
  AddMapdSetting(app, "workers", &o.worker.workers,
                 "worker threads, each computing one passage's update against the map as committed when it\n"
                 "began. An update is committed only if no update committed meanwhile changed what it read\n"
                 "(its neighbourhood), else computed again: the map is the one the passages give applied one\n"
                 "at a time in commit order. With several, each takes among the passages claimed ahead\n"
                 "the one furthest from those being computed; 1 applies them in arrival order. 2 on a\n"
                 "2-core machine applied 100k-landmark city passages 1.64-1.77x as fast, a 1k-landmark\n"
                 "city's no faster (scripts/workers-bench.sh).")
      ->type_name("N");
  AddMapdSetting(app, "retain-passages", &u.retain_passages,
                 "the factors of the last N applied passages are kept apart, so that such a passage can be\n"
                 "excluded (ExcludePassage); older ones are folded into the map's base, which keeps the\n"
                 "storage bounded (at least the young map's joint solves; 0 = keep all)")
      ->type_name("N");
  AddMapdSetting(app, "settled-upload-retention-days", &o.worker.settled_upload_retention_days,
                 "the uploads of passages that ended rejected, excluded or discarded are deleted this many days\n"
                 "after (their records stay; failed and quarantined ones keep theirs for a requeue; 0 = keep\n"
                 "for good)")
      ->type_name("D");
  AddMapdSetting(app, "worker-nice", &o.worker.nice,
                 "scheduling niceness of the worker threads, 0..19: map updates yield the CPU to requests,\n"
                 "so reads stay fast under load")
      ->type_name("N");
  AddMapdSetting(app, "max-queue", &o.max_queue,
                 "passages queued or processing before uploads get RESOURCE_EXHAUSTED (0 = unbounded)")
      ->type_name("N");
  AddMapdSetting(app, "max-message-mb", &o.max_message_mb,
                 "gRPC receive limit per message, MiB; larger passages use UploadPassageChunked")
      ->type_name("N");
  AddMapdSetting(app, "max-passage-mb", &o.max_passage_mb, "largest accepted passage, MiB")->type_name("N");
  AddMapdSetting(app, "max-detection-residual-sigmas", &u.max_detection_residual_sigmas,
                 "a detection whose residual at a subgraph's solution exceeds X pixel sigmas is set aside\n"
                 "as an outlier (0 = off)")
      ->type_name("X");
  AddMapdSetting(app, "max-unfit-detection-fraction", &u.max_unfit_detection_fraction,
                 "a passage more than X of whose detections are set aside as outliers (10 at least) is\n"
                 "quarantined, the map unchanged (0 = off)")
      ->type_name("X");
  AddMapdSetting(app, "sensor-test-sigmas", &u.sensor_test_sigmas,
                 "a sensor (odometry, GNSS, camera) whose residuals' chi-square exceeds their redundancy by X\n"
                 "sigmas has its declared covariances scaled by their ratio for that subgraph (0 = off)")
      ->type_name("X");
  AddSigmasSetting(app, "max-landmark-shift-sigmas", &u.max_landmark_shift_mahalanobis2,
                   "a map landmark a subgraph's solve would move further than X of the map's sigmas is set\n"
                   "aside for that passage (0 = off)");
  AddSigmasSetting(app, "max-update-shift-sigmas", &u.max_update_shift_mahalanobis2,
                   "a passage whose update would move a landmark seen by 10 or more passages further than X of\n"
                   "its sigmas is quarantined, the map unchanged (0 = off)");
  AddMapdSetting(app, "max-new-landmark-ray-sigma-m", &u.max_new_landmark_ray_sigma_m,
                 "a new landmark is created only when its own rays fix it to X metres")
      ->type_name("X");
  AddMapdSetting(app, "max-new-landmark-bias-sigmas", &u.max_new_landmark_bias_sigmas,
                 "...and when the second-order bias correction moves it by at most X of its sigmas (0 = no\n"
                 "such test)")
      ->type_name("X");
  AddMapdSetting(app, "max-chi2-per-dof", &u.max_chi2_per_dof,
                 "refuse a passage when a subgraph's solve leaves chi2 above X per degree of freedom (0 =\n"
                 "never; see README)")
      ->type_name("X");
  AddMapdSetting(app, "estimate-camera-yaw", &u.estimate_camera_yaw,
                 "estimate each vehicle's camera yaw offset in its passages' graphs, its history as the\n"
                 "prior, and keep it (GetVehicle, mapctl vehicles; false: declared calibrations are taken\n"
                 "as exact)")
      ->type_name("BOOL");
  AddMapdSetting(app, "speed-scale-prior-sigma", &u.speed_scale_prior_sigma,
                 "estimate each passage's wheel-speed scale (tyre radius, pressure, wear), prior mean 1 with\n"
                 "this sigma (0: the encoders' speeds are taken as unbiased)")
      ->type_name("X");
  AddMapdSetting(app, "correlated-gnss-min-lag1", &u.correlated_gnss_min_lag1,
                 "a passage declaring white GNSS noise whose fixes' residuals against its own trajectory\n"
                 "have a lag-1 correlation above X (errors correlated over minutes: most receivers) is\n"
                 "estimated with a Gauss-Markov process instead (0 = off: declared noise taken as it is)")
      ->type_name("X");
  AddMapdSetting(app, "fleet-yaw-prior-vehicles", &u.fleet_camera_yaw_prior_vehicles,
                 "with estimate-camera-yaw: once the map has N vehicles' records, a new vehicle's camera\n"
                 "yaw prior is centred on the fleet's mean (width their spread, at least 1 degree) instead\n"
                 "of 0 (0 = off)")
      ->type_name("N");
  app->add_flag("--create", o.create_db,
                "create a new, empty map when --db does not exist yet (or is an empty file), with its\n"
                "directory; without it mapd refuses to start there, so that a mistyped path cannot start\n"
                "an empty map")
      ->envname(MapdEnvName("create"));
  AddMapdSetting(app, "metrics-listen", &o.metrics_listen,
                 "serve Prometheus metrics on http://ADDR/metrics (default: none; e.g. 127.0.0.1:9464; the\n"
                 "endpoint has no authentication)")
      ->type_name("ADDR");
  AddMapdSetting(app, "http-listen", &o.http_listen,
                 "serve the map viewer on http://ADDR/ (default: none; e.g. 127.0.0.1:8080). With\n"
                 "authentication on, its /api/ needs the same bearer tokens as gRPC")
      ->type_name("ADDR");
  AddMapdSetting(app, "viewer-basemap", &o.viewer_basemap,
                 "XYZ tile URL template for the viewer's basemap, e.g.\n"
                 "https://tile.example.org/{z}/{x}/{y}.png (default: none, no tiles)")
      ->type_name("URL");
  AddMapdSetting(app, "log-level", &config->log_level, "trace | debug | info | warn | error | off")
      ->type_name("LEVEL");
  AddMapdSetting(app, "log-format", &config->log_format,
                 "text (key=value lines) | json (one JSON object per line)")
      ->check(CLI::IsMember({"text", "json"}))
      ->type_name("FORMAT");
  // CLI11 2.1 reads no environment variable for the config file option (2.4 does, CLI11 #891):
  // MAPD_CONFIG is its default instead, then required to exist.
  const char* env_config = std::getenv("MAPD_CONFIG");
  const std::string config_file = env_config != nullptr ? env_config : "";
  app->set_config("--config", config_file, "settings file: \"name = value\" lines with the names above",
                  !config_file.empty())
      ->type_name("PATH");
  app->config_formatter(std::make_shared<MapdConfigFile>(app));
  // A plain flag rather than CLI11's version flag, which would stop before the settings are read:
  // `mapd --config FILE --version` checks FILE.
  app->add_flag("--version", config->version, "print the version and exit")->configurable(false);
  AddSecuritySettings(app, &o);
  return mapd;
}

}  // namespace

std::string MapdEnvName(const std::string& name) {
  return absl::StrCat("MAPD_", absl::AsciiStrToUpper(absl::StrReplaceAll(name, {{"-", "_"}})));
}

std::string MapdUsage() {
  MapdConfig defaults;
  return NewMapdCommandLine(&defaults)->help();
}

absl::StatusOr<MapdConfig> ParseMapdConfig(const std::vector<std::string>& args) {
  MapdConfig config;
  std::unique_ptr<CLI::App> mapd = NewMapdCommandLine(&config);
  std::vector<std::string> reversed(args.rbegin(), args.rend());  // CLI11 takes the arguments from the back
  try {
    mapd->parse(reversed);
  } catch (const CLI::CallForHelp&) {
    config.help = true;
    return config;
  } catch (const CLI::ParseError& e) {
    return absl::InvalidArgumentError(e.what());
  }
  if (auto s = config.server.Validate(); !s.ok()) return s;
  return config;
}

std::vector<std::string> MapdConfigCaveats(const MapdConfig& config) {
  const MapUpdateOptions& u = config.server.worker.update;
  const int read_hops = config.server.read_window_hops < 0 ? u.window_hops : config.server.read_window_hops;
  if (u.retain_passages == 0 || (u.window_hops == 0 && read_hops == 0)) return {};
  return {absl::StrCat(
      "window-hops=", u.window_hops, " read-window-hops=", read_hops, " with retain-passages=", u.retain_passages,
      ": a bounded window's covariances are conservative only while the passages around it are retained; once "
      "passages are folded into the map's base, they can be narrower than exact, which reads say in "
      "covariance_bound (docs/results.md, 'Bounded windows over folded passages'). 0 for both = the whole map, exact")};
}

MapUpdateOptions MapdDefaultUpdateOptions() {
  MapUpdateOptions u;
  u.estimate_camera_yaw = true;
  u.fleet_camera_yaw_prior_vehicles = 10;
  u.relinearize_sigmas = 6.0;
  return u;
}

std::string DescribeMapdConfig(const MapdConfig& config) {
  const MapServerOptions& o = config.server;
  const MapUpdateOptions& u = o.worker.update;
  return absl::StrCat(
      "listen=", EscapeForLog(o.listen), " db=", EscapeForLog(o.db_path), " create=", o.create_db ? "true" : "false",
      " strategy=", UpdateStrategyName(u.strategy), " max-subgraph-dim=", u.max_subgraph_dim,
      " detections-per-landmark=", u.detections_per_landmark,
      " spread-detections=", u.spread_detections ? "true" : "false", " window-hops=", u.window_hops, " read-window-hops=", o.read_window_hops, " warmup-passages=", u.warmup_passages,
      " relinearize-until-passages=", u.relinearize_until_passages, " relinearize-sigmas=", u.relinearize_sigmas,
      " relinearizations-per-passage=", u.relinearizations_per_passage, " retain-passages=", u.retain_passages,
      " workers=", o.worker.workers, " worker-nice=", o.worker.nice,
      " settled-upload-retention-days=", o.worker.settled_upload_retention_days, " max-queue=", o.max_queue,
      " max-message-mb=", o.max_message_mb, " max-passage-mb=", o.max_passage_mb,
      " max-detection-residual-sigmas=", u.max_detection_residual_sigmas,
      " max-unfit-detection-fraction=", u.max_unfit_detection_fraction, " sensor-test-sigmas=", u.sensor_test_sigmas,
      " max-landmark-shift-sigmas=", std::sqrt(u.max_landmark_shift_mahalanobis2),
      " max-update-shift-sigmas=", std::sqrt(u.max_update_shift_mahalanobis2),
      " max-new-landmark-ray-sigma-m=", u.max_new_landmark_ray_sigma_m,
      " max-new-landmark-bias-sigmas=", u.max_new_landmark_bias_sigmas, " max-chi2-per-dof=", u.max_chi2_per_dof,
      " estimate-camera-yaw=", u.estimate_camera_yaw ? "true" : "false",
      " fleet-yaw-prior-vehicles=", u.fleet_camera_yaw_prior_vehicles,
      " speed-scale-prior-sigma=", u.speed_scale_prior_sigma,
      " correlated-gnss-min-lag1=", u.correlated_gnss_min_lag1,
      " metrics-listen=", o.metrics_listen.empty() ? "none" : EscapeForLog(o.metrics_listen),
      " http-listen=", o.http_listen.empty() ? "none" : EscapeForLog(o.http_listen),
      " viewer-basemap=", o.viewer_basemap.empty() ? "none" : EscapeForLog(o.viewer_basemap),
      " log-level=", EscapeForLog(config.log_level), " log-format=", config.log_format);
}

}  // namespace crowdmap
