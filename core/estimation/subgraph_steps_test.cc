#include "core/estimation/subgraph_steps.h"

#include <cmath>

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

}  // namespace
}  // namespace crowdmap
