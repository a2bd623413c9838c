#include "core/model/passage.h"

#include <cmath>

#include <functional>
#include <limits>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/sim/city_scenario.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

Passage SimulatedPassage() {
  ScenarioOptions options;
  options.landmarks = 4;
  return Scenario::Create(options)->MakePassage(0);
}

// The smallest passage a vehicle could upload: a few samples of each kind.
Passage HandMadePassage() {
  Passage p;
  p.vehicle_id = "car-1";
  p.passage_id = "drive-1";
  for (int k = 0; k <= 50; ++k) p.odometry.push_back({0.04 * k, 12.0, 0.01});
  for (int k = 0; k < 3; ++k) {
    GnssFix f;
    f.t_s = k;
    f.lat_deg = 48.7 + 1e-4 * k;
    f.lon_deg = 2.17;
    p.gnss.push_back(f);
  }
  p.detections.push_back({0.0, 7, 900.0});
  p.detections.push_back({0.5, 8, 1200.0});
  p.detections.push_back({0.5, 7, 880.0});  // same frame, another landmark: equal times are fine
  return p;
}

// The status must be InvalidArgument and its message must start with "<field>: " (the format
// documented in passage.h), so the field path with its index is named exactly.
void ExpectRejected(const Passage& p, const std::string& field) {
  const absl::Status s = ValidatePassage(p);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << field << ": " << s;
  EXPECT_EQ(std::string(s.message()).rfind(field + ": ", 0), 0u) << "message '" << s.message() << "' does not name " << field;
}

struct BadInput {
  std::string field;
  std::function<void(Passage*)> spoil;
};

