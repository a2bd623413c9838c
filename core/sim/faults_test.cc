#include "core/sim/faults.h"

#include <gtest/gtest.h>

#include "core/sim/city_scenario.h"

namespace crowdmap {
namespace {

Passage CityPassage(const CityScenario& city, int index) { return city.MakePassage(index); }

CityScenario City() {
  absl::StatusOr<CityScenario> city = CityScenario::Create(CityScenarioOptions());
  EXPECT_TRUE(city.ok());
  return *std::move(city);
}

TEST(InjectFaults, NoRateChangesNothing) {
  const CityScenario city = City();
  Passage p = CityPassage(city, 3);
  const InjectedFaults f = InjectFaults(FaultOptions(), 3, city.frame(), &p);
  EXPECT_FALSE(f.any());
  const Passage clean = CityPassage(city, 3);
  ASSERT_EQ(p.detections.size(), clean.detections.size());
  for (size_t i = 0; i < p.detections.size(); ++i) EXPECT_EQ(p.detections[i].landmark_id, clean.detections[i].landmark_id);
  EXPECT_EQ(p.gnss.front().lat_deg, clean.gnss.front().lat_deg);
}

TEST(InjectFaults, CertainFaultsAreAllAppliedAndTheSameEveryTime) {
  const CityScenario city = City();
  FaultOptions options;
  options.mislabel_rate = 1.0;
  options.multipath_rate = 1.0;
  options.overconfident_rate = 1.0;
  options.bad_calibration_rate = 1.0;
  const Passage clean = CityPassage(city, 5);
  Passage a = clean, b = clean;
  const InjectedFaults fa = InjectFaults(options, 5, city.frame(), &a);
  InjectFaults(options, 5, city.frame(), &b);
  EXPECT_EQ(fa.mislabelled_detections, static_cast<int>(clean.detections.size()));
  EXPECT_TRUE(fa.multipath && fa.overconfident && fa.bad_calibration);
  for (size_t i = 0; i < a.detections.size(); ++i) {
    EXPECT_EQ(std::abs(a.detections[i].landmark_id - clean.detections[i].landmark_id), 1);
    EXPECT_EQ(a.detections[i].landmark_id, b.detections[i].landmark_id);
  }
  // The burst moves some fixes by 30 to 80 m, all by the same offset, and leaves the others.
  int moved = 0;
  for (size_t i = 0; i < a.gnss.size(); ++i) {
    const double d = (city.frame().ToLocal(LatLon{a.gnss[i].lat_deg, a.gnss[i].lon_deg}) -
                      city.frame().ToLocal(LatLon{clean.gnss[i].lat_deg, clean.gnss[i].lon_deg}))
                         .norm();
    if (d > 1e-6) {
      ++moved;
      EXPECT_GE(d, 30.0 - 1e-6);
      EXPECT_LE(d, 80.0 + 1e-6);
    }
    EXPECT_NEAR(a.gnss[i].cov_en_m2(0, 0), clean.gnss[i].cov_en_m2(0, 0) / 25.0, 1e-12);
  }
  EXPECT_GE(moved, 15);  // at least 20 s of 1 Hz fixes, less the edges
  EXPECT_NEAR(a.calibration.camera_yaw_rad - clean.calibration.camera_yaw_rad, 3.0 * M_PI / 180.0, 1e-12);
  EXPECT_NEAR(a.calibration.wheelbase_m, 1.15 * clean.calibration.wheelbase_m, 1e-12);
}

TEST(FaultOptions, RefusesARateOutsideZeroToOneNamingIt) {
  FaultOptions options;
  options.multipath_rate = 1.5;
  EXPECT_NE(options.Validate().message().find("multipath_rate"), std::string::npos);
  options = FaultOptions();
  options.mislabel_rate = -0.1;
  EXPECT_NE(options.Validate().message().find("mislabel_rate"), std::string::npos);
  EXPECT_TRUE(FaultOptions().Validate().ok());
}

}  // namespace
}  // namespace crowdmap
