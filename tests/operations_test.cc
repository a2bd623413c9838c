// Operating mapd: the Prometheus endpoint scraped over HTTP after real RPCs, request ids in the
// response metadata, and the refusal to create a map unless asked (--create).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <thread>

#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// GET http://127.0.0.1:port/path over a plain socket; the body, or "" on any failure.
std::string HttpGet(int port, const std::string& path) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return "";
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  std::string response;
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0) {
    const std::string request = "GET " + path + " HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n";
    if (write(fd, request.data(), request.size()) == static_cast<ssize_t>(request.size())) {
      char buffer[65536];
      ssize_t n;
      while ((n = read(fd, buffer, sizeof(buffer))) > 0) response.append(buffer, static_cast<size_t>(n));
    }
  }
  close(fd);
  const size_t body = response.find("\r\n\r\n");
  if (response.rfind("HTTP/1.", 0) != 0 || response.find(" 200 ") == std::string::npos || body == std::string::npos) {
    return "";
  }
  return response.substr(body + 4);
}

// The exposition text as series -> value, a series being the name with its labels as printed
// (prometheus-cpp prints labels sorted by name), e.g. mapd_passages{state="applied"}.
std::map<std::string, double> ParseExposition(const std::string& text) {
  std::map<std::string, double> series;
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty() || line[0] == '#') continue;
    const size_t space = line.rfind(' ');
    series[line.substr(0, space)] = std::stod(line.substr(space + 1));
  }
  return series;
}

std::string Rpc(const std::string& method, const std::string& code) {
  return "{code=\"" + code + "\",method=\"" + method + "\",service=\"mapservice.v1.MapService\"}";
}

// The metrics once `passages` applied passages are in them (their raw text in `text`, if given).
// The worker records a passage's timings once its commit is durable, so a scrape right after the
// store shows it applied can miss the last one.
std::map<std::string, double> ScrapeOnceApplied(int port, int passages, std::string* text = nullptr) {
  std::string scraped;
  std::map<std::string, double> m;
  for (const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);;) {
    scraped = HttpGet(port, "/metrics");
    m = ParseExposition(scraped);
    if (m["mapd_passage_commit_seconds_count"] >= passages || std::chrono::steady_clock::now() > deadline) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (text != nullptr) *text = std::move(scraped);
  return m;
}

// A fleet whose camera is three times as noisy as it declares: its passages' camera tests count.
TEST(Metrics, PassagesWhoseCameraIsNoisierThanDeclaredAreCounted) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.metrics_listen = "127.0.0.1:0";
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  ScenarioOptions noisy;
  noisy.landmarks = 25;
  noisy.duration_s = 80.0;
  noisy.undeclared_noise.pixel = 3.0;
  const absl::StatusOr<Scenario> scenario = Scenario::Create(noisy);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  for (int i = 0; i < 4; ++i) {
    pb::Passage wire;
    PassageToProto(scenario->MakePassage(i), &wire);
    ASSERT_TRUE(vehicle.UploadOnce(wire).ok());
  }
  ASSERT_TRUE(vehicle.WaitUntilIdle().ok());
  std::map<std::string, double> m = ScrapeOnceApplied(server->metrics_port(), 4);
  EXPECT_GE(m["mapd_passage_inflations_total{test=\"camera\"}"], 2);
  EXPECT_EQ(m["mapd_passage_inflations_total{test=\"odometry\"}"], 0);
  EXPECT_EQ(m["mapd_passage_inflations_total{test=\"gnss\"}"], 0);
}

