// Every RPC of mapservice.v1 against an in-process server on an ephemeral port and a temporary
// SQLite file.
#include <grpcpp/generic/generic_stub.h>

#include <cmath>
#include <future>
#include <map>
#include <random>
#include <set>
#include <thread>
#include <tuple>

#include "core/estimation/passage_exclusion.h"
#include "core/map/map_window.h"
#include "server/map_service.h"
#include "server/storage/sqlite_map_store.h"
#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/map_compare.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

class ServiceRpc : public ::testing::Test {
 protected:
  void Start(bool worker, int64_t max_queue = 10000, bool estimate_camera_yaw = false) {
    MapServerOptions options = TestServerOptions(dir_.File("map.db"), worker);
    options.max_queue = max_queue;
    options.worker.update.estimate_camera_yaw = estimate_camera_yaw;
    server_ = StartTestServer(options);
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<MockVehicle>(server_->address());
  }

  pb::UploadPassageResponse MustUpload(const Passage& p) {
    auto r = client_->Upload(p);
    EXPECT_TRUE(r.ok()) << r.status();
    return r.ok() ? *r : pb::UploadPassageResponse();
  }

  TempDir dir_;
  Scenario scenario_ = ShortScenario();
  std::unique_ptr<MapServer> server_;
  std::unique_ptr<MockVehicle> client_;
};

TEST_F(ServiceRpc, UploadPassageAcknowledgesQueuedWithItsId) {
  Start(/*worker=*/false);
  const pb::UploadPassageResponse r = MustUpload(scenario_.MakePassage(0));
  EXPECT_GT(r.status().id(), 0);
  EXPECT_EQ(r.status().state(), pb::PASSAGE_STATE_QUEUED);
  EXPECT_FALSE(r.duplicate());
  // The acknowledgement follows the commit: the store has it.
  auto stored = server_->store()->GetPassage(r.status().id());
  ASSERT_TRUE(stored.ok());
  EXPECT_EQ(stored->passage_id, scenario_.MakePassage(0).passage_id);
}

TEST_F(ServiceRpc, ChunkedUploadCarriesPassagesAboveTheUnaryLimit) {
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), false);
  options.max_message_mb = 1;
  server_ = StartTestServer(options);
  client_ = std::make_unique<MockVehicle>(server_->address());
  ScenarioOptions big;
  big.landmarks = 4;
  big.duration_s = 165;
  big.odometry_rate_hz = 400;  // about 66000 samples, about 2 MiB
  auto scenario = Scenario::Create(big);
  ASSERT_TRUE(scenario.ok());
  pb::Passage wire;
  PassageToProto(scenario->MakePassage(0), &wire);
  ASSERT_GT(wire.ByteSizeLong(), 1u << 20);
  EXPECT_EQ(client_->UploadOnce(wire).status().code(), absl::StatusCode::kResourceExhausted);
  auto r = client_->UploadChunked(wire, 256 << 10);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->status().state(), pb::PASSAGE_STATE_QUEUED);
  EXPECT_EQ(r->status().size_bytes(), static_cast<int64_t>(wire.ByteSizeLong()));
  auto payload = server_->store()->GetPassagePayload(r->status().id());
  ASSERT_TRUE(payload.ok());
  pb::Passage back;
  ASSERT_TRUE(back.ParseFromString(*payload));
  EXPECT_EQ(back.odometry_size(), wire.odometry_size());
}