std::vector<BadInput> BadInputs() {
  return {
      {"odometry[7].speed_mps", [](Passage* p) { p->odometry[7].speed_mps = kNan; }},
      {"odometry[8].speed_mps", [](Passage* p) { p->odometry[8].speed_mps = kInf; }},
      {"odometry[3].steering_rad", [](Passage* p) { p->odometry[3].steering_rad = -kInf; }},
      {"odometry[5].t_s", [](Passage* p) { p->odometry[5].t_s = p->odometry[4].t_s - 0.01; }},
      {"odometry[5].t_s", [](Passage* p) { p->odometry[5].t_s = p->odometry[4].t_s; }},  // must increase
      {"odometry[0].t_s", [](Passage* p) { p->odometry[0].t_s = -1.0; }},
      {"gnss[2].t_s", [](Passage* p) { p->gnss[2].t_s = 1e308; }},
      {"gnss[2].t_s", [](Passage* p) {  // a passage spans a day at most
         for (size_t i = 2; i < p->gnss.size(); ++i) p->gnss[i].t_s += 2 * 86400.0;
       }},
      {"start_time_unix_ms", [](Passage* p) { p->start_time_unix_ms = INT64_MAX; }},
      {"start_time_unix_ms", [](Passage* p) { p->start_time_unix_ms = -1; }},
      {"odometry[0].t_s", [](Passage* p) { p->odometry[0].t_s = 2e10; }},
      {"gnss[2].t_s", [](Passage* p) { p->gnss[2].t_s = p->gnss[1].t_s - 0.5; }},
      {"detections[2].t_s", [](Passage* p) { p->detections[2].t_s = p->detections[1].t_s - 0.25; }},
      {"gnss[1].lat_deg", [](Passage* p) { p->gnss[1].lat_deg = 91.0; }},
      {"gnss[1].lat_deg", [](Passage* p) { p->gnss[1].lat_deg = -90.5; }},
      {"gnss[2].lat_deg", [](Passage* p) { p->gnss[2].lat_deg = kNan; }},
      {"gnss[2].lon_deg", [](Passage* p) { p->gnss[2].lon_deg = -181.0; }},
      {"gnss[0].lon_deg", [](Passage* p) { p->gnss[0].lon_deg = 180.5; }},
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2 << 1.0, 2.0, 2.0, 1.0; }},  // indefinite
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2 << -1.0, 0.0, 0.0, -1.0; }},  // det > 0, not PD
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2.setZero(); }},
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2 << 4.0, 1.0, 0.0, 4.0; }},  // asymmetric
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2(0, 0) = kNan; }},
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2 = Eigen::Matrix2d::Identity() * 1e300; }},
      {"gnss[1].cov_en_m2", [](Passage* p) { p->gnss[1].cov_en_m2 = Eigen::Matrix2d::Identity() * 1e-8; }},
      {"detections[1].u_px", [](Passage* p) { p->detections[1].u_px = p->calibration.image_width_px + 1.0; }},
      {"detections[1].u_px", [](Passage* p) { p->detections[1].u_px = -0.5; }},
      {"detections[0].u_px", [](Passage* p) { p->detections[0].u_px = kNan; }},
      {"vehicle_id", [](Passage* p) { p->vehicle_id.clear(); }},
      {"passage_id", [](Passage* p) { p->passage_id.clear(); }},
      {"odometry", [](Passage* p) { p->odometry.clear(); }},
      {"detections", [](Passage* p) { p->detections.clear(); }},
      {"gnss", [](Passage* p) { p->gnss.resize(1); }},
      {"gnss", [](Passage* p) { p->gnss.clear(); }},
      {"calibration.wheelbase_m", [](Passage* p) { p->calibration.wheelbase_m = 0.0; }},
      {"calibration.wheelbase_m", [](Passage* p) { p->calibration.wheelbase_m = -2.7; }},
      {"calibration.fx_px", [](Passage* p) { p->calibration.fx_px = 0.0; }},
      {"calibration.fx_px", [](Passage* p) { p->calibration.fx_px = -1000.0; }},
      {"calibration.image_width_px", [](Passage* p) { p->calibration.image_width_px = 0.0; }},
      {"calibration.cx_px", [](Passage* p) { p->calibration.cx_px = p->calibration.image_width_px + 1.0; }},
      {"calibration.camera_yaw_rad", [](Passage* p) { p->calibration.camera_yaw_rad = kNan; }},
      {"noise.speed_sigma_mps", [](Passage* p) { p->noise.speed_sigma_mps = -0.56; }},
      {"noise.steering_sigma_rad", [](Passage* p) { p->noise.steering_sigma_rad = -0.044; }},
      {"noise.steering_sigma_rad", [](Passage* p) { p->noise.steering_sigma_rad = 38.0; }},
      {"noise.speed_sigma_mps", [](Passage* p) { p->noise.speed_sigma_mps = 50.0; }},
      {"noise.pixel_sigma_px", [](Passage* p) { p->noise.pixel_sigma_px = -5.0; }},
      {"noise.pixel_sigma_px", [](Passage* p) { p->noise.pixel_sigma_px = 0.0; }},
      {"noise.pixel_sigma_px", [](Passage* p) { p->noise.pixel_sigma_px = 1e-300; }},  // its square is 0
      {"noise.pixel_sigma_px", [](Passage* p) { p->noise.pixel_sigma_px = 1e-4; }},    // finite, absurdly sure
      {"noise.gnss_correlation_time_s", [](Passage* p) { p->noise.gnss_correlation_time_s = -1.0; }},
      {"noise.gnss_correlation_time_s", [](Passage* p) { p->noise.gnss_correlation_time_s = 1e6; }},
      {"noise.gnss_correlation_time_s", [](Passage* p) { p->noise.gnss_correlation_time_s = std::nan(""); }},
      {"noise.gnss_process_sigma_m", [](Passage* p) { p->noise.gnss_process_sigma_m = -10.0; }},
      // Physically impossible inputs (each once applied to a real map; see the trust rules).
      {"gnss[0].lat_deg", [](Passage* p) { for (GnssFix& f : p->gnss) f.lat_deg = -90.0; }},
      {"gnss[1]", [](Passage* p) { p->gnss[1].lat_deg = p->gnss[0].lat_deg + 1.0; }},  // 111 km jump
      {"gnss[1]", [](Passage* p) { p->gnss[1].lon_deg += 180.0 - (p->gnss[1].lon_deg > 0 ? 360.0 : 0.0); }},
      {"gnss[1]", [](Passage* p) { p->gnss[1].lat_deg = 0.0; p->gnss[1].lon_deg = 0.0; }},
      {"calibration.gnss_lever_arm_m.x_m", [](Passage* p) { p->calibration.gnss_lever_arm_m.x() = 1e11; }},
      {"calibration.camera_position_m.y_m", [](Passage* p) { p->calibration.camera_position_m.y() = -50.0; }},
      {"calibration.wheelbase_m", [](Passage* p) { p->calibration.wheelbase_m = 1e15; }},
      {"calibration.fx_px", [](Passage* p) { p->calibration.fx_px = 1e9; }},
      {"calibration.camera_yaw_rad", [](Passage* p) { p->calibration.camera_yaw_rad = 7.0; }},
      {"odometry[0].steering_rad", [](Passage* p) { for (OdometrySample& o : p->odometry) o.steering_rad = 1.57; }},
      {"odometry[2].speed_mps", [](Passage* p) { p->odometry[2].speed_mps = 400.0; }},
      {"odometry[2].speed_mps", [](Passage* p) { p->odometry[2].speed_mps = -40.0; }},
      {"detections[1].landmark_id", [](Passage* p) { p->detections[1].landmark_id = -3; }},
      {"detections[1].landmark_id", [](Passage* p) { p->detections[1].landmark_id = 0; }},
      {"detections[2].t_s", [](Passage* p) { p->detections[2].t_s = p->odometry.back().t_s + 60.0; }},
      // The landmarks under further ids: every detection copied under 11 other ids.
      {"detections", [](Passage* p) {
         const double end_s = p->detections.back().t_s;
         const LandmarkId first = p->detections.front().landmark_id;
         for (int k = 1; k <= 3; ++k) p->detections.push_back({end_s + 0.1 * k, first, 500.0 + k});
         std::vector<Detection> copied;
         for (const Detection& d : p->detections) {
           copied.push_back(d);
           for (LandmarkId c = 1; c <= 11; ++c) {
             copied.push_back({d.t_s, 100000 * c + d.landmark_id, d.u_px + 0.001 * c * p->noise.pixel_sigma_px});
           }
         }
         p->detections = copied;
       }},
      {"detections[16].u_px", [](Passage* p) {  // a frame of detections at one pixel: the 17th named
         std::vector<Detection> frame(17, p->detections.front());
         for (size_t k = 0; k < frame.size(); ++k) frame[k].landmark_id = 1000 + static_cast<LandmarkId>(k);
         p->detections.insert(p->detections.begin(), frame.begin(), frame.end());
       }},
      {"detections[0].t_s", [](Passage* p) {  // an overfull frame
         std::vector<Detection> frame(1001, p->detections.front());
         for (size_t k = 0; k < frame.size(); ++k) frame[k].landmark_id = 1000 + static_cast<LandmarkId>(k);
         p->detections.insert(p->detections.begin(), frame.begin(), frame.end());
       }},
      {"vehicle_id", [](Passage* p) { p->vehicle_id = "v\nerror event=disk_full"; }},
      {"vehicle_id", [](Passage* p) { p->vehicle_id = std::string(200, 'v'); }},
      {"passage_id", [](Passage* p) { p->passage_id = "with space"; }},
  };
}

