#include "core/estimation/factors.h"

#include <memory>
#include <random>
#include <vector>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Evaluates the cost function's Jacobians and compares them with central differences of its
// residuals, block by block.
void ExpectJacobiansMatchFiniteDifferences(const ceres::CostFunction& cost, std::vector<std::vector<double>> params,
                                           double tolerance) {
  const int m = cost.num_residuals();
  const std::vector<int32_t>& sizes = cost.parameter_block_sizes();
  ASSERT_EQ(sizes.size(), params.size());
  std::vector<const double*> ptrs;
  for (auto& p : params) ptrs.push_back(p.data());
  std::vector<RowMajor> analytic;
  std::vector<double*> jac_ptrs;
  for (int32_t s : sizes) analytic.emplace_back(m, s);
  for (auto& j : analytic) jac_ptrs.push_back(j.data());
  Eigen::VectorXd residual(m);
  ASSERT_TRUE(cost.Evaluate(ptrs.data(), residual.data(), jac_ptrs.data()));

  const double h = 1e-6;
  for (size_t b = 0; b < sizes.size(); ++b) {
    for (int k = 0; k < sizes[b]; ++k) {
      const double saved = params[b][k];
      Eigen::VectorXd plus(m), minus(m);
      params[b][k] = saved + h;
      ASSERT_TRUE(cost.Evaluate(ptrs.data(), plus.data(), nullptr));
      params[b][k] = saved - h;
      ASSERT_TRUE(cost.Evaluate(ptrs.data(), minus.data(), nullptr));
      params[b][k] = saved;
      const Eigen::VectorXd numeric = (plus - minus) / (2 * h);
      for (int r = 0; r < m; ++r) {
        EXPECT_NEAR(analytic[b](r, k), numeric(r), tolerance * std::max(1.0, std::abs(numeric(r))))
            << "block " << b << " parameter " << k << " residual " << r;
      }
    }
  }
}

Eigen::Matrix3d RandomCovariance3(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Matrix3d a;
  for (int i = 0; i < 9; ++i) a.data()[i] = 0.1 * n(rng);
  return a * a.transpose() + 0.01 * Eigen::Matrix3d::Identity();
}

TEST(SqrtInformation, WhitensTheCovariance) {
  std::mt19937 rng(3);
  const Eigen::Matrix3d cov = RandomCovariance3(rng);
  const Eigen::MatrixXd s = SqrtInformation(cov);
  EXPECT_TRUE((s.transpose() * s).isApprox(cov.inverse(), 1e-10));
}

// A random preintegrated motion of about 6 m with a small turn.
RelativeMotion RandomMotion(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  RelativeMotion motion;
  motion.delta = Pose2(6.0 + u(rng), 0.3 * u(rng), 0.1 * u(rng));
  motion.cov = RandomCovariance3(rng);
  return motion;
}

TEST(OdometryFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  for (int trial = 0; trial < 20; ++trial) {
    std::unique_ptr<ceres::CostFunction> cost(OdometryFactor::Create(RandomMotion(rng)));
    ExpectJacobiansMatchFiniteDifferences(
        *cost, {{u(rng), u(rng), u(rng)}, {u(rng) + 6.0, u(rng), u(rng)}}, 1e-5);
  }
}

TEST(OdometryFactor, ResidualIsZeroForThePredictedPoseAndWrapsTheAngle) {
  RelativeMotion motion;
  motion.delta = Pose2(5.0, 0.5, 0.2);
  motion.cov = Eigen::Matrix3d::Identity();
  std::unique_ptr<ceres::CostFunction> cost(OdometryFactor::Create(motion));
  const Pose2 a(10.0, -4.0, 3.0);  // near +pi, so b's heading wraps past it
  Pose2 b = ComposeMotion(a, motion.delta);
  const double* params[] = {a.data(), b.data()};
  Eigen::Vector3d r;
  ASSERT_TRUE(cost->Evaluate(params, r.data(), nullptr));
  EXPECT_LT(r.norm(), 1e-12);
  b.z() += 2 * M_PI;
  ASSERT_TRUE(cost->Evaluate(params, r.data(), nullptr));
  EXPECT_LT(r.norm(), 1e-9);
}