TEST_F(ServiceRpc, GetPassageFindsByIdAndByKeyAndReportsNotFound) {
  Start(false);
  const int64_t id = MustUpload(scenario_.MakePassage(0)).status().id();
  const Passage first = scenario_.MakePassage(0);
  auto by_key = client_->GetPassage(first.vehicle_id, first.passage_id);
  ASSERT_TRUE(by_key.ok()) << by_key.status();
  EXPECT_EQ(by_key->id(), id);
  grpc::ClientContext ctx;
  pb::GetPassageRequest request;
  request.set_id(id);
  pb::PassageStatus by_id;
  ASSERT_TRUE(client_->stub()->GetPassage(&ctx, request, &by_id).ok());
  EXPECT_EQ(by_id.passage_id(), first.passage_id);
  EXPECT_EQ(client_->GetPassage("sim-0", "nope").status().code(), absl::StatusCode::kNotFound);
  grpc::ClientContext ctx2;
  EXPECT_EQ(client_->stub()->GetPassage(&ctx2, pb::GetPassageRequest(), &by_id).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  // The id and the key together must name one passage.
  grpc::ClientContext both_ctx;
  request.set_vehicle_id(first.vehicle_id);
  request.set_passage_id(first.passage_id);
  EXPECT_TRUE(client_->stub()->GetPassage(&both_ctx, request, &by_id).ok());
  grpc::ClientContext other_ctx;
  request.set_passage_id("another");
  const grpc::Status other = client_->stub()->GetPassage(&other_ctx, request, &by_id);
  EXPECT_EQ(other.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(other.error_message().find("id: passage"), std::string::npos) << other.error_message();
  // An identifier no upload could have is refused, naming the field but not echoing it.
  for (const std::string& bad : {std::string(10000, 'V'), std::string("with space")}) {
    auto refused = client_->GetPassage(bad, "p");
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
    EXPECT_EQ(std::string(refused.status().message()).rfind("vehicle_id: ", 0), 0u) << refused.status();
    EXPECT_LT(refused.status().message().size(), 200u);
  }
  grpc::ClientContext vehicle_ctx;
  pb::GetVehicleRequest vehicle_request;
  vehicle_request.set_vehicle_id(std::string(1 << 20, 'V'));
  pb::Vehicle vehicle;
  const grpc::Status long_vehicle = client_->stub()->GetVehicle(&vehicle_ctx, vehicle_request, &vehicle);
  EXPECT_EQ(long_vehicle.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_LT(long_vehicle.error_message().size(), 200u);
  Passage long_id = scenario_.MakePassage(1);
  long_id.vehicle_id = std::string(300000, 'V');
  auto upload = client_->Upload(long_id);
  EXPECT_EQ(upload.status().code(), absl::StatusCode::kInvalidArgument) << upload.status();
  EXPECT_LT(upload.status().message().size(), 200u);
}

TEST_F(ServiceRpc, ListPassagesPagesInArrivalOrderAndFilters) {
  Start(false);
  for (int i = 0; i < 5; ++i) MustUpload(scenario_.MakePassage(i));
  std::vector<std::string> seen;
  std::string token;
  int pages = 0;
  do {
    grpc::ClientContext ctx;
    pb::ListPassagesRequest request;
    request.set_page_size(2);
    request.set_page_token(token);
    pb::ListPassagesResponse response;
    ASSERT_TRUE(client_->stub()->ListPassages(&ctx, request, &response).ok());
    for (const auto& p : response.passages()) seen.push_back(p.passage_id());
    token = response.next_page_token();
    ++pages;
  } while (!token.empty());
  EXPECT_EQ(pages, 3);
  std::vector<std::string> expected;
  for (int i = 0; i < 5; ++i) expected.push_back(scenario_.MakePassage(i).passage_id);
  EXPECT_EQ(seen, expected);

  grpc::ClientContext ctx;
  pb::ListPassagesRequest applied_only;
  applied_only.set_state(pb::PASSAGE_STATE_APPLIED);
  pb::ListPassagesResponse none;
  ASSERT_TRUE(client_->stub()->ListPassages(&ctx, applied_only, &none).ok());
  EXPECT_EQ(none.passages_size(), 0);
  grpc::ClientContext bad_ctx;
  pb::ListPassagesRequest bad;
  bad.set_page_token("garbage");
  EXPECT_EQ(client_->stub()->ListPassages(&bad_ctx, bad, &none).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  // A token continues only the listing that issued it: with another filter it is refused.
  grpc::ClientContext first_ctx;
  pb::ListPassagesRequest first;
  first.set_page_size(2);
  pb::ListPassagesResponse first_page;
  ASSERT_TRUE(client_->stub()->ListPassages(&first_ctx, first, &first_page).ok());
  ASSERT_FALSE(first_page.next_page_token().empty());
  grpc::ClientContext other_ctx;
  pb::ListPassagesRequest other;
  other.set_vehicle_id("sim-3");
  other.set_page_token(first_page.next_page_token());
  const grpc::Status refused = client_->stub()->ListPassages(&other_ctx, other, &none);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(refused.error_message().rfind("page_token: issued for a request with other filters", 0), 0u)
      << refused.error_message();
}

TEST_F(ServiceRpc, WorkerAppliesPassagesAndMapInfoCountsThem) {
  Start(true);
  for (int i = 0; i < 3; ++i) MustUpload(scenario_.MakePassage(i));
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_applied(), 3);
  EXPECT_EQ(info->server_version(), CROWDMAP_VERSION);
  EXPECT_EQ(info->queue_depth(), 0);
  EXPECT_EQ(info->landmark_count(), 6);
  EXPECT_GT(info->map_version(), 0);
  EXPECT_EQ(info->strategy(), "cc-gsd");
  auto status = client_->GetPassage("sim-2", scenario_.MakePassage(2).passage_id);
  ASSERT_TRUE(status.ok());
  EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED);
  EXPECT_EQ(status->result().map_version(), info->map_version());
  EXPECT_GT(status->result().landmarks_updated(), 0);
  EXPECT_GT(status->result().nodes(), 0);
  EXPECT_EQ(client_->GetPassage("sim-0", scenario_.MakePassage(0).passage_id)->result().landmarks_created(), 6);
}

TEST_F(ServiceRpc, GetVehicleAndListVehiclesServeTheEstimatedCameraYaw) {
  Start(true, 10000, /*estimate_camera_yaw=*/true);
  ScenarioOptions fleet = scenario_.options();
  fleet.vehicles = 2;
  fleet.vehicle_yaw_bias_sigma_rad = 0.5 * M_PI / 180.0;
  const Scenario scenario = *Scenario::Create(fleet);
  for (int i = 0; i < 3; ++i) MustUpload(scenario.MakePassage(i));
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  ASSERT_EQ(info->passages_applied(), 3);

  auto v0 = client_->client()->GetVehicle("sim-v0");
  ASSERT_TRUE(v0.ok()) << v0.status();
  EXPECT_EQ(v0->vehicle_id(), "sim-v0");
  EXPECT_EQ(v0->passages(), 2);
  EXPECT_GT(v0->camera_yaw_sigma_rad(), 0.0);
  EXPECT_LT(v0->camera_yaw_sigma_rad(), MapUpdateOptions().camera_yaw_prior_sigma_rad);
  EXPECT_GT(v0->map_version(), 0);
  EXPECT_LE(v0->map_version(), info->map_version());
  EXPECT_EQ(v0->updated_unix_ms(), scenario.MakePassage(2).start_time_unix_ms);
  auto missing = client_->client()->GetVehicle("sim-v7");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client_->client()->GetVehicle("").status().code(), absl::StatusCode::kInvalidArgument);

  auto list = client_->client()->ListVehicles();
  ASSERT_TRUE(list.ok()) << list.status();
  ASSERT_EQ(list->vehicles_size(), 2);
  EXPECT_EQ(list->vehicles(0).vehicle_id(), "sim-v0");
  EXPECT_EQ(list->vehicles(0).camera_yaw_offset_rad(), v0->camera_yaw_offset_rad());
  EXPECT_EQ(list->vehicles(1).vehicle_id(), "sim-v1");
  EXPECT_EQ(list->vehicles(1).passages(), 1);

  // Pages of one vehicle: the token carries on after the last one given.
  std::vector<std::string> paged;
  std::string token;
  int pages = 0;
  do {
    grpc::ClientContext ctx;
    pb::ListVehiclesRequest request;
    request.set_page_size(1);
    request.set_page_token(token);
    pb::ListVehiclesResponse page;
    ASSERT_TRUE(client_->stub()->ListVehicles(&ctx, request, &page).ok());
    ASSERT_LE(page.vehicles_size(), 1);
    for (const pb::Vehicle& v : page.vehicles()) paged.push_back(v.vehicle_id());
    token = page.next_page_token();
    ASSERT_LE(++pages, 3);
  } while (!token.empty());
  EXPECT_EQ(paged, (std::vector<std::string>{"sim-v0", "sim-v1"}));
  for (const auto& [size, bad_token, field] : std::vector<std::tuple<int, std::string, std::string>>{
           {-1, "", "page_size"}, {1001, "", "page_size"}, {1, "after:zz:0000000000000000", "page_token"},
           {1, MakePageToken(3, "passages|0|"), "page_token"}}) {
    grpc::ClientContext ctx;
    pb::ListVehiclesRequest request;
    request.set_page_size(size);
    request.set_page_token(bad_token);
    pb::ListVehiclesResponse page;
    const grpc::Status refused = client_->stub()->ListVehicles(&ctx, request, &page);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << size << " " << bad_token;
    EXPECT_EQ(refused.error_message().rfind(field + ":", 0), 0u) << refused.error_message();
  }
}

TEST_F(ServiceRpc, QueryRegionPagesCoverTheMapWithCovariances) {
  Start(true);
  for (int i = 0; i < 3; ++i) MustUpload(scenario_.MakePassage(i));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  auto full = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(full.ok()) << full.status();
  ASSERT_EQ(full->landmark_count(), 6u);
  std::set<int64_t> ids;
  std::string token;
  do {
    grpc::ClientContext ctx;
    pb::QueryRegionRequest request;
    *request.mutable_box() = MockVehicle::World();
    request.set_page_size(4);
    request.set_page_token(token);
    request.set_include_cross_covariance(true);
    pb::QueryRegionResponse response;
    ASSERT_TRUE(client_->stub()->QueryRegion(&ctx, request, &response).ok());
    for (const pb::Landmark& l : response.landmarks()) {
      ids.insert(l.id());
      const Landmark& expected = *full->FindLandmark(l.id());
      EXPECT_NEAR(l.cov_en_m2().ee(), expected.cov_en_m2(0, 0), 1e-9);
      EXPECT_GT(l.cov_en_m2().ee(), 0.0);
      EXPECT_EQ(l.tile().z(), 16);
    }
    for (const pb::CrossCovariance& c : response.cross_covariances()) {
      EXPECT_LT(c.first_id(), c.second_id());
      absl::StatusOr<Eigen::MatrixXd> joint = JointCovariance(*full, {c.first_id(), c.second_id()});
      ASSERT_TRUE(joint.ok()) << joint.status();
      EXPECT_NEAR(c.cov_m2().en(), (*joint)(0, 3), 1e-9);
    }
    token = response.next_page_token();
    if (!token.empty()) {
      // The same token with another box is refused.
      grpc::ClientContext other_ctx;
      pb::QueryRegionRequest other = request;
      other.mutable_box()->set_max_lat_deg(request.box().max_lat_deg() - 1e-6);
      other.set_page_token(token);
      pb::QueryRegionResponse ignored;
      const grpc::Status refused = client_->stub()->QueryRegion(&other_ctx, other, &ignored);
      EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
      EXPECT_EQ(refused.error_message().rfind("page_token:", 0), 0u) << refused.error_message();
    }
  } while (!token.empty());
  EXPECT_EQ(ids.size(), 6u);
  // The download is the region's joint Gaussian: one factor on all its landmarks.
  EXPECT_EQ(full->factor_count(), 1u);
  // A page's joint covariance is read whole: pages with covariances hold at most 2,000 landmarks,
  // and a larger one is refused by name whatever the map holds (without covariances, 10,000).
  for (const auto& [size, cross, ok] : std::vector<std::tuple<int, bool, bool>>{
           {2000, true, true}, {2001, true, false}, {10000, true, false}, {10000, false, true}}) {
    grpc::ClientContext ctx;
    pb::QueryRegionRequest request;
    *request.mutable_box() = MockVehicle::World();
    request.set_page_size(size);
    request.set_include_cross_covariance(cross);
    pb::QueryRegionResponse response;
    const grpc::Status status = client_->stub()->QueryRegion(&ctx, request, &response);
    EXPECT_EQ(status.ok(), ok) << size << " " << cross << ": " << status.error_message();
    if (!ok) {
      EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
      EXPECT_EQ(status.error_message().rfind("page_size:", 0), 0u) << status.error_message();
    }
  }
  // Without a box (which would read as the point (0, 0)) the request is refused by name.
  grpc::ClientContext no_box_ctx;
  pb::QueryRegionResponse no_box_response;
  const grpc::Status no_box = client_->stub()->QueryRegion(&no_box_ctx, pb::QueryRegionRequest(), &no_box_response);
  EXPECT_EQ(no_box.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(no_box.error_message(), "box: required");
}

// The packed layout carries the same matrix as the blocks, on both reads with covariances; a
// layout asked without the covariance, or outside the enum, is refused by name.
TEST_F(ServiceRpc, PackedCovarianceIsTheMatrixOfTheBlocks) {
  Start(true);
  for (int i = 0; i < 2; ++i) MustUpload(scenario_.MakePassage(i));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  pb::QueryRegionRequest region;
  *region.mutable_box() = MockVehicle::World();
  region.set_include_cross_covariance(true);
  pb::QueryRegionResponse blocks, packed;
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(client_->stub()->QueryRegion(&ctx, region, &blocks).ok());
  }
  region.set_covariance_format(pb::COVARIANCE_FORMAT_PACKED);
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(client_->stub()->QueryRegion(&ctx, region, &packed).ok());
  }
  const int n = blocks.landmarks_size();
  ASSERT_GE(n, 3);
  ASSERT_EQ(blocks.cross_covariances_size(), n * (n - 1) / 2);
  EXPECT_FALSE(blocks.has_packed_covariance());
  ASSERT_EQ(packed.landmarks_size(), n);
  EXPECT_EQ(packed.cross_covariances_size(), 0);
  absl::StatusOr<Eigen::MatrixXd> matrix = CovarianceFromPacked(packed.packed_covariance(), n, "packed_covariance");
  ASSERT_TRUE(matrix.ok()) << matrix.status();
  absl::StatusOr<Eigen::MatrixXd> expected =
      CovarianceFromBlocks(blocks.landmarks(), blocks.cross_covariances(), "cross_covariances");
  ASSERT_TRUE(expected.ok()) << expected.status();
  EXPECT_LT((*matrix - *expected).cwiseAbs().maxCoeff(), 1e-15);
  EXPECT_EQ(blocks.covariance_bound(), pb::COVARIANCE_BOUND_EXACT) << "the whole map's window";
  EXPECT_EQ(packed.covariance_bound(), pb::COVARIANCE_BOUND_EXACT);

  const TileId tile = TileContaining(scenario_.landmarks()[0].position);
  pb::GetTileRequest tile_request;
  tile_request.mutable_tile()->set_z(tile.z);
  tile_request.mutable_tile()->set_x(tile.x);
  tile_request.mutable_tile()->set_y(tile.y);
  tile_request.set_include_cross_covariance(true);
  pb::GetTileResponse tile_blocks, tile_packed;
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(client_->stub()->GetTile(&ctx, tile_request, &tile_blocks).ok());
  }
  tile_request.set_covariance_format(pb::COVARIANCE_FORMAT_PACKED);
  {
    grpc::ClientContext ctx;
    ASSERT_TRUE(client_->stub()->GetTile(&ctx, tile_request, &tile_packed).ok());
  }
  ASSERT_GT(tile_packed.landmarks_size(), 0);
  matrix = CovarianceFromPacked(tile_packed.packed_covariance(), tile_packed.landmarks_size(), "packed_covariance");
  ASSERT_TRUE(matrix.ok()) << matrix.status();
  expected = CovarianceFromBlocks(tile_blocks.landmarks(), tile_blocks.cross_covariances(), "cross_covariances");
  ASSERT_TRUE(expected.ok()) << expected.status();
  EXPECT_LT((*matrix - *expected).cwiseAbs().maxCoeff(), 1e-15);
  EXPECT_EQ(tile_packed.covariance_bound(), pb::COVARIANCE_BOUND_EXACT);
  {
    pb::QueryRegionRequest plain;
    *plain.mutable_box() = MockVehicle::World();
    pb::QueryRegionResponse without;
    grpc::ClientContext ctx;
    ASSERT_TRUE(client_->stub()->QueryRegion(&ctx, plain, &without).ok());
    EXPECT_EQ(without.covariance_bound(), pb::COVARIANCE_BOUND_UNSPECIFIED) << "no covariance read";
  }

  region.set_include_cross_covariance(false);
  grpc::ClientContext no_cov_ctx;
  grpc::Status refused = client_->stub()->QueryRegion(&no_cov_ctx, region, &packed);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(refused.error_message().rfind("covariance_format:", 0), 0u) << refused.error_message();
  tile_request.set_covariance_format(static_cast<pb::CovarianceFormat>(7));
  grpc::ClientContext unknown_ctx;
  refused = client_->stub()->GetTile(&unknown_ctx, tile_request, &tile_packed);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(refused.error_message().rfind("covariance_format:", 0), 0u) << refused.error_message();
}

