// OnboardLocalizer against an in-process server on an ephemeral port and a temporary SQLite file.
#include "client/api/onboard_localizer.h"

#include <cmath>
#include <set>
#include <tuple>

#include "core/localization/localization_testing.h"
#include "server/testing/temp_dir.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

using testing_localization::Feed;
using testing_localization::PassageInput;
using testing_localization::PassageInputs;

class OnboardLocalizerRpc : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = StartTestServer(TestServerOptions(dir_.File("map.db"), /*worker=*/true));
    ASSERT_NE(server_, nullptr);
    vehicle_ = std::make_unique<MockVehicle>(server_->address());
    for (int i = 0; i < 3; ++i) ASSERT_TRUE(vehicle_->Upload(scenario_.MakePassage(i)).ok());
    absl::StatusOr<pb::MapInfo> info = vehicle_->WaitUntilIdle();
    ASSERT_TRUE(info.ok()) << info.status();
    map_version_ = info->map_version();
  }

  TempDir dir_;
  Scenario scenario_ = ShortScenario(6, 60.0);
  std::unique_ptr<MapServer> server_;
  std::unique_ptr<MockVehicle> vehicle_;
  int64_t map_version_ = 0;
};

TEST_F(OnboardLocalizerRpc, LocalizesWithTilesDownloadedOnceEach) {
  const Passage passage = scenario_.MakePassage(10);
  absl::StatusOr<std::unique_ptr<OnboardLocalizer>> localizer =
      OnboardLocalizer::Create(vehicle_->client(), passage.calibration, passage.noise);
  ASSERT_TRUE(localizer.ok()) << localizer.status();
  int tracked = 0, used = 0;
  std::set<std::tuple<int, int, int>> visited;
  TileWindow window(1);
  for (const PassageInput& input : PassageInputs(passage)) {
    absl::StatusOr<StreamingUpdate> update = Feed(passage, input, localizer->get());
    ASSERT_TRUE(update.ok()) << update.status();
    if (!update->tracking) continue;
    ++tracked;
    used += update->detections_used;
    window.MoveTo(update->pose.position);
    for (const TileId& t : window.tiles()) visited.insert({t.z, t.x, t.y});
    const Eigen::Vector2d error =
        scenario_.frame().ToLocal(update->pose.position) - scenario_.TruePoseAt(update->pose.t_s).head<2>();
    EXPECT_LT(error.norm(), 5.0 * std::sqrt(update->pose.cov_en(0, 0) + update->pose.cov_en(1, 1)) + 0.5)
        << update->Brief();
  }
  EXPECT_GT(tracked, 500);
  EXPECT_GT(used, 20);
  EXPECT_EQ((*localizer)->filter().landmarks_held(), 6);
  EXPECT_EQ((*localizer)->map_version(), map_version_);
  // Every tile the window covered, once: the tiles of the first fix's window and the ones entered.
  EXPECT_GE((*localizer)->tiles_downloaded(), static_cast<int>(visited.size()));
  EXPECT_LE((*localizer)->tiles_downloaded(), static_cast<int>(visited.size()) + 9);
}

// The tiles are cached: with the server gone, the vehicle keeps localising with the tiles it holds
// (the route's landmarks all lie in the first window) and reports the tiles it could not fetch.
TEST_F(OnboardLocalizerRpc, KeepsLocalizingFromTheCacheWhenTheServerIsGone) {
  const Passage passage = scenario_.MakePassage(11);
  OnboardLocalizerOptions options;
  options.tile_radius = 2;  // the whole 60 s route lies in the first window
  absl::StatusOr<std::unique_ptr<OnboardLocalizer>> localizer =
      OnboardLocalizer::Create(vehicle_->client(), passage.calibration, passage.noise, options);
  ASSERT_TRUE(localizer.ok()) << localizer.status();
  const std::vector<PassageInput> inputs = PassageInputs(passage);
  size_t k = 0;
  for (; k < inputs.size() && !(*localizer)->filter().tracking(); ++k) {
    ASSERT_TRUE(Feed(passage, inputs[k], localizer->get()).ok());
  }
  const int downloaded = (*localizer)->tiles_downloaded();
  EXPECT_EQ(downloaded, 25);
  server_.reset();
  int used = 0;
  for (; k < inputs.size(); ++k) {
    absl::StatusOr<StreamingUpdate> update = Feed(passage, inputs[k], localizer->get());
    ASSERT_TRUE(update.ok()) << update.status();
    used += update->detections_used;
  }
  EXPECT_GT(used, 20);
  EXPECT_EQ((*localizer)->filter().landmarks_held(), 6);
  EXPECT_EQ((*localizer)->tiles_downloaded(), downloaded);
  EXPECT_GT((*localizer)->tiles_missing(), 0);
  EXPECT_EQ((*localizer)->last_download_error().code(), absl::StatusCode::kUnavailable);
}

TEST(OnboardLocalizer, ReportsAnUnreachableServer) {
  MapClientOptions client_options;
  client_options.server = "127.0.0.1:1";
  client_options.call_deadline = std::chrono::milliseconds(300);
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(client_options);
  ASSERT_TRUE(client.ok());
  const Passage passage = ShortScenario().MakePassage(0);
  absl::StatusOr<std::unique_ptr<OnboardLocalizer>> localizer =
      OnboardLocalizer::Create(client->get(), passage.calibration, passage.noise);
  ASSERT_TRUE(localizer.ok());
  absl::StatusOr<StreamingUpdate> update = (*localizer)->AddGnss(passage.gnss[0]);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_EQ((*localizer)->tiles_missing(), 9);
  EXPECT_EQ((*localizer)->tiles_downloaded(), 0);
  EXPECT_NE((*localizer)->last_download_error().message().find("GetTile"), std::string::npos)
      << (*localizer)->last_download_error();
}

}  // namespace
}  // namespace crowdmap
