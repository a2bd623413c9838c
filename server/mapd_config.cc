#include "server/mapd_config.h"

#include <cmath>
#include <fstream>
#include <map>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/strip.h"
#include "server/request_log.h"
#include "server/security_config.h"

namespace crowdmap {
namespace {

const std::vector<std::string>& SettingNames() {
  static const std::vector<std::string> kNames = {
      "listen", "db", "strategy", "max-subgraph-dim", "window-hops", "warmup-passages", "relinearize-until-passages", "workers",
      "retain-passages", "worker-nice", "max-queue", "max-message-mb", "max-passage-mb", "log-level",
      "max-detection-residual-sigmas", "max-landmark-shift-sigmas", "max-new-landmark-ray-sigma-m",
      "max-chi2-per-dof", "metrics-listen", "http-listen", "viewer-basemap", "log-format", "create",
      "estimate-camera-yaw"};
  return kNames;
}

bool IsSetting(const std::string& name) {
  for (const std::string& n : SettingNames()) {
    if (n == name) return true;
  }
  for (const std::string& n : SecuritySettingNames()) {
    if (n == name) return true;
  }
  return false;
}

std::string EnvName(const std::string& flag) {
  return absl::StrCat("MAPD_", absl::AsciiStrToUpper(absl::StrReplaceAll(flag, {{"-", "_"}})));
}

absl::Status ReadConfigFile(const std::string& path, std::map<std::string, std::string>* values) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("config: cannot read ", path));
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    absl::string_view text = line;
    if (const size_t hash = text.find('#'); hash != absl::string_view::npos) text = text.substr(0, hash);
    text = absl::StripAsciiWhitespace(text);
    if (text.empty()) continue;
    const size_t eq = text.find_first_of("=:");
    if (eq == absl::string_view::npos) {
      return absl::InvalidArgumentError(absl::StrCat(path, ":", number, ": expected \"name = value\""));
    }
    std::string name(absl::StripAsciiWhitespace(text.substr(0, eq)));
    std::string value(absl::StripAsciiWhitespace(text.substr(eq + 1)));
    absl::StrReplaceAll({{"_", "-"}}, &name);
    if (!IsSetting(name)) return absl::InvalidArgumentError(absl::StrCat(path, ":", number, ": unknown setting ", name));
    (*values)[name] = value;
  }
  return absl::OkStatus();
}

absl::StatusOr<int64_t> ToInt(const std::string& name, const std::string& value) {
  int64_t v = 0;
  if (!absl::SimpleAtoi(value, &v)) return absl::InvalidArgumentError(absl::StrCat("--", name, ": expected an integer, got '", value, "'"));
  return v;
}

absl::StatusOr<bool> ToBool(const std::string& name, const std::string& value) {
  const std::string v = absl::AsciiStrToLower(value);
  if (v == "true" || v == "1" || v == "yes") return true;
  if (v == "false" || v == "0" || v == "no") return false;
  return absl::InvalidArgumentError(absl::StrCat("--", name, ": expected true or false, got '", value, "'"));
}

absl::StatusOr<double> ToDouble(const std::string& name, const std::string& value) {
  double v = 0.0;
  if (!absl::SimpleAtod(value, &v)) return absl::InvalidArgumentError(absl::StrCat("--", name, ": expected a number, got '", value, "'"));
  return v;
}

// The settings of the map update's trust rules (MapUpdateOptions): true when `name` is one.
absl::StatusOr<bool> SetTrustRule(const std::string& name, const std::string& value, MapUpdateOptions* update) {
  if (name != "max-detection-residual-sigmas" && name != "max-landmark-shift-sigmas" &&
      name != "max-new-landmark-ray-sigma-m" && name != "max-chi2-per-dof") {
    return false;
  }
  absl::StatusOr<double> v = ToDouble(name, value);
  if (!v.ok()) return v.status();
  if (name == "max-detection-residual-sigmas") update->max_detection_residual_sigmas = *v;
  if (name == "max-landmark-shift-sigmas") update->max_landmark_shift_mahalanobis2 = *v * *v;
  if (name == "max-new-landmark-ray-sigma-m") update->max_new_landmark_ray_sigma_m = *v;
  if (name == "max-chi2-per-dof") update->max_chi2_per_dof = *v;
  return true;
}

}  // namespace

