#include "core/model/motion_model.h"

#include <cmath>
#include <random>
#include <tuple>
#include <utility>
#include <vector>

#include <Eigen/Cholesky>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

constexpr double kWheelbase = 2.7;

// Sigmas small enough that neither the bias correction nor the covariance touches the mean.
NoiseModel NoNoise() {
  NoiseModel none;
  none.speed_sigma_mps = 1e-12;
  none.steering_sigma_rad = 1e-12;
  return none;
}

// 25 Hz samples with varying speed and steering, starting at t = 0.
std::vector<OdometrySample> CurvyOdometry(int samples) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < samples; ++j) odometry.push_back({j * 0.04, 12.0 + 0.01 * j, 0.05 * std::sin(0.1 * j)});
  return odometry;
}

// A step follows the arc of constant turn: on a circle of radius R / sin(xi) about its centre.
TEST(BicycleStep, FollowsTheArcOfConstantTurn) {
  const Pose2 pose(1.0, -2.0, 0.7);
  for (const double dt : {0.04, 1.0, 5.0}) {
    const double v = 11.0, xi = 0.3;
    const double radius = kWheelbase / std::sin(xi);
    const Eigen::Vector2d centre = pose.head<2>() + radius * Eigen::Vector2d(-std::sin(0.7), std::cos(0.7));
    const double heading = 0.7 + v * dt / radius;
    const Eigen::Vector2d expected = centre + radius * Eigen::Vector2d(std::sin(heading), -std::cos(heading));
    const Pose2 step = BicycleStep(pose, v, xi, dt, kWheelbase);
    EXPECT_LT((step.head<2>() - expected).norm(), 1e-12) << dt << " s";
    EXPECT_NEAR(step.z(), heading, 1e-15) << dt << " s";
  }
  // Within v dt d^2 / 24 of the thesis's eq. 4.43 (v dt along the mean heading).
  const double v = 11.0, xi = 0.05, dt = 0.04;
  const double turn = v * std::sin(xi) * dt / kWheelbase;
  const Pose2 thesis(1.0 + v * dt * std::cos(0.7 + turn / 2), -2.0 + v * dt * std::sin(0.7 + turn / 2), 0.7 + turn);
  const double leading = v * dt * turn * turn / 24;  // the series term; the next is 1e-5 of it here
  EXPECT_NEAR((BicycleStep(pose, v, xi, dt, kWheelbase) - thesis).norm(), leading, 1e-4 * leading);
}

// A step split at any time ends where the whole step does: a pose node inside a long sample
// interval does not change the motion.
TEST(BicycleStep, AStepSplitInPartsEndsWhereTheWholeStepDoes) {
  const Pose2 pose(3.0, 4.0, -1.2);
  const double v = 10.0, xi = -0.2, dt = 5.0;  // a 5 s encoder gap in a curve of 13.7 m radius
  const Pose2 whole = BicycleStep(pose, v, xi, dt, kWheelbase);
  Pose2 parts = pose;
  for (const double part : {0.7, 1.9, 0.01, 2.39}) parts = BicycleStep(parts, v, xi, part, kWheelbase);
  EXPECT_LT((parts - whole).norm(), 1e-12);
}

