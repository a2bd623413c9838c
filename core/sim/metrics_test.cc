#include "core/sim/metrics.h"

#include <cmath>
#include <limits>
#include <vector>

#include <Eigen/LU>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

const LocalFrame kFrame(LatLon{45.0, 5.0});

TruthLandmark MakeTruth(LandmarkId id, const Eigen::Vector2d& position_m) {
  TruthLandmark t;
  t.id = id;
  t.position_m = position_m;
  t.position = kFrame.ToGeo(position_m);
  return t;
}

// A map landmark displaced from the truth by exactly `offset_en` East/North at the truth.
Landmark Displaced(const TruthLandmark& t, const Eigen::Vector2d& offset_en, const Eigen::Matrix2d& cov) {
  Landmark l;
  l.id = t.id;
  l.position = LocalFrame(t.position).ToGeo(offset_en);
  l.anchor = l.position;
  l.cov_en_m2 = cov;
  return l;
}

// Makes `cov` the joint covariance of landmarks `ids`: one factor with its inverse replaces
// theirs.
void SetJointCovariance(const std::vector<LandmarkId>& ids, const Eigen::MatrixXd& cov, MapState* map) {
  std::vector<int64_t> old;
  for (LandmarkId id : ids) map->AppendFactorIds(id, &old);
  for (int64_t id : old) map->RemoveFactor(id);
  MapFactor f;
  f.id = map->last_factor_id() + 1;
  f.landmarks = ids;
  f.information = cov.inverse();
  f.information_vector = Eigen::VectorXd::Zero(cov.rows());
  map->PutFactor(f);
}

// Puts the landmark with its covariance as the map's information about it.
void Put(const Landmark& l, MapState* map) {
  map->PutLandmark(l);
  SetJointCovariance({l.id}, l.cov_en_m2, map);
}

Eigen::Matrix2d Cov(double ee, double en, double nn) {
  Eigen::Matrix2d c;
  c << ee, en, en, nn;
  return c;
}

TEST(EvaluateMap, GivesExactErrorsSigmasAndNeesOnAHandMadeMap) {
  const std::vector<TruthLandmark> truth = {MakeTruth(1, {0.0, 50.0}), MakeTruth(2, {100.0, 50.0}),
                                            MakeTruth(3, {-300.0, 200.0})};
  MapState map;
  // Offsets (0.3, 0.4), (-0.6, 0.8), (0, -2): distances 0.5, 1.0, 2.0.
  Put(Displaced(truth[0], {0.3, 0.4}, Cov(0.25, 0.0, 1.0)), &map);
  Put(Displaced(truth[1], {-0.6, 0.8}, Cov(0.25, 0.0, 1.0)), &map);
  // Correlated covariance [[2, 1], [1, 2]]: inverse (1/3) [[2, -1], [-1, 2]].
  Put(Displaced(truth[2], {0.0, -2.0}, Cov(2.0, 1.0, 2.0)), &map);

  const MapErrorMetrics m = EvaluateMap(map, truth);
  EXPECT_EQ(m.landmarks_evaluated, 3);
  EXPECT_NEAR(m.mean_dist_err_m, (0.5 + 1.0 + 2.0) / 3, 1e-6);
  EXPECT_NEAR(m.mean_east_err_m, (0.3 - 0.6 + 0.0) / 3, 1e-6);
  EXPECT_NEAR(m.mean_north_err_m, (0.4 + 0.8 - 2.0) / 3, 1e-6);
  // 3 x mean standard deviation: East sqrt(0.25), sqrt(0.25), sqrt(2); North 1, 1, sqrt(2).
  EXPECT_NEAR(m.east_3sigma_m, 3.0 * (0.5 + 0.5 + std::sqrt(2.0)) / 3, 1e-12);
  EXPECT_NEAR(m.north_3sigma_m, 3.0 * (1.0 + 1.0 + std::sqrt(2.0)) / 3, 1e-12);
  // e^T Sigma^-1 e: 0.09/0.25 + 0.16 = 0.52; 0.36/0.25 + 0.64 = 2.08; (1/3)(2 * 4) = 8/3.
  const double nees = 0.52 + 2.08 + 8.0 / 3.0;
  EXPECT_NEAR(m.nees_per_dof, nees / 3 / 2, 1e-5);
  EXPECT_NEAR(m.joint_nees_per_dof, nees / 6, 1e-5) << "no cross blocks: the joint value is the same";
}