TEST(ScaledOdometryFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  for (int trial = 0; trial < 20; ++trial) {
    std::unique_ptr<ceres::CostFunction> cost(ScaledOdometryFactor::Create(RandomMotion(rng)));
    ExpectJacobiansMatchFiniteDifferences(
        *cost, {{u(rng), u(rng), u(rng)}, {u(rng) + 6.0, u(rng), u(rng)}, {1.0 + 0.02 * u(rng)}}, 1e-5);
  }
}

TEST(ScaledOdometryFactor, IsTheOdometryFactorAtScaleOneAndScalesTheDisplacement) {
  RelativeMotion motion;
  motion.delta = Pose2(7.9, 0.8, 0.4);
  motion.cov = Eigen::Matrix3d::Identity() * 1e-4;
  std::unique_ptr<ceres::CostFunction> plain(OdometryFactor::Create(motion));
  std::unique_ptr<ceres::CostFunction> scaled(ScaledOdometryFactor::Create(motion));
  const Pose2 a(3.0, -2.0, 0.7);
  Pose2 b = ComposeMotion(a, Pose2(7.5, 1.2, 0.35));
  double one = 1.0;
  const double* plain_params[] = {a.data(), b.data()};
  const double* scaled_params[] = {a.data(), b.data(), &one};
  Eigen::Vector3d r_plain, r_scaled;
  ASSERT_TRUE(plain->Evaluate(plain_params, r_plain.data(), nullptr));
  ASSERT_TRUE(scaled->Evaluate(scaled_params, r_scaled.data(), nullptr));
  EXPECT_LT((r_plain - r_scaled).norm(), 1e-12);
  // 3% further, the same turn.
  double k = 1.03;
  b = ComposeMotion(a, Pose2(k * 7.9, k * 0.8, 0.4));
  const double* params[] = {a.data(), b.data(), &k};
  Eigen::Vector3d r;
  ASSERT_TRUE(scaled->Evaluate(params, r.data(), nullptr));
  EXPECT_LT(r.norm(), 1e-10);
}

TEST(GnssFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  for (int trial = 0; trial < 20; ++trial) {
    Eigen::Matrix2d cov;
    cov << 90.0, 12.0, 12.0, 110.0;
    std::unique_ptr<ceres::CostFunction> cost(
        GnssFactor::Create(Eigen::Vector2d(u(rng), u(rng)), cov, Eigen::Vector2d(0.5, 0.2)));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{u(rng), u(rng), u(rng)}}, 1e-6);
  }
}

TEST(GnssFactor, ResidualIsZeroAtTheAntenna) {
  const Pose2 pose(3.0, 4.0, M_PI / 2);
  // Lever arm (0.5, 0) forward; heading north puts the antenna 0.5 m north of the pose.
  std::unique_ptr<ceres::CostFunction> cost(
      GnssFactor::Create(Eigen::Vector2d(3.0, 4.5), Eigen::Matrix2d::Identity(), Eigen::Vector2d(0.5, 0.0)));
  const double* params[] = {pose.data()};
  Eigen::Vector2d r;
  ASSERT_TRUE(cost->Evaluate(params, r.data(), nullptr));
  EXPECT_LT(r.norm(), 1e-12);
}

TEST(GnssAr1Factor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-3.0, 3.0);
  Eigen::Matrix2d cov_a, cov_b;
  cov_a << 90.0, 12.0, 12.0, 110.0;
  cov_b << 60.0, -5.0, -5.0, 70.0;
  for (int trial = 0; trial < 20; ++trial) {
    std::unique_ptr<ceres::CostFunction> cost(GnssAr1Factor::Create(
        Eigen::Vector2d(u(rng), u(rng)), cov_a, Eigen::Vector2d(u(rng) + 10.0, u(rng)), cov_b,
        Eigen::Vector2d(0.5, 0.2), 0.3 + 0.1 * (u(rng) + 3.0), 82.8));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{u(rng), u(rng), u(rng)}, {u(rng) + 10.0, u(rng), u(rng)}}, 1e-6);
    std::unique_ptr<ceres::CostFunction> one_node(GnssAr1Factor::CreateAtOneNode(
        Eigen::Vector2d(u(rng), u(rng)), cov_a, Eigen::Vector2d(u(rng), u(rng)), cov_b, Eigen::Vector2d(0.5, 0.2),
        5e-4, 82.8));
    ExpectJacobiansMatchFiniteDifferences(*one_node, {{u(rng), u(rng), u(rng)}}, 1e-6);
  }
}