TEST(BicycleStep, JacobiansMatchCentralFiniteDifferences) {
  struct Case {
    Pose2 pose;
    double v, xi, dt;
  };
  const Case cases[] = {{Pose2(1.0, -2.0, 0.7), 11.0, 0.05, 0.04},
                        {Pose2(-30.0, 12.0, -3.1), 14.0, -0.3, 0.04},
                        {Pose2(0.0, 0.0, M_PI / 2), 3.0, 0.6, 0.1},
                        {Pose2(5.0, 5.0, 2.0), 0.0, 0.1, 0.04},
                        {Pose2(1.0, 2.0, 0.3), 10.0, 0.2, 5.0},     // a long step: the chord well short of v dt
                        {Pose2(1.0, 2.0, 0.3), 10.0, 1e-7, 0.04}};  // the series of sin(h) / h
  const double h = 1e-6;
  for (const Case& c : cases) {
    Eigen::Matrix3d d_pose;
    Eigen::Matrix<double, 3, 2> d_input;
    BicycleStep(c.pose, c.v, c.xi, c.dt, kWheelbase, &d_pose, &d_input);
    for (int k = 0; k < 3; ++k) {
      Pose2 plus = c.pose, minus = c.pose;
      plus[k] += h;
      minus[k] -= h;
      const Eigen::Vector3d numeric =
          (BicycleStep(plus, c.v, c.xi, c.dt, kWheelbase) - BicycleStep(minus, c.v, c.xi, c.dt, kWheelbase)) / (2 * h);
      EXPECT_LT((d_pose.col(k) - numeric).cwiseAbs().maxCoeff(), 1e-7) << "pose column " << k << " v " << c.v;
    }
    const Eigen::Vector3d dv =
        (BicycleStep(c.pose, c.v + h, c.xi, c.dt, kWheelbase) - BicycleStep(c.pose, c.v - h, c.xi, c.dt, kWheelbase)) / (2 * h);
    const Eigen::Vector3d dxi =
        (BicycleStep(c.pose, c.v, c.xi + h, c.dt, kWheelbase) - BicycleStep(c.pose, c.v, c.xi - h, c.dt, kWheelbase)) / (2 * h);
    EXPECT_LT((d_input.col(0) - dv).cwiseAbs().maxCoeff(), 1e-7) << "speed, v " << c.v;
    EXPECT_LT((d_input.col(1) - dxi).cwiseAbs().maxCoeff(), 1e-7) << "steering, v " << c.v;
    // With the turn scaled, as Preintegrate's noise corrections do.
    const double scale = 1.3;
    BicycleStep(c.pose, c.v, c.xi, c.dt, kWheelbase, &d_pose, &d_input, scale);
    const auto step = [&](double v, double xi) { return BicycleStep(c.pose, v, xi, c.dt, kWheelbase, nullptr, nullptr, scale); };
    EXPECT_LT((d_input.col(0) - (step(c.v + h, c.xi) - step(c.v - h, c.xi)) / (2 * h)).cwiseAbs().maxCoeff(), 1e-7)
        << "speed, turn scaled, v " << c.v;
    EXPECT_LT((d_input.col(1) - (step(c.v, c.xi + h) - step(c.v, c.xi - h)) / (2 * h)).cwiseAbs().maxCoeff(), 1e-7)
        << "steering, turn scaled, v " << c.v;
  }
}

TEST(Preintegrate, StraightConstantSpeedMotionIsSpeedTimesDuration) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 50; ++j) odometry.push_back({j * 0.04, 10.0, 0.0});
  const RelativeMotion m = Preintegrate(odometry, 0.1, 1.1, kWheelbase, NoNoise());
  EXPECT_NEAR(m.delta.x(), 10.0, 1e-9);
  EXPECT_EQ(m.delta.y(), 0.0);
  EXPECT_EQ(m.delta.z(), 0.0);
  EXPECT_DOUBLE_EQ(m.duration_s, 1.0);
}

TEST(Preintegrate, StraightMotionWithTheThesisNoiseStaysOnTheLineAndNearSpeedTimesDuration) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 50; ++j) odometry.push_back({j * 0.04, 10.0, 0.0});
  const RelativeMotion m = Preintegrate(odometry, 0.1, 1.1, kWheelbase, NoiseModel());
  EXPECT_EQ(m.delta.y(), 0.0);
  EXPECT_EQ(m.delta.z(), 0.0);
  // Any mean correction must stay far below the along-track sigma (about 0.11 m here).
  EXPECT_NEAR(m.delta.x(), 10.0, 0.01);
  EXPECT_GT(std::sqrt(m.cov(0, 0)), 0.05);
}

// Over a long gap between nodes (a GNSS outage without detections) the heading variance grows
// large; the lengthening that makes a short step unbiased, exp(var / 2), must not follow it: ten
// minutes straight at 10 m/s on 2 Hz encoders gathered var of about 8 rad^2, a motion stretched
// 50-fold at its end.
TEST(Preintegrate, ALongGapBetweenNodesIsLengthenedByAboutHalfAPercentAtMost) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j <= 1200; ++j) odometry.push_back({j * 0.5, 10.0, 0.0});
  const RelativeMotion m = Preintegrate(odometry, 0.0, 600.0, kWheelbase, NoiseModel());
  EXPECT_GT(m.cov(2, 2), 1.0) << "the heading is lost over the gap";
  EXPECT_GE(m.delta.x(), 6000.0);
  EXPECT_LE(m.delta.x(), 6000.0 * std::exp(0.5 * 0.01) + 1e-6);  // the cap: var 0.01 rad^2
}

TEST(Preintegrate, EqualsTheCompositionOfItsPartsSplitAtASampleTime) {
  const std::vector<OdometrySample> odometry = CurvyOdometry(100);
  const NoiseModel none = NoNoise();
  for (const auto& [t0, tm, t1] : {std::tuple{0.0, 1.0, 2.0}, std::tuple{0.25, 1.0, 2.5}, std::tuple{0.3, 2.96, 3.5}}) {
    const Pose2 whole = Preintegrate(odometry, t0, t1, kWheelbase, none).delta;
    const Pose2 split = ComposeMotion(Preintegrate(odometry, t0, tm, kWheelbase, none).delta,
                                      Preintegrate(odometry, tm, t1, kWheelbase, none).delta);
    EXPECT_LT((whole - split).cwiseAbs().maxCoeff(), 1e-12) << t0 << " " << tm << " " << t1;
  }
}

