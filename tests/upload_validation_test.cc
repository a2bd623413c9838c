// Every validation rule of UploadPassage: INVALID_ARGUMENT, a message naming the field (with its
// index), and nothing stored.
#include <cmath>
#include <functional>
#include <limits>

#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

class UploadValidation : public ::testing::Test {
 protected:
  void SetUp() override {
    MapServerOptions options = TestServerOptions(dir_.File("map.db"), /*start_worker=*/true);
    options.max_passage_mb = 1;
    server_ = StartTestServer(options);
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<MockVehicle>(server_->address());
    PassageToProto(ShortScenario().MakePassage(0), &valid_);
    ASSERT_GT(valid_.detections_size(), 3);
    ASSERT_GT(valid_.gnss_size(), 5);
  }

  // Uploads `valid_` changed by `mutate`, expects INVALID_ARGUMENT whose message starts with
  // "<field>:", then checks that the database holds nothing.
  void ExpectRejected(const std::function<void(pb::Passage*)>& mutate, const std::string& field) {
    pb::Passage wire = valid_;
    mutate(&wire);
    auto response = client_->UploadOnce(wire);
    EXPECT_EQ(response.status().code(), absl::StatusCode::kInvalidArgument) << response.status();
    EXPECT_EQ(std::string(response.status().message()).substr(0, field.size() + 1), field + ":")
        << response.status().message();
    ExpectNothingStored();
  }

  void ExpectNothingStored() {
    auto stats = server_->store()->GetStats();
    ASSERT_TRUE(stats.ok());
    EXPECT_EQ(stats->map_version, 0);
    EXPECT_EQ(stats->landmark_count, 0);
    for (int64_t n : stats->passages_by_state) EXPECT_EQ(n, 0);
    auto listed = server_->store()->ListPassages(PassageQuery{});
    ASSERT_TRUE(listed.ok());
    EXPECT_TRUE(listed->empty());
  }

  TempDir dir_;
  std::unique_ptr<MapServer> server_;
  std::unique_ptr<MockVehicle> client_;
  pb::Passage valid_;
};

TEST_F(UploadValidation, ValidPassageIsAccepted) {
  // The baseline the other cases mutate must itself pass, or they would prove nothing.
  auto response = client_->UploadOnce(valid_);
  ASSERT_TRUE(response.ok()) << response.status();
  EXPECT_EQ(response->status().state(), pb::PASSAGE_STATE_QUEUED);
}

TEST_F(UploadValidation, RejectsNonFiniteOdometry) {
  ExpectRejected([](pb::Passage* p) { p->mutable_odometry(3)->set_speed_mps(kNaN); }, "odometry[3].speed_mps");
}

TEST_F(UploadValidation, RejectsNonFiniteGnssCovariance) {
  ExpectRejected([](pb::Passage* p) { p->mutable_gnss(1)->mutable_cov_en_m2()->set_ee(kInf); }, "gnss[1].cov_en_m2");
}

TEST_F(UploadValidation, RejectsNonFiniteDetectionTime) {
  ExpectRejected([](pb::Passage* p) { p->mutable_detections(2)->set_t_s(kNaN); }, "detections[2].t_s");
}

TEST_F(UploadValidation, RejectsOdometryTimeGoingBackwards) {
  ExpectRejected([](pb::Passage* p) { p->mutable_odometry(5)->set_t_s(p->odometry(4).t_s() - 0.01); },
                 "odometry[5].t_s");
}

TEST_F(UploadValidation, RejectsGnssTimeGoingBackwards) {
  ExpectRejected([](pb::Passage* p) { p->mutable_gnss(2)->set_t_s(p->gnss(1).t_s()); }, "gnss[2].t_s");
}

TEST_F(UploadValidation, RejectsDetectionTimeGoingBackwards) {
  ExpectRejected([](pb::Passage* p) { p->mutable_detections(3)->set_t_s(p->detections(2).t_s() - 1.0); },
                 "detections[3].t_s");
}

TEST_F(UploadValidation, RejectsLatitudeOutOfRange) {
  ExpectRejected([](pb::Passage* p) { p->mutable_gnss(4)->set_lat_deg(91.0); }, "gnss[4].lat_deg");
}

