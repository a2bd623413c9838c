#include "core/estimation/gnss_correlation.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "core/estimation/graph_builder.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

// Fixes 1 s apart on a trajectory at rest at the origin (heading 0, no lever arm), each off by
// `errors[k]` and declaring `sigma_m`.
std::vector<GnssObservation> FixesWithErrors(const std::vector<Eigen::Vector2d>& errors, double sigma_m) {
  std::vector<GnssObservation> fixes;
  for (size_t k = 0; k < errors.size(); ++k) {
    GnssObservation o;
    o.node = static_cast<int>(k);
    o.t_s = static_cast<double>(k);
    o.position_m = errors[k];
    o.cov_m2 = Eigen::Matrix2d::Identity() * sigma_m * sigma_m;
    fixes.push_back(o);
  }
  return fixes;
}

// A first-order Gauss-Markov sequence of unit stationary variance per axis scaled by sigma_m.
std::vector<Eigen::Vector2d> Ar1Errors(int n, double alpha, double sigma_m, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal;
  std::vector<Eigen::Vector2d> e(n);
  e[0] = Eigen::Vector2d(normal(rng), normal(rng));
  for (int k = 1; k < n; ++k) {
    e[k] = alpha * e[k - 1] + std::sqrt(1.0 - alpha * alpha) * Eigen::Vector2d(normal(rng), normal(rng));
  }
  for (Eigen::Vector2d& v : e) v *= sigma_m;
  return e;
}

TEST(MeasureGnssResiduals, NormalisesEachResidualByItsFixAndTakesTheLeverArm) {
  // Heading north: a lever arm 2 m ahead puts the antenna at (0, 2); the fix reads (3, 2) with
  // sigmas 3 m East and 1 m North: the normalised residual is (-1, 0).
  GnssObservation fix;
  fix.node = 0;
  fix.position_m = Eigen::Vector2d(3.0, 2.0);
  fix.cov_m2 = Eigen::Vector2d(9.0, 1.0).asDiagonal();
  std::vector<GnssObservation> fixes = {fix, fix};
  fixes[1].t_s = 1.0;
  fixes[1].node = 1;
  fixes[1].position_m = Eigen::Vector2d(0.0, 3.0);  // normalised (0, -1)
  const std::vector<Pose2> poses(2, Pose2(0.0, 0.0, M_PI / 2));
  const GnssResidualStats stats = MeasureGnssResiduals(fixes, poses, Eigen::Vector2d(2.0, 0.0));
  EXPECT_EQ(stats.fixes, 2);
  EXPECT_EQ(stats.pairs, 1);
  EXPECT_NEAR(stats.mean_square, 0.5, 1e-12);                // (1 + 1) / (2 fixes x 2 axes)
  EXPECT_NEAR(stats.lag1, 0.0, 1e-12);                       // (-1, 0) . (0, -1)
  EXPECT_NEAR(stats.difference_mean_square, 1.0, 1e-12);     // |(1, -1)|^2 / 2
  EXPECT_NEAR(stats.typical_interval_s, 1.0, 1e-12);
}

TEST(MeasureGnssResiduals, AGapBreaksTheSequence) {
  std::vector<GnssObservation> fixes = FixesWithErrors(Ar1Errors(30, 0.9, 1.0, 1), 1.0);
  for (size_t k = 15; k < fixes.size(); ++k) fixes[k].t_s += 100.0;  // an outage of 100 s
  const std::vector<Pose2> poses(fixes.size(), Pose2::Zero());
  EXPECT_EQ(MeasureGnssResiduals(fixes, poses, Eigen::Vector2d::Zero()).pairs, 28);
}

TEST(CorrelatedGnssFromResiduals, WhiteErrorsAreLeftWhite) {
  const std::vector<Pose2> poses(200, Pose2::Zero());
  for (uint64_t seed = 1; seed <= 20; ++seed) {
    const GnssResidualStats stats =
        MeasureGnssResiduals(FixesWithErrors(Ar1Errors(200, 0.0, 3.0, seed), 3.0), poses, Eigen::Vector2d::Zero());
    EXPECT_FALSE(CorrelatedGnssFromResiduals(stats, CorrelatedGnssOptions()).has_value()) << seed;
    // Short passages too, where chance correlations are larger.
    const std::vector<GnssObservation> short_fixes = FixesWithErrors(Ar1Errors(9, 0.0, 3.0, seed), 3.0);
    EXPECT_FALSE(CorrelatedGnssFromResiduals(MeasureGnssResiduals(short_fixes, poses, Eigen::Vector2d::Zero()),
                                             CorrelatedGnssOptions())
                     .has_value())
        << seed;
  }
}