TEST(GnssAr1Factor, ResidualIsTheProcessInnovation) {
  // Errors e_a, e_b of two fixes 1 s apart with tau = 82.8 s: r = (e_b - alpha e_a) / (sigma beta).
  const double sigma = 10.0, alpha = std::exp(-1.0 / 82.8), beta = std::sqrt(1.0 - alpha * alpha);
  const Pose2 a(3.0, 4.0, M_PI / 2), b(3.0, 16.0, M_PI / 2);  // antennas at (3, 4.5) and (3, 16.5)
  const Eigen::Vector2d e_a(2.0, -1.0), e_b(1.5, 0.5);
  std::unique_ptr<ceres::CostFunction> cost(GnssAr1Factor::Create(
      Eigen::Vector2d(3.0, 4.5) - e_a, sigma * sigma * Eigen::Matrix2d::Identity(), Eigen::Vector2d(3.0, 16.5) - e_b,
      sigma * sigma * Eigen::Matrix2d::Identity(), Eigen::Vector2d(0.5, 0.0), 1.0, 82.8));
  const double* params[] = {a.data(), b.data()};
  Eigen::Vector2d r;
  ASSERT_TRUE(cost->Evaluate(params, r.data(), nullptr));
  EXPECT_LT((r - (e_b - alpha * e_a) / (sigma * beta)).norm(), 1e-12);
}

TEST(CameraFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Calibration calib;
  calib.camera_yaw_rad = 0.05;
  calib.camera_position_m = {1.5, 0.2};
  for (int trial = 0; trial < 20; ++trial) {
    const double heading = u(rng);
    const Pose2 pose(u(rng), u(rng), heading);
    // A landmark 10-40 m ahead, within the field of view.
    const double range = 25.0 + 15.0 * u(rng), bearing = heading + 0.5 * u(rng);
    const std::vector<double> landmark{pose.x() + range * std::cos(bearing), pose.y() + range * std::sin(bearing)};
    std::unique_ptr<ceres::CostFunction> cost(CameraFactor::Create(900.0 + 100 * u(rng), 5.0, calib));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{pose.x(), pose.y(), pose.z()}, landmark}, 1e-5);
  }
}

TEST(CameraFactor, RejectsALandmarkBehindTheCamera) {
  Calibration calib;
  std::unique_ptr<ceres::CostFunction> cost(CameraFactor::Create(960.0, 5.0, calib));
  const Pose2 pose(0.0, 0.0, 0.0);
  const Eigen::Vector2d behind(-10.0, 0.0);
  const double* params[] = {pose.data(), behind.data()};
  double r;
  EXPECT_FALSE(cost->Evaluate(params, &r, nullptr));
}

TEST(CameraFactor, ResidualIsZeroForTheProjectedPixel) {
  Calibration calib;
  const Pose2 pose(1.0, 2.0, 0.3);
  const Eigen::Vector2d landmark(20.0, 12.0);
  double u;
  ASSERT_TRUE(ProjectLandmark(pose.data(), landmark.data(), calib, &u));
  std::unique_ptr<ceres::CostFunction> cost(CameraFactor::Create(u, 5.0, calib));
  const double* params[] = {pose.data(), landmark.data()};
  double r;
  ASSERT_TRUE(cost->Evaluate(params, &r, nullptr));
  EXPECT_NEAR(r, 0.0, 1e-12);
}

TEST(CameraYawFactor, JacobianMatchesFiniteDifferencesInPoseLandmarkAndYawOffset) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Calibration calib;
  calib.camera_yaw_rad = 0.05;
  calib.camera_position_m = {1.5, 0.2};
  for (int trial = 0; trial < 20; ++trial) {
    const double heading = u(rng);
    const Pose2 pose(u(rng), u(rng), heading);
    const double range = 25.0 + 15.0 * u(rng), bearing = heading + 0.5 * u(rng);
    const std::vector<double> landmark{pose.x() + range * std::cos(bearing), pose.y() + range * std::sin(bearing)};
    std::unique_ptr<ceres::CostFunction> cost(CameraYawFactor::Create(900.0 + 100 * u(rng), 5.0, calib));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{pose.x(), pose.y(), pose.z()}, landmark, {0.02 * u(rng)}}, 1e-5);
  }
}