std::string MapdUsage() {
  return R"(mapd: the crowdsourced landmark map service (gRPC, mapservice.v1).

Usage: mapd [--flag value | --flag=value]...

  --listen ADDR               host:port to serve on (default 127.0.0.1:50051)
  --db PATH                   SQLite map database, created on first start (default ./var/map.db);
                              the passage queue is kept beside it in PATH.queue
  --strategy NAME             map update strategy: cc | dc | cc-gsd (default cc-gsd)
  --max-subgraph-dim N        largest subgraph state dimension with cc-gsd (default 500)
  --window-hops N             after each subgraph the map is re-solved, and covariances are
                              recovered, within N links (shared factors) of its landmarks;
                              outside covariances are conservative (default 0: whole map, exact)
  --warmup-passages N         a new map's first N passages are solved jointly, re-solved with
                              each one, so their arrival order does not stay in the map
                              (default 8; 0 = off; see README)
  --relinearize-until-passages N  after the warm-up, the map's passages are all re-solved jointly
                              each time their count doubles (16, 32, ...), up to N passages, so
                              that none stays in the map as taken at a young map's poor estimate
                              (default 128; 0 = off; see README)
  --workers N                 worker threads (default 1). They claim and decode passages in
                              parallel, but map updates are applied one at a time in arrival
                              order, so the map is the same for any N.
  --retain-passages N         the factors of the last N applied passages are kept apart, so that
                              such a passage can be excluded (ExcludePassage); older ones are
                              folded into the map's base, which keeps the storage bounded
                              (default 256; at least the young map's joint solves; 0 = keep all)
  --worker-nice N             scheduling niceness of the worker threads, 0..19 (default 10): map
                              updates yield the CPU to requests, so reads stay fast under load
  --max-queue N               passages queued or processing before uploads get
                              RESOURCE_EXHAUSTED (default 10000; 0 = unbounded)
  --max-message-mb N          gRPC receive limit per message, MiB (default 4); larger passages
                              use UploadPassageChunked
  --max-passage-mb N          largest accepted passage, MiB (default 64)
  --max-detection-residual-sigmas X  a detection whose residual at a subgraph's solution exceeds X
                              pixel sigmas is set aside as an outlier (default 5; 0 = off)
  --max-landmark-shift-sigmas X  a map landmark a subgraph's solve would move further than X of
                              the map's sigmas is set aside for that passage (default 5; 0 = off)
  --max-new-landmark-ray-sigma-m X  a new landmark is created only when its own rays fix it to X
                              metres (default 3)
  --max-chi2-per-dof X        refuse a passage when a subgraph's solve leaves chi2 above X per
                              degree of freedom (default 0 = never; see README)
  --estimate-camera-yaw B     estimate each vehicle's camera yaw offset in its passages' graphs,
                              its history as the prior, and keep it (GetVehicle, mapctl vehicles;
                              default true; false: declared calibrations are taken as exact)
  --create                    create a new, empty map when --db does not exist yet (or is an
                              empty file), with its directory; without it mapd refuses to start
                              there, so that a mistyped path cannot start an empty map
  --metrics-listen ADDR       serve Prometheus metrics on http://ADDR/metrics (default: none;
                              e.g. 127.0.0.1:9464; the endpoint has no authentication)
  --http-listen ADDR          serve the map viewer on http://ADDR/ (default: none; e.g.
                              127.0.0.1:8080). With authentication on, its /api/ needs the
                              same bearer tokens as gRPC
  --viewer-basemap URL        XYZ tile URL template for the viewer's basemap, e.g.
                              https://tile.example.org/{z}/{x}/{y}.png (default: none, no tiles)
  --log-level LEVEL           trace | debug | info | warn | error | off (default info)
  --log-format FORMAT         text (key=value lines) | json (one JSON object per line)
                              (default text)
  --config PATH               settings file: "name = value" lines with the names above
  --version                   print the version and exit
  --help                      this text
)" + SecurityUsage() + R"(
Every setting also reads the environment (MAPD_LISTEN, MAPD_DB, MAPD_MAX_QUEUE, ...; MAPD_CONFIG for
the file). Precedence: flag, environment, config file, default.
SIGTERM / SIGINT: health turns NOT_SERVING, uploads are refused (UNAVAILABLE), the passage being
applied is finished, and mapd exits 0. SIGHUP: the --auth-file is read again.
)";
}