// Reference: each sample held from its own time to the next sample's, integrated step by step.
Pose2 HeldInputIntegral(const std::vector<OdometrySample>& odometry, double t0, double t1) {
  Pose2 pose = Pose2::Zero();
  for (size_t i = 0; i < odometry.size(); ++i) {
    const double begin = i == 0 ? -1e9 : odometry[i].t_s;
    const double end = i + 1 < odometry.size() ? odometry[i + 1].t_s : 1e9;
    const double from = std::max(begin, t0), to = std::min(end, t1);
    if (to > from) pose = BicycleStep(pose, odometry[i].speed_mps, odometry[i].steering_rad, to - from, kWheelbase);
  }
  pose.z() = WrapAngle(pose.z());
  return pose;
}

TEST(Preintegrate, HoldsEachSampleUntilTheNextOnAPartialInterval) {
  const std::vector<OdometrySample> odometry = CurvyOdometry(100);
  const NoiseModel none = NoNoise();
  // Start and end inside sample intervals; also before the first and after the last sample.
  for (const auto& [t0, t1] : {std::pair{0.013, 1.987}, std::pair{1.01, 1.03}, std::pair{-0.5, 0.3}, std::pair{3.9, 4.5}}) {
    const RelativeMotion m = Preintegrate(odometry, t0, t1, kWheelbase, none);
    EXPECT_LT((m.delta - HeldInputIntegral(odometry, t0, t1)).cwiseAbs().maxCoeff(), 1e-12) << t0 << " " << t1;
    EXPECT_DOUBLE_EQ(m.duration_s, t1 - t0);
  }
  // Splitting inside a sample turns each part at its own mid-heading: a second-order difference,
  // sub-micron over a few metres of curve, far below any sensor noise.
  const Pose2 whole = Preintegrate(odometry, 0.25, 2.5, kWheelbase, none).delta;
  const Pose2 split = ComposeMotion(Preintegrate(odometry, 0.25, 1.013, kWheelbase, none).delta,
                                    Preintegrate(odometry, 1.013, 2.5, kWheelbase, none).delta);
  EXPECT_LT((whole - split).norm(), 1e-6);
}

TEST(Preintegrate, FirstOrderCovarianceMatchesMonteCarlo) {
  // 0.5 s at 12 m/s, 25 Hz: 12 full sample intervals and a half one, each with its own noise.
  std::vector<OdometrySample> odometry;
  for (int j = 0; j <= 20; ++j) odometry.push_back({j * 0.04, 12.0, 0.02});
  const NoiseModel noise;
  const double t1 = 0.5;
  const RelativeMotion m = Preintegrate(odometry, 0.0, t1, kWheelbase, noise);

  std::mt19937_64 rng(42);
  std::normal_distribution<double> normal(0.0, 1.0);
  const int draws = 20000;
  std::vector<Pose2> samples;
  samples.reserve(draws);
  Pose2 mean = Pose2::Zero();
  for (int k = 0; k < draws; ++k) {
    Pose2 pose = Pose2::Zero();
    for (int j = 0; j * 0.04 < t1 - 1e-12; ++j) {
      const double dt = std::min(0.04, t1 - j * 0.04);
      pose = BicycleStep(pose, 12.0 + noise.speed_sigma_mps * normal(rng), 0.02 + noise.steering_sigma_rad * normal(rng),
                         dt, kWheelbase);
    }
    samples.push_back(pose);
    mean += pose / draws;
  }
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const Pose2& s : samples) cov += (s - mean) * (s - mean).transpose() / (draws - 1);

  // The standard error of a variance from 20000 draws is 1%: 5% is five of them.
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(m.cov(k, k), cov(k, k), 0.05 * cov(k, k)) << "diagonal " << k;
  // Lateral position and heading are strongly correlated; the correlation must match too.
  const double rho_model = m.cov(1, 2) / std::sqrt(m.cov(1, 1) * m.cov(2, 2));
  const double rho_mc = cov(1, 2) / std::sqrt(cov(1, 1) * cov(2, 2));
  EXPECT_NEAR(rho_model, rho_mc, 0.02);
  EXPECT_GT(rho_mc, 0.5);
}

TEST(Preintegrate, CovarianceGrowsWithDurationAndIsPositiveDefinite) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 100; ++j) odometry.push_back({j * 0.04, 12.0, 0.02});
  const NoiseModel noise;
  const RelativeMotion short_motion = Preintegrate(odometry, 0.0, 0.5, kWheelbase, noise);
  const RelativeMotion long_motion = Preintegrate(odometry, 0.0, 2.0, kWheelbase, noise);
  EXPECT_GT(long_motion.cov(2, 2), 3.0 * short_motion.cov(2, 2));
  EXPECT_EQ(long_motion.cov.llt().info(), Eigen::Success);
  // Heading variance of n independent steps: n (v cos(xi) dt sigma_xi / R)^2 (+ the tiny speed term).
  const double per_step = 12.0 * std::cos(0.02) * 0.04 * noise.steering_sigma_rad / kWheelbase;
  EXPECT_NEAR(short_motion.cov(2, 2), 12.5 * per_step * per_step, 0.05 * short_motion.cov(2, 2));
}

