#include "server/security_config.h"

#include "server/mapd_config.h"

namespace crowdmap {

void AddSecuritySettings(CLI::App* mapd, MapServerOptions* options) {
  SecurityOptions& sec = options->security;
  const std::string security = "TLS and authentication (README \"Security\")";
  AddMapdSetting(mapd, "tls-cert", &sec.tls_cert, "PEM certificate chain; with --tls-key mapd serves TLS only")
      ->type_name("PATH")
      ->group(security);
  AddMapdSetting(mapd, "tls-key", &sec.tls_key, "PEM private key of --tls-cert")->type_name("PATH")->group(security);
  AddMapdSetting(mapd, "tls-client-ca", &sec.tls_client_ca,
                 "PEM CA bundle: clients present certificates it signed (mTLS); without --auth-file a\n"
                 "certificate is required")
      ->type_name("PATH")
      ->group(security);
  AddMapdSetting(mapd, "auth", &sec.auth, "authenticate every RPC (auto: on unless --listen is loopback)")
      ->type_name("auto|on|off")
      ->group(security);
  AddMapdSetting(mapd, "auth-file", &sec.auth_file,
                 "identities and roles, reloaded on SIGHUP; lines \"sha256:HEX ROLE NAME\" (a bearer\n"
                 "token's SHA-256) or \"x509:CN ROLE NAME\" (a client certificate's CN; x509:* ROLE * for\n"
                 "any); ROLE vehicle | operator | admin; a vehicle's NAME is its vehicle_id")
      ->type_name("PATH")
      ->group(security);
  AddMapdSetting(mapd, "reflection", &sec.reflection, "gRPC server reflection (auto: on when auth is off)")
      ->type_name("auto|on|off")
      ->group(security);

  LimitOptions& limits = options->limits;
  const std::string quotas =
      "Quotas and limits (RESOURCE_EXHAUSTED, with retry-after trailing metadata where waiting helps)";
  AddMapdSetting(mapd, "vehicle-upload-rate", &limits.vehicle_uploads_per_s,
                 "passages per second per vehicle_id, sustained (0 = off)")
      ->type_name("X")
      ->group(quotas);
  AddMapdSetting(mapd, "vehicle-upload-burst", &limits.vehicle_upload_burst, "passages a vehicle may upload at once")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "vehicle-upload-mb-per-s", &limits.vehicle_upload_mb_per_s,
                 "MiB per second per vehicle_id, sustained (0 = off)")
      ->type_name("X")
      ->group(quotas);
  AddMapdSetting(mapd, "vehicle-upload-burst-mb", &limits.vehicle_upload_burst_mb,
                 "MiB a vehicle may upload at once, >= --max-passage-mb")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-upload-streams", &limits.max_upload_streams,
                 "concurrent UploadPassageChunked calls (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-upload-streams-per-identity", &limits.max_upload_streams_per_identity,
                 "concurrent UploadPassageChunked calls of one authenticated identity (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-watch-streams", &limits.max_watch_streams, "concurrent WatchRegion calls (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-watch-streams-per-identity", &limits.max_watch_streams_per_identity,
                 "concurrent WatchRegion calls of one authenticated identity (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-covariance-reads", &limits.max_covariance_reads,
                 "concurrent GetTile and QueryRegion calls with include_cross_covariance, and LocalizePassage\n"
                 "calls; each holds a dense covariance, up to a few hundred MB at 2,000 landmarks (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "upload-idle-timeout-s", &limits.upload_idle_timeout_s,
                 "a chunked upload that sends no bytes for N s, or averages under 1 KiB/s once open N s, is\n"
                 "cancelled; at least one chunk's time on the slowest link (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-inflight-mb", &limits.max_inflight_mb,
                 "upload bytes held by the handlers at once (0 = off)")
      ->type_name("N")
      ->group(quotas);
  AddMapdSetting(mapd, "max-threads", &limits.max_threads,
                 "threads for synchronous RPCs; calls beyond get RESOURCE_EXHAUSTED; more than the two\n"
                 "stream caps + 16")
      ->type_name("N")
      ->group(quotas);
}

}  // namespace crowdmap
