#include "core/sim/scenario.h"

#include <cmath>
#include <vector>

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

Eigen::Vector2d Rotate(double angle, const Eigen::Vector2d& v) {
  return {std::cos(angle) * v.x() - std::sin(angle) * v.y(), std::sin(angle) * v.x() + std::cos(angle) * v.y()};
}

bool SamePassage(const Passage& a, const Passage& b) {
  if (a.vehicle_id != b.vehicle_id || a.passage_id != b.passage_id || a.start_time_unix_ms != b.start_time_unix_ms ||
      a.odometry.size() != b.odometry.size() || a.gnss.size() != b.gnss.size() ||
      a.detections.size() != b.detections.size()) {
    return false;
  }
  for (size_t i = 0; i < a.odometry.size(); ++i) {
    const OdometrySample &x = a.odometry[i], &y = b.odometry[i];
    if (x.t_s != y.t_s || x.speed_mps != y.speed_mps || x.steering_rad != y.steering_rad) return false;
  }
  for (size_t i = 0; i < a.gnss.size(); ++i) {
    const GnssFix &x = a.gnss[i], &y = b.gnss[i];
    if (x.t_s != y.t_s || x.lat_deg != y.lat_deg || x.lon_deg != y.lon_deg || x.cov_en_m2 != y.cov_en_m2) return false;
  }
  for (size_t i = 0; i < a.detections.size(); ++i) {
    const Detection &x = a.detections[i], &y = b.detections[i];
    if (x.t_s != y.t_s || x.landmark_id != y.landmark_id || x.u_px != y.u_px) return false;
  }
  return true;
}

// GNSS errors (fix minus true antenna position) per passage, East and North as separate series.
std::vector<std::vector<double>> GnssErrorSeries(const Scenario& s, int passages) {
  std::vector<std::vector<double>> series;
  const Eigen::Vector2d arm = s.options().calibration.gnss_lever_arm_m;
  for (int i = 0; i < passages; ++i) {
    std::vector<double> east, north;
    for (const GnssFix& f : s.MakePassage(i).gnss) {
      const Pose2 pose = s.TruePoseAt(f.t_s);
      const Eigen::Vector2d antenna = pose.head<2>() + Rotate(pose.z(), arm);
      const Eigen::Vector2d e = s.frame().ToLocal({f.lat_deg, f.lon_deg}) - antenna;
      east.push_back(e.x());
      north.push_back(e.y());
    }
    series.push_back(east);
    series.push_back(north);
  }
  return series;
}

struct SeriesStats {
  double sigma = 0.0;  // root mean square (the errors have mean zero by construction)
  double lag1 = 0.0;   // sum e_k e_(k-1) / sum e_(k-1)^2
};

SeriesStats Stats(const std::vector<std::vector<double>>& series) {
  double sum2 = 0.0, cross = 0.0, previous2 = 0.0;
  int n = 0;
  for (const std::vector<double>& e : series) {
    for (size_t k = 0; k < e.size(); ++k) {
      sum2 += e[k] * e[k];
      ++n;
      if (k > 0) {
        cross += e[k] * e[k - 1];
        previous2 += e[k - 1] * e[k - 1];
      }
    }
  }
  return {std::sqrt(sum2 / n), cross / previous2};
}

TEST(Scenario, RouteIsAboutTwoKilometresDrivenIn165Seconds) {
  const Scenario s = Make(4);
  EXPECT_GT(s.route_length_m(), 1800.0);
  EXPECT_LT(s.route_length_m(), 2200.0);
  const Passage p = s.MakePassage(0);
  EXPECT_NEAR(p.odometry.back().t_s, 165.0, 1e-9);
  EXPECT_NEAR(p.gnss.back().t_s, 165.0, 1e-9);
  EXPECT_NEAR(s.route_length_m() / 165.0, 12.0, 0.5) << "about 12 m/s";
  // The route ends far from where it starts and turns in both directions.
  EXPECT_GT(s.true_poses().back().head<2>().norm(), 300.0);
  double min_steering = 0.0, max_steering = 0.0;
  for (const OdometrySample& u : s.true_inputs()) {
    min_steering = std::min(min_steering, u.steering_rad);
    max_steering = std::max(max_steering, u.steering_rad);
  }
  EXPECT_LT(min_steering, -0.01);
  EXPECT_GT(max_steering, 0.01);
}

