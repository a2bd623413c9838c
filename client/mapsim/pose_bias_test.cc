#include "client/mapsim/pose_bias.h"

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

TEST(PoseBias, ErrorsAreMeasuredAgainstTheTruePosesInTheirOwnFrame) {
  PoseBiasOptions options;
  options.passages = 60;
  options.bin_s = 20.0;
  options.scenario.noise_model.steering_sigma_rad *= 0.01;  // nearly no heading noise: no bias
  absl::StatusOr<std::vector<PoseBiasBin>> bins = RunPoseBias(options);
  ASSERT_TRUE(bins.ok()) << bins.status();
  ASSERT_GE(bins->size(), 8u);
  for (const PoseBiasBin& b : *bins) {
    EXPECT_GT(b.samples, options.passages) << b.start_s;
    // One pose is metres off (10 m GNSS), a few decimetres along track with this odometry...
    EXPECT_GT(b.sd.x(), 0.3) << b.start_s;
    EXPECT_LT(b.sd.x(), 3.0) << b.start_s;
    EXPECT_LT(b.sd.z(), 0.02) << b.start_s;
    // ...and unbiased: the mean error stays within 4 standard errors (a frame or time mismatch
    // would put it metres off).
    for (int k = 0; k < 3; ++k) {
      EXPECT_GT(b.mean_se[k], 0.0);
      EXPECT_LT(std::abs(b.mean[k]), 4.0 * b.mean_se[k]) << b.start_s << " component " << k;
      EXPECT_LT(std::abs(b.corrected_mean[k]), 4.0 * b.corrected_se[k]) << b.start_s << " component " << k;
    }
  }
}

TEST(PoseBias, RejectsTooFewPassages) {
  PoseBiasOptions options;
  options.passages = 1;
  EXPECT_EQ(RunPoseBias(options).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap
