#ifndef CROWDMAP_SERVER_MAPD_CONFIG_H_
#define CROWDMAP_SERVER_MAPD_CONFIG_H_

#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "server/map_server.h"

namespace crowdmap {

struct MapdConfig {
  MapServerOptions server;
  std::string log_level = "info";  // trace | debug | info | warn | error | off
  std::string log_format = "text";  // text (key=value lines) | json (one object per line)
  bool help = false;
  bool version = false;  // --version
};

// Resolves mapd's settings from `args` (without the program name) and the process environment.
// Precedence: command-line flag, then environment variable (MAPD_ + the flag name in upper case
// with '_', e.g. MAPD_MAX_QUEUE), then the config file (--config or MAPD_CONFIG; lines
// "name = value", '#' comments, names as the flags without "--"), then defaults.
absl::StatusOr<MapdConfig> ParseMapdConfig(const std::vector<std::string>& args);

// The map update options mapd starts from before its settings are applied: MapUpdateOptions'
// defaults with the camera yaw of each vehicle estimated, the fleet's prior for a new vehicle's
// yaw, and local re-linearisation (which mapd's worker does while its queue is empty).
MapUpdateOptions MapdDefaultUpdateOptions();

// Every effective setting as key=value pairs, for the log line at start.
std::string DescribeMapdConfig(const MapdConfig& config);

// What the settings trade away that an operator should know at start, one sentence each (logged
// as warnings): bounded windows (window-hops, read-window-hops) over a map that folds passages
// (retain-passages) can give covariances narrower than exact. From the settings alone: a map that
// an earlier run with other settings folded stays so, unwarned.
std::vector<std::string> MapdConfigCaveats(const MapdConfig& config);

// The --help text.
std::string MapdUsage();

// The environment variable of the setting `name`: "max-queue" -> MAPD_MAX_QUEUE.
std::string MapdEnvName(const std::string& name);

// Adds the setting `name` bound to `*value`: the flag --NAME, the variable MapdEnvName(NAME) and
// the config file's line "NAME = value".
template <typename T>
CLI::Option* AddMapdSetting(CLI::App* mapd, const std::string& name, T* value, const std::string& description) {
  return mapd->add_option("--" + name, *value, description)->envname(MapdEnvName(name));
}

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAPD_CONFIG_H_
