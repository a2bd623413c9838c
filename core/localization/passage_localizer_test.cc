#include "core/localization/passage_localizer.h"

#include <cmath>

#include <gtest/gtest.h>

#include "core/estimation/factors.h"
#include "core/localization/localization_testing.h"
#include "core/localization/pose_covariance.h"
#include "core/sim/scenario.h"
#include "core/sim/sensor_simulation.h"

namespace crowdmap {
namespace {

using testing_localization::MakeMap;
using testing_localization::NoiseFree;
using testing_localization::PoseError;

Scenario MakeScenario(int landmarks, NoiseConfig noise = NoiseConfig::kWhite, uint64_t seed = 1) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.noise = noise;
  options.seed = seed;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  return *std::move(scenario);
}

TEST(PassageLocalizer, RecoversNoiseFreePassageExactly) {
  const Scenario scenario = MakeScenario(25);
  int unprojected = 0;
  const Passage passage = NoiseFree(scenario, scenario.MakePassage(0), &unprojected);
  EXPECT_EQ(unprojected, 0);
  const LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 1, /*exact=*/true);
  absl::StatusOr<PassageLocalization> result = LocalizePassage(passage, map);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_TRUE(result->rejected.empty());
  EXPECT_EQ(result->map_version, 7);
  EXPECT_EQ(result->landmarks_used.size(), 25u);
  ASSERT_GT(result->poses.size(), 165u);
  double worst_m = 0.0, worst_rad = 0.0;
  for (const LocalizedPose& p : result->poses) {
    const Eigen::Vector3d e = PoseError(scenario, p);
    worst_m = std::max(worst_m, e.head<2>().norm());
    worst_rad = std::max(worst_rad, std::abs(e.z()));
  }
  // The passage's frame (at its first fix) and the scenario's are tangent planes at points 0.5 m
  // apart: over the 2 km route they differ by a few micrometres.
  EXPECT_LT(worst_m, 1e-5);
  EXPECT_LT(worst_rad, 1e-6);
  EXPECT_LT(result->chi2, 1e-8);
}

// Pose NEES over independent passages and maps (white noise, a consistent correlated map): the
// covariance says how far the poses are.
TEST(PassageLocalizer, PoseCovarianceIsConsistentOverManyPassages) {
  const Scenario scenario = MakeScenario(25);
  constexpr int kRuns = 24;
  double nees_sum = 0.0;
  int count = 0;
  for (int run = 0; run < kRuns; ++run) {
    const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 100 + run, /*exact=*/false);
    absl::StatusOr<PassageLocalization> result = LocalizePassage(scenario.MakePassage(run), map);
    ASSERT_TRUE(result.ok()) << result.status();
    for (const LocalizedPose& p : result->poses) {
      const Eigen::Vector3d e = PoseError(scenario, p);
      nees_sum += e.dot(p.cov.ldlt().solve(e));
      ++count;
    }
  }
  const double nees_per_dof = nees_sum / (3.0 * count);
  RecordProperty("pose_nees_per_dof", std::to_string(nees_per_dof));
  EXPECT_GT(nees_per_dof, 0.75);
  EXPECT_LT(nees_per_dof, 1.3);
}

