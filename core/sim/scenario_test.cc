#include "core/sim/scenario.h"

#include <cmath>

#include <gtest/gtest.h>

#include "core/model/camera_model.h"

namespace crowdmap {
namespace {

Scenario Make(int landmarks, NoiseConfig noise = NoiseConfig::kWhite) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.noise = noise;
  return *Scenario::Create(options);
}

TEST(Scenario, RouteIsAboutTwoKilometresIn165Seconds) {
  const Scenario s = Make(4);
  EXPECT_GT(s.route_length_m(), 1800.0);
  EXPECT_LT(s.route_length_m(), 2200.0);
  const Passage p = s.MakePassage(0);
  EXPECT_NEAR(p.odometry.back().t_s, 165.0, 1e-6);
  EXPECT_EQ(p.odometry.size(), 165u * 25 + 1);
  EXPECT_EQ(p.gnss.size(), 166u);
  for (const Detection& d : p.detections) {
    EXPECT_NEAR(std::fmod(d.t_s * 2.0, 1.0), 0.0, 1e-9);
    EXPECT_GE(d.u_px, 0.0);
    EXPECT_LE(d.u_px, p.calibration.image_width_px);
  }
}

TEST(Scenario, PassagesAreDeterministicAndIndependent) {
  const Scenario s = Make(25);
  const Passage a = s.MakePassage(5), b = s.MakePassage(5), c = s.MakePassage(6);
  EXPECT_EQ(a.gnss[10].lat_deg, b.gnss[10].lat_deg);
  EXPECT_EQ(a.odometry[100].speed_mps, b.odometry[100].speed_mps);
  EXPECT_NE(a.gnss[10].lat_deg, c.gnss[10].lat_deg);
  EXPECT_EQ(a.passage_id, "p5");
}

TEST(Scenario, LargerScenariosExtendSmallerOnes) {
  const Scenario small = Make(25), large = Make(50);
  for (int i = 0; i < 25; ++i) EXPECT_EQ(small.landmarks()[i].position_m, large.landmarks()[i].position_m);
}

// GNSS errors (fix minus true antenna) of many passages, per axis East.
std::vector<std::vector<double>> EastErrors(const Scenario& s, int passages) {
  std::vector<std::vector<double>> out;
  for (int i = 0; i < passages; ++i) {
    const Passage p = s.MakePassage(i);
    std::vector<double> e;
    for (const GnssFix& f : p.gnss) {
      const Pose2 pose = s.TruePoseAt(f.t_s);
      const Eigen::Vector2d arm = s.options().calibration.gnss_lever_arm_m;
      const Eigen::Vector2d antenna =
          pose.head<2>() + Eigen::Vector2d(std::cos(pose.z()) * arm.x() - std::sin(pose.z()) * arm.y(),
                                           std::sin(pose.z()) * arm.x() + std::cos(pose.z()) * arm.y());
      e.push_back((s.frame().ToLocal({f.lat_deg, f.lon_deg}) - antenna).x());
    }
    out.push_back(e);
  }
  return out;
}

TEST(Scenario, GnssNoiseHasTheConfiguredSigmaAndCorrelation) {
  for (NoiseConfig noise : {NoiseConfig::kWhite, NoiseConfig::kGnssAr1}) {
    double sum2 = 0.0, lag1 = 0.0;
    int n = 0, m = 0;
    for (const auto& e : EastErrors(Make(4, noise), 60)) {
      for (size_t k = 0; k < e.size(); ++k) {
        sum2 += e[k] * e[k];
        ++n;
        if (k > 0) {
          lag1 += e[k] * e[k - 1];
          ++m;
        }
      }
    }
    const double sigma = std::sqrt(sum2 / n), rho = (lag1 / m) / (sum2 / n);
    EXPECT_NEAR(sigma, 10.0, noise == NoiseConfig::kWhite ? 0.5 : 2.0);
    EXPECT_NEAR(rho, noise == NoiseConfig::kWhite ? 0.0 : 0.988, noise == NoiseConfig::kWhite ? 0.05 : 0.02);
  }
}

TEST(Scenario, YawBiasShiftsPixelsByAboutFxTimesTheBias) {
  const Scenario s = Make(25, NoiseConfig::kYawBias);
  const Calibration nominal = s.options().calibration;
  double sum = 0.0;
  int n = 0;
  for (int i = 0; i < 20; ++i) {
    for (const Detection& d : s.MakePassage(i).detections) {
      const Pose2 pose = s.TruePoseAt(d.t_s);
      double u;
      if (!ProjectLandmark(pose.data(), s.landmarks()[d.landmark_id - 1].position_m.data(), nominal, &u)) continue;
      // A camera yawed left by dyaw sees the bearing dyaw smaller: u grows by fx (1 + tan^2) dyaw.
      const double t = (nominal.cx_px - u) / nominal.fx_px;
      sum += (d.u_px - u) / (1.0 + t * t);
      ++n;
    }
  }
  EXPECT_NEAR(sum / n, nominal.fx_px * 0.009, 1.0);
}

}  // namespace
}  // namespace crowdmap
