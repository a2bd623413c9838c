#include "core/estimation/map_updater.h"

#include <Eigen/Cholesky>
#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

Scenario MakeScenario(int landmarks) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok());
  return *std::move(scenario);
}

TEST(MapUpdateOptions, RejectsOutOfRangeValuesNamingTheField) {
  MapUpdateOptions options;
  options.max_subgraph_dim = 5;
  EXPECT_NE(options.Validate().message().find("max_subgraph_dim"), std::string::npos);
  options = MapUpdateOptions();
  options.correlation_radius_m = 0.0;
  EXPECT_NE(options.Validate().message().find("correlation_radius_m"), std::string::npos);
  options = MapUpdateOptions();
  options.detections_per_landmark = -1;
  EXPECT_NE(options.Validate().message().find("detections_per_landmark"), std::string::npos);
  EXPECT_TRUE(MapUpdateOptions().Validate().ok());
}

TEST(ParseUpdateStrategy, RoundTripsEveryName) {
  for (const char* name : {"cc", "dc", "cc-gsd"}) {
    absl::StatusOr<UpdateStrategy> s = ParseUpdateStrategy(name);
    ASSERT_TRUE(s.ok());
    EXPECT_STREQ(UpdateStrategyName(*s), name);
  }
  EXPECT_FALSE(ParseUpdateStrategy("gsd").ok());
}

TEST(ComputePassageUpdate, FirstPassageCreatesEveryLandmarkWithAPositiveDefiniteCovariance) {
  const Scenario scenario = MakeScenario(25);
  MapState map;
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(scenario.MakePassage(0), MapUpdateOptions(), map);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_EQ(update->summary.landmarks_created, 25);
  EXPECT_EQ(update->summary.landmarks_updated, 0);
  EXPECT_GE(update->summary.subgraphs, 2);  // about 250 nodes: more than 500 state dimensions
  EXPECT_EQ(update->delta.version, update->summary.subgraphs);
  EXPECT_EQ(map.landmark_count(), 0u) << "the input map must not change";
  map.Apply(update->delta);
  ASSERT_EQ(map.landmark_count(), 25u);
  map.ForEachLandmark([](const Landmark& l) {
    EXPECT_EQ(Eigen::LLT<Eigen::Matrix2d>(l.cov_en_m2).info(), Eigen::Success) << l.id;
    EXPECT_EQ(l.passages_seen, 1) << l.id;
  });
}

TEST(ComputePassageUpdate, SecondPassageUpdatesAndShrinksTheCovariance) {
  const Scenario scenario = MakeScenario(10);
  MapState map;
  map.Apply(ComputePassageUpdate(scenario.MakePassage(0), MapUpdateOptions(), map)->delta);
  const double before = map.FindLandmark(1)->cov_en_m2.trace();
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(scenario.MakePassage(1), MapUpdateOptions(), map);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_EQ(update->summary.landmarks_updated, 10);
  EXPECT_EQ(update->summary.landmarks_created, 0);
  map.Apply(update->delta);
  EXPECT_LT(map.FindLandmark(1)->cov_en_m2.trace(), before);
  EXPECT_EQ(map.FindLandmark(1)->passages_seen, 2);
}

TEST(ComputePassageUpdate, CorrelationRadiusBoundsTheCrossCovarianceBlocks) {
  const Scenario scenario = MakeScenario(25);
  MapUpdateOptions dense, bounded;
  bounded.correlation_radius_m = 150.0;
  MapState dense_map, bounded_map;
  dense_map.Apply(ComputePassageUpdate(scenario.MakePassage(0), dense, dense_map)->delta);
  bounded_map.Apply(ComputePassageUpdate(scenario.MakePassage(0), bounded, bounded_map)->delta);
  EXPECT_GT(bounded_map.cross_block_count(), 0u);
  EXPECT_LT(bounded_map.cross_block_count(), dense_map.cross_block_count());
  // Every stored block joins landmarks within the radius.
  for (LandmarkId a : bounded_map.LandmarkIds()) {
    std::vector<LandmarkId> neighbours;
    bounded_map.AppendNeighbors(a, &neighbours);
    for (LandmarkId b : neighbours) {
      EXPECT_LE(EastNorthOffset(bounded_map.FindLandmark(a)->position, bounded_map.FindLandmark(b)->position).norm(),
                150.0);
    }
  }
}

TEST(ComputePassageUpdate, PassageWithoutUsableDetectionsIsRejectedWithoutADelta) {
  const Scenario scenario = MakeScenario(4);
  Passage passage = scenario.MakePassage(0);
  // A single detection per landmark cannot place a new landmark.
  std::vector<Detection> one_each;
  for (const Detection& d : passage.detections) {
    bool seen = false;
    for (const Detection& k : one_each) seen |= k.landmark_id == d.landmark_id;
    if (!seen) one_each.push_back(d);
  }
  passage.detections = one_each;
  MapState map;
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(passage, MapUpdateOptions(), map);
  ASSERT_FALSE(update.ok());
  EXPECT_EQ(update.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(update.status().message().find("detections"), std::string::npos);
}

}  // namespace
}  // namespace crowdmap