TEST(EvaluateMap, SkipsLandmarksMissingFromTheMapAndIgnoresExtraOnes) {
  const TruthLandmark a = MakeTruth(1, {10.0, 10.0}), missing = MakeTruth(99, {50.0, 0.0});
  MapState map;
  Put(Displaced(a, {3.0, -4.0}, Cov(1.0, 0.0, 1.0)), &map);
  Landmark extra = Displaced(MakeTruth(7, {0.0, 0.0}), {100.0, 100.0}, Cov(1.0, 0.0, 1.0));
  Put(extra, &map);  // in the map, not in the truth: not evaluated
  const MapErrorMetrics m = EvaluateMap(map, {missing, a});
  EXPECT_EQ(m.landmarks_evaluated, 1);
  EXPECT_NEAR(m.mean_dist_err_m, 5.0, 1e-6);
  EXPECT_NEAR(m.mean_east_err_m, 3.0, 1e-6);
  EXPECT_NEAR(m.mean_north_err_m, -4.0, 1e-6);
  EXPECT_NEAR(m.nees_per_dof, 25.0 / 2, 1e-5);
}

TEST(EvaluateVehicleYaw, CountsEstimatesWithinTwoSigmaAndSkipsVehiclesWithout) {
  MapState map;
  VehicleCalibration a;
  a.vehicle_id = "a";
  a.camera_yaw_offset_rad = 0.011;
  a.camera_yaw_variance_rad2 = 0.001 * 0.001;  // error 1 sigma
  a.passages = 10;
  VehicleCalibration b = a;
  b.vehicle_id = "b";
  b.camera_yaw_offset_rad = -0.003;  // error 3 sigma
  map.PutVehicle(a);
  map.PutVehicle(b);
  const VehicleYawMetrics m = EvaluateVehicleYaw(map, {{"a", 0.010}, {"b", 0.0}, {"c", 0.002}});
  ASSERT_EQ(m.vehicles.size(), 3u);
  EXPECT_EQ(m.estimated, 2);
  EXPECT_DOUBLE_EQ(m.within_2sigma_fraction, 0.5);
  EXPECT_NEAR(m.nees, (1.0 + 9.0) / 2.0, 1e-9);
  EXPECT_NEAR(m.rms_error_rad, std::sqrt((1e-6 + 9e-6) / 2.0), 1e-12);
  EXPECT_NEAR(m.mean_error_rad, (0.001 - 0.003) / 2.0, 1e-12);
  EXPECT_NEAR(m.mean_sigma_rad, 0.001, 1e-12);
  EXPECT_EQ(m.vehicles[0].passages, 10);
  EXPECT_TRUE(std::isnan(m.vehicles[2].estimate_rad));
}

TEST(EvaluateMap, GivesZerosForAnEmptyMap) {
  const MapErrorMetrics m = EvaluateMap(MapState(), {MakeTruth(1, {0.0, 0.0})});
  EXPECT_EQ(m.landmarks_evaluated, 0);
  EXPECT_EQ(m.mean_dist_err_m, 0.0);
  EXPECT_EQ(m.nees_per_dof, 0.0);
}

