// mapd as a child process: SIGKILL while it applies a passage, restart on the same file; every
// acknowledged passage ends applied exactly once and the map equals an uninterrupted run's.
// Repeat with CROWDMAP_CRASH_REPEAT=20 (see server/README.md).
#include <cstdlib>

#include "core/estimation/map_updater.h"
#include "core/map/map_window.h"
#include "server/storage/sqlite_map_store.h"
#include "server/testing/temp_dir.h"
#include "server/mapd_config.h"
#include "tests/support/map_compare.h"
#include "tests/support/mapd_process.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// With the default settings the 16th passage re-solves the map's first 15 jointly, so a round also
// covers a joint solve that needs passages applied before the kill, read back from the store.
constexpr int kPassages = 17;

// Polls until a passage is being applied; false if the queue drained first.
bool WaitUntilProcessing(MockVehicle* client) {
  for (int i = 0; i < 20000; ++i) {
    auto info = client->GetMapInfo();
    if (info.ok() && info->passages_processing() > 0) return true;
    if (info.ok() && info->queue_depth() == 0) return false;
  }
  return false;
}

void ExpectAllAppliedOnce(MockVehicle* client, const Scenario& scenario, const MapState& expected) {
  auto info = client->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), kPassages);
  EXPECT_EQ(info->passages_failed() + info->passages_rejected(), 0);
  for (int i = 0; i < kPassages; ++i) {
    const Passage p = scenario.MakePassage(i);
    auto status = client->GetPassage(p.vehicle_id, p.passage_id);
    ASSERT_TRUE(status.ok()) << status.status();
    EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED) << p.passage_id;
  }
  auto map = client->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(map.ok()) << map.status();
  // Same passages in the same order from the same map: the same arithmetic, so equal to rounding.
  EXPECT_TRUE(MapsMatch(expected, *map, 1e-6, 1e-9));
  EXPECT_EQ(map->version(), expected.version());
}

int Repeats() {
  const char* v = std::getenv("CROWDMAP_CRASH_REPEAT");
  return v != nullptr && std::atoi(v) > 0 ? std::atoi(v) : 1;
}

TEST(MapdCrash, SigkillWhileApplyingLosesNothingAndAppliesNothingTwice) {
  const Scenario scenario = ShortScenario(10, 60.0);
  const MapState expected = MapFromPassages(scenario, kPassages, ReplayableMapdUpdateOptions());
  int caught_processing = 0;
  for (int round = 0; round < Repeats(); ++round) {
    SCOPED_TRACE("round " + std::to_string(round));
    TempDir dir;
    const std::string db = dir.File("map.db");
    {
      MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, ReplayableMapdFlags());
      ASSERT_TRUE(mapd.WaitReady());
      MockVehicle client(mapd.address());
      for (int i = 0; i < kPassages; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
      caught_processing += WaitUntilProcessing(&client);
      const int status = mapd.Kill(SIGKILL);
      ASSERT_TRUE(WIFSIGNALED(status));
    }
    MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, ReplayableMapdFlags());
    ASSERT_TRUE(mapd.WaitReady());
    MockVehicle client(mapd.address());
    // The vehicles re-send everything (as if acknowledgements were lost): nothing is applied twice.
    for (int i = 0; i < kPassages; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    ExpectAllAppliedOnce(&client, scenario, expected);
    const int status = mapd.Kill(SIGTERM);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  }
  // The kill must have hit a passage in progress at least once, or the test proved little.
  EXPECT_GT(caught_processing, 0);
  std::printf("crash rounds=%d killed_while_processing=%d\n", Repeats(), caught_processing);
}

TEST(MapdCrash, SigtermFinishesThePassageInProgressAndExitsZero) {
  const Scenario scenario = ShortScenario(10, 60.0);
  const MapState expected = MapFromPassages(scenario, kPassages, ReplayableMapdUpdateOptions());
  TempDir dir;
  const std::string db = dir.File("map.db");
  {
    MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, ReplayableMapdFlags());
    ASSERT_TRUE(mapd.WaitReady());
    MockVehicle client(mapd.address());
    for (int i = 0; i < kPassages; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    WaitUntilProcessing(&client);
    const int status = mapd.Kill(SIGTERM);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  }
  {
    // Nothing was left half-done: no passage is processing in the file.
    auto store = CreateSqliteMapStore(db);
    ASSERT_TRUE(store.ok());
    auto stats = (*store)->GetStats();
    ASSERT_TRUE(stats.ok());
    EXPECT_EQ(stats->passages_by_state[static_cast<int>(PassageState::kProcessing)], 0);
  }
  MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, ReplayableMapdFlags());
  ASSERT_TRUE(mapd.WaitReady());
  MockVehicle client(mapd.address());
  ExpectAllAppliedOnce(&client, scenario, expected);
}

// mapd re-linearises stale passages once its queue is empty (--relinearize-sigmas): a SIGKILL in the
// middle of that leaves the committed map as it was before the change under way (one transaction),
// and the restarted server applies nothing twice, loads a map that passes its checks and whose
// whole information factorises. (Which map exactly depends on when the queue emptied, so it is
// not compared with a replay.)
TEST(MapdCrash, SigkillWhileRelinearizingLeavesAConsistentMap) {
  const Scenario scenario = ShortScenario(10, 60.0);
  const std::vector<std::string> flags = {"--warmup-passages", "0", "--relinearize-until-passages", "0",
                                          "--relinearize-sigmas", "0.5"};
  TempDir dir;
  const std::string db = dir.File("map.db");
  bool caught_relinearizing = false;
  {
    MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, flags);
    ASSERT_TRUE(mapd.WaitReady());
    MockVehicle client(mapd.address());
    for (int i = 0; i < kPassages; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
    for (int i = 0; i < 200000; ++i) {
      auto info = client.GetMapInfo();
      if (!info.ok() || info->queue_depth() > 0) continue;
      caught_relinearizing = info->relinearizations_due() > 0;
      break;
    }
    const int status = mapd.Kill(SIGKILL);
    ASSERT_TRUE(WIFSIGNALED(status));
  }
  EXPECT_TRUE(caught_relinearizing) << "the kill came after the re-linearisations: the test proved little";
  {
    MapdProcess mapd(db, dir.File("mapd.log"), /*port=*/0, flags);
    ASSERT_TRUE(mapd.WaitReady()) << "the restarted server refused its map";
    MockVehicle client(mapd.address());
    for (int i = 0; i < kPassages; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());  // resent
    auto info = client.WaitUntilIdle();
    ASSERT_TRUE(info.ok()) << info.status();
    EXPECT_EQ(info->passages_applied(), kPassages);
    EXPECT_EQ(info->passages_failed() + info->passages_rejected() + info->passages_quarantined(), 0);
    EXPECT_EQ(mapd.Kill(SIGTERM), 0);
  }
  auto store = CreateSqliteMapStore(db);
  ASSERT_TRUE(store.ok()) << store.status();
  MapState stored;
  ASSERT_TRUE((*store)->LoadMap(&stored).ok());
  EXPECT_TRUE(CheckStoredMap(stored).ok()) << CheckStoredMap(stored);
  std::vector<LandmarkId> ids;
  stored.ForEachLandmark([&](const Landmark& l) { ids.push_back(l.id); });
  ASSERT_FALSE(ids.empty());
  absl::StatusOr<MapWindow> whole = MapWindow::Build(stored, ids, MapWindowOptions{0});
  EXPECT_TRUE(whole.ok()) << whole.status();
}

}  // namespace
}  // namespace crowdmap