TEST_F(ServiceRpc, ExcludePassageGivesTheMapWithoutIt) {
  Start(true);
  for (int i = 0; i < 4; ++i) MustUpload(scenario_.MakePassage(i));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  const Passage excluded = scenario_.MakePassage(2);
  // Provenance: every passage saw landmark 1.
  absl::StatusOr<pb::GetLandmarkResponse> before = client_->client()->GetLandmark(1);
  ASSERT_TRUE(before.ok()) << before.status();
  ASSERT_EQ(before->passages_size(), 4);
  EXPECT_EQ(before->landmark().passages_seen(), 4);
  absl::StatusOr<pb::ExcludePassageResponse> r =
      client_->client()->ExcludePassage(PassageKey{0, excluded.vehicle_id, excluded.passage_id});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->status().state(), pb::PASSAGE_STATE_EXCLUDED);
  EXPECT_GT(r->landmarks_updated(), 0);
  EXPECT_EQ(client_->GetMapInfo()->map_version(), r->map_version());
  EXPECT_EQ(client_->GetMapInfo()->passages_applied(), 3);
  absl::StatusOr<pb::GetLandmarkResponse> after = client_->client()->GetLandmark(1);
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->passages_size(), 3);
  for (const pb::PassageKey& key : after->passages()) EXPECT_NE(key.passage_id(), excluded.passage_id);
  EXPECT_EQ(after->map_version(), r->map_version());
  EXPECT_EQ(client_->client()->GetLandmark(9999).status().code(), absl::StatusCode::kNotFound);

  // The server computes what the core computes: the four passages applied in order, then the
  // exclusion.
  MapState reference;
  MapUpdater updater{MapUpdateOptions()};
  for (int i = 0; i < 4; ++i) {
    const Passage p = scenario_.MakePassage(i);
    absl::StatusOr<PassageUpdate> u = updater.Compute(p, reference);
    ASSERT_TRUE(u.ok()) << u.status();
    reference.Apply(u->delta);
    updater.Applied(p, u->delta);
  }
  absl::StatusOr<PassageUpdate> exclusion =
      ComputePassageExclusion(excluded.vehicle_id, excluded.passage_id, MapUpdateOptions(), reference);
  ASSERT_TRUE(exclusion.ok()) << exclusion.status();
  reference.Apply(exclusion->delta);
  // And it is the map of the other passages alone up to where they were linearised (with passage 2
  // in the map): on this young map within a tenth of a standard deviation (README: measured).
  const MapState without = MapFromPassages(scenario_, 4, MapUpdateOptions(), /*skip=*/2);
  absl::StatusOr<MapState> served = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(served.ok()) << served.status();
  ASSERT_EQ(served->LandmarkIds(), reference.LandmarkIds());
  ASSERT_EQ(served->LandmarkIds(), without.LandmarkIds());
  for (LandmarkId id : reference.LandmarkIds()) {
    const Landmark& got = *served->FindLandmark(id);
    EXPECT_LT(EastNorthOffset(reference.FindLandmark(id)->position, got.position).norm(), 1e-6) << id;
    EXPECT_EQ(got.passages_seen, without.FindLandmark(id)->passages_seen) << id;
    const double sigma_m = std::sqrt(without.FindLandmark(id)->cov_en_m2.trace() / 2.0);
    EXPECT_LT(EastNorthOffset(without.FindLandmark(id)->position, got.position).norm(), 0.1 * sigma_m) << id;
  }

  // Only an applied passage can be excluded; an unknown one is not found.
  grpc::ClientContext again_ctx;
  pb::ExcludePassageRequest again;
  again.set_id(r->status().id());
  pb::ExcludePassageResponse ignored;
  EXPECT_EQ(client_->stub()->ExcludePassage(&again_ctx, again, &ignored).error_code(),
            grpc::StatusCode::FAILED_PRECONDITION);
  grpc::ClientContext unknown_ctx;
  pb::ExcludePassageRequest unknown;
  unknown.set_id(9999);
  EXPECT_EQ(client_->stub()->ExcludePassage(&unknown_ctx, unknown, &ignored).error_code(), grpc::StatusCode::NOT_FOUND);
  grpc::ClientContext empty_ctx;
  EXPECT_EQ(client_->stub()->ExcludePassage(&empty_ctx, pb::ExcludePassageRequest(), &ignored).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  // An id and a key of two passages: refused, and neither is taken out.
  const Passage kept = scenario_.MakePassage(3);
  grpc::ClientContext mixed_ctx;
  pb::ExcludePassageRequest mixed;
  mixed.set_id(client_->GetPassage(scenario_.MakePassage(0).vehicle_id, scenario_.MakePassage(0).passage_id)->id());
  mixed.set_vehicle_id(kept.vehicle_id);
  mixed.set_passage_id(kept.passage_id);
  EXPECT_EQ(client_->stub()->ExcludePassage(&mixed_ctx, mixed, &ignored).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(client_->GetMapInfo()->passages_applied(), 3);

  // A later passage is applied on the map without passage 2.
  MustUpload(scenario_.MakePassage(4));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  EXPECT_EQ(client_->GetMapInfo()->passages_applied(), 4);
}

// The uploads of settled passages (rejected, excluded) are deleted by the idle worker once their
// retention has passed; their records stay, and an applied passage keeps its upload.
TEST_F(ServiceRpc, TheWorkerDeletesSettledUploadsAfterTheirRetention) {
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), true);
  options.worker.update.warmup_passages = 0;
  options.worker.settled_upload_retention_days = 1e-9;  // under a millisecond
  options.worker.idle_prune_every = std::chrono::milliseconds(20);
  server_ = StartTestServer(options);
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<MockVehicle>(server_->address());
  for (int i = 0; i < 3; ++i) MustUpload(scenario_.MakePassage(i));
  const Passage kept = scenario_.MakePassage(0), excluded = scenario_.MakePassage(3);
  // Each detection of a landmark the map does not know, one apiece: nothing the passage could
  // estimate (a new landmark needs three rays), which the worker rejects.
  Passage rejected = scenario_.MakePassage(4);
  for (size_t k = 0; k < rejected.detections.size(); ++k) rejected.detections[k].landmark_id = 100000 + k;
  for (const Passage& p : {excluded, rejected}) MustUpload(p);
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  ASSERT_TRUE(client_->client()->ExcludePassage(PassageKey{0, excluded.vehicle_id, excluded.passage_id}).ok());
  auto pruned = [&](const Passage& p) {
    absl::StatusOr<pb::PassageStatus> status = client_->GetPassage(p.vehicle_id, p.passage_id);
    return status.ok() && status->payload_pruned_unix_ms() > 0;
  };
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!(pruned(excluded) && pruned(rejected)) && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  for (const auto& [p, state] : {std::pair<const Passage*, pb::PassageState>{&excluded, pb::PASSAGE_STATE_EXCLUDED},
                                 {&rejected, pb::PASSAGE_STATE_REJECTED}}) {
    absl::StatusOr<pb::PassageStatus> status = client_->GetPassage(p->vehicle_id, p->passage_id);
    ASSERT_TRUE(status.ok()) << status.status();
    EXPECT_EQ(status->state(), state) << "the record stays";
    EXPECT_GT(status->payload_pruned_unix_ms(), 0) << p->passage_id;
    EXPECT_EQ(server_->store()->GetPassagePayload(status->id()).status().code(), absl::StatusCode::kNotFound);
  }
  absl::StatusOr<pb::PassageStatus> applied = client_->GetPassage(kept.vehicle_id, kept.passage_id);
  ASSERT_TRUE(applied.ok()) << applied.status();
  EXPECT_EQ(applied->payload_pruned_unix_ms(), 0);
  EXPECT_TRUE(server_->store()->GetPassagePayload(applied->id()).ok());
}