TEST(EvaluateMap, NanCovarianceGivesNanNeesButStillMeasuresTheErrors) {
  const TruthLandmark a = MakeTruth(1, {0.0, 0.0}), b = MakeTruth(2, {40.0, 0.0});
  MapState map;
  Put(Displaced(a, {1.0, 0.0}, Eigen::Matrix2d::Constant(std::numeric_limits<double>::quiet_NaN())), &map);
  Put(Displaced(b, {0.0, 3.0}, Cov(1.0, 0.0, 1.0)), &map);
  const MapErrorMetrics m = EvaluateMap(map, {a, b});
  EXPECT_EQ(m.landmarks_evaluated, 2);
  EXPECT_NEAR(m.mean_dist_err_m, 2.0, 1e-6);
  EXPECT_TRUE(std::isnan(m.nees_per_dof));
  EXPECT_TRUE(std::isnan(m.joint_nees_per_dof));
}

TEST(EvaluateMap, JointNeesUsesTheCrossCovariances) {
  // Two landmarks with the same error (x, x) on each axis and correlation rho between them:
  // per axis (x, x)^T [[1, rho], [rho, 1]]^-1 (x, x) = 2 x^2 / (1 + rho).
  const double x = 1.5, rho = 0.6;
  const TruthLandmark a = MakeTruth(1, {0.0, 0.0}), b = MakeTruth(2, {20.0, 0.0});
  MapState map;
  Put(Displaced(a, {x, x}, Eigen::Matrix2d::Identity()), &map);
  Put(Displaced(b, {x, x}, Eigen::Matrix2d::Identity()), &map);
  Eigen::MatrixXd joint = Eigen::MatrixXd::Identity(4, 4);
  joint.block<2, 2>(0, 2) = joint.block<2, 2>(2, 0) = rho * Eigen::Matrix2d::Identity();
  SetJointCovariance({1, 2}, joint, &map);
  const MapErrorMetrics m = EvaluateMap(map, {a, b});
  EXPECT_NEAR(m.nees_per_dof, (2 * x * x + 2 * x * x) / 2 / 2, 1e-5) << "per landmark: blocks only";
  EXPECT_NEAR(m.joint_nees_per_dof, 2 * (2 * x * x / (1 + rho)) / 4, 1e-5);
}

TEST(NeesPerDofSdIfConsistent, GrowsFromIndependentToCommonErrors) {
  // nees_per_dof of two landmarks with correlation rho on each axis (scales do not matter):
  // chi2(4)/4 (sd sqrt(1/2)) for rho = 0, chi2(2)/2 (sd 1) for rho = 1; in general
  // sd = sqrt(2 tr(C^2)) / 4 with tr(C^2) = 4 + 4 rho^2.
  const TruthLandmark a = MakeTruth(1, {0.0, 0.0}), b = MakeTruth(2, {20.0, 0.0});
  for (double rho : {0.0, 0.6, 0.999}) {  // rho = 1 has no information form
    MapState map;
    Put(Displaced(a, {0.1, 0.2}, 0.25 * Eigen::Matrix2d::Identity()), &map);
    Put(Displaced(b, {0.3, -0.1}, 4.0 * Eigen::Matrix2d::Identity()), &map);
    Eigen::MatrixXd joint = Eigen::MatrixXd::Zero(4, 4);
    joint.block<2, 2>(0, 0) = 0.25 * Eigen::Matrix2d::Identity();
    joint.block<2, 2>(2, 2) = 4.0 * Eigen::Matrix2d::Identity();
    joint.block<2, 2>(0, 2) = joint.block<2, 2>(2, 0) = rho * 0.5 * 2.0 * Eigen::Matrix2d::Identity();
    SetJointCovariance({1, 2}, joint, &map);
    EXPECT_NEAR(NeesPerDofSdIfConsistent(map, {a, b}), std::sqrt(2.0 * (4.0 + 4.0 * rho * rho)) / 4.0, 1e-9)
        << "rho=" << rho;
  }
  EXPECT_TRUE(std::isnan(NeesPerDofSdIfConsistent(MapState(), {a, b}))) << "nothing mapped";
}

}  // namespace
}  // namespace crowdmap
