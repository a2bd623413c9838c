#include "core/estimation/cramer_rao.h"

#include <cmath>

#include <gtest/gtest.h>

#include "core/estimation/map_updater.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

TEST(ExpectedDistance, IsotropicErrorHasTheRayleighMean) {
  EXPECT_NEAR(ExpectedDistance(4.0 * Eigen::Matrix2d::Identity()), 2.0 * std::sqrt(M_PI / 2.0), 1e-12);
  // Along one axis only: E|a x| = a sqrt(2 / pi).
  Eigen::Matrix2d line = Eigen::Matrix2d::Zero();
  line(0, 0) = 9.0;
  EXPECT_NEAR(ExpectedDistance(line), 3.0 * std::sqrt(2.0 / M_PI), 1e-3);
}

struct LoopBound {
  Scenario scenario;
  GraphOptions options;
};

LoopBound MakeLoop(int landmarks, uint64_t seed) {
  ScenarioOptions o;
  o.landmarks = landmarks;
  o.seed = seed;
  absl::StatusOr<Scenario> scenario = Scenario::Create(o);
  EXPECT_TRUE(scenario.ok());
  GraphOptions options;
  options.frame_origin = scenario->options().origin;
  return {*std::move(scenario), options};
}

PassageFisherInformation Information(const LoopBound& loop, int index) {
  absl::StatusOr<PassageFisherInformation> info = PassageLandmarkInformation(
      loop.scenario.MakePassage(index), loop.options, [&](double t) { return loop.scenario.TruePoseAt(t); },
      [&](LandmarkId id) -> std::optional<Eigen::Vector2d> {
        if (id < 1 || id > static_cast<LandmarkId>(loop.scenario.landmarks().size())) return std::nullopt;
        return loop.scenario.landmarks()[id - 1].position_m;
      });
  EXPECT_TRUE(info.ok()) << info.status();
  return *std::move(info);
}

TEST(CramerRaoBound, TheSamePassageTwiceHalvesTheBound) {
  const LoopBound loop = MakeLoop(10, 1);
  const PassageFisherInformation info = Information(loop, 0);
  EXPECT_EQ(info.landmarks.size(), 10u);
  CramerRaoBound once, twice;
  once.Add(info);
  twice.Add(info);
  twice.Add(info);
  const auto a = once.Covariances(), b = twice.Covariances();
  ASSERT_TRUE(a.ok() && b.ok());
  for (const auto& [id, cov] : *a) EXPECT_LT((b->at(id) - 0.5 * cov).norm(), 1e-9 * cov.norm()) << id;
}

TEST(CramerRaoBound, OnePassageBoundMatchesTheEstimatorsErrorOverManyNoiseDraws) {
  // The estimator is efficient on one passage with white noise: its landmark errors over noise
  // draws have about the bound's covariance (the passages differ only in their noise).
  constexpr int kDraws = 40;
  double squared_error = 0.0, bound = 0.0;
  for (int seed = 1; seed <= kDraws; ++seed) {
    const LoopBound loop = MakeLoop(10, seed);
    CramerRaoBound crlb;
    crlb.Add(Information(loop, 0));
    const auto cov = crlb.Covariances();
    ASSERT_TRUE(cov.ok());
    MapUpdateOptions options;
    options.bias_correction = false;
    MapState map;
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(loop.scenario.MakePassage(0), options, map);
    ASSERT_TRUE(update.ok()) << update.status();
    map.Apply(update->delta);
    for (const auto& [id, c] : *cov) {
      const Landmark* l = map.FindLandmark(id);
      ASSERT_NE(l, nullptr);
      const Eigen::Vector2d e = loop.scenario.frame().ToLocal(l->position) - loop.scenario.landmarks()[id - 1].position_m;
      squared_error += e.squaredNorm();
      bound += c.trace();
    }
  }
  // Measured: 1.33 (the draws share each passage's common GNSS error, so 40 draws leave this ratio
  // a standard error of about 0.16).
  const double ratio = squared_error / bound;
  EXPECT_GT(ratio, 0.6);
  EXPECT_LT(ratio, 1.6);
}

}  // namespace
}  // namespace crowdmap
