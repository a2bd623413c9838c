#include "server/mapd_config.h"

#include <stdlib.h>

#include <fstream>
#include <map>

#include "absl/strings/match.h"
#include "gtest/gtest.h"
#include "server/testing/temp_dir.h"

extern char** environ;

namespace crowdmap {
namespace {

// mapd reads the process environment: these MAPD_* variables are set for one test (every other
// MAPD_* variable unset), and the environment is restored after it.
class ScopedMapdEnvironment {
 public:
  explicit ScopedMapdEnvironment(const std::map<std::string, std::string>& vars) {
    for (char** entry = environ; *entry != nullptr; ++entry) {
      const std::string text = *entry;
      if (absl::StartsWith(text, "MAPD_")) saved_[text.substr(0, text.find('='))] = text.substr(text.find('=') + 1);
    }
    for (const auto& [name, value] : saved_) unsetenv(name.c_str());
    for (const auto& [name, value] : vars) setenv(name.c_str(), value.c_str(), 1);
    set_ = vars;
  }
  ~ScopedMapdEnvironment() {
    for (const auto& [name, value] : set_) unsetenv(name.c_str());
    for (const auto& [name, value] : saved_) setenv(name.c_str(), value.c_str(), 1);
  }

 private:
  std::map<std::string, std::string> saved_, set_;
};

absl::StatusOr<MapdConfig> ParseWithEnvironment(const std::vector<std::string>& args,
                                                const std::map<std::string, std::string>& env) {
  ScopedMapdEnvironment scoped(env);
  return ParseMapdConfig(args);
}

TEST(MapdConfig, DefaultsMatchTheDocumentedOnes) {
  auto c = ParseWithEnvironment({}, {});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.listen, "127.0.0.1:50051");
  EXPECT_EQ(c->server.db_path, "./var/map.db");
  EXPECT_EQ(c->server.worker.update.strategy, UpdateStrategy::kCorrelatedSubdivided);
  EXPECT_EQ(c->server.max_message_mb, 4);
}

TEST(MapdConfig, FlagBeatsEnvironmentBeatsConfigFile) {
  TempDir dir;
  const std::string path = dir.File("mapd.conf");
  std::ofstream(path) << "# comment\nmax_queue = 11\nworkers = 3\nstrategy: dc\nlisten = 0.0.0.0:1\n";
  auto c = ParseWithEnvironment({"--config", path, "--max-queue=33"},
                                {{"MAPD_MAX_QUEUE", "22"}, {"MAPD_WORKERS", "2"}, {"MAPD_DB", "/x/y.db"}});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.max_queue, 33);
  EXPECT_EQ(c->server.worker.workers, 2);
  EXPECT_EQ(c->server.worker.update.strategy, UpdateStrategy::kDecorrelated);
  EXPECT_EQ(c->server.listen, "0.0.0.0:1");
  EXPECT_EQ(c->server.db_path, "/x/y.db");
}

TEST(MapdConfig, ReadsTheConfigFileNamedByMapdConfigAndChecksItEvenWithVersion) {
  TempDir dir;
  const std::string path = dir.File("mapd.conf");
  std::ofstream(path) << "db = /x/from-file.db\nmax_queue: 7\n";
  auto c = ParseWithEnvironment({}, {{"MAPD_CONFIG", path}});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.db_path, "/x/from-file.db");
  EXPECT_EQ(c->server.max_queue, 7);
  EXPECT_FALSE(ParseWithEnvironment({}, {{"MAPD_CONFIG", dir.File("missing.conf")}}).ok());
  EXPECT_FALSE(ParseWithEnvironment({"--config", dir.File("missing.conf")}, {}).ok());

  const std::string bad = dir.File("bad.conf");
  std::ofstream(bad) << "# mapd\nlisten = 127.0.0.1:1\nmax-quue = 3\n";
  auto unknown = ParseWithEnvironment({"--config", bad, "--version"}, {});
  ASSERT_FALSE(unknown.ok());
  EXPECT_NE(unknown.status().message().find(bad + ":3: unknown setting max-quue"), std::string::npos)
      << unknown.status();
  const std::string bad_value = dir.File("bad_value.conf");
  std::ofstream(bad_value) << "workers = many\n";
  EXPECT_FALSE(ParseWithEnvironment({"--config", bad_value, "--version"}, {}).ok());
}

