// LocalizePassage against an in-process server on an ephemeral port and a temporary SQLite file.
#include <chrono>
#include <cmath>
#include <memory>
#include <thread>
#include <vector>

#include "core/estimation/map_update_options.h"
#include "core/estimation/vehicle_calibration.h"
#include "absl/strings/match.h"
#include "client/api/map_client.h"
#include "core/localization/passage_localizer.h"
#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

class LocalizeRpc : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = StartTestServer(TestServerOptions(dir_.File("map.db"), /*worker=*/true));
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<MockVehicle>(server_->address());
    for (int i = 0; i < 3; ++i) ASSERT_TRUE(client_->Upload(scenario_.MakePassage(i)).ok());
    absl::StatusOr<pb::MapInfo> info = client_->WaitUntilIdle();
    ASSERT_TRUE(info.ok()) << info.status();
    ASSERT_EQ(info->passages_applied(), 3);
    map_version_ = info->map_version();
  }

  TempDir dir_;
  Scenario scenario_ = ShortScenario();
  std::unique_ptr<MapServer> server_;
  std::unique_ptr<MockVehicle> client_;
  int64_t map_version_ = 0;
};

// A localisation reads its landmarks' joint covariance whole (up to 2,000 landmarks), as a read
// with covariances does: it takes a place among those (mapd --max-covariance-reads) or is told to
// retry, and the client retries it as it does the reads.
TEST_F(LocalizeRpc, TakesAPlaceAmongTheReadsWithCovariances) {
  std::vector<std::unique_ptr<ConcurrentCalls::Lease>> held;
  for (;;) {
    absl::StatusOr<std::unique_ptr<ConcurrentCalls::Lease>> place = server_->covariance_reads()->Enter();
    if (!place.ok()) break;
    held.push_back(*std::move(place));
  }
  ASSERT_FALSE(held.empty());
  pb::Passage wire;
  PassageToProto(scenario_.MakePassage(10), &wire);
  MapClientOptions once;
  once.server = server_->address();
  once.max_attempts = 1;
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(once);
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<pb::LocalizePassageResponse> refused = (*client)->LocalizePassage(wire);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "--max-covariance-reads")) << refused.status();
  std::thread give_back([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // the first attempt refused, the retry 1 s later
    held.clear();
  });
  MapClientOptions retrying;  // the defaults: it waits as the server's pushback says (1 s)
  retrying.server = server_->address();
  absl::StatusOr<std::unique_ptr<MapClient>> patient = MapClient::Create(retrying);
  ASSERT_TRUE(patient.ok()) << patient.status();
  absl::StatusOr<pb::LocalizePassageResponse> served = (*patient)->LocalizePassage(wire);
  give_back.join();
  EXPECT_TRUE(served.ok()) << served.status();
  EXPECT_EQ(server_->covariance_reads()->running(), 0) << "its place given back";
}