TEST(Scenario, TruePoseAtSampleTimesIsTheRoute) {
  const Scenario s = Make(4);
  for (size_t j : {0u, 1u, 500u, 4125u}) {
    EXPECT_LT((s.TruePoseAt(s.true_inputs()[j].t_s) - s.true_poses()[j]).norm(), 1e-9) << j;
  }
  // Between samples it moves at the held speed: 12 m/s for 0.02 s is about 0.24 m.
  const double step = (s.TruePoseAt(100.02).head<2>() - s.TruePoseAt(100.0).head<2>()).norm();
  EXPECT_NEAR(step, s.true_inputs()[2500].speed_mps * 0.02, 1e-6);
}

TEST(Scenario, AlternatingDirectionsDriveOddPassagesBackAlongTheRoute) {
  ScenarioOptions options = Make(50).options();
  options.alternate_directions = true;
  const absl::StatusOr<Scenario> s = Scenario::Create(options);
  ASSERT_TRUE(s.ok()) << s.status();
  const double duration = options.duration_s;
  // Even passages are the route; odd ones start at its end, facing back, and end near its start.
  EXPECT_LT((s->TruePoseAt(2, 37.0) - s->TruePoseAt(37.0)).norm(), 1e-12);
  const Pose2 start = s->TruePoseAt(1, 0.0), end = s->TruePoseAt(1, duration);
  EXPECT_LT((start.head<2>() - s->TruePoseAt(duration).head<2>()).norm(), 1e-9);
  EXPECT_NEAR(std::remainder(start.z() - s->TruePoseAt(duration).z() - M_PI, 2 * M_PI), 0.0, 1e-12);
  EXPECT_LT((end.head<2>() - s->TruePoseAt(0.0).head<2>()).norm(), 2.0) << "the same road, driven back";
  // Halfway the backward drive passes where the forward one is halfway.
  double nearest = INFINITY;
  for (double t = 0.0; t <= duration; t += 0.1) {
    nearest = std::min(nearest, (s->TruePoseAt(1, duration / 2).head<2>() - s->TruePoseAt(t).head<2>()).norm());
  }
  EXPECT_LT(nearest, 1.0);
  // Its measurements follow its own drive: a landmark seen first going forward is seen late going back.
  const Passage forward = s->MakePassage(0), backward = s->MakePassage(1);
  ASSERT_FALSE(forward.detections.empty());
  ASSERT_FALSE(backward.detections.empty());
  const LandmarkId first = forward.detections.front().landmark_id;
  double seen_back = -1.0;
  for (const auto& d : backward.detections) {
    if (d.landmark_id == first) seen_back = d.t_s;
  }
  EXPECT_GT(seen_back, duration / 2) << "landmark " << first;
  options.piece_min_m = 300.0;
  options.piece_max_m = 600.0;
  EXPECT_EQ(options.Validate().code(), absl::StatusCode::kInvalidArgument) << "not with partial drives";
}

TEST(Scenario, MakePassageIsDeterministicAndIndicesDiffer) {
  const Scenario s = Make(25);
  const Passage a = s.MakePassage(5), b = s.MakePassage(5), c = s.MakePassage(6);
  EXPECT_TRUE(SamePassage(a, b));
  EXPECT_TRUE(SamePassage(a, Make(25).MakePassage(5))) << "independent of the Scenario object";
  EXPECT_FALSE(SamePassage(a, c));
  EXPECT_NE(a.gnss[10].lat_deg, c.gnss[10].lat_deg);
  EXPECT_NE(a.odometry[100].speed_mps, c.odometry[100].speed_mps);
  EXPECT_NE(a.detections[0].u_px, c.detections[0].u_px);
  EXPECT_EQ(a.passage_id, "p5-s1-n25-white");
  EXPECT_EQ(c.passage_id, "p6-s1-n25-white");
  // Another scenario's passage 5 is another drive: another id, so a server does not take it for a duplicate.
  ScenarioOptions other_seed = s.options();
  other_seed.seed = 2;
  EXPECT_EQ(Scenario::Create(other_seed)->MakePassage(5).passage_id, "p5-s2-n25-white");
  EXPECT_NE(Make(50).MakePassage(5).passage_id, a.passage_id);
  EXPECT_EQ(a.vehicle_id, "sim-5");
}

