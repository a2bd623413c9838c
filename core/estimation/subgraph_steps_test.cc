#include "core/estimation/subgraph_steps.h"

#include <cmath>
#include <random>
#include <vector>

#include <ceres/ceres.h>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

Calibration CameraAtTheVehicleOrigin() {
  Calibration calib;
  calib.camera_position_m = Eigen::Vector2d::Zero();
  calib.camera_yaw_rad = 0.0;
  return calib;
}

TEST(NewLandmarkGeometry, TwoPerpendicularRaysFixThePositionToRangeTimesPixelAngle) {
  // A bearing detection constrains only the direction across its ray, to range * sigma / fx.
  // Seen straight ahead from 10 m along x and along y, both directions are fixed to that.
  const Calibration calib = CameraAtTheVehicleOrigin();
  const Eigen::Vector2d landmark(10.0, 0.0);
  const std::vector<Pose2> poses = {Pose2(0.0, 0.0, 0.0), Pose2(10.0, -10.0, M_PI / 2)};
  const CameraObservation ahead0{0, 7, calib.cx_px}, ahead1{1, 7, calib.cx_px};
  const double sigma_px = 2.0;
  const RayGeometry g = NewLandmarkGeometry(poses, 0, {&ahead0, &ahead1}, landmark, calib, sigma_px);
  EXPECT_NEAR(g.sigma_m, 10.0 * sigma_px / calib.fx_px, 1e-12);
  EXPECT_NEAR(g.max_range_m, 10.0, 1e-12);
}

TEST(NewLandmarkGeometry, RaysAlongOneLineLeaveTheDistanceUndetermined) {
  const Calibration calib = CameraAtTheVehicleOrigin();
  const std::vector<Pose2> poses = {Pose2(0.0, 0.0, 0.0), Pose2(5.0, 0.0, 0.0)};
  const CameraObservation a{0, 7, calib.cx_px}, b{1, 7, calib.cx_px};
  const RayGeometry g = NewLandmarkGeometry(poses, 0, {&a, &b}, Eigen::Vector2d(30.0, 0.0), calib, 2.0);
  EXPECT_GT(g.sigma_m, 1e6);
  MapUpdateOptions options;
  EXPECT_FALSE(WellDeterminedNewLandmark(g, options));
}

TEST(NewLandmarkGeometry, ALandmarkBehindACameraThatSawItIsUndetermined) {
  const Calibration calib = CameraAtTheVehicleOrigin();
  const std::vector<Pose2> poses = {Pose2(0.0, 0.0, 0.0), Pose2(5.0, 0.0, M_PI)};
  const CameraObservation a{0, 7, calib.cx_px + 100}, b{1, 7, calib.cx_px};
  const RayGeometry g = NewLandmarkGeometry(poses, 0, {&a, &b}, Eigen::Vector2d(8.0, 1.0), calib, 2.0);
  EXPECT_TRUE(std::isinf(g.sigma_m));
}

TEST(WellDeterminedNewLandmark, AppliesTheRangeAndTheSigmaBounds) {
  MapUpdateOptions options;
  options.max_new_landmark_range_m = 100.0;
  options.max_new_landmark_ray_sigma_m = 2.0;
  EXPECT_TRUE(WellDeterminedNewLandmark({1.0, 50.0}, options));
  EXPECT_FALSE(WellDeterminedNewLandmark({1.0, 150.0}, options));
  EXPECT_FALSE(WellDeterminedNewLandmark({2.5, 50.0}, options));
}

TEST(CheckDetectionsFit, RefusesAPassageMoreThanTheFractionOfWhoseDetectionsDoNotFit) {
  MapUpdateOptions options;
  options.max_unfit_detection_fraction = 0.25;
  EXPECT_TRUE(CheckDetectionsFit(25, 100, options).ok());  // the fraction itself is allowed
  const absl::Status refused = CheckDetectionsFit(26, 100, options);
  EXPECT_TRUE(absl::IsFailedPrecondition(refused)) << refused;
  EXPECT_NE(refused.message().find("26 of its 100 detections"), absl::string_view::npos) << refused;
  // A short passage's few: one landmark's detections under another's id are not the camera's fault.
  EXPECT_TRUE(CheckDetectionsFit(MapUpdateOptions::kMinUnfitDetections - 1, 12, options).ok());
  EXPECT_FALSE(CheckDetectionsFit(MapUpdateOptions::kMinUnfitDetections, 12, options).ok());
  options.max_unfit_detection_fraction = 0.0;  // off
  EXPECT_TRUE(CheckDetectionsFit(100, 100, options).ok());
}


