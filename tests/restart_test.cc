// Stopping the server and starting it on the same file keeps the map, its versions and the queue.
#include "absl/strings/str_cat.h"
#include "server/storage/sqlite_db.h"
#include "server/storage/sqlite_map_store.h"
#include "server/testing/temp_dir.h"
#include "tests/support/map_compare.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// The restarts come after the map's warm-up (2 passages) and before its re-solve at 4 passages,
// so the worker must read the passages it already applied back from the store.
MapUpdateOptions WarmUp() {
  MapUpdateOptions options;
  options.warmup_passages = 2;
  options.relinearize_until_passages = 8;
  return options;
}

MapServerOptions WarmingUp(MapServerOptions options) {
  options.worker.update = WarmUp();
  return options;
}

TEST(ServiceRestart, MapVersionsAndQueueSurviveARestart) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  const Scenario scenario = ShortScenario();
  MapState map_before;
  pb::MapInfo info_before;
  {
    auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/true)));
    MockVehicle client(server->address());
    for (int i = 0; i < 3; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    auto info = client.WaitUntilIdle();
    ASSERT_TRUE(info.ok());
    info_before = *info;
    auto map = client.DownloadMap(MockVehicle::World());
    ASSERT_TRUE(map.ok());
    map_before = std::move(*map);
    server->Shutdown();
  }
  {
    // Same file, no worker: the map is intact, and new uploads wait in the queue.
    auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/false)));
    MockVehicle client(server->address());
    auto info = client.GetMapInfo();
    ASSERT_TRUE(info.ok());
    EXPECT_EQ(info->map_version(), info_before.map_version());
    EXPECT_EQ(info->landmark_count(), info_before.landmark_count());
    EXPECT_EQ(info->passages_applied(), 3);
    auto map = client.DownloadMap(MockVehicle::World());
    ASSERT_TRUE(map.ok());
    EXPECT_TRUE(MapsMatch(map_before, *map, 0.0, 0.0));
    EXPECT_EQ(map->version(), map_before.version());
    for (int i = 3; i < 5; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    // A re-sent old passage is still recognised after the restart.
    auto again = client.Upload(scenario.MakePassage(0));
    ASSERT_TRUE(again.ok());
    EXPECT_TRUE(again->duplicate());
    EXPECT_EQ(again->status().state(), pb::PASSAGE_STATE_APPLIED);
    server->Shutdown();
  }
  {
    auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/false)));
    MockVehicle client(server->address());
    auto info = client.GetMapInfo();
    ASSERT_TRUE(info.ok());
    EXPECT_EQ(info->passages_queued(), 2);
    EXPECT_EQ(info->map_version(), info_before.map_version());
    server->Shutdown();
  }
  {
    // With the worker the queued passages are applied, after the three earlier ones.
    auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/true)));
    MockVehicle client(server->address());
    auto info = client.WaitUntilIdle();
    ASSERT_TRUE(info.ok());
    EXPECT_EQ(info->passages_applied(), 5);
    EXPECT_GT(info->map_version(), info_before.map_version());
    EXPECT_GT(client.GetPassage("sim-4", scenario.MakePassage(4).passage_id)->id(),
              client.GetPassage("sim-2", scenario.MakePassage(2).passage_id)->id());
    // The worker read the three applied passages back from the store for the joint solve of the
    // fourth: the map is the uninterrupted one.
    auto map = client.DownloadMap(MockVehicle::World());
    ASSERT_TRUE(map.ok());
    EXPECT_TRUE(MapsMatch(MapFromPassages(scenario, 5, WarmUp()), *map, 1e-6, 1e-9));
  }
}

// A young map whose worker finds an applied passage without its upload (a map restored from a
// backup taken before the passage was excluded, its upload deleted since) starts all the same: it
// gives up its joint solves, which need every passage, and applies the next passages sequentially.
TEST(ServiceRestart, AYoungMapMissingAnAppliedPassagesUploadGoesOnWithoutJointSolves) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  const Scenario scenario = ShortScenario();
  {
    auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/true)));
    MockVehicle client(server->address());
    for (int i = 0; i < 3; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    ASSERT_TRUE(client.WaitUntilIdle().ok());
    server->Shutdown();
  }
  {
    auto queue = SqliteConnection::Open(SqliteQueuePath(db), 1000, /*read_only=*/false);
    ASSERT_TRUE(queue.ok()) << queue.status();
    ASSERT_TRUE((*queue)
                    ->Exec("UPDATE passages SET payload_pruned_unix_ms = 1 WHERE id = (SELECT MIN(id) FROM passages); "
                           "DELETE FROM passage_payloads WHERE id = (SELECT MIN(id) FROM passages)")
                    .ok());
  }
  auto server = StartTestServer(WarmingUp(TestServerOptions(db, /*start_worker=*/true)));
  ASSERT_NE(server, nullptr);
  MockVehicle client(server->address());
  for (int i = 3; i < 5; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
  auto info = client.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), 5);
  EXPECT_EQ(info->passages_failed(), 0);
  // The fourth passage, otherwise the young map's joint re-solve of its first four, is sequential.
  auto fourth = client.GetPassage("sim-3", scenario.MakePassage(3).passage_id);
  ASSERT_TRUE(fourth.ok()) << fourth.status();
  EXPECT_EQ(fourth->result().strategy().find("+joint"), std::string::npos) << fourth->result().strategy();
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// Passages left processing by a stop: the start-up requeue does not count the interrupted
// attempt, but a passage interrupted max_interruptions times is failed so that it cannot keep a
// crashing server from serving.
TEST(ServiceRestart, InterruptedAttemptsDoNotCountButEndlessInterruptionsFail) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  const Scenario scenario = ShortScenario();
  const Passage passage = scenario.MakePassage(0);
  {
    // Uploaded with no worker, then claimed as a worker would before a crash.
    auto server = StartTestServer(TestServerOptions(db, /*start_worker=*/false));
    MockVehicle client(server->address());
    ASSERT_TRUE(client.Upload(passage).ok());
    server->Shutdown();
  }
  for (int interruption = 1; interruption <= 2; ++interruption) {
    {
      auto store = CreateSqliteMapStore(db);
      ASSERT_TRUE(store.ok()) << store.status();
      auto claimed = (*store)->ClaimNextPassage();
      ASSERT_TRUE(claimed.ok() && claimed->has_value());
    }
    MapServerOptions options = TestServerOptions(db, /*start_worker=*/interruption == 2);
    options.worker.max_interruptions = 2;
    auto server = StartTestServer(options);
    MockVehicle client(server->address());
    if (interruption == 1) {
      absl::StatusOr<pb::PassageStatus> status = client.GetPassage(passage.vehicle_id, passage.passage_id);
      ASSERT_TRUE(status.ok());
      EXPECT_EQ(status->state(), pb::PASSAGE_STATE_QUEUED);
      EXPECT_EQ(status->attempts(), 0) << "the interrupted attempt does not count";
    } else {
      ASSERT_TRUE(client.WaitUntilIdle().ok());
      absl::StatusOr<pb::PassageStatus> status = client.GetPassage(passage.vehicle_id, passage.passage_id);
      ASSERT_TRUE(status.ok());
      EXPECT_EQ(status->state(), pb::PASSAGE_STATE_FAILED);
      EXPECT_NE(status->error().find("interrupted 2 times"), std::string::npos) << status->error();
    }
    server->Shutdown();
  }
}

