#include "server/wire_convert.h"

#include <cmath>

#include "gtest/gtest.h"

namespace crowdmap {
namespace {

Passage SmallPassage() {
  Passage p;
  p.vehicle_id = "veh";
  p.passage_id = "p1";
  p.start_time_unix_ms = 1700000000000;
  p.calibration.camera_yaw_rad = 0.01;
  p.noise.pixel_sigma_px = 3.0;
  for (int i = 0; i < 10; ++i) p.odometry.push_back({0.1 * i, 12.0, 0.01});
  for (int i = 0; i < 3; ++i) {
    GnssFix g;
    g.t_s = 0.5 * i;
    g.lat_deg = 48.7 + 1e-5 * i;
    g.lon_deg = 2.17;
    g.cov_en_m2 << 4.0, 0.5, 0.5, 9.0;
    p.gnss.push_back(g);
  }
  p.detections.push_back({0.2, 7, 900.0});
  p.detections.push_back({0.4, 8, 1000.0});
  return p;
}

TEST(WireConvert, PassageRoundTripKeepsEveryField) {
  const Passage p = SmallPassage();
  pb::Passage wire;
  PassageToProto(p, &wire);
  auto back = PassageFromProto(wire);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->vehicle_id, p.vehicle_id);
  EXPECT_EQ(back->passage_id, p.passage_id);
  EXPECT_EQ(back->start_time_unix_ms, p.start_time_unix_ms);
  EXPECT_EQ(back->calibration.camera_yaw_rad, 0.01);
  EXPECT_EQ(back->calibration.gnss_lever_arm_m, p.calibration.gnss_lever_arm_m);
  EXPECT_EQ(back->noise.pixel_sigma_px, 3.0);
  ASSERT_EQ(back->odometry.size(), p.odometry.size());
  EXPECT_EQ(back->odometry[3].t_s, p.odometry[3].t_s);
  ASSERT_EQ(back->gnss.size(), 3u);
  EXPECT_EQ(back->gnss[2].lat_deg, p.gnss[2].lat_deg);
  EXPECT_EQ(back->gnss[1].cov_en_m2, p.gnss[1].cov_en_m2);
  ASSERT_EQ(back->detections.size(), 2u);
  EXPECT_EQ(back->detections[1].landmark_id, 8);
  EXPECT_EQ(back->detections[1].u_px, 1000.0);
}

TEST(WireConvert, MissingCalibrationIsRejectedByName) {
  pb::Passage wire;
  PassageToProto(SmallPassage(), &wire);
  wire.clear_calibration();
  auto p = PassageFromProto(wire);
  EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(p.status().message().substr(0, 12), "calibration:");
}

TEST(WireConvert, AbsentNoiseFieldsTakeTheThesisDefaults) {
  pb::Passage wire;
  PassageToProto(SmallPassage(), &wire);
  wire.clear_noise();
  auto p = PassageFromProto(wire);
  ASSERT_TRUE(p.ok()) << p.status();
  const NoiseModel defaults;
  EXPECT_EQ(p->noise.speed_sigma_mps, defaults.speed_sigma_mps);
  EXPECT_EQ(p->noise.steering_sigma_rad, defaults.steering_sigma_rad);
  EXPECT_EQ(p->noise.pixel_sigma_px, defaults.pixel_sigma_px);
}

TEST(WireConvert, TheGnssProcessTravelsOnlyWhenDeclared) {
  Passage p = SmallPassage();
  pb::Passage wire;
  PassageToProto(p, &wire);
  EXPECT_FALSE(wire.noise().has_gnss_correlation_time_s());  // white: nothing on the wire
  EXPECT_FALSE(wire.noise().has_gnss_process_sigma_m());
  auto white = PassageFromProto(wire);
  ASSERT_TRUE(white.ok()) << white.status();
  EXPECT_EQ(white->noise.gnss_correlation_time_s, 0.0);
  EXPECT_EQ(white->noise.gnss_process_sigma_m, 0.0);

  p.noise.gnss_correlation_time_s = kStandardReceiverGnssCorrelationTimeS;
  p.noise.gnss_process_sigma_m = kStandardReceiverGnssProcessSigmaM;
  wire.Clear();
  PassageToProto(p, &wire);
  auto back = PassageFromProto(wire);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->noise.gnss_correlation_time_s, kStandardReceiverGnssCorrelationTimeS);
  EXPECT_EQ(back->noise.gnss_process_sigma_m, kStandardReceiverGnssProcessSigmaM);

