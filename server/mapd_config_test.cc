#include "server/mapd_config.h"

#include <fstream>
#include <map>

#include "gtest/gtest.h"
#include "server/testing/temp_dir.h"

namespace crowdmap {
namespace {

EnvLookup FakeEnv(std::map<std::string, std::string> vars) {
  auto shared = std::make_shared<std::map<std::string, std::string>>(std::move(vars));
  return [shared](const char* name) -> const char* {
    auto it = shared->find(name);
    return it == shared->end() ? nullptr : it->second.c_str();
  };
}

TEST(MapdConfig, DefaultsMatchTheDocumentedOnes) {
  auto c = ParseMapdConfig({}, FakeEnv({}));
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
  auto c = ParseMapdConfig({"--config", path, "--max-queue=33"},
                           FakeEnv({{"MAPD_MAX_QUEUE", "22"}, {"MAPD_WORKERS", "2"}, {"MAPD_DB", "/x/y.db"}}));
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.max_queue, 33);
  EXPECT_EQ(c->server.worker.workers, 2);
  EXPECT_EQ(c->server.worker.update.strategy, UpdateStrategy::kDecorrelated);
  EXPECT_EQ(c->server.listen, "0.0.0.0:1");
  EXPECT_EQ(c->server.db_path, "/x/y.db");
}

TEST(MapdConfig, RejectsUnknownFlagsAndBadValues) {
  EXPECT_FALSE(ParseMapdConfig({"--bogus", "1"}, FakeEnv({})).ok());
  EXPECT_FALSE(ParseMapdConfig({"--workers", "many"}, FakeEnv({})).ok());
  EXPECT_FALSE(ParseMapdConfig({"--workers", "0"}, FakeEnv({})).ok());
  EXPECT_FALSE(ParseMapdConfig({"--strategy", "best"}, FakeEnv({})).ok());
  EXPECT_FALSE(ParseMapdConfig({"--max-message-mb=0"}, FakeEnv({})).ok());
  auto nice = ParseMapdConfig({"--worker-nice", "20"}, FakeEnv({}));
  ASSERT_FALSE(nice.ok());
  EXPECT_NE(nice.status().message().find("worker-nice"), std::string::npos) << nice.status();
}

TEST(MapdConfig, ReadsUpdateOptions) {
  auto c = ParseMapdConfig({"--max-subgraph-dim", "300", "--window-hops", "3"}, FakeEnv({}));
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.worker.update.max_subgraph_dim, 300);
  EXPECT_EQ(c->server.worker.update.warmup_passages, 8);
  auto w = ParseMapdConfig({}, FakeEnv({{"MAPD_WARMUP_PASSAGES", "0"}}));
  ASSERT_TRUE(w.ok()) << w.status();
  EXPECT_EQ(w->server.worker.update.warmup_passages, 0);
  EXPECT_EQ(c->server.worker.update.relinearize_until_passages, 128);
  auto r = ParseMapdConfig({"--relinearize-until-passages", "0"}, FakeEnv({}));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->server.worker.update.relinearize_until_passages, 0);
  auto bad_r = ParseMapdConfig({}, FakeEnv({{"MAPD_RELINEARIZE_UNTIL_PASSAGES", "-3"}}));
  ASSERT_FALSE(bad_r.ok());
  EXPECT_NE(bad_r.status().message().find("relinearize_until_passages"), std::string::npos) << bad_r.status();
  auto bad = ParseMapdConfig({"--warmup-passages", "-1"}, FakeEnv({}));
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("warmup_passages"), std::string::npos) << bad.status();
  EXPECT_EQ(c->server.worker.update.window_hops, 3);
  EXPECT_EQ(c->server.worker.nice, 10);
  auto n = ParseMapdConfig({}, FakeEnv({{"MAPD_WORKER_NICE", "0"}}));
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(n->server.worker.nice, 0);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

TEST(MapdConfig, VersionFlagIsRecognised) {
  auto c = ParseMapdConfig({"--version"}, FakeEnv({}));
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_TRUE(c->version);
  EXPECT_FALSE(ParseMapdConfig({}, FakeEnv({}))->version);
}

TEST(MapdConfig, ReadsTheTrustRules) {
  auto c = ParseMapdConfig({"--max-detection-residual-sigmas", "4", "--max-landmark-shift-sigmas=6",
                            "--max-new-landmark-ray-sigma-m", "2.5"},
                           FakeEnv({{"MAPD_MAX_CHI2_PER_DOF", "8"}}));
  ASSERT_TRUE(c.ok()) << c.status();
  const MapUpdateOptions& u = c->server.worker.update;
  EXPECT_EQ(u.max_detection_residual_sigmas, 4.0);
  EXPECT_EQ(u.max_landmark_shift_mahalanobis2, 36.0);
  EXPECT_EQ(u.max_new_landmark_ray_sigma_m, 2.5);
  EXPECT_EQ(u.max_chi2_per_dof, 8.0);
  auto bad = ParseMapdConfig({"--max-detection-residual-sigmas", "many"}, FakeEnv({}));
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("max-detection-residual-sigmas"), std::string::npos) << bad.status();
  auto negative = ParseMapdConfig({"--max-new-landmark-ray-sigma-m", "-1"}, FakeEnv({}));
  ASSERT_FALSE(negative.ok());
  EXPECT_NE(negative.status().message().find("max_new_landmark_ray_sigma_m"), std::string::npos) << negative.status();
}