TEST_F(LocalizeRpc, ReturnsTheTrajectoryWithCovarianceAndLeavesTheMapAlone) {
  const Passage passage = scenario_.MakePassage(10);
  pb::Passage wire;
  PassageToProto(passage, &wire);
  absl::StatusOr<pb::LocalizePassageResponse> response = client_->client()->LocalizePassage(wire);
  ASSERT_TRUE(response.ok()) << response.status();
  EXPECT_EQ(response->map_version(), map_version_);
  EXPECT_EQ(response->landmarks_used_size(), 6);
  EXPECT_GT(response->detections_used(), 0);
  EXPECT_GT(response->dof(), 0);
  ASSERT_GT(response->poses_size(), 40);
  for (const pb::LocalizedPose& p : response->poses()) {
    ASSERT_EQ(p.covariance_size(), 9);
    EXPECT_GT(p.covariance(0), 0.0);
    EXPECT_GT(p.covariance(8), 0.0);
    EXPECT_DOUBLE_EQ(p.covariance(1), p.covariance(3));
    const Eigen::Vector2d error = scenario_.frame().ToLocal({p.lat_deg(), p.lon_deg()}) -
                                  scenario_.TruePoseAt(p.t_s()).head<2>();
    EXPECT_LT(error.norm(), 5.0 * std::sqrt(p.covariance(0) + p.covariance(4)) + 0.5) << "t=" << p.t_s();
  }
  // The same as localising in-process against the map read back.
  absl::StatusOr<MapState> map = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(map.ok()) << map.status();
  absl::StatusOr<LocalizationMap> local_map = ReadLocalizationMap(*map, passage);
  ASSERT_TRUE(local_map.ok()) << local_map.status();
  // A vehicle without a calibration record: its camera yaw offset estimated with the map update's prior.
  PassageLocalizerOptions options;
  options.camera_yaw_sigma_rad = MapUpdateOptions().camera_yaw_prior_sigma_rad;
  absl::StatusOr<PassageLocalization> local = LocalizePassage(passage, *local_map, options);
  ASSERT_TRUE(local.ok()) << local.status();
  EXPECT_EQ(response->camera_yaw_offset_rad(), 0.0);
  EXPECT_GT(response->camera_yaw_estimate_sigma_rad(), 0.0);
  EXPECT_NEAR(response->camera_yaw_estimate_sigma_rad(), local->camera_yaw_sigma_rad, 1e-9);
  EXPECT_NEAR(response->camera_yaw_estimate_rad(), local->camera_yaw_offset_rad, 1e-9);
  ASSERT_EQ(static_cast<int>(local->poses.size()), response->poses_size());
  for (size_t k = 0; k < local->poses.size(); ++k) {
    EXPECT_NEAR(local->poses[k].position.lat_deg, response->poses(k).lat_deg(), 1e-9);
    EXPECT_NEAR(local->poses[k].heading_en_rad, response->poses(k).heading_rad(), 1e-7);
    EXPECT_NEAR(local->poses[k].cov_en(0, 0), response->poses(k).covariance(0), 1e-6);
  }
  // Read-only.
  absl::StatusOr<pb::MapInfo> info = client_->GetMapInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->map_version(), map_version_);
}