// r = (a^T x - b) / sigma on a 2-D state.
struct LinearResidual {
  LinearResidual(double a0, double a1, double b, double sigma) : a0(a0), a1(a1), b(b), sigma(sigma) {}
  template <typename T>
  bool operator()(const T* x, T* r) const {
    r[0] = (T(a0) * x[0] + T(a1) * x[1] - T(b)) / T(sigma);
    return true;
  }
  double a0, a1, b, sigma;
};

// Three sensors measure a landmark (2-D) and another state (2-D), each declaring sigma 1; the
// camera's noise is drawn 3 times as large. Its own test finds a variance factor near 9; the
// others, as declared, keep theirs. The whole graph's test alone would scale all three alike.
TEST(SensorVarianceFactors, TheSensorNoisierThanDeclaredIsFoundAndOnlyIt) {
  for (const double camera_scale : {1.0, 3.0}) {
    std::mt19937 rng(3);
    std::normal_distribution<double> noise(0.0, 1.0);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    const Eigen::Vector2d true_landmark(2.0, -1.0), true_other(0.5, 0.3);
    Eigen::Vector2d landmark = Eigen::Vector2d::Zero(), other = Eigen::Vector2d::Zero();
    MeasurementWeights weights;
    ceres::Problem::Options problem_options;
    problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    ceres::Problem problem(problem_options);
    auto add = [&](MeasurementWeights::Sensor sensor, double* block, const Eigen::Vector2d& truth, double scale) {
      const double a0 = u(rng), a1 = u(rng);
      const double b = a0 * truth.x() + a1 * truth.y() + scale * noise(rng);
      problem.AddResidualBlock(new ceres::AutoDiffCostFunction<LinearResidual, 1, 2>(new LinearResidual(a0, a1, b, 1.0)),
                               weights.loss(sensor), block);
    };
    for (int k = 0; k < 400; ++k) {
      add(MeasurementWeights::kCamera, landmark.data(), true_landmark, camera_scale);
      add(MeasurementWeights::kGnss, landmark.data(), true_landmark, 1.0);
      add(MeasurementWeights::kOdometry, other.data(), true_other, 1.0);
    }
    ceres::Solver::Options options;
    options.linear_solver_type = ceres::DENSE_QR;
    ceres::Solver::Summary summary;
    ceres::Solve(options, &problem, &summary);
    ASSERT_TRUE(summary.IsSolutionUsable());
    absl::StatusOr<GraphLinearization> linearization = GraphLinearization::Compute(&problem, {landmark.data()});
    ASSERT_TRUE(linearization.ok()) << linearization.status();
    std::vector<ceres::ResidualBlockId> blocks;
    problem.GetResidualBlocks(&blocks);
    const SensorResiduals residuals = SensorResidualsOf(&problem, blocks, linearization->Redundancies(), weights);
    // 400 residuals each, less 2 parameters shared by the camera and GNSS, 2 for the odometry.
    EXPECT_NEAR(residuals.redundancy[MeasurementWeights::kOdometry], 398.0, 1e-9);
    EXPECT_NEAR(residuals.redundancy[MeasurementWeights::kCamera] + residuals.redundancy[MeasurementWeights::kGnss],
                798.0, 1e-9);
    const bool raised = RaiseSensorVarianceFactors(residuals, 4.0, &weights);
    EXPECT_EQ(raised, camera_scale > 1.0);
    EXPECT_EQ(weights.factor(MeasurementWeights::kOdometry), 1.0);
    EXPECT_EQ(weights.factor(MeasurementWeights::kGnss), 1.0);
    if (camera_scale > 1.0) {
      EXPECT_GT(weights.factor(MeasurementWeights::kCamera), 0.8 * 9.0);
      EXPECT_LT(weights.factor(MeasurementWeights::kCamera), 1.25 * 9.0);
    } else {
      EXPECT_EQ(weights.factor(MeasurementWeights::kCamera), 1.0);
    }
  }
}

// A sensor the rest of the graph barely checks (under one degree of freedom) is not tested: its
// chi-square says nothing about its variance.
TEST(SensorVarianceFactors, ASensorWithUnderOneDegreeOfFreedomIsLeftAsDeclared) {
  MeasurementWeights weights;
  SensorResiduals residuals;
  residuals.chi2[MeasurementWeights::kGnss] = 40.0;
  residuals.redundancy[MeasurementWeights::kGnss] = 0.6;
  residuals.chi2[MeasurementWeights::kCamera] = 40.0;
  residuals.redundancy[MeasurementWeights::kCamera] = 1.5;
  EXPECT_TRUE(RaiseSensorVarianceFactors(residuals, 4.0, &weights));
  EXPECT_EQ(weights.factor(MeasurementWeights::kGnss), 1.0);
  EXPECT_NEAR(weights.factor(MeasurementWeights::kCamera), 40.0 / 1.5, 1e-12);
}

}  // namespace
}  // namespace crowdmap
