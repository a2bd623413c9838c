#ifndef CROWDMAP_SERVER_SECURITY_CONFIG_H_
#define CROWDMAP_SERVER_SECURITY_CONFIG_H_

#include <CLI/CLI.hpp>

#include "server/map_server.h"

namespace crowdmap {

// mapd's settings for TLS, authentication and limits (SecurityOptions, LimitOptions), bound to
// `options` as flags, MAPD_* variables and config-file lines alike (AddMapdSetting), in two
// --help groups of their own.
void AddSecuritySettings(CLI::App* mapd, MapServerOptions* options);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_SECURITY_CONFIG_H_