// Uploads `passage` to a fresh database with no worker, then leaves it interrupted `times` times
// while being applied, as restarts during its update would (claimed, then requeued at start).
void UploadAndInterrupt(const std::string& db, const Passage& passage, int times) {
  {
    auto server = StartTestServer(TestServerOptions(db, /*start_worker=*/false));
    MockVehicle client(server->address());
    ASSERT_TRUE(client.Upload(passage).ok());
    server->Shutdown();
  }
  for (int interruption = 0; interruption < times; ++interruption) {
    auto store = CreateSqliteMapStore(db);
    ASSERT_TRUE(store.ok()) << store.status();
    ASSERT_TRUE((*store)->RequeueProcessingPassages().ok());
    auto claimed = (*store)->ClaimNextPassage();
    ASSERT_TRUE(claimed.ok() && claimed->has_value());
  }
}

// A passage whose joint solve keeps being interrupted (restarts during a solve of seconds) is
// applied by a sequential update instead of failing; interrupted fewer times, it is still solved
// jointly.
TEST(ServiceRestart, APassageWhoseJointSolveKeepsBeingInterruptedIsAppliedSequentially) {
  TempDir dir;
  const Passage passage = ShortScenario().MakePassage(0);
  for (const int interruptions : {2, 3}) {
    SCOPED_TRACE(interruptions);
    const std::string db = dir.File("map" + std::to_string(interruptions) + ".db");
    UploadAndInterrupt(db, passage, interruptions);
    MapServerOptions options = TestServerOptions(db, /*start_worker=*/true);
    options.worker.update.warmup_passages = 4;  // its first passage is a joint solve
    options.worker.sequential_after_interruptions = 3;
    auto server = StartTestServer(options);
    MockVehicle client(server->address());
    ASSERT_TRUE(client.WaitUntilIdle().ok());
    absl::StatusOr<pb::PassageStatus> status = client.GetPassage(passage.vehicle_id, passage.passage_id);
    ASSERT_TRUE(status.ok());
    EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED) << status->error();
    EXPECT_EQ(status->result().strategy(), interruptions >= 3 ? "cc-gsd" : "cc-gsd+joint");
    server->Shutdown();
  }
}
}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

TEST(ServiceRestart, ADamagedStoredMapIsRefusedAtStartNamingTheRecord) {
  TempDir dir;
  const std::string db = dir.File("map.db");
  {
    auto server = StartTestServer(TestServerOptions(db, /*start_worker=*/true));
    MockVehicle client(server->address());
    ASSERT_TRUE(client.Upload(ShortScenario().MakePassage(0)).ok());
    ASSERT_TRUE(client.WaitUntilIdle().ok());
    server->Shutdown();
  }
  int64_t damaged = 0;
  {
    auto connection = SqliteConnection::Open(db, 1000, /*read_only=*/false);
    ASSERT_TRUE(connection.ok()) << connection.status();
    auto select = (*connection)->Prepare("SELECT MIN(id) FROM landmarks");
    ASSERT_TRUE(select.ok());
    absl::StatusOr<bool> row = select->Step();
    ASSERT_TRUE(row.ok() && *row);
    damaged = select->Int(0);
    ASSERT_TRUE((*connection)->Exec(absl::StrCat("UPDATE landmarks SET cov_ee = -1 WHERE id = ", damaged)).ok());
  }
  absl::StatusOr<std::unique_ptr<MapServer>> server = MapServer::Start(TestServerOptions(db, true));
  ASSERT_FALSE(server.ok());
  EXPECT_EQ(server.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(server.status().message().find(absl::StrCat("stored map is damaged: landmark ", damaged, ": covariance")),
            std::string::npos)
      << server.status();
}

}  // namespace
}  // namespace crowdmap