TEST_F(LocalizeRpc, RefusesAnInvalidPassage) {
  pb::Passage wire;
  PassageToProto(scenario_.MakePassage(10), &wire);
  wire.mutable_gnss(3)->set_lat_deg(91.0);
  absl::StatusOr<pb::LocalizePassageResponse> response = client_->client()->LocalizePassage(wire);
  ASSERT_FALSE(response.ok());
  EXPECT_EQ(response.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(response.status().message().find("gnss[3].lat_deg"), std::string::npos) << response.status();
}

// A passage naming more distinct landmarks than one joint covariance read may hold is refused by
// name, before the map is read.
TEST_F(LocalizeRpc, RefusesAPassageNamingMoreLandmarksThanOneReadHolds) {
  Passage passage = scenario_.MakePassage(10);
  const Detection first = passage.detections.front();
  passage.detections.clear();
  for (LandmarkId id = 1; id <= 2001; ++id) {
    Detection d = first;
    d.landmark_id = id;
    d.t_s += 1e-3 * static_cast<double>(id);  // a frame holds at most 1,000 detections
    passage.detections.push_back(d);
  }
  pb::Passage wire;
  PassageToProto(passage, &wire);
  absl::StatusOr<pb::LocalizePassageResponse> response = client_->client()->LocalizePassage(wire);
  ASSERT_FALSE(response.ok());
  EXPECT_EQ(response.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(response.status().message().find("passage.detections: 2001 distinct landmarks"), std::string::npos)
      << response.status();
  passage.detections.resize(2000);  // repeated ids count once
  passage.detections.push_back(passage.detections.back());
  PassageToProto(passage, &wire);
  response = client_->client()->LocalizePassage(wire);
  EXPECT_NE(response.status().code(), absl::StatusCode::kInvalidArgument) << response.status();
}

// A vehicle never seen is localised with the fleet's mean camera yaw (FleetCameraYawPrior over the
// records ListVehicles serves, as the map update would start it), once the map has enough vehicles.
TEST(LocalizeRpcFleet, AVehicleNeverSeenTakesTheFleetsMeanCameraYaw) {
  TempDir dir;
  MapServerOptions options = TestServerOptions(dir.File("map.db"), /*worker=*/true);
  options.worker.update.estimate_camera_yaw = true;
  options.worker.update.fleet_camera_yaw_prior_vehicles = 3;
  auto server = StartTestServer(options);
  ASSERT_NE(server, nullptr);
  MockVehicle client(server->address());
  ScenarioOptions yaw_bias = ShortScenario().options();
  yaw_bias.noise = NoiseConfig::kYawBias;  // every camera turned alike
  const Scenario scenario = *Scenario::Create(yaw_bias);
  pb::Passage wire;
  PassageToProto(scenario.MakePassage(10), &wire);
  auto localize = [&]() {
    absl::StatusOr<pb::LocalizePassageResponse> response = client.client()->LocalizePassage(wire);
    EXPECT_TRUE(response.ok()) << response.status();
    return response.ok() ? response->camera_yaw_offset_rad() : std::nan("");
  };
  for (int i = 0; i < 2; ++i) ASSERT_TRUE(client.Upload(scenario.MakePassage(i)).ok());
  ASSERT_TRUE(client.WaitUntilIdle().ok());
  EXPECT_EQ(localize(), 0.0) << "two vehicles are not a fleet of three";

  ASSERT_TRUE(client.Upload(scenario.MakePassage(2)).ok());
  ASSERT_TRUE(client.WaitUntilIdle().ok());
  absl::StatusOr<pb::ListVehiclesResponse> list = client.client()->ListVehicles();
  ASSERT_TRUE(list.ok()) << list.status();
  ASSERT_EQ(list->vehicles_size(), 3);
  std::vector<VehicleCalibration> fleet;
  for (const pb::Vehicle& v : list->vehicles()) {
    VehicleCalibration record;
    record.vehicle_id = v.vehicle_id();
    record.camera_yaw_offset_rad = v.camera_yaw_offset_rad();
    record.camera_yaw_variance_rad2 = v.camera_yaw_sigma_rad() * v.camera_yaw_sigma_rad();
    fleet.push_back(record);
  }
  const std::optional<VehicleCalibration> prior =
      FleetCameraYawPrior(fleet, wire.vehicle_id(), 3, options.worker.update.camera_yaw_prior_sigma_rad);
  ASSERT_TRUE(prior.has_value());
  const double offset = localize();
  EXPECT_NE(offset, 0.0);
  EXPECT_NEAR(offset, prior->camera_yaw_offset_rad, 1e-9);
  // Estimated again from the passage, the fleet's width its prior: the estimate lies within three
  // of its sigmas of the camera's true offset.
  absl::StatusOr<pb::LocalizePassageResponse> response = client.client()->LocalizePassage(wire);
  ASSERT_TRUE(response.ok()) << response.status();
  EXPECT_GT(response->camera_yaw_estimate_sigma_rad(), 0.0);
  EXPECT_LT(response->camera_yaw_estimate_sigma_rad(), std::sqrt(prior->camera_yaw_variance_rad2));
  EXPECT_LT(std::abs(response->camera_yaw_estimate_rad() - scenario.CameraYawErrorRad(10)),
            3.0 * response->camera_yaw_estimate_sigma_rad());
  EXPECT_EQ(client.client()->GetVehicle(wire.vehicle_id()).status().code(), absl::StatusCode::kNotFound)
      << "localising records nothing";
}

}  // namespace
}  // namespace crowdmap