TEST_F(ServiceRpc, PassagesBeyondTheRetentionAreFoldedIntoTheBase) {
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), true);
  options.worker.update.warmup_passages = 0;  // no joint solve needs the passages back
  options.worker.update.retain_passages = 2;
  server_ = StartTestServer(options);
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<MockVehicle>(server_->address());
  for (int i = 0; i < 5; ++i) MustUpload(scenario_.MakePassage(i));
  absl::StatusOr<pb::MapInfo> info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  ASSERT_EQ(info->passages_applied(), 5);
  // cc-gsd: one factor per subgraph; only the last two passages keep theirs.
  MapUpdateOptions update;
  update.warmup_passages = 0;
  int64_t last_two = 0;
  for (int i = 3; i < 5; ++i) {
    absl::StatusOr<pb::PassageStatus> status =
        client_->GetPassage(scenario_.MakePassage(i).vehicle_id, scenario_.MakePassage(i).passage_id);
    last_two += status->result().subgraphs();
  }
  EXPECT_EQ(info->factor_count(), last_two);
  // The stored uploads of the folded passages are deleted; the retained ones' are kept. The worker
  // deletes them just after its commit, which may come after the queue looks idle: waited for.
  const auto pruned = [&](int i) {
    absl::StatusOr<pb::PassageStatus> status =
        client_->GetPassage(scenario_.MakePassage(i).vehicle_id, scenario_.MakePassage(i).passage_id);
    return status.ok() && status->payload_pruned_unix_ms() > 0;
  };
  for (int attempt = 0; attempt < 200 && !(pruned(0) && pruned(1) && pruned(2)); ++attempt) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  for (int i = 0; i < 5; ++i) {
    const Passage p = scenario_.MakePassage(i);
    absl::StatusOr<pb::PassageStatus> status = client_->GetPassage(p.vehicle_id, p.passage_id);
    ASSERT_TRUE(status.ok()) << status.status();
    EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED);
    EXPECT_EQ(status->payload_pruned_unix_ms() > 0, i < 3) << "passage " << i;
    EXPECT_EQ(server_->store()->GetPassagePayload(status->id()).ok(), i >= 3) << "passage " << i;
  }
  // Folding changes nothing in the map.
  absl::StatusOr<MapState> served = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(served.ok()) << served.status();
  EXPECT_TRUE(MapsMatch(MapFromPassages(scenario_, 5, update), *served, 1e-6, 1e-9));
  // A folded passage can no longer be excluded; a retained one can.
  const Passage oldest = scenario_.MakePassage(0), newest = scenario_.MakePassage(4);
  EXPECT_EQ(client_->client()->ExcludePassage(PassageKey{0, oldest.vehicle_id, oldest.passage_id}).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(client_->client()->ExcludePassage(PassageKey{0, newest.vehicle_id, newest.passage_id}).ok());
  // After a restart the worker knows which passages it retains.
  server_.reset();
  server_ = StartTestServer(options);
  client_ = std::make_unique<MockVehicle>(server_->address());
  MustUpload(scenario_.MakePassage(5));
  info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  int64_t retained = 0;
  for (int i : {3, 5}) {
    retained += client_->GetPassage(scenario_.MakePassage(i).vehicle_id, scenario_.MakePassage(i).passage_id)
                    ->result()
                    .subgraphs();
  }
  EXPECT_EQ(info->factor_count(), retained) << "passage 4 excluded, 3 and 5 retained";
}