  wire.mutable_noise()->set_gnss_correlation_time_s(-5.0);
  auto negative = PassageFromProto(wire);
  EXPECT_EQ(negative.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(negative.status().message().find("noise.gnss_correlation_time_s"), std::string::npos)
      << negative.status();
}

TEST(WireConvert, GnssSigmaStandsInForAMissingCovariance) {
  pb::Passage wire;
  PassageToProto(SmallPassage(), &wire);
  wire.mutable_gnss(1)->clear_cov_en_m2();
  wire.mutable_gnss(1)->set_sigma_m(3.0);
  auto p = PassageFromProto(wire);
  ASSERT_TRUE(p.ok()) << p.status();
  EXPECT_EQ(p->gnss[1].cov_en_m2, Eigen::Matrix2d::Identity() * 9.0);

  // Sigmas whose squares are not covariances (infinite, zero) are refused by their own name.
  for (const double sigma : {1e200, 1e-170, 0.0, -1.0}) {
    wire.mutable_gnss(1)->set_sigma_m(sigma);
    p = PassageFromProto(wire);
    EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument) << sigma;
    EXPECT_NE(p.status().message().find("gnss[1].sigma_m"), absl::string_view::npos) << p.status();
  }

  wire.mutable_gnss(1)->clear_sigma_m();
  p = PassageFromProto(wire);
  EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(p.status().message().find("gnss[1].cov_en_m2"), absl::string_view::npos) << p.status();
}

TEST(WireConvert, CoreValidationNamesTheWireField) {
  pb::Passage wire;
  PassageToProto(SmallPassage(), &wire);
  wire.mutable_gnss(2)->set_lat_deg(91.0);
  auto p = PassageFromProto(wire);
  EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(p.status().message().find("gnss[2].lat_deg"), absl::string_view::npos) << p.status();
}

TEST(WireConvert, OversizePassageIsRejected) {
  WireLimits limits;
  limits.max_passage_bytes = 100;
  EXPECT_TRUE(CheckPassageSize(100, limits).ok());
  absl::Status s = CheckPassageSize(101, limits);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(s.message().substr(0, 8), "passage:");
}

TEST(WireConvert, LandmarkCovarianceTravelsAsStored) {
  Landmark l;
  l.id = 12;
  l.position = {48.71, 2.18};
  l.cov_en_m2 << 0.3, 0.01, 0.0100000001, 0.2;
  l.version = 9;
  l.passages_seen = 4;
  pb::Landmark wire;
  LandmarkToProto(l, &wire);
  EXPECT_EQ(wire.tile().z(), kStorageZoom);
  const Landmark back = LandmarkFromProto(wire);
  EXPECT_EQ(back.cov_en_m2, l.cov_en_m2);
  EXPECT_EQ(back.position.lat_deg, l.position.lat_deg);
  EXPECT_EQ(back.version, 9);
  EXPECT_EQ(back.passages_seen, 4);
}

TEST(WireConvert, VehicleTravelsWithItsSigmaAndRoundTrips) {
  VehicleCalibration v;
  v.vehicle_id = "veh-042";
  v.camera_yaw_offset_rad = 0.0091;
  v.camera_yaw_variance_rad2 = 0.0005 * 0.0005;
  v.passages = 14;
  v.version = 77;
  v.updated_unix_ms = 1767225600000;
  pb::Vehicle wire;
  VehicleToProto(v, &wire);
  EXPECT_EQ(wire.vehicle_id(), "veh-042");
  EXPECT_DOUBLE_EQ(wire.camera_yaw_sigma_rad(), 0.0005);
  EXPECT_EQ(wire.passages(), 14);
  EXPECT_EQ(wire.map_version(), 77);
  const VehicleCalibration back = VehicleFromProto(wire);
  EXPECT_EQ(back.camera_yaw_offset_rad, v.camera_yaw_offset_rad);
  EXPECT_NEAR(back.camera_yaw_variance_rad2, v.camera_yaw_variance_rad2, 1e-20);
  EXPECT_EQ(back.updated_unix_ms, v.updated_unix_ms);
}