TEST(Metrics, ScrapedValuesMatchTheRpcsUploadsAndAppliedPassages) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.metrics_listen = "127.0.0.1:0";
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  ASSERT_GT(server->metrics_port(), 0);
  MockVehicle vehicle(server->address());
  const Scenario scenario = ShortScenario();

  double uploaded_bytes = 0;
  for (int i = 0; i < 3; ++i) {
    pb::Passage wire;
    PassageToProto(scenario.MakePassage(i), &wire);
    uploaded_bytes += static_cast<double>(wire.ByteSizeLong());
    ASSERT_TRUE(vehicle.UploadOnce(wire).ok());
  }
  pb::Passage again;
  PassageToProto(scenario.MakePassage(0), &again);
  auto duplicate = vehicle.UploadOnce(again);
  ASSERT_TRUE(duplicate.ok());
  ASSERT_TRUE(duplicate->duplicate());
  uploaded_bytes += static_cast<double>(again.ByteSizeLong());
  EXPECT_EQ(vehicle.client()->GetPassage(987654).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(vehicle.client()->GetPassage(987655).status().code(), absl::StatusCode::kNotFound);
  auto idle = vehicle.WaitUntilIdle();
  ASSERT_TRUE(idle.ok()) << idle.status();
  ASSERT_EQ(idle->passages_applied(), 3);
  auto info = vehicle.GetMapInfo();
  ASSERT_TRUE(info.ok());
  {
    pb::QueryRegionRequest region;  // the whole map's window: exact
    *region.mutable_box() = MockVehicle::World();
    region.set_include_cross_covariance(true);
    pb::QueryRegionResponse response;
    grpc::ClientContext ctx;
    ASSERT_TRUE(vehicle.stub()->QueryRegion(&ctx, region, &response).ok());
    ASSERT_EQ(response.covariance_bound(), pb::COVARIANCE_BOUND_EXACT);
  }

  std::string text;
  std::map<std::string, double> m = ScrapeOnceApplied(server->metrics_port(), 3, &text);
  ASSERT_FALSE(text.empty()) << "no answer from the metrics endpoint";
  EXPECT_EQ(m["mapd_rpc_duration_seconds_count" + Rpc("UploadPassage", "OK")], 4);
  EXPECT_EQ(m["mapd_rpc_duration_seconds_count" + Rpc("GetPassage", "NOT_FOUND")], 2);
  EXPECT_GT(m["mapd_rpc_duration_seconds_sum" + Rpc("UploadPassage", "OK")], 0);
  // Every RPC is counted once: the +Inf bucket holds them all.
  EXPECT_EQ(m["mapd_rpc_duration_seconds_bucket{code=\"OK\",method=\"UploadPassage\",service=\"mapservice.v1.MapService\",le=\"+Inf\"}"], 4);
  EXPECT_GE(m["mapd_rpc_duration_seconds_count" + Rpc("GetMapInfo", "OK")], 2);
  EXPECT_EQ(m["mapd_upload_bytes_total"], uploaded_bytes);
  EXPECT_EQ(m["mapd_uploads_total{outcome=\"queued\"}"], 3);
  EXPECT_EQ(m["mapd_uploads_total{outcome=\"duplicate\"}"], 1);
  EXPECT_EQ(m["mapd_covariance_reads_total{bound=\"exact\"}"], 1);
  EXPECT_EQ(m["mapd_covariance_reads_total{bound=\"may_be_narrower\"}"], 0);
  EXPECT_NE(text.find("mapd_covariance_reads_total{bound=\"conservative\"} 0"), std::string::npos)
      << "every bound is exported from the start";
  EXPECT_EQ(m["mapd_passages{state=\"applied\"}"], 3);
  EXPECT_EQ(m["mapd_passages{state=\"queued\"}"], 0);
  EXPECT_EQ(m["mapd_queue_depth"], 0);
  EXPECT_EQ(m["mapd_store_up"], 1);
  for (const char* step : {"apply", "solve", "covariance", "commit"}) {
    EXPECT_EQ(m[std::string("mapd_passage_") + step + "_seconds_count"], 3) << step;
    EXPECT_GT(m[std::string("mapd_passage_") + step + "_seconds_sum"], 0) << step;
  }
  EXPECT_GT(m["mapd_passage_apply_seconds_sum"], m["mapd_passage_commit_seconds_sum"]);
  EXPECT_GE(m["mapd_passage_apply_seconds_sum"], m["mapd_passage_solve_seconds_sum"]);
  ASSERT_EQ(m.count("mapd_passage_recomputed_total"), 1u);
  EXPECT_EQ(m["mapd_passage_recomputed_total"], 0) << "one worker never computes an update again";
  for (const char* test : {"whole", "odometry", "gnss", "camera"}) {
    const std::string series = std::string("mapd_passage_inflations_total{test=\"") + test + "\"}";
    ASSERT_EQ(m.count(series), 1u) << series;
    EXPECT_EQ(m[series], 0) << "honest passages: " << series;
  }
  ASSERT_EQ(m.count("mapd_relinearizations_total{outcome=\"committed\"}"), 1u);
  EXPECT_EQ(m["mapd_relinearizations_total{outcome=\"committed\"}"], 0) << "off by default";
  EXPECT_GT(info->landmark_count(), 0);
  EXPECT_EQ(m["mapd_map_landmarks"], info->landmark_count());
  EXPECT_EQ(m["mapd_map_factors"], info->factor_count());
  EXPECT_EQ(m["mapd_map_version"], info->map_version());
  EXPECT_EQ(m[std::string("mapd_build_info{version=\"") + CROWDMAP_VERSION + "\"}"], 1);
}

