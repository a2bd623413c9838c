#ifndef CROWDMAP_SERVER_SECURITY_CONFIG_H_
#define CROWDMAP_SERVER_SECURITY_CONFIG_H_

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/map_server.h"

namespace crowdmap {

// mapd's settings for TLS, authentication and limits (SecurityOptions, LimitOptions), bound to
// flags, MAPD_* variables and the config file by mapd_config.cc.
const std::vector<std::string>& SecuritySettingNames();
// Sets `name` to `value` in `options`; false when `name` is not one of SecuritySettingNames().
absl::StatusOr<bool> SetSecuritySetting(const std::string& name, const std::string& value, MapServerOptions* options);
// Their part of `mapd --help`.
std::string SecurityUsage();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_SECURITY_CONFIG_H_