TEST(MapdConfig, RejectsUnknownFlagsAndBadValues) {
  EXPECT_FALSE(ParseWithEnvironment({"--bogus", "1"}, {}).ok());
  EXPECT_FALSE(ParseWithEnvironment({"--workers", "many"}, {}).ok());
  EXPECT_FALSE(ParseWithEnvironment({"--workers", "0"}, {}).ok());
  auto many = ParseWithEnvironment({"--workers", "65"}, {});
  ASSERT_FALSE(many.ok());
  EXPECT_NE(many.status().message().find("workers: must lie in [1, 64]"), std::string::npos) << many.status();
  EXPECT_FALSE(ParseWithEnvironment({"--strategy", "best"}, {}).ok());
  EXPECT_FALSE(ParseWithEnvironment({"--max-message-mb=0"}, {}).ok());
  auto nice = ParseWithEnvironment({"--worker-nice", "20"}, {});
  ASSERT_FALSE(nice.ok());
  EXPECT_NE(nice.status().message().find("worker-nice"), std::string::npos) << nice.status();
  auto retention = ParseWithEnvironment({"--settled-upload-retention-days", "-1"}, {});
  ASSERT_FALSE(retention.ok());
  EXPECT_NE(retention.status().message().find("settled-upload-retention-days"), std::string::npos)
      << retention.status();
  for (const char* beyond : {"1e300", "inf", "nan"}) {
    auto huge = ParseWithEnvironment({"--settled-upload-retention-days", beyond}, {});
    ASSERT_FALSE(huge.ok()) << beyond;
    EXPECT_NE(huge.status().message().find("settled-upload-retention-days"), std::string::npos) << huge.status();
  }
  auto kept = ParseWithEnvironment({}, {{"MAPD_SETTLED_UPLOAD_RETENTION_DAYS", "0"}});
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_EQ(kept->server.worker.settled_upload_retention_days, 0.0);
  EXPECT_EQ(MapWorkerOptions().settled_upload_retention_days, 30.0);
}