TEST(ValidatePassage, AcceptsASimulatedPassage) {
  const absl::Status s = ValidatePassage(SimulatedPassage());
  EXPECT_TRUE(s.ok()) << s;
}

TEST(ValidatePassage, AcceptsEverySimulatedPassageOfVariedFleets) {
  // The bounds must never refuse honest data: loop passages under every noise configuration and
  // city passages of short and long routes, varied sensor rates and per-vehicle camera errors.
  int checked = 0;
  for (NoiseConfig noise : {NoiseConfig::kWhite, NoiseConfig::kGnssAr1, NoiseConfig::kYawBias, NoiseConfig::kGnssAr1YawBias}) {
    ScenarioOptions options;
    options.landmarks = 25;
    options.noise = noise;
    absl::StatusOr<Scenario> loop = Scenario::Create(options);
    ASSERT_TRUE(loop.ok());
    for (int i = 0; i < 25; ++i, ++checked) EXPECT_TRUE(ValidatePassage(loop->MakePassage(i)).ok()) << i;
  }
  for (double route_m : {300.0, 1500.0}) {
    CityScenarioOptions city;
    city.route_length_m = route_m;
    city.rate_variation = 0.2;
    city.vehicle_yaw_bias_sigma_rad = 0.01;
    city.noise = NoiseConfig::kGnssAr1;
    absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
    ASSERT_TRUE(scenario.ok());
    for (int i = 0; i < 40; ++i, ++checked) {
      const absl::Status s = ValidatePassage(scenario->MakePassage(i));
      EXPECT_TRUE(s.ok()) << route_m << " m, passage " << i << ": " << s;
    }
  }
  EXPECT_EQ(checked, 180);
}