// A node inside a sample's interval splits that sample's error between two motions, which then
// share one draw. Each takes its share of the interval's variance (dt / interval of it): the parts
// add up to the whole interval's variance, and each claims no more than it knows (for parts a and
// b the independent diag(a, b) * interval exceeds the shared draw's [[a^2, ab], [ab, b^2]] by
// ab [[1, -1], [-1, 1]], which is positive semi-definite).
TEST(Preintegrate, PartsOfASampleIntervalShareItsVariance) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 10; ++j) odometry.push_back({j * 0.04, 12.0, 0.0});  // straight: heading from steering only
  const NoiseModel noise;
  const RelativeMotion whole = Preintegrate(odometry, 0.08, 0.12, kWheelbase, noise);
  const RelativeMotion first = Preintegrate(odometry, 0.08, 0.09, kWheelbase, noise);
  const RelativeMotion second = Preintegrate(odometry, 0.09, 0.12, kWheelbase, noise);
  EXPECT_NEAR(first.cov(2, 2) + second.cov(2, 2), whole.cov(2, 2), 1e-12 * whole.cov(2, 2));
  // A quarter of the interval: a quarter of its variance, not a sixteenth.
  const double floor = kMotionCovarianceFloor * 0.01;
  EXPECT_NEAR(first.cov(2, 2) - floor, 0.25 * (whole.cov(2, 2) - kMotionCovarianceFloor * 0.04),
              1e-9 * whole.cov(2, 2));
}

TEST(Preintegrate, StandingStillKeepsAnInvertibleCovariance) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 30; ++j) odometry.push_back({j * 0.04, 0.0, 0.0});
  const RelativeMotion m = Preintegrate(odometry, 0.0, 1.0, kWheelbase, NoiseModel());
  EXPECT_EQ(m.delta, Pose2::Zero());
  EXPECT_EQ(m.cov.llt().info(), Eigen::Success);
  EXPECT_GT(m.cov.diagonal().minCoeff(), 0.0);
}

TEST(ComposeMotion, RotatesTheDeltaIntoTheStartFrame) {
  const Pose2 composed = ComposeMotion(Pose2(1.0, 2.0, M_PI / 2), Pose2(3.0, 1.0, 0.5));
  EXPECT_NEAR(composed.x(), 1.0 - 1.0, 1e-12);
  EXPECT_NEAR(composed.y(), 2.0 + 3.0, 1e-12);
  EXPECT_NEAR(composed.z(), M_PI / 2 + 0.5, 1e-12);
  EXPECT_NEAR(ComposeMotion(Pose2(0.0, 0.0, 3.0), Pose2(0.0, 0.0, 0.5)).z(), 3.5 - 2 * M_PI, 1e-12) << "wrapped";
}

TEST(WrapAngle, MapsIntoTheHalfOpenIntervalMinusPiToPi) {
  EXPECT_EQ(WrapAngle(0.0), 0.0);
  EXPECT_NEAR(WrapAngle(-0.3), -0.3, 1e-15);
  EXPECT_NEAR(WrapAngle(M_PI), M_PI, 1e-15);
  EXPECT_NEAR(WrapAngle(-M_PI), M_PI, 1e-15) << "-pi is excluded";
  EXPECT_NEAR(WrapAngle(3 * M_PI), M_PI, 1e-12);
  EXPECT_NEAR(WrapAngle(-3 * M_PI), M_PI, 1e-12);
  EXPECT_NEAR(WrapAngle(2 * M_PI + 0.1), 0.1, 1e-12);
  EXPECT_NEAR(WrapAngle(-2 * M_PI - 0.1), -0.1, 1e-12);
  EXPECT_NEAR(WrapAngle(M_PI + 1e-9), -M_PI + 1e-9, 1e-12);
  EXPECT_NEAR(WrapAngle(-M_PI + 1e-9), -M_PI + 1e-9, 1e-12);
  for (double a = -50.0; a <= 50.0; a += 0.37) {
    const double w = WrapAngle(a);
    EXPECT_GT(w, -M_PI) << a;
    EXPECT_LE(w, M_PI) << a;
    EXPECT_NEAR(std::cos(w), std::cos(a), 1e-12) << a;
    EXPECT_NEAR(std::sin(w), std::sin(a), 1e-12) << a;
  }
}

}  // namespace
}  // namespace crowdmap
