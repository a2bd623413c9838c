#include "core/model/motion_model.h"

#include <Eigen/LU>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(BicycleStep, JacobiansMatchFiniteDifferences) {
  const Pose2 pose(1.0, -2.0, 0.7);
  const double v = 11.0, xi = 0.05, dt = 0.04, wheelbase = 2.7, h = 1e-6;
  Eigen::Matrix3d d_pose;
  Eigen::Matrix<double, 3, 2> d_input;
  BicycleStep(pose, v, xi, dt, wheelbase, &d_pose, &d_input);
  for (int k = 0; k < 3; ++k) {
    Pose2 plus = pose, minus = pose;
    plus[k] += h;
    minus[k] -= h;
    const Eigen::Vector3d numeric = (BicycleStep(plus, v, xi, dt, wheelbase) - BicycleStep(minus, v, xi, dt, wheelbase)) / (2 * h);
    EXPECT_TRUE(d_pose.col(k).isApprox(numeric, 1e-7)) << k;
  }
  const Eigen::Vector3d dv = (BicycleStep(pose, v + h, xi, dt, wheelbase) - BicycleStep(pose, v - h, xi, dt, wheelbase)) / (2 * h);
  const Eigen::Vector3d dxi = (BicycleStep(pose, v, xi + h, dt, wheelbase) - BicycleStep(pose, v, xi - h, dt, wheelbase)) / (2 * h);
  EXPECT_LT((d_input.col(0) - dv).norm(), 1e-7);
  EXPECT_LT((d_input.col(1) - dxi).norm(), 1e-7);
}

TEST(Preintegrate, StraightConstantSpeedMotionWithoutNoiseIsExact) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 50; ++j) odometry.push_back({j * 0.04, 10.0, 0.0});
  NoiseModel none;
  none.speed_sigma_mps = 1e-12;
  none.steering_sigma_rad = 1e-12;
  const RelativeMotion m = Preintegrate(odometry, 0.1, 1.1, 2.7, none);
  EXPECT_NEAR(m.delta.x(), 10.0, 1e-9);
  EXPECT_NEAR(m.delta.y(), 0.0, 1e-12);
  EXPECT_NEAR(m.delta.z(), 0.0, 1e-12);
  EXPECT_DOUBLE_EQ(m.duration_s, 1.0);
}

TEST(Preintegrate, ComposesAcrossASplitTimeWithoutNoise) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 100; ++j) odometry.push_back({j * 0.04, 12.0 + 0.01 * j, 0.05 * std::sin(0.1 * j)});
  NoiseModel none;
  none.speed_sigma_mps = 1e-12;
  none.steering_sigma_rad = 1e-12;
  const Pose2 whole = Preintegrate(odometry, 0.25, 2.5, 2.7, none).delta;
  auto split_at = [&](double t) {
    return ComposeMotion(Preintegrate(odometry, 0.25, t, 2.7, none).delta, Preintegrate(odometry, t, 2.5, 2.7, none).delta);
  };
  // On a sample time the composition is exact.
  EXPECT_LT((whole - split_at(1.0)).norm(), 1e-9);
  // Inside a sample two partial steps differ from one full step at second order (each step
  // turns at its own mid-heading): sub-micron here, far below any sensor noise.
  EXPECT_LT((whole - split_at(1.013)).norm(), 1e-6);
}

TEST(Preintegrate, CovarianceGrowsWithDurationAndIsPositiveDefinite) {
  std::vector<OdometrySample> odometry;
  for (int j = 0; j < 100; ++j) odometry.push_back({j * 0.04, 12.0, 0.02});
  const NoiseModel noise;
  const RelativeMotion short_motion = Preintegrate(odometry, 0.0, 0.5, 2.7, noise);
  const RelativeMotion long_motion = Preintegrate(odometry, 0.0, 2.0, 2.7, noise);
  EXPECT_GT(long_motion.cov(2, 2), 3.0 * short_motion.cov(2, 2));
  EXPECT_GT(long_motion.cov.determinant(), 0.0);
  // Heading variance of n independent steps: n (v cos(xi) dt sigma_xi / R)^2.
  const double per_step = 12.0 * std::cos(0.02) * 0.04 * noise.steering_sigma_rad / 2.7;
  EXPECT_NEAR(short_motion.cov(2, 2), 12.5 * per_step * per_step, 0.05 * short_motion.cov(2, 2));
}

TEST(WrapAngle, MapsIntoMinusPiPi) {
  EXPECT_NEAR(WrapAngle(3 * M_PI), M_PI, 1e-12);
  EXPECT_NEAR(WrapAngle(-M_PI), M_PI, 1e-12);
  EXPECT_NEAR(WrapAngle(2 * M_PI + 0.1), 0.1, 1e-12);
  EXPECT_NEAR(WrapAngle(-0.3), -0.3, 1e-15);
}

}  // namespace
}  // namespace crowdmap