TEST(Scenario, LargerScenariosExtendSmallerOnes) {
  const Scenario s4 = Make(4), s25 = Make(25), s50 = Make(50), s100 = Make(100);
  ASSERT_EQ(s4.landmarks().size(), 4u);
  ASSERT_EQ(s50.landmarks().size(), 50u);
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(s4.landmarks()[i].position_m, s25.landmarks()[i].position_m) << i;
    EXPECT_EQ(s4.landmarks()[i].position_m, s100.landmarks()[i].position_m) << i;
  }
  for (int i = 0; i < 25; ++i) {
    EXPECT_EQ(s25.landmarks()[i].id, i + 1);
    EXPECT_EQ(s25.landmarks()[i].position_m, s50.landmarks()[i].position_m) << i;
    EXPECT_EQ(s25.landmarks()[i].position.lat_deg, s50.landmarks()[i].position.lat_deg) << i;
  }
  // Distinct landmarks, a few metres off the road.
  for (int i = 0; i < 50; ++i) {
    for (int j = 0; j < i; ++j) EXPECT_NE(s50.landmarks()[i].position_m, s50.landmarks()[j].position_m);
  }
}

TEST(Scenario, SensorsRunAtTheirRates) {
  const Scenario s = Make(25);
  const Passage p = s.MakePassage(0);
  ASSERT_EQ(p.odometry.size(), 165u * 25 + 1);
  for (size_t k = 0; k < p.odometry.size(); ++k) EXPECT_NEAR(p.odometry[k].t_s, k / 25.0, 1e-9) << k;
  ASSERT_EQ(p.gnss.size(), 166u);
  for (size_t k = 0; k < p.gnss.size(); ++k) EXPECT_NEAR(p.gnss[k].t_s, static_cast<double>(k), 1e-9) << k;
  ASSERT_FALSE(p.detections.empty());
  for (const Detection& d : p.detections) {
    EXPECT_NEAR(d.t_s * 2.0, std::round(d.t_s * 2.0), 1e-9) << "2 Hz frames: " << d.t_s;
  }
  EXPECT_TRUE(ValidatePassage(p).ok());
}

TEST(Scenario, DetectionsLieInsideTheImageAndInTheDetectionRange) {
  const Scenario s = Make(25);
  const ScenarioOptions& o = s.options();
  std::vector<bool> seen(26, false);
  for (int i = 0; i < 3; ++i) {
    for (const Detection& d : s.MakePassage(i).detections) {
      EXPECT_GE(d.u_px, 0.0);
      EXPECT_LE(d.u_px, o.calibration.image_width_px);
      ASSERT_GE(d.landmark_id, 1);
      ASSERT_LE(d.landmark_id, 25);
      seen[d.landmark_id] = true;
      const Eigen::Vector2d cam =
          LandmarkInCameraFrame(s.TruePoseAt(d.t_s), s.landmarks()[d.landmark_id - 1].position_m, o.calibration);
      EXPECT_GT(cam.x(), 0.0) << "in front";
      EXPECT_GE(cam.norm(), o.min_detection_range_m - 1e-9);
      EXPECT_LE(cam.norm(), o.max_detection_range_m + 1e-9);
    }
  }
  for (int id = 1; id <= 25; ++id) EXPECT_TRUE(seen[id]) << "landmark " << id << " never detected";
}

TEST(Scenario, WhiteGnssErrorsHaveTenMetreSigmaAndNoCorrelation) {
  // 20 passages x 166 fixes x 2 axes: the standard error of sigma is 0.09 m, of the lag-1
  // correlation 0.012.
  const SeriesStats stats = Stats(GnssErrorSeries(Make(4), 20));
  EXPECT_NEAR(stats.sigma, 10.0, 0.5);
  EXPECT_NEAR(stats.lag1, 0.0, 0.06);
}