TEST_F(ServiceRpc, RefusedPassagesAreQuarantinedThenRequeuedOrDiscardedByAnOperator) {
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), true);
  options.worker.update.max_chi2_per_dof = 1e-3;  // every honest solve leaves about 1: all refused
  server_ = StartTestServer(options);
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<MockVehicle>(server_->address());
  const Passage passage = scenario_.MakePassage(0);
  MustUpload(passage);
  absl::StatusOr<pb::MapInfo> info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_quarantined(), 1);
  EXPECT_EQ(info->landmark_count(), 0) << "the map is unchanged";
  absl::StatusOr<pb::PassageStatus> status = client_->GetPassage(passage.vehicle_id, passage.passage_id);
  ASSERT_TRUE(status.ok());
  EXPECT_EQ(status->state(), pb::PASSAGE_STATE_QUARANTINED);
  EXPECT_NE(status->error().find("inconsistent"), std::string::npos) << status->error();

  const PassageKey key{0, passage.vehicle_id, passage.passage_id};
  absl::StatusOr<pb::PassageStatus> requeued = client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::REQUEUE);
  ASSERT_TRUE(requeued.ok()) << requeued.status();
  EXPECT_EQ(requeued->state(), pb::PASSAGE_STATE_QUEUED);
  EXPECT_EQ(requeued->attempts(), 0);
  info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_quarantined(), 1) << "the same checks refuse it again";

  absl::StatusOr<pb::PassageStatus> discarded =
      client_->client()->ResolvePassage(PassageKey{status->id(), "", ""}, pb::ResolvePassageRequest::DISCARD);
  ASSERT_TRUE(discarded.ok()) << discarded.status();
  EXPECT_EQ(discarded->state(), pb::PASSAGE_STATE_DISCARDED);
  info = client_->client()->GetMapInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_quarantined(), 0);
  EXPECT_EQ(info->passages_discarded(), 1);

  EXPECT_EQ(client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::REQUEUE).status().code(),
            absl::StatusCode::kFailedPrecondition)
      << "a discarded passage stays discarded";
  EXPECT_EQ(client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::ACTION_UNSPECIFIED).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->client()->ResolvePassage(PassageKey{999, "", ""}, pb::ResolvePassageRequest::DISCARD).status().code(),
            absl::StatusCode::kNotFound);
}

