#include "core/estimation/triangulation.h"

#include <cmath>

#include <gtest/gtest.h>

#include "core/model/camera_model.h"
#include "core/sim/metrics.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

TEST(IntersectRays, NoiseFreeRaysMeetAtTheLandmark) {
  const Calibration calib;
  const Eigen::Vector2d landmark(30.0, 6.0);
  std::vector<BearingRay> rays;
  for (int k = 0; k < 4; ++k) {
    const Pose2 pose(6.0 * k, 0.0, 0.02 * k);
    double u;
    ASSERT_TRUE(ProjectLandmark(pose.data(), landmark.data(), calib, &u));
    rays.push_back(CameraRay(pose, calib, u));
  }
  const std::optional<Eigen::Vector2d> p = IntersectRays(rays);
  ASSERT_TRUE(p.has_value());
  EXPECT_LT((*p - landmark).norm(), 1e-9);
}

TEST(IntersectRays, ParallelOrSingleRaysHaveNoIntersection) {
  const BearingRay a{{0.0, 0.0}, {1.0, 0.0}}, b{{0.0, 1.0}, {1.0, 0.0}};
  EXPECT_FALSE(IntersectRays({a}).has_value());
  EXPECT_FALSE(IntersectRays({a, b}).has_value());
}

TEST(TriangulationMapper, MapsTheRouteWithinAFewMetresAndNoCovariance) {
  ScenarioOptions options;
  options.landmarks = 4;
  const Scenario scenario = *Scenario::Create(options);
  TriangulationMapper mapper;
  for (int i = 0; i < 20; ++i) ASSERT_TRUE(mapper.AddPassage(scenario.MakePassage(i)).ok());
  const MapErrorMetrics m = EvaluateMap(mapper.map(), scenario.landmarks());
  EXPECT_EQ(m.landmarks_evaluated, 4);
  EXPECT_LT(m.mean_dist_err_m, 3.0);
  EXPECT_TRUE(std::isnan(m.nees_per_dof));
}

}  // namespace
}  // namespace crowdmap
