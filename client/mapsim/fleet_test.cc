// mapsim fleet against a real in-process mapd: one sequential vehicle gives the map of
// `mapsim experiment`; several concurrent vehicles get every passage applied.
#include "client/mapsim/fleet.h"

#include <algorithm>
#include <filesystem>

#include "server/testing/temp_dir.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

FleetOptions SmallFleet(const std::string& address, int vehicles) {
  FleetOptions options;
  options.server = address;
  options.scenario = ShortScenario().options();
  options.scenario.seed = 3;
  options.passages = 8;
  options.vehicles = vehicles;
  options.strategy = "cc-gsd";
  options.sample_interval = std::chrono::milliseconds(20);
  return options;
}

TEST(Fleet, OneSequentialVehicleMatchesTheExperiment) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  const FleetOptions options = SmallFleet(server->address(), 1);
  auto fleet = RunFleet(options);
  ASSERT_TRUE(fleet.ok()) << fleet.status();

  ExperimentOptions experiment;
  experiment.scenario = options.scenario;
  experiment.passages = options.passages;
  experiment.strategy = "cc-gsd";
  auto expected = RunExperiment(experiment);
  ASSERT_TRUE(expected.ok()) << expected.status();
  EXPECT_EQ(fleet->experiment.records.back().passage, options.passages);
  EXPECT_NEAR(fleet->experiment.final_mean_dist_err_m, expected->final_mean_dist_err_m, 1e-3);
  EXPECT_EQ(fleet->map_version, expected->final_map.version());
  EXPECT_EQ(fleet->experiment.failed_passages, 0);
}

TEST(Fleet, TheReplayUsesTheServersEstimatorSettings) {
  TempDir dir;
  MapServerOptions server_options = TestServerOptions(dir.File("map.db"));
  server_options.worker.update.warmup_passages = 2;
  server_options.worker.update.relinearize_until_passages = 4;
  server_options.worker.update.max_subgraph_dim = 300;
  server_options.worker.update.detections_per_landmark = 4;
  server_options.worker.update.spread_detections = true;
  server_options.worker.update.estimate_camera_yaw = true;
  server_options.worker.update.fleet_camera_yaw_prior_vehicles = 2;
  auto server = StartTestServer(server_options);
  ASSERT_NE(server, nullptr);
  auto fleet = RunFleet(SmallFleet(server->address(), 2));
  ASSERT_TRUE(fleet.ok()) << fleet.status();
  EXPECT_EQ(fleet->server_update.warmup_passages, 2);
  EXPECT_EQ(fleet->server_update.relinearize_until_passages, 4);
  EXPECT_EQ(fleet->server_update.max_subgraph_dim, 300);
  EXPECT_EQ(fleet->server_update.detections_per_landmark, 4);
  EXPECT_TRUE(fleet->server_update.spread_detections);
  EXPECT_TRUE(fleet->server_update.estimate_camera_yaw);
  EXPECT_EQ(fleet->server_update.fleet_camera_yaw_prior_vehicles, 2);
  ASSERT_TRUE(fleet->replay.has_value());
  EXPECT_LT(fleet->replay->max_position_diff_m, 1e-6);
}