TEST(MapdConfig, CreateMetricsAndLogFormatAreOffOrTextByDefaultAndSettable) {
  auto defaults = ParseMapdConfig({}, FakeEnv({}));
  ASSERT_TRUE(defaults.ok()) << defaults.status();
  EXPECT_FALSE(defaults->server.create_db) << "mapd creates a map only with --create";
  EXPECT_EQ(defaults->server.metrics_listen, "");
  EXPECT_EQ(defaults->log_format, "text");
  auto set = ParseMapdConfig({"--create", "--metrics-listen", "127.0.0.1:9464", "--log-format=json"}, FakeEnv({}));
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_TRUE(set->server.create_db);
  EXPECT_EQ(set->server.metrics_listen, "127.0.0.1:9464");
  EXPECT_EQ(set->log_format, "json");
  auto env = ParseMapdConfig({}, FakeEnv({{"MAPD_CREATE", "true"}, {"MAPD_LOG_FORMAT", "json"}}));
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_TRUE(env->server.create_db);
  EXPECT_EQ(env->log_format, "json");
  const std::string described = DescribeMapdConfig(*set);
  EXPECT_NE(described.find("create=true"), std::string::npos) << described;
  EXPECT_NE(described.find("metrics-listen=127.0.0.1:9464"), std::string::npos) << described;
  EXPECT_NE(described.find("max-landmark-shift-sigmas=5 "), std::string::npos) << described;
  EXPECT_NE(described.find("estimate-camera-yaw=true"), std::string::npos) << described;
  EXPECT_TRUE(set->server.worker.update.estimate_camera_yaw) << "mapd estimates camera yaw by default";
  auto off = ParseMapdConfig({"--estimate-camera-yaw", "false"}, FakeEnv({}));
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_FALSE(off->server.worker.update.estimate_camera_yaw);
  auto bad = ParseMapdConfig({}, FakeEnv({{"MAPD_ESTIMATE_CAMERA_YAW", "sometimes"}}));
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("--estimate-camera-yaw"), absl::string_view::npos) << bad.status();
}

TEST(MapdConfig, BadLogFormatAndCreateValuesNameTheFlag) {
  auto format = ParseMapdConfig({"--log-format", "xml"}, FakeEnv({}));
  ASSERT_FALSE(format.ok());
  EXPECT_NE(format.status().message().find("--log-format"), absl::string_view::npos) << format.status();
  auto create = ParseMapdConfig({}, FakeEnv({{"MAPD_CREATE", "maybe"}}));
  ASSERT_FALSE(create.ok());
  EXPECT_NE(create.status().message().find("--create"), absl::string_view::npos) << create.status();
}

TEST(MapdConfig, SecurityAndLimitSettingsComeFromFlagsEnvironmentAndFile) {
  TempDir dir;
  const std::string path = dir.File("mapd.conf");
  std::ofstream(path) << "tls_cert = /etc/mapd/cert.pem\ntls_key = /etc/mapd/key.pem\nauth_file = /etc/mapd/auth\n";
  auto c = ParseMapdConfig({"--config", path, "--max-threads", "256", "--vehicle-upload-rate=0.5"},
                           FakeEnv({{"MAPD_MAX_UPLOAD_STREAMS", "8"}, {"MAPD_AUTH", "on"}}));
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->server.security.tls_cert, "/etc/mapd/cert.pem");
  EXPECT_EQ(c->server.security.auth_file, "/etc/mapd/auth");
  EXPECT_EQ(c->server.security.auth, "on");
  EXPECT_EQ(c->server.limits.max_threads, 256);
  EXPECT_EQ(c->server.limits.max_upload_streams, 8);
  EXPECT_DOUBLE_EQ(c->server.limits.vehicle_uploads_per_s, 0.5);
}

TEST(MapdConfig, SecurityErrorsNameTheFlag) {
  auto half_tls = ParseMapdConfig({"--tls-cert", "c.pem"}, FakeEnv({}));
  ASSERT_FALSE(half_tls.ok());
  EXPECT_NE(half_tls.status().message().find("--tls-key"), std::string::npos) << half_tls.status();
  auto ca_alone = ParseMapdConfig({"--tls-client-ca", "ca.pem"}, FakeEnv({}));
  ASSERT_FALSE(ca_alone.ok());
  EXPECT_NE(ca_alone.status().message().find("--tls-client-ca"), std::string::npos) << ca_alone.status();
  auto auth = ParseMapdConfig({"--auth", "maybe"}, FakeEnv({}));
  ASSERT_FALSE(auth.ok());
  EXPECT_NE(auth.status().message().find("--auth"), std::string::npos) << auth.status();
  auto threads = ParseMapdConfig({"--max-threads", "many"}, FakeEnv({}));
  ASSERT_FALSE(threads.ok());
  EXPECT_NE(threads.status().message().find("--max-threads"), std::string::npos) << threads.status();
  auto few_threads = ParseMapdConfig({"--max-threads", "100"}, FakeEnv({}));  // streams could take them all
  ASSERT_FALSE(few_threads.ok());
  EXPECT_NE(few_threads.status().message().find("--max-upload-streams + --max-watch-streams"), std::string::npos)
      << few_threads.status();
  auto burst = ParseMapdConfig({"--vehicle-upload-burst-mb", "8"}, FakeEnv({}));
  ASSERT_FALSE(burst.ok());
  EXPECT_NE(burst.status().message().find("--max-passage-mb"), std::string::npos) << burst.status();
}

}  // namespace
}  // namespace crowdmap
