#include "client/mapsim/passage_consistency.h"

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

PassageConsistencyOptions SmallRun() {
  PassageConsistencyOptions options;
  options.scenario.landmarks = 8;
  options.passages = 40;
  options.update.strategy = UpdateStrategy::kCorrelated;
  return options;
}

TEST(PassageConsistency, SinglePassageMapsAreConsistentWhenTheModelIsNearlyLinear) {
  // With a tenth of the steering noise the headings are known well enough for the linearised
  // covariance to hold: every NEES is that of chi2 draws (16 dof x 40 passages), about 1.
  PassageConsistencyOptions options = SmallRun();
  options.scenario.noise_model.steering_sigma_rad *= 0.1;
  absl::StatusOr<PassageConsistency> r = RunPassageConsistency(options);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->passages_used, 40);
  EXPECT_EQ(r->dof, 16);
  EXPECT_NEAR(r->own_nees_per_dof, 1.0, 0.25);
  EXPECT_NEAR(r->spread_nees_per_dof, 1.0, 0.35);
  EXPECT_LT(r->bias_nees_per_dof, 0.15);
  EXPECT_NEAR(r->fused_nees_per_dof, 1.0, 0.6) << "chi2(16)/16: sd 0.35";
}

TEST(PassageConsistency, TheLinearisedCovarianceFollowsTheErrorWithTheThesisSteeringNoise) {
  // With the thesis's steering noise the headings are known to a few hundredths of a radian: each
  // passage's covariance, computed at its own estimate, is too small along its own error (most of
  // all for the best-known combinations, such as the relative positions of nearby landmarks),
  // although on average it covers the errors' spread. Combining the passages by their own
  // information then biases the map. Measured with the thesis's last 5 detections per landmark:
  // 1.22, 0.88, 2.1 against 0.9, and 8.4. With all of them less so (`mapsim passage-consistency
  // --landmarks 25 --passages 40 --strategy cc --detections-per-landmark 0`: 1.09, 0.95, 1.22
  // against 0.94, and 4.5; with 5 there: 1.15, 0.87, 1.77 against 0.92, and 6.5).
  PassageConsistencyOptions options = SmallRun();
  options.scenario.landmarks = 25;
  options.update.detections_per_landmark = 5;
  absl::StatusOr<PassageConsistency> r = RunPassageConsistency(options);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_GT(r->own_nees_per_dof, 1.12);
  EXPECT_LT(r->spread_nees_per_dof, 1.05);
  EXPECT_GT(r->own_nees_most_precise_fifth, 1.5 * r->own_nees_least_precise_fifth);
  EXPECT_GT(r->fused_nees_per_dof, 3.0);
}

TEST(PassageConsistency, RefusesTheDecorrelatedStrategy) {
  PassageConsistencyOptions options = SmallRun();
  options.update.strategy = UpdateStrategy::kDecorrelated;
  const absl::StatusOr<PassageConsistency> r = RunPassageConsistency(options);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("strategy"), std::string::npos) << r.status();
}

}  // namespace
}  // namespace crowdmap
