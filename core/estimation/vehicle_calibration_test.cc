#include "core/estimation/vehicle_calibration.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/map/map_state.h"

namespace crowdmap {
namespace {

// A solve whose own measurements carry information `own` about the yaw, given its landmarks, and
// whose landmarks add `share^2` to its own estimate's variance: the marginal variance parts of its
// posterior with prior variance `prior_var` (Gaussian fusion of prior and own estimate).
struct Solve {
  double given_landmarks;
  double from_landmarks;
};
Solve SolveWith(double prior_var, double own, double share) {
  const double w = own / (own + 1.0 / prior_var);  // the own estimate's weight in the posterior
  return {1.0 / (1.0 / prior_var + own), w * w * share * share};
}

TEST(ConsiderCameraYawSolve, WithoutMapBorneErrorsItIsTheBayesianPosteriorAndChainsLikeOneBatch) {
  VehicleCalibration v = NewVehicleCalibration("v", 0.02);
  const double own[] = {4.0e5, 1.0e6, 2.5e5};
  double information = 1.0 / (0.02 * 0.02);
  for (double j : own) {
    const Solve s = SolveWith(v.camera_yaw_variance_rad2, j, 0.0);
    v = ConsiderCameraYawSolve(v, 0.001, s.given_landmarks, s.from_landmarks);
    information += j;
    EXPECT_NEAR(v.camera_yaw_variance_rad2 * information, 1.0, 1e-12);
  }
  EXPECT_EQ(v.camera_yaw_offset_rad, 0.001);
  EXPECT_EQ(v.camera_yaw_map_term, 0.0);
}

TEST(ConsiderCameraYawSolve, AMapBorneErrorSharedByEverySolveIsNeverAveragedAway) {
  const double own = 1.0e6, share = 4.0e-4;  // each solve alone: sigma 1e-3 given its landmarks, 4e-4 from them
  VehicleCalibration v = NewVehicleCalibration("v", 0.02);
  double previous = v.camera_yaw_variance_rad2;
  for (int k = 1; k <= 50; ++k) {
    const Solve s = SolveWith(v.camera_yaw_variance_rad2, own, share);
    v = ConsiderCameraYawSolve(v, 0.0, s.given_landmarks, s.from_landmarks);
    EXPECT_LT(v.camera_yaw_variance_rad2, previous) << k;
    previous = v.camera_yaw_variance_rad2;
    // The weighted mean of the prior and k estimates that share one map error (the prior's pairs
    // with the solves counted with it): variance 1/I + share^2 (1 - (I0 / I)^2).
    const double prior_information = 1.0 / (0.02 * 0.02), information = prior_information + k * own;
    const double expected =
        1.0 / information + share * share * (1.0 - std::pow(prior_information / information, 2));
    EXPECT_NEAR(v.camera_yaw_variance_rad2 / expected, 1.0, 1e-9) << k;
    EXPECT_GT(v.camera_yaw_variance_rad2, 0.99 * share * share) << k;
  }
}

TEST(ConsiderCameraYawSolve, AsTheMapImprovesTheRecordFollowsItsLatestMapBorneError) {
  // Solve k's map-borne error has sigma s_k = s_1 / sqrt(k), nested: the weighted mean of the
  // solves' errors sum_k w_k e_k has variance sum_ij w_i w_j s_max(i,j)^2.
  const double own = 1.0e6, s1 = 2.0e-3;
  const int solves = 30;
  VehicleCalibration v = NewVehicleCalibration("v", 0.02);
  std::vector<double> j_of = {1.0 / (0.02 * 0.02)}, s_of = {0.0};  // the prior as solve 0, no map error
  for (int k = 1; k <= solves; ++k) {
    const double share = s1 / std::sqrt(k);
    const Solve s = SolveWith(v.camera_yaw_variance_rad2, own, share);
    v = ConsiderCameraYawSolve(v, 0.0, s.given_landmarks, s.from_landmarks);
    j_of.push_back(own);
    s_of.push_back(share);
  }
  double information = 0.0, pairs = 0.0;
  for (double j : j_of) information += j;
  for (size_t a = 0; a < j_of.size(); ++a) {
    for (size_t b = 0; b < j_of.size(); ++b) pairs += j_of[a] * j_of[b] * std::pow(s_of[std::max(a, b)], 2);
  }
  EXPECT_NEAR(v.camera_yaw_variance_rad2 / ((1.0 + pairs / information) / information), 1.0, 1e-9);
  // Well below the first map's share, and above the latest one's.
  EXPECT_LT(v.camera_yaw_variance_rad2, 0.25 * s1 * s1);
  EXPECT_GT(v.camera_yaw_variance_rad2, s_of.back() * s_of.back());
}

TEST(ConsiderCameraYawSolve, ASolveThatSaysNothingAboutTheYawKeepsTheRecord) {
  VehicleCalibration v = NewVehicleCalibration("v", 0.01);
  v.passages = 3;
  const VehicleCalibration after = ConsiderCameraYawSolve(v, 0.0, v.camera_yaw_variance_rad2, 0.0);
  EXPECT_EQ(after.camera_yaw_variance_rad2, v.camera_yaw_variance_rad2);
  EXPECT_EQ(after.camera_yaw_information, v.camera_yaw_information);
  EXPECT_EQ(after.passages, 3);
}

VehicleCalibration Record(const std::string& id, double offset, double variance) {
  VehicleCalibration v;
  v.vehicle_id = id;
  v.camera_yaw_offset_rad = offset;
  v.camera_yaw_variance_rad2 = variance;
  v.camera_yaw_information = 1.0 / variance;
  return v;
}

TEST(FleetCameraYawPrior, NoneBeforeTheFleetIsLargeEnough) {
  MapState map;
  for (int k = 0; k < 4; ++k) map.PutVehicle(Record("v" + std::to_string(k), 0.01, 1e-6));
  EXPECT_FALSE(FleetCameraYawPrior(map, "new", 5, 0.0).has_value());
  EXPECT_TRUE(FleetCameraYawPrior(map, "new", 4, 0.0).has_value());
  MapState one;
  one.PutVehicle(Record("v", 0.01, 1e-6));
  EXPECT_FALSE(FleetCameraYawPrior(one, "new", 1, 0.0).has_value()) << "one record has no spread";
}

TEST(FleetCameraYawPrior, TheRecordsWeightedMeanWithTheirSpreadAndUncertaintyAsVariance) {
  MapState map;
  const double offsets[] = {0.010, 0.012, 0.007, 0.011, 0.009, 0.013, 0.008, 0.010, 0.006, 0.014};
  const double variances[] = {1e-6, 2e-6, 1e-6, 3e-6, 1e-6, 2e-6, 1e-6, 1e-6, 4e-6, 1e-6};
  double weights = 0.0, mean = 0.0, mean_variance = 0.0;
  for (int k = 0; k < 10; ++k) {
    map.PutVehicle(Record("v" + std::to_string(k), offsets[k], variances[k]));
    weights += 1.0 / variances[k];
    mean += offsets[k] / variances[k];
    mean_variance += variances[k] / 10;
  }
  mean /= weights;  // precision-weighted: 0.01 and 0.006 (variances 3e-6, 4e-6) count less
  double sample_variance = 0.0;
  for (double x : offsets) sample_variance += (x - mean) * (x - mean) / 9;
  const std::optional<VehicleCalibration> prior = FleetCameraYawPrior(map, "new", 10, 0.0);
  ASSERT_TRUE(prior.has_value());
  EXPECT_EQ(prior->vehicle_id, "new");
  EXPECT_NEAR(prior->camera_yaw_offset_rad, mean, 1e-15);
  const double expected = (sample_variance + mean_variance) * (1.0 + 2.0 * std::sqrt(2.0 / 9.0)) + mean_variance / 10;
  EXPECT_NEAR(prior->camera_yaw_variance_rad2, expected, 1e-12 * expected);
  EXPECT_NEAR(prior->camera_yaw_information * prior->camera_yaw_variance_rad2, 1.0, 1e-12);
  EXPECT_EQ(prior->camera_yaw_map_term, 0.0);
  EXPECT_EQ(prior->passages, 0);
  // Never narrower than the fixed prior.
  const std::optional<VehicleCalibration> floored = FleetCameraYawPrior(map, "new", 10, 0.01);
  ASSERT_TRUE(floored.has_value());
  EXPECT_NEAR(floored->camera_yaw_offset_rad, mean, 1e-15);
  EXPECT_EQ(floored->camera_yaw_variance_rad2, 1e-4);
  EXPECT_EQ(floored->camera_yaw_information, 1e4);
}

TEST(FleetCameraYawPrior, CamerasThatShareOneErrorAreNotKnownBetterThanTheirRecords) {
  MapState map;
  for (int k = 0; k < 200; ++k) map.PutVehicle(Record("v" + std::to_string(k), 0.009, 4e-6));
  const std::optional<VehicleCalibration> prior = FleetCameraYawPrior(map, "new", 10, 0.0);
  ASSERT_TRUE(prior.has_value());
  EXPECT_NEAR(prior->camera_yaw_offset_rad, 0.009, 1e-15);
  EXPECT_GE(prior->camera_yaw_variance_rad2, 4e-6);
  EXPECT_LT(prior->camera_yaw_variance_rad2, 1.5 * 4e-6);
}

}  // namespace
}  // namespace crowdmap