TEST(CorrelatedGnssFromResiduals, ACorrelatedProcessIsFoundWithItsCorrelationTime) {
  const std::vector<Pose2> poses(300, Pose2::Zero());
  for (const double alpha : {0.9, 0.97, 0.988}) {
    const GnssResidualStats stats =
        MeasureGnssResiduals(FixesWithErrors(Ar1Errors(300, alpha, 5.0, 7), 5.0), poses, Eigen::Vector2d::Zero());
    const std::optional<CorrelatedGnss> found = CorrelatedGnssFromResiduals(stats, CorrelatedGnssOptions());
    ASSERT_TRUE(found.has_value()) << alpha;
    const double tau_s = -1.0 / std::log(alpha);
    EXPECT_NEAR(found->correlation_time_s / tau_s, 1.0, 0.35) << alpha;
    EXPECT_DOUBLE_EQ(found->covariance_scale, 1.0) << "the residuals are within their declared sigma";
  }
  // Declared sigmas too small (the receiver's white part only): the covariance is scaled up.
  const GnssResidualStats understated =
      MeasureGnssResiduals(FixesWithErrors(Ar1Errors(300, 0.97, 5.0, 8), 2.0), poses, Eigen::Vector2d::Zero());
  const std::optional<CorrelatedGnss> scaled = CorrelatedGnssFromResiduals(understated, CorrelatedGnssOptions());
  ASSERT_TRUE(scaled.has_value());
  EXPECT_GT(scaled->covariance_scale, 3.0);
  // Too few fixes decide nothing.
  CorrelatedGnssOptions strict;
  strict.min_pairs = 400;
  EXPECT_FALSE(CorrelatedGnssFromResiduals(understated, strict).has_value());
}

// A simulated passage with the thesis's AR(1) GNSS noise (alpha = 0.988 at 1 Hz) declared white:
// the graph takes the process back with about its correlation time; declared as it is, or white
// and white, nothing changes.
TEST(BuildPassageGraph, FindsTheProcessOfCorrelatedGnssDeclaredWhite) {
  ScenarioOptions options;
  options.landmarks = 25;
  options.noise = NoiseConfig::kGnssAr1;
  const Scenario scenario = *Scenario::Create(options);
  GraphOptions detect;
  detect.refine_initial_poses = false;
  detect.detect_correlated_gnss = CorrelatedGnssOptions();
  const double tau_s = -1.0 / std::log(0.988);
  int found = 0;
  for (int i = 0; i < 6; ++i) {
    Passage passage = scenario.MakePassage(i);
    const PassageGraph declared = *BuildPassageGraph(passage, detect);
    EXPECT_FALSE(declared.gnss_residuals.has_value()) << "a declared process is taken as it is";
    EXPECT_NEAR(declared.gnss_correlation_time_s, tau_s, 1e-9);
    passage.noise.gnss_correlation_time_s = 0.0;
    const PassageGraph g = *BuildPassageGraph(passage, detect);
    ASSERT_TRUE(g.gnss_residuals.has_value());
    if (!g.correlated_gnss.has_value()) continue;
    ++found;
    EXPECT_EQ(g.gnss_correlation_time_s, g.correlated_gnss->correlation_time_s);
    EXPECT_GT(g.gnss_correlation_time_s, tau_s / 3.0) << i;
    EXPECT_LT(g.gnss_correlation_time_s, tau_s * 3.0) << i;
    GraphOptions plain;
    plain.refine_initial_poses = false;
    EXPECT_EQ(g.initial_poses, BuildPassageGraph(passage, plain)->initial_poses)
        << "the check leaves the initial guess as it was";
  }
  EXPECT_GE(found, 5);

  ScenarioOptions white_options;
  white_options.landmarks = 25;
  const Scenario white = *Scenario::Create(white_options);
  for (int i = 0; i < 6; ++i) {
    const PassageGraph g = *BuildPassageGraph(white.MakePassage(i), detect);
    ASSERT_TRUE(g.gnss_residuals.has_value());
    EXPECT_FALSE(g.correlated_gnss.has_value()) << i << ": lag-1 " << g.gnss_residuals->lag1;
    EXPECT_EQ(g.gnss_correlation_time_s, 0.0);
  }
}

}  // namespace
}  // namespace crowdmap