// The viewer's change list (GET /api/landmarks?since_version=V) names the landmarks removed after
// V, so that a page drops them; a full read has no such list.
TEST(Viewer, AChangeListNamesTheLandmarksAnExclusionRemoved) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.http_listen = "127.0.0.1:0";
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  ASSERT_GT(server->http_port(), 0);
  MockVehicle vehicle(server->address());
  const Scenario scenario = ShortScenario();
  const Passage lone = WithLandmarkRenamed(scenario.MakePassage(1), 1, 500);
  ASSERT_TRUE(vehicle.Upload(scenario.MakePassage(0)).ok());
  ASSERT_TRUE(vehicle.Upload(lone).ok());
  ASSERT_TRUE(vehicle.WaitUntilIdle().ok());
  auto excluded = vehicle.client()->ExcludePassage(PassageKey{0, lone.vehicle_id, lone.passage_id});
  ASSERT_TRUE(excluded.ok()) << excluded.status();
  const int64_t version = excluded->map_version();
  const std::string world = "/api/landmarks?bbox=-180,-85,180,85";
  const std::string before = HttpGet(server->http_port(), world + "&since_version=" + std::to_string(version - 1));
  EXPECT_NE(before.find("\"removed_ids\":[500]"), std::string::npos) << before;
  const std::string after = HttpGet(server->http_port(), world + "&since_version=" + std::to_string(version));
  EXPECT_NE(after.find("\"removed_ids\":[]"), std::string::npos) << after;
  const std::string all = HttpGet(server->http_port(), world);
  ASSERT_FALSE(all.empty());
  EXPECT_EQ(all.find("removed_ids"), std::string::npos) << all.substr(0, 200);
}

// With --relinearize-sigmas the worker's re-linearisations are counted by outcome.
TEST(Metrics, RelinearizationsAreCounted) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"));
  options.metrics_listen = "127.0.0.1:0";
  options.worker.update.warmup_passages = 0;
  options.worker.update.relinearize_until_passages = 0;
  options.worker.update.relinearize_sigmas = 0.1;
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  const Scenario scenario = ShortScenario();
  for (int i = 0; i < 4; ++i) ASSERT_TRUE(vehicle.Upload(scenario.MakePassage(i)).ok());
  auto idle = vehicle.WaitUntilIdle();
  ASSERT_TRUE(idle.ok()) << idle.status();
  ASSERT_EQ(idle->passages_applied(), 4);
  std::map<std::string, double> m = ScrapeOnceApplied(server->metrics_port(), 4);
  // A young map moves by far more than a tenth of its sigmas with each passage.
  EXPECT_GE(m["mapd_relinearizations_total{outcome=\"committed\"}"], 1);
  ASSERT_EQ(m.count("mapd_relinearizations_total{outcome=\"refused\"}"), 1u);
  ASSERT_EQ(m.count("mapd_relinearizations_due"), 1u);
  EXPECT_EQ(m["mapd_relinearizations_due"], 0) << "idle: nothing owed";
}

TEST(Metrics, UnknownMethodsShareOneLabelValue) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"), /*start_worker=*/false);
  options.metrics_listen = "127.0.0.1:0";
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  server->metrics()->ObserveRpc("/mapservice.v1.MapService/NoSuchMethod\nx", grpc::StatusCode::UNIMPLEMENTED, 0.001);
  server->metrics()->ObserveRpc("/evil.Service/Anything", grpc::StatusCode::UNIMPLEMENTED, 0.001);
  std::map<std::string, double> m = ParseExposition(HttpGet(server->metrics_port(), "/metrics"));
  EXPECT_EQ(m["mapd_rpc_duration_seconds_count{code=\"UNIMPLEMENTED\",method=\"unknown\",service=\"unknown\"}"], 2);
}

TEST(Metrics, APortInUseIsRefusedNamingTheFlag) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("a.db"), /*start_worker=*/false);
  options.metrics_listen = "127.0.0.1:0";
  auto first = StartTestServer(options);
  ASSERT_NE(first, nullptr);
  MapServerOptions second = TestServerOptions(dir.File("b.db"), /*start_worker=*/false);
  second.metrics_listen = "127.0.0.1:" + std::to_string(first->metrics_port());
  auto refused = MapServer::Start(second);
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find("metrics-listen"), absl::string_view::npos) << refused.status();
}

TEST(RequestId, EveryRpcReturnsADistinctIdInItsTrailingMetadata) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db"), /*start_worker=*/false));
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  std::set<std::string> ids;
  const std::regex hex16("[0-9a-f]{16}");
  for (int i = 0; i < 3; ++i) {
    grpc::ClientContext ctx;
    pb::MapInfo info;
    ASSERT_TRUE(vehicle.stub()->GetMapInfo(&ctx, pb::GetMapInfoRequest(), &info).ok());
    EXPECT_TRUE(ctx.GetServerInitialMetadata().empty()) << "initial metadata would commit the call (no retries)";
    auto it = ctx.GetServerTrailingMetadata().find("x-request-id");
    ASSERT_NE(it, ctx.GetServerTrailingMetadata().end());
    const std::string id(it->second.data(), it->second.size());
    EXPECT_TRUE(std::regex_match(id, hex16)) << id;
    ids.insert(id);
  }
  EXPECT_EQ(ids.size(), 3u);
  // A failed call carries one as well.
  grpc::ClientContext ctx;
  pb::GetPassageRequest request;
  request.set_id(424242);
  pb::PassageStatus status;
  EXPECT_EQ(vehicle.stub()->GetPassage(&ctx, request, &status).error_code(), grpc::StatusCode::NOT_FOUND);
  auto it = ctx.GetServerTrailingMetadata().find("x-request-id");
  ASSERT_NE(it, ctx.GetServerTrailingMetadata().end());
  EXPECT_TRUE(std::regex_match(std::string(it->second.data(), it->second.size()), hex16));
}