TEST(MapdConfig, ReadsUpdateOptions) {
  auto c = ParseWithEnvironment({"--max-subgraph-dim", "300", "--window-hops", "3"}, {});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.worker.update.max_subgraph_dim, 300);
  EXPECT_EQ(c->server.worker.update.warmup_passages, 8);
  auto w = ParseWithEnvironment({}, {{"MAPD_WARMUP_PASSAGES", "0"}});
  ASSERT_TRUE(w.ok()) << w.status();
  EXPECT_EQ(w->server.worker.update.warmup_passages, 0);
  EXPECT_EQ(c->server.worker.update.relinearize_until_passages, 128);
  auto r = ParseWithEnvironment({"--relinearize-until-passages", "0"}, {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->server.worker.update.relinearize_until_passages, 0);
  auto bad_r = ParseWithEnvironment({}, {{"MAPD_RELINEARIZE_UNTIL_PASSAGES", "-3"}});
  ASSERT_FALSE(bad_r.ok());
  EXPECT_NE(bad_r.status().message().find("relinearize_until_passages"), std::string::npos) << bad_r.status();
  EXPECT_EQ(c->server.worker.update.relinearize_sigmas, 6.0) << "local re-linearisation, while the queue is empty";
  auto local = ParseWithEnvironment({"--relinearize-sigmas", "0.5"}, {{"MAPD_RELINEARIZATIONS_PER_PASSAGE", "2"}});
  ASSERT_TRUE(local.ok()) << local.status();
  EXPECT_EQ(local->server.worker.update.relinearize_sigmas, 0.5);
  EXPECT_EQ(local->server.worker.update.relinearizations_per_passage, 2);
  auto bad_local = ParseWithEnvironment({"--relinearize-sigmas", "-1"}, {});
  ASSERT_FALSE(bad_local.ok());
  EXPECT_NE(bad_local.status().message().find("relinearize_sigmas"), std::string::npos) << bad_local.status();
  auto bad = ParseWithEnvironment({"--warmup-passages", "-1"}, {});
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("warmup_passages"), std::string::npos) << bad.status();
  EXPECT_EQ(c->server.worker.update.window_hops, 3);
  EXPECT_EQ(c->server.read_window_hops, -1) << "reads use the updates' window unless told";
  auto reads = ParseWithEnvironment({"--read-window-hops", "1"}, {});
  ASSERT_TRUE(reads.ok()) << reads.status();
  EXPECT_EQ(reads->server.read_window_hops, 1);
  auto bad_reads = ParseWithEnvironment({}, {{"MAPD_READ_WINDOW_HOPS", "-2"}});
  ASSERT_FALSE(bad_reads.ok());
  EXPECT_NE(bad_reads.status().message().find("read_window_hops"), std::string::npos) << bad_reads.status();
  EXPECT_EQ(c->server.worker.update.detections_per_landmark, 5);
  auto all = ParseWithEnvironment({"--detections-per-landmark", "0"}, {});
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_EQ(all->server.worker.update.detections_per_landmark, 0);
  auto too_few = ParseWithEnvironment({}, {{"MAPD_DETECTIONS_PER_LANDMARK", "2"}});
  ASSERT_FALSE(too_few.ok());
  EXPECT_NE(too_few.status().message().find("detections_per_landmark"), std::string::npos) << too_few.status();
  EXPECT_FALSE(c->server.worker.update.spread_detections);
  auto spread = ParseWithEnvironment({}, {{"MAPD_SPREAD_DETECTIONS", "true"}});
  ASSERT_TRUE(spread.ok()) << spread.status();
  EXPECT_TRUE(spread->server.worker.update.spread_detections);
  EXPECT_EQ(c->server.worker.nice, 10);
  auto n = ParseWithEnvironment({}, {{"MAPD_WORKER_NICE", "0"}});
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->server.worker.nice, 0);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// Bounded windows over a map that folds passages: a warning at start, which names the settings.
TEST(MapdConfig, BoundedWindowsOverFoldedPassagesComeWithACaveat) {
  auto exact = ParseWithEnvironment({}, {});
  ASSERT_TRUE(exact.ok()) << exact.status();
  EXPECT_TRUE(MapdConfigCaveats(*exact).empty()) << "the whole map: exact";
  auto city = ParseWithEnvironment({"--window-hops", "2"}, {});
  ASSERT_TRUE(city.ok()) << city.status();
  const std::vector<std::string> caveats = MapdConfigCaveats(*city);
  ASSERT_EQ(caveats.size(), 1u);
  EXPECT_NE(caveats[0].find("window-hops=2 read-window-hops=2 with retain-passages=256"), std::string::npos)
      << caveats[0];
  EXPECT_EQ(caveats[0].find('"'), std::string::npos) << "logged inside a quoted value";
  auto reads = ParseWithEnvironment({"--read-window-hops", "1"}, {});
  ASSERT_TRUE(reads.ok()) << reads.status();
  ASSERT_EQ(MapdConfigCaveats(*reads).size(), 1u) << "bounded reads alone";
  EXPECT_NE(MapdConfigCaveats(*reads)[0].find("read-window-hops=1"), std::string::npos);
  auto kept = ParseWithEnvironment({"--window-hops", "2", "--retain-passages", "0"}, {});
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_TRUE(MapdConfigCaveats(*kept).empty()) << "nothing is ever folded";
}

TEST(MapdConfig, VersionFlagIsRecognised) {
  auto c = ParseWithEnvironment({"--version"}, {});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_TRUE(c->version);
  EXPECT_FALSE(ParseWithEnvironment({}, {})->version);
}