// AR(1) GNSS errors (alpha = 0.988 at 1 Hz) that the passages declare white: found in their fixes'
// residuals and modelled, the poses' covariance is as honest as with the process declared (pose
// NEES/dof measured 1.20 both ways over 12 passages); taken as white (the check off), the fixes' slow
// common offset is taken as averaging away (3.64).
TEST(PassageLocalizer, CorrelatedGnssDeclaredWhiteIsFoundAndThePosesStayConsistent) {
  const Scenario scenario = MakeScenario(25, NoiseConfig::kGnssAr1);
  constexpr int kRuns = 12;
  enum Mode { kWhite, kFound, kDeclared };
  double nees[3] = {0.0, 0.0, 0.0};
  int count[3] = {0, 0, 0}, found = 0;
  for (int run = 0; run < kRuns; ++run) {
    const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 200 + run, /*exact=*/false);
    const Passage declared = scenario.MakePassage(run);
    Passage white = declared;
    white.noise.gnss_correlation_time_s = 0.0;
    for (const Mode mode : {kWhite, kFound, kDeclared}) {
      PassageLocalizerOptions options;
      if (mode == kWhite) options.correlated_gnss_min_lag1 = 0.0;
      absl::StatusOr<PassageLocalization> result =
          LocalizePassage(mode == kDeclared ? declared : white, map, options);
      ASSERT_TRUE(result.ok()) << result.status();
      if (mode == kFound && result->gnss_correlation_time_s > 0.0) ++found;
      if (mode != kFound) EXPECT_EQ(result->gnss_correlation_time_s, 0.0) << "declared, or the check off";
      for (const LocalizedPose& p : result->poses) {
        const Eigen::Vector3d e = PoseError(scenario, p);
        nees[mode] += e.dot(p.cov.ldlt().solve(e));
        ++count[mode];
      }
    }
  }
  double per_dof[3];
  for (int m = 0; m < 3; ++m) per_dof[m] = nees[m] / (3.0 * count[m]);
  RecordProperty("pose_nees_per_dof_white", std::to_string(per_dof[kWhite]));
  RecordProperty("pose_nees_per_dof_found", std::to_string(per_dof[kFound]));
  RecordProperty("pose_nees_per_dof_declared", std::to_string(per_dof[kDeclared]));
  EXPECT_GE(found, kRuns - 1);
  EXPECT_GT(per_dof[kWhite], 2.0);
  EXPECT_LT(per_dof[kFound], 1.4);
  EXPECT_GT(per_dof[kFound], 0.6);
}

// A camera turned by the yaw-bias scenario's 0.009 rad, localised against consistent maps: with the
// offset estimated (1 degree prior) it is recovered and the pose covariance stays honest; taken as
// calibrated, the turned bearings bend the poses beyond what their covariance says. A noise-free
// passage with the offset estimated is still recovered exactly.
TEST(PassageLocalizer, EstimatesTheCameraYawOffset) {
  const Scenario scenario = MakeScenario(150, NoiseConfig::kYawBias);
  PassageLocalizerOptions estimated;
  estimated.camera_yaw_sigma_rad = 0.0174533;
  constexpr int kRuns = 8;
  double nees[2] = {0.0, 0.0}, yaw_nees = 0.0;
  int count = 0;
  for (int run = 0; run < kRuns; ++run) {
    const LocalizationMap map = MakeMap(scenario, 0.3, 0.4, 300 + run, /*exact=*/false);
    const Passage passage = scenario.MakePassage(run);
    absl::StatusOr<PassageLocalization> fixed = LocalizePassage(passage, map);
    absl::StatusOr<PassageLocalization> free = LocalizePassage(passage, map, estimated);
    ASSERT_TRUE(fixed.ok() && free.ok());
    EXPECT_EQ(fixed->camera_yaw_sigma_rad, 0.0);
    ASSERT_GT(free->camera_yaw_sigma_rad, 0.0);
    EXPECT_LT(free->camera_yaw_sigma_rad, 0.2 * estimated.camera_yaw_sigma_rad) << "the passage informs it";
    const double yaw_error = free->camera_yaw_offset_rad - scenario.CameraYawErrorRad(run);
    yaw_nees += yaw_error * yaw_error / (free->camera_yaw_sigma_rad * free->camera_yaw_sigma_rad);
    ASSERT_EQ(fixed->poses.size(), free->poses.size());
    for (size_t k = 0; k < free->poses.size(); ++k) {
      const Eigen::Vector3d a = PoseError(scenario, fixed->poses[k]), b = PoseError(scenario, free->poses[k]);
      nees[0] += a.dot(fixed->poses[k].cov.ldlt().solve(a));
      nees[1] += b.dot(free->poses[k].cov.ldlt().solve(b));
      ++count;
    }
  }
  const double fixed_nees = nees[0] / (3.0 * count), free_nees = nees[1] / (3.0 * count);
  RecordProperty("pose_nees_per_dof_calibration_fixed", std::to_string(fixed_nees));
  RecordProperty("pose_nees_per_dof_yaw_estimated", std::to_string(free_nees));
  EXPECT_GT(free_nees, 0.75);
  EXPECT_LT(free_nees, 1.3);
  EXPECT_GT(fixed_nees, free_nees + 0.2);
  EXPECT_LT(yaw_nees / kRuns, 3.0) << "the offset's sigma says how far it is";

  int unprojected = 0;
  const Passage exact = NoiseFree(scenario, scenario.MakePassage(0), &unprojected);
  absl::StatusOr<PassageLocalization> result =
      LocalizePassage(exact, MakeMap(scenario, 0.0, 0.3, 1, /*exact=*/true), estimated);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_NEAR(result->camera_yaw_offset_rad, 0.0, 1e-8);
  for (const LocalizedPose& p : result->poses) EXPECT_LT(PoseError(scenario, p).head<2>().norm(), 1e-5);
  EXPECT_LT(result->chi2, 1e-6);
}