TEST(Scenario, Ar1GnssErrorsHaveTenMetreSigmaAndTheirCorrelation) {
  const ScenarioOptions& defaults = ScenarioOptions();
  const double alpha = defaults.gnss_ar1_alpha;
  ASSERT_EQ(alpha, 0.988);
  const std::vector<std::vector<double>> series = GnssErrorSeries(Make(4, NoiseConfig::kGnssAr1), 200);
  const SeriesStats stats = Stats(series);
  // Each 166 s series holds about one correlation time (83 s): with 400 series the standard
  // error of sigma is about 0.35 m.
  EXPECT_NEAR(stats.sigma, 10.0, 1.5);
  // Over 400 series the standard error of the lag-1 estimate is under 0.001; the tolerance
  // leaves room for its small-sample bias on 166-fix series (at most about 2 alpha / 166 = 0.012).
  EXPECT_NEAR(stats.lag1, alpha, 0.02);
  EXPECT_GT(stats.lag1, 0.95);
  // A sharper check free of that bias: the innovations w_k = (e_k - alpha e_(k-1)) / beta must be
  // white with the same sigma (standard error 0.03 m over 66000 values).
  const double beta = std::sqrt(1.0 - alpha * alpha);
  std::vector<std::vector<double>> innovations;
  for (const std::vector<double>& e : series) {
    std::vector<double> w;
    for (size_t k = 1; k < e.size(); ++k) w.push_back((e[k] - alpha * e[k - 1]) / beta);
    innovations.push_back(w);
  }
  const SeriesStats white = Stats(innovations);
  EXPECT_NEAR(white.sigma, 10.0, 0.2);
  EXPECT_NEAR(white.lag1, 0.0, 0.02);
}

// Mean over detections of (u - u_nominal) / (1 + t^2), t = (cx - u_nominal) / fx: a camera yawed
// left by dyaw sees every bearing dyaw smaller, which moves u by fx (1 + t^2) dyaw to first order.
double MeanNormalisedPixelShift(const Scenario& s, int passages) {
  const Calibration nominal = s.options().calibration;
  double sum = 0.0;
  int n = 0;
  for (int i = 0; i < passages; ++i) {
    for (const Detection& d : s.MakePassage(i).detections) {
      const Pose2 pose = s.TruePoseAt(d.t_s);
      double u;
      if (!ProjectLandmark(pose.data(), s.landmarks()[d.landmark_id - 1].position_m.data(), nominal, &u)) continue;
      const double t = (nominal.cx_px - u) / nominal.fx_px;
      sum += (d.u_px - u) / (1.0 + t * t);
      ++n;
    }
  }
  EXPECT_GT(n, 1000);
  return sum / n;
}

TEST(Scenario, YawBiasShiftsPixelsByAboutFxTimesTheBias) {
  const Scenario biased = Make(25, NoiseConfig::kYawBias);
  // fx 1000 px x 0.009 rad = 9 px; pixel noise 5 px over thousands of detections averages to
  // 0.1 px, second-order terms are below 0.1 px.
  const double expected = biased.options().calibration.fx_px * biased.options().camera_yaw_bias_rad;
  EXPECT_NEAR(MeanNormalisedPixelShift(biased, 20), expected, 0.5);
  EXPECT_NEAR(MeanNormalisedPixelShift(Make(25, NoiseConfig::kWhite), 20), 0.0, 0.5) << "no bias without the config";
}