TEST_F(ServiceRpc, AReleasedQuarantinedPassageIsAppliedWithTheMapsChecksOffOnce) {
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), true);
  options.worker.update.max_chi2_per_dof = 1e-3;  // every honest solve leaves about 1: all refused
  server_ = StartTestServer(options);
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<MockVehicle>(server_->address());
  const Passage first = scenario_.MakePassage(0), second = scenario_.MakePassage(1);
  MustUpload(first);
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  const PassageKey key{0, first.vehicle_id, first.passage_id};
  absl::StatusOr<pb::PassageStatus> released = client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::RELEASE);
  ASSERT_TRUE(released.ok()) << released.status();
  EXPECT_EQ(released->state(), pb::PASSAGE_STATE_QUEUED);
  absl::StatusOr<pb::MapInfo> info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_applied(), 1) << "applied despite the chi-square gate";
  EXPECT_GT(info->landmark_count(), 0);
  // Only that passage: the next one meets the same checks.
  MustUpload(second);
  info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_quarantined(), 1);
  // A failed passage cannot be released (it failed for reasons the checks do not cover).
  EXPECT_EQ(client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::RELEASE).status().code(),
            absl::StatusCode::kFailedPrecondition)
      << "an applied passage";
}

// A passage whose detections carry landmark ids at random: most of them do not fit, and the
// worker quarantines it whole; released by an operator it is applied with that check off too.
TEST_F(ServiceRpc, APassageMostOfWhoseDetectionsDoNotFitIsQuarantined) {
  Start(true);
  for (int i = 0; i < 2; ++i) MustUpload(scenario_.MakePassage(i));
  absl::StatusOr<pb::MapInfo> before = client_->WaitUntilIdle();
  ASSERT_TRUE(before.ok()) << before.status();
  Passage garbage = scenario_.MakePassage(2);
  std::mt19937 rng(3);
  std::uniform_int_distribution<LandmarkId> any(1, static_cast<LandmarkId>(scenario_.landmarks().size()));
  for (Detection& d : garbage.detections) d.landmark_id = any(rng);
  MustUpload(garbage);
  absl::StatusOr<pb::MapInfo> info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->passages_quarantined(), 1);
  EXPECT_EQ(info->map_version(), before->map_version()) << "the map is unchanged";
  absl::StatusOr<pb::PassageStatus> status = client_->GetPassage(garbage.vehicle_id, garbage.passage_id);
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(status->state(), pb::PASSAGE_STATE_QUARANTINED);
  EXPECT_NE(status->error().find("detections do not fit"), std::string::npos) << status->error();
  const PassageKey key{0, garbage.vehicle_id, garbage.passage_id};
  ASSERT_TRUE(client_->client()->ResolvePassage(key, pb::ResolvePassageRequest::RELEASE).ok());
  info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok()) << info.status();
  status = client_->GetPassage(garbage.vehicle_id, garbage.passage_id);
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(status->state(), pb::PASSAGE_STATE_APPLIED) << status->error();
}

TEST_F(ServiceRpc, GetTileReturnsItsLandmarksAndVersion) {
  Start(true);
  MustUpload(scenario_.MakePassage(0));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());
  const TileId tile = TileContaining(scenario_.landmarks()[0].position);
  grpc::ClientContext ctx;
  pb::GetTileRequest request;
  request.mutable_tile()->set_z(tile.z);
  request.mutable_tile()->set_x(tile.x);
  request.mutable_tile()->set_y(tile.y);
  request.set_include_cross_covariance(true);
  pb::GetTileResponse response;
  ASSERT_TRUE(client_->stub()->GetTile(&ctx, request, &response).ok());
  ASSERT_GT(response.landmarks_size(), 0);
  int64_t max_version = 0;
  for (const pb::Landmark& l : response.landmarks()) {
    EXPECT_EQ(l.tile().x(), tile.x);
    EXPECT_EQ(l.tile().y(), tile.y);
    max_version = std::max(max_version, l.version());
  }
  EXPECT_EQ(response.tile_version(), max_version);
  EXPECT_GE(response.map_version(), max_version);

  grpc::ClientContext bad_ctx;
  request.mutable_tile()->set_z(15);
  EXPECT_EQ(client_->stub()->GetTile(&bad_ctx, request, &response).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
}

TEST_F(ServiceRpc, WatchRegionStreamsLandmarksChangedAfterTheVersion) {
  Start(true);
  MustUpload(scenario_.MakePassage(0));
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  const int64_t since = info->map_version();

  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  pb::WatchRegionRequest request;
  *request.mutable_box() = MockVehicle::World();
  request.set_since_version(since);
  auto reader = client_->stub()->WatchRegion(&ctx, request);
  pb::WatchRegionResponse first;
  ASSERT_TRUE(reader->Read(&first));
  EXPECT_EQ(first.map_version(), since);
  EXPECT_EQ(first.landmarks_size(), 0);

  MustUpload(scenario_.MakePassage(1));
  pb::WatchRegionResponse change;
  ASSERT_TRUE(reader->Read(&change));
  EXPECT_GT(change.map_version(), since);
  ASSERT_GT(change.landmarks_size(), 0);
  for (const pb::Landmark& l : change.landmarks()) EXPECT_GT(l.version(), since);
  ctx.TryCancel();
  reader->Finish();
}