TEST(PassageLocalizer, RejectsMislabelledDetection) {
  const Scenario scenario = MakeScenario(150);
  const Passage clean = scenario.MakePassage(3);
  const LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 5, /*exact=*/false);
  Passage mislabelled = clean;
  // One detection of landmark 5 reported as landmark 20, which stands elsewhere on the route.
  Detection* wrong = nullptr;
  for (Detection& d : mislabelled.detections) {
    if (d.landmark_id == 5) wrong = &d;
  }
  ASSERT_NE(wrong, nullptr);
  wrong->landmark_id = 20;
  absl::StatusOr<PassageLocalization> a = LocalizePassage(clean, map);
  absl::StatusOr<PassageLocalization> b = LocalizePassage(mislabelled, map);
  ASSERT_TRUE(a.ok() && b.ok());
  bool found = false;
  for (const RejectedDetection& r : b->rejected) {
    found |= r.landmark_id == 20 && std::abs(r.t_s - wrong->t_s) < 1e-6 && r.u_px == wrong->u_px;
  }
  EXPECT_TRUE(found) << b->Brief();
  EXPECT_LE(b->rejected.size(), a->rejected.size() + 1) << a->Brief() << "\n" << b->Brief();
  ASSERT_EQ(a->poses.size(), b->poses.size());
  double worst = 0.0;
  for (size_t k = 0; k < a->poses.size(); ++k) {
    worst = std::max(worst, (a->poses[k].pose_m.head<2>() - b->poses[k].pose_m.head<2>()).norm());
  }
  EXPECT_LT(worst, 0.05);
}

TEST(PassageLocalizer, RejectsLandmarkWhoseDetectionsAllBelongElsewhere) {
  // Dense enough that other landmarks are in view with it: a landmark seen alone, with metres of
  // GNSS noise, moves the poses instead and nothing disagrees.
  const Scenario scenario = MakeScenario(150);
  LocalizationMap map = MakeMap(scenario, 0.0, 0.3, 6, /*exact=*/false);
  // Landmark 9's map entry is 6 m from where it stands (twenty map sigmas).
  map.positions[8] = scenario.frame().ToGeo(scenario.frame().ToLocal(map.positions[8]) + Eigen::Vector2d(6.0, 0.0));
  absl::StatusOr<PassageLocalization> result = LocalizePassage(scenario.MakePassage(4), map);
  ASSERT_TRUE(result.ok()) << result.status();
  int whole = 0;
  for (const RejectedDetection& r : result->rejected) whole += r.landmark_id == 9 && r.whole_landmark;
  EXPECT_GT(whole, 0) << result->Brief();
  EXPECT_EQ(std::count(result->landmarks_used.begin(), result->landmarks_used.end(), 9), 0);
}

TEST(PassageLocalizer, LocalizesWithoutMap) {
  const Scenario scenario = MakeScenario(10);
  absl::StatusOr<PassageLocalization> result = LocalizePassage(scenario.MakePassage(0), LocalizationMap{});
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_TRUE(result->landmarks_used.empty());
  EXPECT_GT(result->detections_unmapped, 0);
}

TEST(ChiSquareUpperQuantile, MatchesTables) {
  EXPECT_NEAR(ChiSquareUpperQuantile(1, 1e-3), 10.83, 0.01);
  EXPECT_NEAR(ChiSquareUpperQuantile(2, 1e-3), 13.82, 0.01);
  EXPECT_NEAR(ChiSquareUpperQuantile(10, 1e-3), 29.59, 0.3);
  EXPECT_NEAR(ChiSquareUpperQuantile(10, 0.5), 9.34, 0.05);
}

TEST(PassageLocalizerOptions, RejectsInvalidGates) {
  PassageLocalizerOptions options;
  options.landmark_gate_probability = 0.0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.max_gating_rounds = 0;
  EXPECT_FALSE(options.Validate().ok());
  options = {};
  options.camera_yaw_sigma_rad = -0.01;
  EXPECT_FALSE(options.Validate().ok());
  options.camera_yaw_sigma_rad = std::nan("");
  EXPECT_FALSE(options.Validate().ok());
}

}  // namespace
}  // namespace crowdmap