TEST(WireConvert, BoundingBoxOutOfRangeNamesTheField) {
  pb::BoundingBox box;
  box.set_min_lat_deg(10);
  box.set_max_lat_deg(11);
  box.set_min_lon_deg(10);
  box.set_max_lon_deg(200);
  auto b = BoundingBoxFromProto(box, "box");
  EXPECT_EQ(b.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(b.status().message().find("box.max_lon_deg"), absl::string_view::npos);
  box.set_max_lon_deg(9);
  b = BoundingBoxFromProto(box, "box");
  EXPECT_NE(b.status().message().find("box.min_lon_deg"), absl::string_view::npos);
}

TEST(WireConvert, CovarianceBlocksPutTheSmallerIdFirst) {
  LandmarkPage page;
  page.landmarks.resize(2);
  page.landmarks[0].id = 9;
  page.landmarks[1].id = 4;
  page.covariance.resize(4, 4);
  page.covariance << 1, 2, 3, 4,  //
      2, 5, 6, 7,                 //
      3, 6, 8, 9,                 //
      4, 7, 9, 10;
  google::protobuf::RepeatedPtrField<pb::CrossCovariance> blocks;
  CovarianceToBlocks(page, &blocks);
  ASSERT_EQ(blocks.size(), 1);
  EXPECT_EQ(blocks[0].first_id(), 4);
  EXPECT_EQ(blocks[0].second_id(), 9);
  // Rows in landmark 4's axes (page rows 2 and 3), columns in landmark 9's.
  EXPECT_EQ(blocks[0].cov_m2().ee(), 3);
  EXPECT_EQ(blocks[0].cov_m2().en(), 6);
  EXPECT_EQ(blocks[0].cov_m2().ne(), 4);
  EXPECT_EQ(blocks[0].cov_m2().nn(), 7);
}

// The blocks a server sends give back the page's matrix; a block of a landmark the response does
// not hold is refused by name.
TEST(WireConvert, CovarianceFromBlocksIsThePagesMatrix) {
  LandmarkPage page;
  page.landmarks.resize(3);
  const int ids[] = {9, 4, 7};
  Eigen::MatrixXd a = Eigen::MatrixXd::Random(6, 6);
  page.covariance = a * a.transpose() + Eigen::MatrixXd::Identity(6, 6);
  google::protobuf::RepeatedPtrField<pb::Landmark> landmarks;
  for (int i = 0; i < 3; ++i) {
    page.landmarks[i].id = ids[i];
    page.landmarks[i].cov_en_m2 = page.covariance.block<2, 2>(2 * i, 2 * i);
    LandmarkToProto(page.landmarks[i], landmarks.Add());
  }
  google::protobuf::RepeatedPtrField<pb::CrossCovariance> blocks;
  CovarianceToBlocks(page, &blocks);
  absl::StatusOr<Eigen::MatrixXd> back = CovarianceFromBlocks(landmarks, blocks, "cross_covariances");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_LT((*back - page.covariance).cwiseAbs().maxCoeff(), 1e-15);
  blocks[1].set_second_id(5);
  absl::StatusOr<Eigen::MatrixXd> stray = CovarianceFromBlocks(landmarks, blocks, "cross_covariances");
  EXPECT_EQ(stray.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(stray.status().message().rfind("cross_covariances[1]:", 0), 0u) << stray.status();
}

TEST(WireConvert, PackedCovarianceIsTheUpperTriangleRowByRow) {
  const int n = 3, dim = 2 * n;
  Eigen::MatrixXd cov(dim, dim);
  for (int r = 0; r < dim; ++r) {
    for (int c = 0; c < dim; ++c) cov(r, c) = 10 * std::min(r, c) + std::max(r, c);
  }
  pb::PackedCovariance packed;
  CovarianceToPacked(cov, &packed);
  EXPECT_EQ(packed.dim(), dim);
  ASSERT_EQ(packed.upper_m2_size(), dim * (dim + 1) / 2);
  for (int r = 0; r < dim; ++r) {
    const int start = r * (4 * n - r + 1) / 2;  // as map.proto documents
    for (int c = r; c < dim; ++c) EXPECT_EQ(packed.upper_m2(start + c - r), cov(r, c)) << r << "," << c;
  }
  absl::StatusOr<Eigen::MatrixXd> back = CovarianceFromPacked(packed, n, "packed_covariance");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(*back, cov);
  absl::StatusOr<Eigen::MatrixXd> wrong = CovarianceFromPacked(packed, n + 1, "packed_covariance");
  EXPECT_EQ(wrong.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(wrong.status().message().rfind("packed_covariance:", 0), 0u) << wrong.status();
}

TEST(WireConvert, CovarianceFormatNeedsTheCovarianceAndAKnownValue) {
  EXPECT_EQ(*CovarianceFormatFromProto(pb::COVARIANCE_FORMAT_UNSPECIFIED, false, "f"), pb::COVARIANCE_FORMAT_BLOCKS);
  EXPECT_EQ(*CovarianceFormatFromProto(pb::COVARIANCE_FORMAT_UNSPECIFIED, true, "f"), pb::COVARIANCE_FORMAT_BLOCKS);
  EXPECT_EQ(*CovarianceFormatFromProto(pb::COVARIANCE_FORMAT_PACKED, true, "f"), pb::COVARIANCE_FORMAT_PACKED);
  EXPECT_EQ(CovarianceFormatFromProto(pb::COVARIANCE_FORMAT_PACKED, false, "f").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(CovarianceFormatFromProto(9, true, "f").status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap
