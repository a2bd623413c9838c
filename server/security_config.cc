#include "server/security_config.h"

#include <map>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace crowdmap {

const std::vector<std::string>& SecuritySettingNames() {
  static const std::vector<std::string> kNames = {
      "tls-cert", "tls-key", "tls-client-ca", "auth", "auth-file", "reflection",
      "vehicle-upload-rate", "vehicle-upload-burst", "vehicle-upload-mb-per-s", "vehicle-upload-burst-mb",
      "max-upload-streams", "max-watch-streams", "upload-idle-timeout-s", "max-inflight-mb", "max-threads"};
  return kNames;
}

absl::StatusOr<bool> SetSecuritySetting(const std::string& name, const std::string& value, MapServerOptions* options) {
  SecurityOptions& sec = options->security;
  LimitOptions& limits = options->limits;
  const std::map<std::string, std::string*> strings = {
      {"tls-cert", &sec.tls_cert}, {"tls-key", &sec.tls_key}, {"tls-client-ca", &sec.tls_client_ca},
      {"auth", &sec.auth},         {"auth-file", &sec.auth_file}, {"reflection", &sec.reflection}};
  const std::map<std::string, double*> numbers = {{"vehicle-upload-rate", &limits.vehicle_uploads_per_s},
                                                  {"vehicle-upload-mb-per-s", &limits.vehicle_upload_mb_per_s}};
  const std::map<std::string, int*> integers = {
      {"vehicle-upload-burst", &limits.vehicle_upload_burst}, {"vehicle-upload-burst-mb", &limits.vehicle_upload_burst_mb},
      {"max-upload-streams", &limits.max_upload_streams},     {"max-watch-streams", &limits.max_watch_streams},
      {"upload-idle-timeout-s", &limits.upload_idle_timeout_s}, {"max-inflight-mb", &limits.max_inflight_mb},
      {"max-threads", &limits.max_threads}};
  if (auto it = strings.find(name); it != strings.end()) {
    *it->second = value;
  } else if (auto it = numbers.find(name); it != numbers.end()) {
    if (!absl::SimpleAtod(value, it->second)) {
      return absl::InvalidArgumentError(absl::StrCat("--", name, ": expected a number, got '", value, "'"));
    }
  } else if (auto it = integers.find(name); it != integers.end()) {
    if (!absl::SimpleAtoi(value, it->second)) {
      return absl::InvalidArgumentError(absl::StrCat("--", name, ": expected an integer, got '", value, "'"));
    }
  } else {
    return false;
  }
  return true;
}

std::string SecurityUsage() {
  return R"(
TLS and authentication (README "Security"):
  --tls-cert PATH             PEM certificate chain; with --tls-key mapd serves TLS only
  --tls-key PATH              PEM private key of --tls-cert
  --tls-client-ca PATH        PEM CA bundle: clients present certificates it signed (mTLS); without
                              --auth-file a certificate is required
  --auth auto|on|off          authenticate every RPC (default auto: on unless --listen is loopback)
  --auth-file PATH            identities and roles, reloaded on SIGHUP; lines
                              "sha256:HEX ROLE NAME" (a bearer token's SHA-256) or
                              "x509:CN ROLE NAME" (a client certificate's CN; x509:* ROLE * for
                              any); ROLE vehicle | operator | admin; a vehicle's NAME is its vehicle_id
  --reflection auto|on|off    gRPC server reflection (default auto: on when auth is off)
Quotas and limits (RESOURCE_EXHAUSTED, with retry-after trailing metadata where waiting helps):
  --vehicle-upload-rate X     passages per second per vehicle_id, sustained (default 1; 0 = off)
  --vehicle-upload-burst N    passages a vehicle may upload at once (default 30)
  --vehicle-upload-mb-per-s X MiB per second per vehicle_id, sustained (default 8; 0 = off)
  --vehicle-upload-burst-mb N MiB a vehicle may upload at once, >= --max-passage-mb (default 128)
  --max-upload-streams N      concurrent UploadPassageChunked calls (default 64; 0 = off)
  --max-watch-streams N       concurrent WatchRegion calls (default 128; 0 = off)
  --upload-idle-timeout-s N   a chunked upload that sends no chunk for N s is cancelled; at least
                              one chunk's time on the slowest link (default 60; 0 = off)
  --max-inflight-mb N         upload bytes held by the handlers at once (default 512; 0 = off)
  --max-threads N             threads for synchronous RPCs; calls beyond get RESOURCE_EXHAUSTED;
                              more than the two stream caps + 16 (default 512)
)";
}

}  // namespace crowdmap
