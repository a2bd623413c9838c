#ifndef CROWDMAP_SERVER_MAPD_CONFIG_H_
#define CROWDMAP_SERVER_MAPD_CONFIG_H_

#include <functional>
#include <string>
#include <vector>

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

// Looks up an environment variable; nullptr when unset.
using EnvLookup = std::function<const char*(const char*)>;

// Resolves mapd's settings. Precedence: command-line flag, then environment variable (MAPD_ + the
// flag name in upper case with '_', e.g. MAPD_MAX_QUEUE), then the config file (--config or
// MAPD_CONFIG; lines "name = value", '#' comments, names as the flags without "--"), then defaults.
absl::StatusOr<MapdConfig> ParseMapdConfig(const std::vector<std::string>& args, const EnvLookup& env);

// Every effective setting as key=value pairs, for the log line at start.
std::string DescribeMapdConfig(const MapdConfig& config);

// The --help text.
std::string MapdUsage();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAPD_CONFIG_H_