TEST(Pushback, AFullQueueTellsClientsWhenToRetry) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"), /*start_worker=*/false);
  options.max_queue = 1;
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  const Scenario scenario = ShortScenario();
  pb::UploadPassageRequest request;
  PassageToProto(scenario.MakePassage(0), request.mutable_passage());
  pb::UploadPassageResponse response;
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(vehicle.stub()->UploadPassage(&ctx, request, &response).ok());
    EXPECT_EQ(ctx.GetServerTrailingMetadata().count("grpc-retry-pushback-ms"), 0u);
  }
  PassageToProto(scenario.MakePassage(1), request.mutable_passage());
  grpc::ClientContext ctx;
  EXPECT_EQ(vehicle.stub()->UploadPassage(&ctx, request, &response).error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  auto it = ctx.GetServerTrailingMetadata().find("grpc-retry-pushback-ms");
  ASSERT_NE(it, ctx.GetServerTrailingMetadata().end());
  EXPECT_EQ(std::string(it->second.data(), it->second.size()), "1000");

  // A client whose retry policy would pause at most 10 ms waits the server's second instead.
  MapClientOptions retrying;
  retrying.server = server->address();
  retrying.max_attempts = 2;
  retrying.initial_backoff = std::chrono::milliseconds(10);
  retrying.max_backoff = std::chrono::milliseconds(10);
  auto client = MapClient::Create(retrying);
  ASSERT_TRUE(client.ok());
  const auto start = std::chrono::steady_clock::now();
  EXPECT_EQ((*client)->Upload(request.passage()).status().code(), absl::StatusCode::kResourceExhausted);
  // gRPC's timers count whole milliseconds from their own clock reading: the retry came 999.6 ms
  // after `start` once (CI, 2026-11-26). Its own backoff would have been 10 ms.
  EXPECT_GE(std::chrono::steady_clock::now() - start, std::chrono::milliseconds(990));
}

MapServerOptions NoCreate(const std::string& db) {
  MapServerOptions options = TestServerOptions(db, /*start_worker=*/false);
  options.create_db = false;
  return options;
}

TEST(DatabaseCreation, AMissingDirectoryIsRefusedUnlessCreateIsGiven) {
  TempDir dir;
  const std::string db = dir.File("mistyped/map.db");
  auto refused = MapServer::Start(NoCreate(db));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find(dir.File("mistyped")), absl::string_view::npos) << refused.status();
  EXPECT_NE(refused.status().message().find("--create"), absl::string_view::npos) << refused.status();
  EXPECT_FALSE(std::filesystem::exists(dir.File("mistyped"))) << "nothing created";

  MapServerOptions create = NoCreate(db);
  create.create_db = true;
  ASSERT_NE(StartTestServer(create), nullptr);
  EXPECT_GT(std::filesystem::file_size(db), 0u);
}

TEST(DatabaseCreation, AMissingFileIsRefusedUnlessCreateIsGivenAndAnExistingMapOpens) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  auto refused = MapServer::Start(NoCreate(db));
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find(db + " does not exist"), absl::string_view::npos) << refused.status();
  EXPECT_FALSE(std::filesystem::exists(db));
  {
    MapServerOptions create = NoCreate(db);
    create.create_db = true;
    ASSERT_NE(StartTestServer(create), nullptr);
  }
  EXPECT_NE(StartTestServer(NoCreate(db)), nullptr) << "an existing map opens without --create";
}

TEST(DatabaseCreation, AZeroLengthFileIsRefusedUnlessCreateIsGiven) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  std::ofstream(db).close();
  ASSERT_EQ(std::filesystem::file_size(db), 0u);
  auto refused = MapServer::Start(NoCreate(db));
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find(db + " is an empty file"), absl::string_view::npos) << refused.status();
  EXPECT_EQ(std::filesystem::file_size(db), 0u) << "left as it was";
  MapServerOptions create = NoCreate(db);
  create.create_db = true;
  ASSERT_NE(StartTestServer(create), nullptr);
}

}  // namespace
}  // namespace crowdmap
