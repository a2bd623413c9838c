#include "core/model/passage.h"

#include <limits>
#include <string>

#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

Passage GoodPassage() {
  ScenarioOptions options;
  options.landmarks = 4;
  return Scenario::Create(options)->MakePassage(0);
}

void ExpectRejected(const Passage& p, const std::string& field) {
  const absl::Status s = ValidatePassage(p);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << field;
  EXPECT_NE(s.message().find(field), std::string::npos) << "message '" << s.message() << "' lacks " << field;
}

TEST(ValidatePassage, AcceptsASimulatedPassage) { EXPECT_TRUE(ValidatePassage(GoodPassage()).ok()); }

TEST(ValidatePassage, RejectsEachBadInputNamingTheFieldAndIndex) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  Passage p = GoodPassage();
  p.odometry[7].speed_mps = nan;
  ExpectRejected(p, "odometry[7].speed_mps");
  p = GoodPassage();
  p.odometry[5].t_s = p.odometry[4].t_s;
  ExpectRejected(p, "odometry[5].t_s");
  p = GoodPassage();
  p.gnss[3].t_s = p.gnss[2].t_s - 0.5;
  ExpectRejected(p, "gnss[3].t_s");
  p = GoodPassage();
  p.detections[2].t_s = p.detections[1].t_s - 1.0;
  ExpectRejected(p, "detections[2].t_s");
  p = GoodPassage();
  p.gnss[3].lat_deg = 91.0;
  ExpectRejected(p, "gnss[3].lat_deg");
  p = GoodPassage();
  p.gnss[4].lon_deg = -181.0;
  ExpectRejected(p, "gnss[4].lon_deg");
  p = GoodPassage();
  p.gnss[1].cov_en_m2 << 1.0, 2.0, 2.0, 1.0;  // indefinite
  ExpectRejected(p, "gnss[1].cov_en_m2");
  p = GoodPassage();
  p.detections[0].u_px = p.calibration.image_width_px + 1.0;
  ExpectRejected(p, "detections[0].u_px");
  p = GoodPassage();
  p.vehicle_id.clear();
  ExpectRejected(p, "vehicle_id");
  p = GoodPassage();
  p.passage_id.clear();
  ExpectRejected(p, "passage_id");
  p = GoodPassage();
  p.odometry.clear();
  ExpectRejected(p, "odometry");
  p = GoodPassage();
  p.detections.clear();
  ExpectRejected(p, "detections");
  p = GoodPassage();
  p.gnss.resize(1);
  ExpectRejected(p, "gnss");
  p = GoodPassage();
  p.calibration.wheelbase_m = 0.0;
  ExpectRejected(p, "calibration.wheelbase_m");
  p = GoodPassage();
  p.calibration.fx_px = -1.0;
  ExpectRejected(p, "calibration.fx_px");
  p = GoodPassage();
  p.noise.pixel_sigma_px = -5.0;
  ExpectRejected(p, "noise.pixel_sigma_px");
}

}  // namespace
}  // namespace crowdmap