// A sign on its pole has the pole's bearing from everywhere: two ids at the same pixel in every
// frame, a few such pairs, are honest data; a passage in which more than a fifth of the ids (and
// more than 10) repeat others' detections is refused (above).
TEST(ValidatePassage, AcceptsAFewLandmarksStandingTogether) {
  Passage p = SimulatedPassage();
  std::vector<Detection> with_signs;
  for (const Detection& d : p.detections) {
    with_signs.push_back(d);
    if (d.landmark_id <= 2) with_signs.push_back({d.t_s, 1000 + d.landmark_id, d.u_px});
  }
  p.detections = with_signs;
  const absl::Status s = ValidatePassage(p);
  EXPECT_TRUE(s.ok()) << s;
}

// Frames of new ids piled at one pixel: refused once a thousand pairs of ids coincide, before the
// check holds more (its memory on a 64 MiB upload).
TEST(ValidatePassage, RefusesThousandsOfIdsPiledAtOnePixel) {
  Passage p = SimulatedPassage();
  const Detection first = p.detections.front();
  p.detections.clear();
  for (int frame = 0; frame < 10; ++frame) {
    for (int k = 0; k < 15; ++k) {
      p.detections.push_back({first.t_s + 0.1 * frame, 1000 + 15 * frame + k, first.u_px});
    }
  }
  const absl::Status s = ValidatePassage(p);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("more than 1000 pairs of landmark ids"), std::string::npos) << s;
}

TEST(ValidatePassage, AcceptsAMinimalHandMadePassageWithSimultaneousDetections) {
  const absl::Status s = ValidatePassage(HandMadePassage());
  EXPECT_TRUE(s.ok()) << s;
}

TEST(ValidatePassage, RejectsEachBadSimulatedInputNamingTheFieldAndIndex) {
  for (const BadInput& bad : BadInputs()) {
    Passage p = SimulatedPassage();
    bad.spoil(&p);
    ExpectRejected(p, bad.field);
  }
}

TEST(ValidatePassage, RejectsEachBadHandMadeInputNamingTheFieldAndIndex) {
  for (const BadInput& bad : BadInputs()) {
    Passage p = HandMadePassage();
    bad.spoil(&p);
    ExpectRejected(p, bad.field);
  }
}

TEST(ValidatePassage, NamesTheIndexOfALateBadFix) {
  Passage p = SimulatedPassage();
  ASSERT_GT(p.gnss.size(), 100u);
  p.gnss[100].lat_deg = 91.0;
  ExpectRejected(p, "gnss[100].lat_deg");
  EXPECT_NE(ValidatePassage(p).message().find("91"), std::string::npos) << "the message shows the bad value";
}

