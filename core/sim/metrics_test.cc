#include "core/sim/metrics.h"

#include <cmath>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(EvaluateMap, GivesExactErrorsSigmasAndNeesOnAHandMadeMap) {
  const LocalFrame frame(LatLon{45.0, 5.0});
  std::vector<TruthLandmark> truth;
  MapState map;
  const Eigen::Vector2d offsets[] = {{0.3, 0.4}, {-0.6, 0.8}};
  for (int i = 0; i < 2; ++i) {
    TruthLandmark t;
    t.id = i + 1;
    t.position_m = {100.0 * i, 50.0};
    t.position = frame.ToGeo(t.position_m);
    truth.push_back(t);
    Landmark l;
    l.id = t.id;
    l.position = LocalFrame(t.position).ToGeo(offsets[i]);
    l.cov_en_m2 = Eigen::Vector2d(0.25, 1.0).asDiagonal();
    map.PutLandmark(l);
  }
  TruthLandmark missing;
  missing.id = 99;
  truth.push_back(missing);

  const MapErrorMetrics m = EvaluateMap(map, truth);
  EXPECT_EQ(m.landmarks_evaluated, 2);
  EXPECT_NEAR(m.mean_dist_err_m, (0.5 + 1.0) / 2, 1e-6);
  EXPECT_NEAR(m.mean_east_err_m, (0.3 - 0.6) / 2, 1e-6);
  EXPECT_NEAR(m.mean_north_err_m, (0.4 + 0.8) / 2, 1e-6);
  EXPECT_NEAR(m.east_3sigma_m, 1.5, 1e-12);
  EXPECT_NEAR(m.north_3sigma_m, 3.0, 1e-12);
  const double nees1 = 0.09 / 0.25 + 0.16, nees2 = 0.36 / 0.25 + 0.64;
  EXPECT_NEAR(m.nees_per_dof, (nees1 + nees2) / 4, 1e-5);
  EXPECT_NEAR(m.joint_nees_per_dof, (nees1 + nees2) / 4, 1e-5) << "no cross blocks: equals the mean";
}

TEST(EvaluateMap, MissingCovarianceGivesNanNees) {
  const LatLon p{45.0, 5.0};
  TruthLandmark t;
  t.id = 1;
  t.position = p;
  MapState map;
  Landmark l;
  l.id = 1;
  l.position = p;
  l.cov_en_m2 = Eigen::Matrix2d::Constant(std::nan(""));
  map.PutLandmark(l);
  EXPECT_TRUE(std::isnan(EvaluateMap(map, {t}).nees_per_dof));
}

}  // namespace
}  // namespace crowdmap