TEST(MapdConfig, ReadsTheTrustRules) {
  auto c = ParseWithEnvironment({"--max-detection-residual-sigmas", "4", "--max-landmark-shift-sigmas=6",
                                 "--max-new-landmark-ray-sigma-m", "2.5", "--max-new-landmark-bias-sigmas", "2",
                                 "--sensor-test-sigmas", "3", "--max-unfit-detection-fraction", "0.4"},
                                {{"MAPD_MAX_CHI2_PER_DOF", "8"}, {"MAPD_MAX_UPDATE_SHIFT_SIGMAS", "4"}});
  ASSERT_TRUE(c.ok()) << c.status();
  const MapUpdateOptions& u = c->server.worker.update;
  EXPECT_EQ(u.max_detection_residual_sigmas, 4.0);
  EXPECT_EQ(u.max_landmark_shift_mahalanobis2, 36.0);
  EXPECT_EQ(u.max_update_shift_mahalanobis2, 16.0);
  // A gate in sigmas is squared: a negative value is refused, not taken as its opposite.
  auto negative_sigmas = ParseWithEnvironment({"--max-update-shift-sigmas", "-3"}, {});
  ASSERT_FALSE(negative_sigmas.ok());
  EXPECT_NE(negative_sigmas.status().message().find("max-update-shift-sigmas"), std::string::npos)
      << negative_sigmas.status();
  EXPECT_EQ(u.max_new_landmark_ray_sigma_m, 2.5);
  EXPECT_EQ(u.max_new_landmark_bias_sigmas, 2.0);
  EXPECT_EQ(MapUpdateOptions().max_new_landmark_bias_sigmas, 1.0);
  EXPECT_EQ(u.max_chi2_per_dof, 8.0);
  EXPECT_EQ(u.sensor_test_sigmas, 3.0);
  EXPECT_EQ(MapUpdateOptions().sensor_test_sigmas, 4.0);
  EXPECT_EQ(u.max_unfit_detection_fraction, 0.4);
  auto whole = ParseWithEnvironment({"--max-unfit-detection-fraction", "1"}, {});
  ASSERT_FALSE(whole.ok());
  EXPECT_NE(whole.status().message().find("max_unfit_detection_fraction"), std::string::npos) << whole.status();
  auto negative_test = ParseWithEnvironment({"--sensor-test-sigmas", "-1"}, {});
  ASSERT_FALSE(negative_test.ok());
  EXPECT_NE(negative_test.status().message().find("sensor_test_sigmas"), std::string::npos) << negative_test.status();
  auto bad = ParseWithEnvironment({"--max-detection-residual-sigmas", "many"}, {});
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("max-detection-residual-sigmas"), std::string::npos) << bad.status();
  auto negative = ParseWithEnvironment({"--max-new-landmark-ray-sigma-m", "-1"}, {});
  ASSERT_FALSE(negative.ok());
  EXPECT_NE(negative.status().message().find("max_new_landmark_ray_sigma_m"), std::string::npos) << negative.status();
  auto negative_bias = ParseWithEnvironment({"--max-new-landmark-bias-sigmas", "-1"}, {});
  ASSERT_FALSE(negative_bias.ok());
  EXPECT_NE(negative_bias.status().message().find("max_new_landmark_bias_sigmas"), std::string::npos)
      << negative_bias.status();
}

TEST(MapdConfig, CreateMetricsAndLogFormatAreOffOrTextByDefaultAndSettable) {
  auto defaults = ParseWithEnvironment({}, {});
  ASSERT_TRUE(defaults.ok()) << defaults.status();
  EXPECT_FALSE(defaults->server.create_db) << "mapd creates a map only with --create";
  EXPECT_EQ(defaults->server.metrics_listen, "");
  EXPECT_EQ(defaults->log_format, "text");
  auto set = ParseWithEnvironment({"--create", "--metrics-listen", "127.0.0.1:9464", "--log-format=json"}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_TRUE(set->server.create_db);
  EXPECT_EQ(set->server.metrics_listen, "127.0.0.1:9464");
  EXPECT_EQ(set->log_format, "json");
  auto env = ParseWithEnvironment({}, {{"MAPD_CREATE", "true"}, {"MAPD_LOG_FORMAT", "json"}});
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_TRUE(env->server.create_db);
  EXPECT_EQ(env->log_format, "json");
  const std::string described = DescribeMapdConfig(*set);
  EXPECT_NE(described.find("create=true"), std::string::npos) << described;
  EXPECT_NE(described.find("metrics-listen=127.0.0.1:9464"), std::string::npos) << described;
  EXPECT_NE(described.find("max-landmark-shift-sigmas=5 "), std::string::npos) << described;
  EXPECT_NE(described.find("estimate-camera-yaw=true"), std::string::npos) << described;
  EXPECT_TRUE(set->server.worker.update.estimate_camera_yaw) << "mapd estimates camera yaw by default";
  auto off = ParseWithEnvironment({"--estimate-camera-yaw", "false"}, {});
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_FALSE(off->server.worker.update.estimate_camera_yaw);
  auto bad = ParseWithEnvironment({}, {{"MAPD_ESTIMATE_CAMERA_YAW", "sometimes"}});
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("--estimate-camera-yaw"), absl::string_view::npos) << bad.status();
}