// A copy of a region kept by WatchRegion alone stays the served map when an exclusion removes
// landmarks: they come as removed_landmark_ids in the change that removed them.
TEST_F(ServiceRpc, WatchRegionReportsTheLandmarksAnExclusionRemoves) {
  Start(true);
  const Passage lone = WithLandmarkRenamed(scenario_.MakePassage(1), 1, 500);
  MustUpload(scenario_.MakePassage(0));
  MustUpload(lone);
  MustUpload(scenario_.MakePassage(2));
  ASSERT_TRUE(client_->WaitUntilIdle().ok());

  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  pb::WatchRegionRequest request;
  *request.mutable_box() = MockVehicle::World();
  auto reader = client_->stub()->WatchRegion(&ctx, request);
  std::map<int64_t, pb::Landmark> copy;
  pb::WatchRegionResponse change;
  ASSERT_TRUE(reader->Read(&change));
  for (const pb::Landmark& l : change.landmarks()) copy[l.id()] = l;
  EXPECT_TRUE(change.removed_landmark_ids().empty());
  ASSERT_EQ(copy.count(500), 1u);

  absl::StatusOr<pb::ExcludePassageResponse> r =
      client_->client()->ExcludePassage(PassageKey{0, lone.vehicle_id, lone.passage_id});
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(reader->Read(&change));
  EXPECT_EQ(change.map_version(), r->map_version());
  EXPECT_EQ(std::vector<int64_t>(change.removed_landmark_ids().begin(), change.removed_landmark_ids().end()),
            std::vector<int64_t>{500});
  for (const pb::Landmark& l : change.landmarks()) copy[l.id()] = l;
  for (int64_t id : change.removed_landmark_ids()) copy.erase(id);
  ctx.TryCancel();
  reader->Finish();

  absl::StatusOr<MapState> served = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(served.ok()) << served.status();
  std::vector<LandmarkId> kept;
  for (const auto& [id, l] : copy) {
    kept.push_back(id);
    EXPECT_EQ(l.version(), served->FindLandmark(id)->version) << id;
  }
  EXPECT_EQ(kept, served->LandmarkIds());

  // A watch that starts after the removal, from a version before it, is told too; one from the
  // removal's version is not.
  for (const auto& [since, want] : std::vector<std::pair<int64_t, size_t>>{{r->map_version() - 1, 1}, {r->map_version(), 0}}) {
    grpc::ClientContext late_ctx;
    late_ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    request.set_since_version(since);
    auto late = client_->stub()->WatchRegion(&late_ctx, request);
    ASSERT_TRUE(late->Read(&change));
    EXPECT_EQ(static_cast<size_t>(change.removed_landmark_ids_size()), want) << "since " << since;
    late_ctx.TryCancel();
    late->Finish();
  }
}

// A client whose version the map has not reached (it watched another map, or one since restored
// from a backup) is told so instead of waiting, silently stale, for versions that will mean
// something else.
TEST_F(ServiceRpc, WatchRegionRefusesAVersionAheadOfTheMap) {
  Start(true);
  MustUpload(scenario_.MakePassage(0));
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  pb::WatchRegionRequest request;
  *request.mutable_box() = MockVehicle::World();
  request.set_since_version(info->map_version() + 1);
  auto reader = client_->stub()->WatchRegion(&ctx, request);
  pb::WatchRegionResponse first;
  EXPECT_FALSE(reader->Read(&first));
  const grpc::Status status = reader->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << status.error_message();
  EXPECT_NE(status.error_message().find("since_version"), std::string::npos) << status.error_message();
}

// A change of more landmarks than one message holds comes in parts: only the last carries the new
// version, so that a client resuming from the version it last saw gets the whole change again.
TEST_F(ServiceRpc, WatchRegionSendsALargeChangeInPartsTheLastWithItsVersion) {
  constexpr int kLandmarks = 2500;
  {
    auto store = CreateSqliteMapStore(dir_.File("map.db"));
    ASSERT_TRUE(store.ok()) << store.status();
    ASSERT_TRUE((*store)->EnqueuePassages({NewPassage{"v", "p", "bytes", 1000}}, 0).ok());
    auto claimed = (*store)->ClaimNextPassage();
    ASSERT_TRUE(claimed.ok() && claimed->has_value()) << claimed.status();
    MapDelta delta;
    delta.base_version = 0;
    delta.version = 1;
    for (LandmarkId id = 1; id <= kLandmarks; ++id) {
      Landmark l;
      l.id = id;
      l.anchor = {48.0 + 1e-4 * static_cast<double>(id / 50), 2.0 + 1e-4 * static_cast<double>(id % 50)};
      l.position = l.anchor;
      l.version = 1;
      delta.landmarks.emplace(id, l);
    }
    ASSERT_TRUE((*store)->CommitPassageApplied((*claimed)->record.id, delta, PassageResult()).ok());
  }
  MapServerOptions options = TestServerOptions(dir_.File("map.db"), /*start_worker=*/false);
  options.worker.update.warmup_passages = 0;  // no joint solve reads the passage's (made-up) upload
  options.worker.update.relinearize_until_passages = 0;
  server_ = StartTestServer(options);
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<MockVehicle>(server_->address());

  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  pb::WatchRegionRequest request;
  *request.mutable_box() = MockVehicle::World();
  auto reader = client_->stub()->WatchRegion(&ctx, request);
  std::vector<std::pair<int, int64_t>> parts;  // landmarks, version
  std::set<int64_t> ids;
  pb::WatchRegionResponse part;
  while (static_cast<int>(ids.size()) < kLandmarks && reader->Read(&part)) {
    parts.emplace_back(part.landmarks_size(), part.map_version());
    for (const pb::Landmark& l : part.landmarks()) ids.insert(l.id());
  }
  EXPECT_EQ(parts, (std::vector<std::pair<int, int64_t>>{{1000, 0}, {1000, 0}, {500, 1}}));
  EXPECT_EQ(static_cast<int>(ids.size()), kLandmarks);
  ctx.TryCancel();
  reader->Finish();
}