TEST(CameraYawFactor, AnOffsetActsAsTheSameTurnOfTheDeclaredCameraYaw) {
  Calibration calib;
  calib.camera_yaw_rad = 0.01;
  Calibration turned = calib;
  turned.camera_yaw_rad += 0.008;
  const Pose2 pose(1.0, 2.0, 0.3);
  const Eigen::Vector2d landmark(20.0, 12.0);
  double u_turned;
  ASSERT_TRUE(ProjectLandmark(pose.data(), landmark.data(), turned, &u_turned));
  std::unique_ptr<ceres::CostFunction> with_offset(CameraYawFactor::Create(u_turned, 5.0, calib));
  const double offset = 0.008;
  const double* params[] = {pose.data(), landmark.data(), &offset};
  double r;
  ASSERT_TRUE(with_offset->Evaluate(params, &r, nullptr));
  EXPECT_NEAR(r, 0.0, 1e-9);
  const double none = 0.0;
  const double* unturned[] = {pose.data(), landmark.data(), &none};
  ASSERT_TRUE(with_offset->Evaluate(unturned, &r, nullptr));
  EXPECT_GT(std::abs(r), 1.0);  // 0.008 rad is some 8 px, 1.6 sigma
}

TEST(ScalarPriorFactor, JacobianMatchesFiniteDifferencesAndResidualIsWhitened) {
  std::unique_ptr<ceres::CostFunction> cost(ScalarPriorFactor::Create(0.01, 0.02));
  ExpectJacobiansMatchFiniteDifferences(*cost, {{0.03}}, 1e-8);
  const double x = 0.05;
  const double* params[] = {&x};
  double r;
  ASSERT_TRUE(cost->Evaluate(params, &r, nullptr));
  EXPECT_NEAR(r, 2.0, 1e-12);
}

TEST(BearingFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(6);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Calibration calib;
  calib.camera_yaw_rad = -0.03;
  for (int trial = 0; trial < 20; ++trial) {
    const Pose2 pose(u(rng), u(rng), u(rng));
    // Anywhere around the vehicle, behind the camera included: the bearing form is defined there.
    const double range = 20.0 + 15.0 * u(rng), bearing = 3.0 * u(rng);
    const std::vector<double> landmark{pose.x() + range * std::cos(bearing), pose.y() + range * std::sin(bearing)};
    std::unique_ptr<ceres::CostFunction> cost(BearingFactor::Create(960.0 + 800 * u(rng), 5.0, calib));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{pose.x(), pose.y(), pose.z()}, landmark}, 1e-5);
  }
}

TEST(ShiftedBearingFactor, JacobianMatchesFiniteDifferences) {
  std::mt19937 rng(16);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Calibration calib;
  calib.camera_yaw_rad = 0.02;
  for (int trial = 0; trial < 20; ++trial) {
    const Pose2 pose(5.0 * u(rng), 5.0 * u(rng), u(rng));
    const Eigen::Vector2d landmark = pose.head<2>() + 25.0 * Eigen::Vector2d(std::cos(pose.z()), std::sin(pose.z())) +
                                     Eigen::Vector2d(3.0 * u(rng), 3.0 * u(rng));
    std::unique_ptr<ceres::CostFunction> cost(
        ShiftedBearingFactor::Create(pose, landmark, 0.5 + 0.5 * u(rng), 960.0 + 400 * u(rng), 5.0, calib));
    ExpectJacobiansMatchFiniteDifferences(*cost, {{2.0 * u(rng), 2.0 * u(rng)}, {2.0 * u(rng), 2.0 * u(rng)}}, 1e-5);
  }
}

TEST(ShiftedBearingFactor, IsTheBearingFactorAtTheInterpolatedShift) {
  Calibration calib;
  const Pose2 pose(1.0, 2.0, 0.3);
  const Eigen::Vector2d landmark(30.0, 14.0), a(1.5, -2.0), b(-0.5, 3.0);
  const double w = 0.25;
  std::unique_ptr<ceres::CostFunction> shifted(ShiftedBearingFactor::Create(pose, landmark, w, 900.0, 5.0, calib));
  std::unique_ptr<ceres::CostFunction> plain(BearingFactor::Create(900.0, 5.0, calib));
  Pose2 moved = pose;
  moved.head<2>() += (1.0 - w) * a + w * b;
  const double* shifted_params[] = {a.data(), b.data()};
  const double* plain_params[] = {moved.data(), landmark.data()};
  double r_shifted = 0.0, r_plain = 0.0;
  ASSERT_TRUE(shifted->Evaluate(shifted_params, &r_shifted, nullptr));
  ASSERT_TRUE(plain->Evaluate(plain_params, &r_plain, nullptr));
  EXPECT_NEAR(r_shifted, r_plain, 1e-12);
}