TEST(PassageContentDigest, IsTheSameUnderOtherIdsAndDiffersWithAnyMeasurement) {
  const Passage passage = SimulatedPassage();
  const std::string digest = PassageContentDigest(passage);
  EXPECT_EQ(digest.size(), 32u);
  Passage renamed = passage;
  renamed.vehicle_id = "another-vehicle";
  renamed.passage_id = "another-passage";
  EXPECT_EQ(PassageContentDigest(renamed), digest);

  // Any one measured number changed, by the least a double can change, is another drive.
  const std::vector<std::pair<const char*, std::function<void(Passage*)>>> changes = {
      {"start time", [](Passage* p) { ++p->start_time_unix_ms; }},
      {"wheelbase", [](Passage* p) { p->calibration.wheelbase_m = std::nextafter(p->calibration.wheelbase_m, 10.0); }},
      {"lever arm", [](Passage* p) { p->calibration.gnss_lever_arm_m.y() += 1e-9; }},
      {"camera position", [](Passage* p) { p->calibration.camera_position_m.x() += 1e-9; }},
      {"camera yaw", [](Passage* p) { p->calibration.camera_yaw_rad += 1e-9; }},
      {"focal length", [](Passage* p) { p->calibration.fx_px += 1e-6; }},
      {"principal point", [](Passage* p) { p->calibration.cx_px += 1e-6; }},
      {"image width", [](Passage* p) { p->calibration.image_width_px += 1.0; }},
      {"speed sigma", [](Passage* p) { p->noise.speed_sigma_mps += 1e-9; }},
      {"steering sigma", [](Passage* p) { p->noise.steering_sigma_rad += 1e-9; }},
      {"pixel sigma", [](Passage* p) { p->noise.pixel_sigma_px += 1e-9; }},
      {"gnss correlation", [](Passage* p) { p->noise.gnss_correlation_time_s = 60.0; }},
      {"gnss process sigma", [](Passage* p) { p->noise.gnss_process_sigma_m = 3.0; }},
      {"odometry speed", [](Passage* p) { p->odometry.back().speed_mps = std::nextafter(p->odometry.back().speed_mps, 100.0); }},
      {"odometry steering", [](Passage* p) { p->odometry[3].steering_rad += 1e-12; }},
      {"odometry time", [](Passage* p) { p->odometry.back().t_s += 1e-9; }},
      {"one sample fewer", [](Passage* p) { p->odometry.pop_back(); }},
      {"gnss latitude", [](Passage* p) { p->gnss[1].lat_deg = std::nextafter(p->gnss[1].lat_deg, 90.0); }},
      {"gnss longitude", [](Passage* p) { p->gnss[1].lon_deg += 1e-12; }},
      {"gnss covariance", [](Passage* p) { p->gnss[0].cov_en_m2(0, 1) = p->gnss[0].cov_en_m2(1, 0) = 0.01; }},
      {"gnss time", [](Passage* p) { p->gnss.back().t_s += 1e-9; }},
      {"detection pixel", [](Passage* p) { p->detections[5].u_px += 1e-9; }},
      {"detection landmark", [](Passage* p) { p->detections[5].landmark_id += 1; }},
      {"detection time", [](Passage* p) { p->detections.back().t_s += 1e-9; }},
      // The same numbers in other lists are another drive: each list's length is part of it.
      {"a detection fewer, a fix more",
       [](Passage* p) {
         p->detections.pop_back();
         p->gnss.push_back(p->gnss.back());
         p->gnss.back().t_s += 1.0;
       }},
  };
  for (const auto& [what, change] : changes) {
    Passage other = passage;
    change(&other);
    EXPECT_NE(PassageContentDigest(other), digest) << what;
  }
}

}  // namespace
}  // namespace crowdmap