TEST(Fleet, ConcurrentVehiclesGetEveryPassageAppliedAndWriteTheOutputs) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  const FleetOptions options = SmallFleet(server->address(), 4);
  auto fleet = RunFleet(options);
  ASSERT_TRUE(fleet.ok()) << fleet.status();
  EXPECT_EQ(fleet->experiment.records.back().passage, options.passages);
  EXPECT_EQ(static_cast<int>(fleet->landmarks.size()), options.scenario.landmarks);
  EXPECT_GT(fleet->experiment.median_passage_ms, 0.0);
  // The server's map is exactly the in-process one for the order in which it received the passages.
  std::vector<int> order = fleet->arrival_order;
  std::sort(order.begin(), order.end());
  for (int i = 0; i < options.passages; ++i) EXPECT_EQ(order[i], i);
  ASSERT_TRUE(fleet->replay.has_value());
  EXPECT_EQ(fleet->replay->missing_landmarks, 0);
  EXPECT_LT(fleet->replay->max_position_diff_m, 1e-6);
  EXPECT_LT(fleet->replay->max_cov_diff_m2, 1e-9);
  EXPECT_NEAR(fleet->replay->final_mean_dist_err_m, fleet->experiment.final_mean_dist_err_m, 1e-6);
  ASSERT_TRUE(WriteFleetOutputs(options, *fleet, dir.File("out")).ok());
  for (const char* name : {"passages.csv", "summary.json", "errors.svg", "map.geojson"}) {
    EXPECT_GT(std::filesystem::file_size(dir.File(std::string("out/") + name)), 0u) << name;
  }
  absl::StatusOr<std::vector<int>> written = ReadOrderFile(dir.File("out/arrival_order.txt"));
  ASSERT_TRUE(written.ok()) << written.status();
  EXPECT_EQ(*written, fleet->arrival_order);
  // A second run on the same database uploads nothing new.
  auto again = RunFleet(options);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->duplicates, options.passages);
  EXPECT_FALSE(again->replay.has_value());  // the map did not start empty
}

TEST(Fleet, CityPassagesAreUploadedAndTheMapMeasuredAgainstTheCitysLandmarks) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  FleetOptions options = SmallFleet(server->address(), 2);
  options.city = true;
  options.city_scenario.blocks_x = options.city_scenario.blocks_y = 2;
  options.city_scenario.route_length_m = 600.0;
  options.passages = 6;
  EXPECT_NE(options.Validate().message().find("replay"), std::string::npos) << "no replay of city passages";
  options.replay = false;
  auto fleet = RunFleet(options);
  ASSERT_TRUE(fleet.ok()) << fleet.status();
  EXPECT_EQ(fleet->experiment.records.back().passage, options.passages);
  EXPECT_EQ(fleet->experiment.failed_passages, 0);
  EXPECT_GT(fleet->landmarks.size(), 10u);
  // Evaluated against the city's landmarks: the loop's would be kilometres away.
  EXPECT_LT(fleet->experiment.final_mean_dist_err_m, 5.0);
  EXPECT_GT(fleet->experiment.records.back().metrics.landmarks_evaluated, 10);
  ASSERT_TRUE(WriteFleetOutputs(options, *fleet, dir.File("out")).ok());
}

TEST(Fleet, RefusesAServerRunningAnotherStrategy) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  FleetOptions options = SmallFleet(server->address(), 2);
  options.strategy = "dc";
  auto fleet = RunFleet(options);
  EXPECT_EQ(fleet.status().code(), absl::StatusCode::kFailedPrecondition);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// The progress line names the joint solve the server is running while the count stands still.
TEST(Fleet, TheJointSolveUnderWayFollowsTheServersSettings) {
  pb::MapInfo info;
  info.set_strategy("cc-gsd");
  info.set_warmup_passages(8);
  info.set_relinearize_until_passages(128);
  info.set_passages_applied(3);
  EXPECT_EQ(JointSolveUnderWay(info), 4) << "in the warm-up";
  info.set_passages_applied(10);
  EXPECT_EQ(JointSolveUnderWay(info), 0) << "passage 11: sequential";
  info.set_passages_applied(31);
  EXPECT_EQ(JointSolveUnderWay(info), 32) << "the re-solve at 32";
  info.set_passages_applied(255);
  EXPECT_EQ(JointSolveUnderWay(info), 0) << "past the re-solves";
  info.set_strategy("dc");
  info.set_passages_applied(31);
  EXPECT_EQ(JointSolveUnderWay(info), 0) << "dc re-solves nothing";
  info.set_strategy("bogus");
  info.set_passages_applied(3);
  EXPECT_EQ(JointSolveUnderWay(info), 0);
}

}  // namespace
}  // namespace crowdmap
