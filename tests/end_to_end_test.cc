// 40 simulated passages uploaded by the mock vehicle client give the map `mapsim experiment`
// computes on the same seed with cc-gsd.
#include "client/mapsim/experiment.h"
#include "server/testing/temp_dir.h"
#include "tests/support/map_compare.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

TEST(EndToEnd, UploadedPassagesGiveTheSimulatorsMap) {
  constexpr int kPassages = 40;
  ExperimentOptions experiment;
  experiment.passages = kPassages;
  experiment.strategy = "cc-gsd";
  experiment.scenario.seed = 7;
  auto expected = RunExperiment(experiment);
  ASSERT_TRUE(expected.ok()) << expected.status();
  ASSERT_EQ(expected->failed_passages, 0);

  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db")));
  ASSERT_NE(server, nullptr);
  MockVehicle vehicle(server->address());
  auto scenario = Scenario::Create(experiment.scenario);
  ASSERT_TRUE(scenario.ok());
  for (int i = 0; i < kPassages; ++i) {
    auto r = vehicle.Upload(scenario->MakePassage(i));
    ASSERT_TRUE(r.ok()) << r.status();
  }
  auto info = vehicle.WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), kPassages);
  auto map = vehicle.DownloadMap(MockVehicle::World());
  ASSERT_TRUE(map.ok()) << map.status();
  EXPECT_TRUE(MapsMatch(expected->final_map, *map, 1e-3, 1e-6));
  EXPECT_EQ(map->version(), expected->final_map.version());
}

}  // namespace
}  // namespace crowdmap