TEST(Scenario, YawBiasShiftsEveryLandmarkTheSameWay) {
  const Scenario s = Make(25, NoiseConfig::kYawBias);
  const Calibration nominal = s.options().calibration;
  std::vector<double> sum(26, 0.0);
  std::vector<int> count(26, 0);
  for (int i = 0; i < 20; ++i) {
    for (const Detection& d : s.MakePassage(i).detections) {
      double u;
      if (!ProjectLandmark(s.TruePoseAt(d.t_s).data(), s.landmarks()[d.landmark_id - 1].position_m.data(), nominal, &u)) {
        continue;
      }
      const double t = (nominal.cx_px - u) / nominal.fx_px;
      sum[d.landmark_id] += (d.u_px - u) / (1.0 + t * t);
      ++count[d.landmark_id];
    }
  }
  for (int id = 1; id <= 25; ++id) {
    ASSERT_GE(count[id], 100) << id;
    // At least 100 detections of 5 px noise: standard error at most 0.5 px.
    EXPECT_NEAR(sum[id] / count[id], 9.0, 2.0) << "landmark " << id;
  }
}

TEST(ScenarioOptions, RejectsInvalidSettings) {
  ScenarioOptions o;
  EXPECT_TRUE(o.Validate().ok());
  o.landmarks = 0;
  EXPECT_EQ(Scenario::Create(o).status().code(), absl::StatusCode::kInvalidArgument);
  o = ScenarioOptions();
  o.gnss_ar1_alpha = 1.0;
  EXPECT_EQ(o.Validate().code(), absl::StatusCode::kInvalidArgument);
  o = ScenarioOptions();
  o.gnss_sigma_m = 0.0;
  EXPECT_EQ(o.Validate().code(), absl::StatusCode::kInvalidArgument);
}

TEST(NoiseConfig, NamesRoundTrip) {
  for (NoiseConfig c : {NoiseConfig::kWhite, NoiseConfig::kGnssAr1, NoiseConfig::kYawBias, NoiseConfig::kGnssAr1YawBias}) {
    const absl::StatusOr<NoiseConfig> parsed = ParseNoiseConfig(NoiseConfigName(c));
    ASSERT_TRUE(parsed.ok()) << NoiseConfigName(c);
    EXPECT_EQ(*parsed, c);
  }
  EXPECT_EQ(ParseNoiseConfig("pink").status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

TEST(Scenario, PartialDrivesKeepOnePieceOfTheRouteOfTheDrawnLength) {
  ScenarioOptions options;
  options.piece_min_m = 300.0;
  options.piece_max_m = 1500.0;
  const Scenario pieces = *Scenario::Create(options);
  const Scenario whole = *Scenario::Create(ScenarioOptions());
  for (int i = 0; i < 20; ++i) {
    const Passage p = pieces.MakePassage(i);
    ASSERT_TRUE(ValidatePassage(p).ok()) << ValidatePassage(p);
    const auto [first, last] = pieces.PieceOf(i);
    ASSERT_FALSE(p.odometry.empty());
    EXPECT_GE(p.odometry.front().t_s, first);
    EXPECT_LE(p.odometry.back().t_s, last);
    EXPECT_GE(p.gnss.front().t_s, first);
    EXPECT_LE(p.gnss.back().t_s, last);
    double driven = 0.0;
    for (size_t k = 1; k < p.odometry.size(); ++k) {
      driven += p.odometry[k - 1].speed_mps * (p.odometry[k].t_s - p.odometry[k - 1].t_s);
    }
    EXPECT_GT(driven, 300.0 * 0.8) << i;  // measured speeds: within their noise of the truth
    EXPECT_LT(driven, 1500.0 * 1.2) << i;
    // The same values as the whole passage, within the piece.
    const Passage full = whole.MakePassage(i);
    const auto it = std::find_if(full.odometry.begin(), full.odometry.end(),
                                 [&](const OdometrySample& o) { return o.t_s == p.odometry.front().t_s; });
    ASSERT_NE(it, full.odometry.end());
    EXPECT_EQ(it->speed_mps, p.odometry.front().speed_mps);
    EXPECT_NE(p.passage_id, full.passage_id);
  }
  EXPECT_NE(pieces.PieceOf(1), pieces.PieceOf(2));
  EXPECT_EQ(pieces.PieceOf(3), Scenario::Create(options)->PieceOf(3)) << "deterministic";
  ScenarioOptions bad;
  bad.piece_min_m = 500.0;
  bad.piece_max_m = 100.0;
  EXPECT_NE(bad.Validate().message().find("piece_min_m"), std::string::npos);
}

}  // namespace
}  // namespace crowdmap