TEST(Ar1StepFactor, JacobianMatchesFiniteDifferencesAndWhitensTheStep) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> u(-5.0, 5.0);
  std::unique_ptr<ceres::CostFunction> cost(Ar1StepFactor::Create(0.8, 10.0));
  for (int trial = 0; trial < 10; ++trial) {
    ExpectJacobiansMatchFiniteDifferences(*cost, {{u(rng), u(rng)}, {u(rng), u(rng)}}, 1e-6);
  }
  const Eigen::Vector2d a(10.0, -5.0), b(14.0, -1.0);
  const double* params[] = {a.data(), b.data()};
  Eigen::Vector2d r;
  ASSERT_TRUE(cost->Evaluate(params, r.data(), nullptr));
  EXPECT_NEAR(r.x(), (14.0 - 8.0) / (10.0 * 0.6), 1e-12);
  EXPECT_NEAR(r.y(), (-1.0 + 4.0) / (10.0 * 0.6), 1e-12);
}

TEST(BearingFactor, AgreesWithThePixelResidualToFirstOrder) {
  // Near the measurement the whitened bearing residual has the magnitude of the whitened pixel
  // residual (opposite sign: u decreases as the bearing increases), so both give the same cost.
  Calibration calib;
  const Pose2 pose(0.0, 0.0, 0.2);
  const Eigen::Vector2d landmark(25.0, 9.0);
  double u;
  ASSERT_TRUE(ProjectLandmark(pose.data(), landmark.data(), calib, &u));
  const double measured = u + 2.0;  // 0.4 sigma off
  std::unique_ptr<ceres::CostFunction> bearing(BearingFactor::Create(measured, 5.0, calib));
  std::unique_ptr<ceres::CostFunction> pixel(CameraFactor::Create(measured, 5.0, calib));
  const double* params[] = {pose.data(), landmark.data()};
  double rb, rp;
  ASSERT_TRUE(bearing->Evaluate(params, &rb, nullptr));
  ASSERT_TRUE(pixel->Evaluate(params, &rp, nullptr));
  EXPECT_NEAR(std::abs(rb), std::abs(rp), 0.01 * std::abs(rp));
}

TEST(LandmarkPriorFactor, JacobianMatchesFiniteDifferencesForAJointPrior) {
  std::mt19937 rng(5);
  std::normal_distribution<double> n(0.0, 1.0);
  const int k = 4;
  Eigen::MatrixXd a(2 * k, 2 * k);
  for (int i = 0; i < a.size(); ++i) a.data()[i] = n(rng);
  const Eigen::MatrixXd cov = a * a.transpose() + Eigen::MatrixXd::Identity(2 * k, 2 * k);
  Eigen::VectorXd mean(2 * k);
  for (int i = 0; i < 2 * k; ++i) mean(i) = n(rng);
  LandmarkPriorFactor cost(mean, SqrtInformation(cov));
  std::vector<std::vector<double>> params;
  for (int i = 0; i < k; ++i) params.push_back({n(rng), n(rng)});
  ExpectJacobiansMatchFiniteDifferences(cost, params, 1e-7);
}

TEST(LandmarkPriorFactor, CostIsTheMahalanobisDistance) {
  Eigen::Matrix4d cov;
  cov << 2.0, 0.3, 0.5, 0.0,  //
      0.3, 1.0, 0.1, 0.2,     //
      0.5, 0.1, 3.0, 0.4,     //
      0.0, 0.2, 0.4, 1.5;
  const Eigen::Vector4d mean(1.0, 2.0, 3.0, 4.0);
  LandmarkPriorFactor cost(mean, SqrtInformation(cov));
  const Eigen::Vector2d a(1.5, 1.0), b(2.0, 4.5);
  const double* params[] = {a.data(), b.data()};
  Eigen::Vector4d r;
  ASSERT_TRUE(cost.Evaluate(params, r.data(), nullptr));
  Eigen::Vector4d e;
  e << a - mean.head<2>(), b - mean.tail<2>();
  EXPECT_NEAR(r.squaredNorm(), e.dot(cov.inverse() * e), 1e-12);
}

}  // namespace
}  // namespace crowdmap