absl::StatusOr<MapdConfig> ParseMapdConfig(const std::vector<std::string>& args, const EnvLookup& env) {
  std::map<std::string, std::string> flags;
  std::string config_path;
  MapdConfig config;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a == "--help" || a == "-h") {
      config.help = true;
      continue;
    }
    if (a == "--version") {
      config.version = true;
      continue;
    }
    if (a == "--create") {
      flags["create"] = "true";
      continue;
    }
    if (a.rfind("--", 0) != 0) return absl::InvalidArgumentError(absl::StrCat("unexpected argument '", a, "'"));
    std::string name = a.substr(2), value;
    if (const size_t eq = name.find('='); eq != std::string::npos) {
      value = name.substr(eq + 1);
      name = name.substr(0, eq);
    } else {
      if (i + 1 >= args.size()) return absl::InvalidArgumentError(absl::StrCat("--", name, ": needs a value"));
      value = args[++i];
    }
    if (name == "config") {
      config_path = value;
    } else if (IsSetting(name)) {
      flags[name] = value;
    } else {
      return absl::InvalidArgumentError(absl::StrCat("unknown flag --", name, " (see --help)"));
    }
  }

  std::map<std::string, std::string> values;
  if (config_path.empty() && env("MAPD_CONFIG") != nullptr) config_path = env("MAPD_CONFIG");
  if (!config_path.empty()) {
    if (auto s = ReadConfigFile(config_path, &values); !s.ok()) return s;
  }
  for (const std::vector<std::string>* names : {&SettingNames(), &SecuritySettingNames()}) {
    for (const std::string& name : *names) {
      if (const char* v = env(EnvName(name).c_str()); v != nullptr) values[name] = v;
    }
  }
  for (const auto& [name, value] : flags) values[name] = value;

  MapServerOptions& o = config.server;
  o.create_db = false;  // mapd creates a map only when told to (--create)
  o.worker.update.estimate_camera_yaw = true;
  for (const auto& [name, value] : values) {
    if (name == "listen") {
      o.listen = value;
    } else if (name == "db") {
      o.db_path = value;
    } else if (name == "strategy") {
      auto strategy = ParseUpdateStrategy(value);
      if (!strategy.ok()) return absl::InvalidArgumentError(absl::StrCat("--strategy: ", strategy.status().message()));
      o.worker.update.strategy = *strategy;
    } else if (absl::StatusOr<bool> security = SetSecuritySetting(name, value, &o); !security.ok() || *security) {
      if (!security.ok()) return security.status();
    } else if (name == "log-level") {
      config.log_level = value;
    } else if (name == "log-format") {
      if (value != "text" && value != "json") {
        return absl::InvalidArgumentError(absl::StrCat("--log-format: expected text or json, got '", value, "'"));
      }
      config.log_format = value;
    } else if (name == "metrics-listen") {
      o.metrics_listen = value;
    } else if (name == "http-listen") {
      o.http_listen = value;
    } else if (name == "viewer-basemap") {
      o.viewer_basemap = value;
    } else if (name == "create") {
      absl::StatusOr<bool> create = ToBool(name, value);
      if (!create.ok()) return create.status();
      o.create_db = *create;
    } else if (name == "estimate-camera-yaw") {
      absl::StatusOr<bool> estimate = ToBool(name, value);
      if (!estimate.ok()) return estimate.status();
      o.worker.update.estimate_camera_yaw = *estimate;
    } else if (absl::StatusOr<bool> rule = SetTrustRule(name, value, &o.worker.update); !rule.ok() || *rule) {
      if (!rule.ok()) return rule.status();
    } else {
      auto v = ToInt(name, value);
      if (!v.ok()) return v.status();
      if (name == "max-subgraph-dim") o.worker.update.max_subgraph_dim = static_cast<int>(*v);
      if (name == "window-hops") o.worker.update.window_hops = static_cast<int>(*v);
      if (name == "retain-passages") o.worker.update.retain_passages = static_cast<int>(*v);
      if (name == "warmup-passages") o.worker.update.warmup_passages = static_cast<int>(*v);
      if (name == "relinearize-until-passages") o.worker.update.relinearize_until_passages = static_cast<int>(*v);
      if (name == "workers") o.worker.workers = static_cast<int>(*v);
      if (name == "worker-nice") o.worker.nice = static_cast<int>(*v);
      if (name == "max-queue") o.max_queue = *v;
      if (name == "max-message-mb") o.max_message_mb = static_cast<int>(*v);
      if (name == "max-passage-mb") o.max_passage_mb = static_cast<int>(*v);
    }
  }
  if (auto s = o.Validate(); !s.ok()) return s;
  return config;
}

std::string DescribeMapdConfig(const MapdConfig& config) {
  const MapServerOptions& o = config.server;
  const MapUpdateOptions& u = o.worker.update;
  return absl::StrCat(
      "listen=", EscapeForLog(o.listen), " db=", EscapeForLog(o.db_path), " create=", o.create_db ? "true" : "false",
      " strategy=", UpdateStrategyName(u.strategy), " max-subgraph-dim=", u.max_subgraph_dim,
      " window-hops=", u.window_hops, " warmup-passages=", u.warmup_passages,
      " relinearize-until-passages=", u.relinearize_until_passages, " retain-passages=", u.retain_passages,
      " workers=", o.worker.workers, " worker-nice=", o.worker.nice, " max-queue=", o.max_queue,
      " max-message-mb=", o.max_message_mb, " max-passage-mb=", o.max_passage_mb,
      " max-detection-residual-sigmas=", u.max_detection_residual_sigmas,
      " max-landmark-shift-sigmas=", std::sqrt(u.max_landmark_shift_mahalanobis2),
      " max-new-landmark-ray-sigma-m=", u.max_new_landmark_ray_sigma_m, " max-chi2-per-dof=", u.max_chi2_per_dof,
      " estimate-camera-yaw=", u.estimate_camera_yaw ? "true" : "false",
      " metrics-listen=", o.metrics_listen.empty() ? "none" : EscapeForLog(o.metrics_listen),
      " http-listen=", o.http_listen.empty() ? "none" : EscapeForLog(o.http_listen),
      " viewer-basemap=", o.viewer_basemap.empty() ? "none" : EscapeForLog(o.viewer_basemap),
      " log-level=", EscapeForLog(config.log_level), " log-format=", config.log_format);
}

}  // namespace crowdmap