TEST(MapdConfig, BadLogFormatAndCreateValuesNameTheFlag) {
  auto format = ParseWithEnvironment({"--log-format", "xml"}, {});
  ASSERT_FALSE(format.ok());
  EXPECT_NE(format.status().message().find("--log-format"), absl::string_view::npos) << format.status();
  auto create = ParseWithEnvironment({}, {{"MAPD_CREATE", "maybe"}});
  ASSERT_FALSE(create.ok());
  EXPECT_NE(create.status().message().find("--create"), absl::string_view::npos) << create.status();
}

TEST(MapdConfig, SecurityAndLimitSettingsComeFromFlagsEnvironmentAndFile) {
  TempDir dir;
  const std::string path = dir.File("mapd.conf");
  std::ofstream(path) << "tls_cert = /etc/mapd/cert.pem\ntls_key = /etc/mapd/key.pem\nauth_file = /etc/mapd/auth\n";
  auto c = ParseWithEnvironment({"--config", path, "--max-threads", "256", "--vehicle-upload-rate=0.5"},
                                {{"MAPD_MAX_UPLOAD_STREAMS", "8"}, {"MAPD_AUTH", "on"}});
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.security.tls_cert, "/etc/mapd/cert.pem");
  EXPECT_EQ(c->server.security.auth_file, "/etc/mapd/auth");
  EXPECT_EQ(c->server.security.auth, "on");
  EXPECT_EQ(c->server.limits.max_threads, 256);
  EXPECT_EQ(c->server.limits.max_upload_streams, 8);
  EXPECT_DOUBLE_EQ(c->server.limits.vehicle_uploads_per_s, 0.5);
}

TEST(MapdConfig, SecurityErrorsNameTheFlag) {
  auto half_tls = ParseWithEnvironment({"--tls-cert", "c.pem"}, {});
  ASSERT_FALSE(half_tls.ok());
  EXPECT_NE(half_tls.status().message().find("--tls-key"), std::string::npos) << half_tls.status();
  auto ca_alone = ParseWithEnvironment({"--tls-client-ca", "ca.pem"}, {});
  ASSERT_FALSE(ca_alone.ok());
  EXPECT_NE(ca_alone.status().message().find("--tls-client-ca"), std::string::npos) << ca_alone.status();
  auto auth = ParseWithEnvironment({"--auth", "maybe"}, {});
  ASSERT_FALSE(auth.ok());
  EXPECT_NE(auth.status().message().find("--auth"), std::string::npos) << auth.status();
  auto threads = ParseWithEnvironment({"--max-threads", "many"}, {});
  ASSERT_FALSE(threads.ok());
  EXPECT_NE(threads.status().message().find("--max-threads"), std::string::npos) << threads.status();
  auto few_threads = ParseWithEnvironment({"--max-threads", "100"}, {});  // streams could take them all
  ASSERT_FALSE(few_threads.ok());
  EXPECT_NE(few_threads.status().message().find("--max-upload-streams + --max-watch-streams"), std::string::npos)
      << few_threads.status();
  auto burst = ParseWithEnvironment({"--vehicle-upload-burst-mb", "8"}, {});
  ASSERT_FALSE(burst.ok());
  EXPECT_NE(burst.status().message().find("--max-passage-mb"), std::string::npos) << burst.status();
}

}  // namespace
}  // namespace crowdmap