TEST_F(ServiceRpc, SamePassageUploadedTwiceIsQueuedOnceAndAppliedOnce) {
  Start(true);
  const Passage p = scenario_.MakePassage(0);
  const pb::UploadPassageResponse first = MustUpload(p);
  const pb::UploadPassageResponse second = MustUpload(p);
  EXPECT_FALSE(first.duplicate());
  EXPECT_TRUE(second.duplicate());
  EXPECT_EQ(first.status().id(), second.status().id());
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_applied(), 1);
  auto map = client_->DownloadMap(MockVehicle::World());
  ASSERT_TRUE(map.ok());
  map->ForEachLandmark([](const Landmark& l) { EXPECT_EQ(l.passages_seen, 1); });
}

TEST_F(ServiceRpc, TheSameDriveUnderOtherIdsIsRefusedAndAppliedOnce) {
  Start(true);
  const Passage p = scenario_.MakePassage(0);
  MustUpload(p);
  // A client that retries with a fresh id, or replays a drive under other vehicles' names.
  for (const auto& [vehicle, passage] : {std::pair<std::string, std::string>{p.vehicle_id, "retry-1"},
                                         std::pair<std::string, std::string>{"another-vehicle", p.passage_id}}) {
    Passage again = p;
    again.vehicle_id = vehicle;
    again.passage_id = passage;
    auto r = client_->Upload(again);
    ASSERT_FALSE(r.ok()) << passage;
    EXPECT_EQ(r.status().code(), absl::StatusCode::kAlreadyExists) << r.status();
    // The vehicle's own earlier upload is named; another vehicle's ids are not told.
    const bool named = r.status().message().find(p.vehicle_id + "/" + p.passage_id) != std::string::npos;
    EXPECT_EQ(named, vehicle == p.vehicle_id) << r.status();
  }
  // Another drive is taken, though it differs from the first by one detection's pixel.
  Passage other = p;
  other.passage_id = "nearly-the-same";
  other.detections.front().u_px += 0.5;
  EXPECT_FALSE(MustUpload(other).duplicate());
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_applied(), 2);
  auto refused = client_->GetPassage("another-vehicle", p.passage_id);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kNotFound) << "a refused upload leaves no record";
}

TEST_F(ServiceRpc, ConcurrentDuplicateUploadsGetOneRecord) {
  Start(true);
  const Passage p = scenario_.MakePassage(0);
  constexpr int kClients = 8;
  std::vector<pb::UploadPassageResponse> responses(kClients);
  std::vector<std::thread> threads;
  for (int i = 0; i < kClients; ++i) {
    threads.emplace_back([&, i] {
      MockVehicle vehicle(server_->address());
      auto r = vehicle.Upload(p);
      ASSERT_TRUE(r.ok()) << r.status();
      responses[i] = *r;
    });
  }
  for (auto& t : threads) t.join();
  int originals = 0;
  for (const auto& r : responses) {
    EXPECT_EQ(r.status().id(), responses[0].status().id());
    originals += !r.duplicate();
  }
  EXPECT_EQ(originals, 1);
  auto info = client_->WaitUntilIdle();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->passages_applied(), 1);
  EXPECT_EQ(info->passages_queued() + info->passages_processing() + info->passages_failed(), 0);
}

TEST_F(ServiceRpc, FullQueueAnswersResourceExhausted) {
  Start(false, /*max_queue=*/2);
  MustUpload(scenario_.MakePassage(0));
  MustUpload(scenario_.MakePassage(1));
  pb::Passage third;
  PassageToProto(scenario_.MakePassage(2), &third);
  EXPECT_EQ(client_->UploadOnce(third).status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(client_->GetMapInfo()->queue_depth(), 2);
}

// Status from grpc.health.v1.Health/Check for the whole server, via the generic stub (the
// response is HealthCheckResponse{status = 1 (SERVING) | 2 (NOT_SERVING)}).
absl::StatusOr<int> HealthStatus(const std::shared_ptr<grpc::Channel>& channel) {
  grpc::GenericStub generic(channel);
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  grpc::Slice empty("");
  grpc::ByteBuffer request(&empty, 1), response;
  std::promise<grpc::Status> done;
  generic.UnaryCall(&ctx, "/grpc.health.v1.Health/Check", grpc::StubOptions(), &request, &response,
                    [&](grpc::Status s) { done.set_value(s); });
  grpc::Status s = done.get_future().get();
  if (!s.ok()) return FromGrpcStatus(s);
  std::vector<grpc::Slice> slices;
  if (!response.Dump(&slices).ok()) return absl::InternalError("bad health response");
  std::string bytes;
  for (const auto& slice : slices) bytes.append(reinterpret_cast<const char*>(slice.begin()), slice.size());
  if (bytes.size() != 2 || bytes[0] != 0x08) return absl::InternalError("unexpected health response");
  return static_cast<int>(bytes[1]);
}

TEST_F(ServiceRpc, ASecondServerOnTheSameDatabaseOrPortRefusesToStart) {
  Start(true);
  // The same database: refused by its lock, with a message that says so.
  MapServerOptions same_db = TestServerOptions(dir_.File("map.db"), true);
  absl::StatusOr<std::unique_ptr<MapServer>> second = MapServer::Start(same_db);
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(second.status().message().find("in use by another mapd"), std::string::npos) << second.status();
  // The same port: refused (gRPC would otherwise share it, and clients would see two maps).
  MapServerOptions same_port = TestServerOptions(dir_.File("other.db"), true);
  same_port.listen = server_->address();
  absl::StatusOr<std::unique_ptr<MapServer>> third = MapServer::Start(same_port);
  ASSERT_FALSE(third.ok());
  EXPECT_NE(third.status().message().find("cannot bind"), std::string::npos) << third.status();
  // Once the first is stopped, its database can be opened again.
  server_.reset();
  absl::StatusOr<std::unique_ptr<MapServer>> after = MapServer::Start(same_db);
  EXPECT_TRUE(after.ok()) << after.status();
}

TEST_F(ServiceRpc, HealthIsServingUntilShutdownThenUploadsAreRefused) {
  Start(false);
  auto health = HealthStatus(client_->channel());
  ASSERT_TRUE(health.ok()) << health.status();
  EXPECT_EQ(*health, 1);
  server_->Shutdown(std::chrono::milliseconds(100));
  pb::Passage wire;
  PassageToProto(scenario_.MakePassage(0), &wire);
  EXPECT_EQ(client_->UploadOnce(wire).status().code(), absl::StatusCode::kUnavailable);
  EXPECT_FALSE(HealthStatus(client_->channel()).ok());
  EXPECT_FALSE(server_->store()->FindPassage("sim-0", scenario_.MakePassage(0).passage_id).ok());
}

}  // namespace
}  // namespace crowdmap