TEST_F(UploadValidation, RejectsLongitudeOutOfRange) {
  ExpectRejected([](pb::Passage* p) { p->mutable_gnss(0)->set_lon_deg(-180.5); }, "gnss[0].lon_deg");
}

TEST_F(UploadValidation, RejectsDetectionRightOfTheImage) {
  ExpectRejected([](pb::Passage* p) { p->mutable_detections(2)->set_u_px(1920.5); }, "detections[2].u_px");
}

TEST_F(UploadValidation, RejectsDetectionLeftOfTheImage) {
  ExpectRejected([](pb::Passage* p) { p->mutable_detections(0)->set_u_px(-1.0); }, "detections[0].u_px");
}

TEST_F(UploadValidation, RejectsMissingCalibration) {
  ExpectRejected([](pb::Passage* p) { p->clear_calibration(); }, "calibration");
}

TEST_F(UploadValidation, RejectsUnusableCalibration) {
  ExpectRejected([](pb::Passage* p) { p->mutable_calibration()->set_fx_px(0.0); }, "calibration.fx_px");
}

TEST_F(UploadValidation, RejectsMissingGnssCovariance) {
  ExpectRejected([](pb::Passage* p) { p->mutable_gnss(3)->clear_cov_en_m2(); }, "gnss[3].cov_en_m2");
}

TEST_F(UploadValidation, RejectsPassageWithoutOdometry) {
  ExpectRejected([](pb::Passage* p) { p->clear_odometry(); }, "odometry");
}

TEST_F(UploadValidation, RejectsPassageWithoutDetections) {
  ExpectRejected([](pb::Passage* p) { p->clear_detections(); }, "detections");
}

TEST_F(UploadValidation, RejectsEmptyPassage) {
  ExpectRejected([](pb::Passage* p) { p->Clear(); }, "vehicle_id");  // the key is checked first
  ExpectRejected(
      [](pb::Passage* p) {
        const pb::Calibration c = p->calibration();
        const std::string vehicle = p->vehicle_id(), passage = p->passage_id();
        p->Clear();
        *p->mutable_calibration() = c;
        p->set_vehicle_id(vehicle);
        p->set_passage_id(passage);
      },
      "odometry");
}

TEST_F(UploadValidation, RejectsUnsetVehicleId) {
  ExpectRejected([](pb::Passage* p) { p->clear_vehicle_id(); }, "vehicle_id");
}

TEST_F(UploadValidation, RejectsUnsetPassageId) {
  ExpectRejected([](pb::Passage* p) { p->clear_passage_id(); }, "passage_id");
}

TEST_F(UploadValidation, RejectsOversizePassage) {
  // Over the 1 MiB passage limit of this server, sent in chunks below the message limit.
  pb::Passage big = valid_;
  const pb::OdometrySample last = big.odometry(big.odometry_size() - 1);
  for (int i = 1; i <= 40000; ++i) {
    pb::OdometrySample* o = big.add_odometry();
    *o = last;
    o->set_t_s(last.t_s() + 0.001 * i);
  }
  ASSERT_GT(big.ByteSizeLong(), 1u << 20);
  auto response = client_->UploadChunked(big, 128 << 10);
  EXPECT_EQ(response.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(std::string(response.status().message()).substr(0, 8), "passage:") << response.status();
  ExpectNothingStored();
}

TEST_F(UploadValidation, RejectsChunksThatAreNotAPassage) {
  pb::Passage wire = valid_;
  // Truncated mid-field: a field header (field 1000, length-delimited) announcing 100 bytes that
  // never come. (Cutting the message at an arbitrary point may land on a field boundary, and a
  // prefix ending there parses.)
  std::string bytes = wire.SerializeAsString() + std::string("\xc2\x3e\x64", 3);
  grpc::ClientContext ctx;
  pb::UploadPassageResponse response;
  auto writer = client_->stub()->UploadPassageChunked(&ctx, &response);
  pb::UploadPassageChunk chunk;
  chunk.set_data(bytes);
  writer->Write(chunk);
  writer->WritesDone();
  grpc::Status s = writer->Finish();
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  const std::string expected = "passage.<field 1000>: length 100 runs past the end";
  EXPECT_EQ(s.error_message().substr(0, expected.size()), expected) << s.error_message();
  ExpectNothingStored();
}

}  // namespace
}  // namespace crowdmap
