#include "core/estimation/graph_builder.h"

#include <algorithm>
#include <map>

#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

class GraphBuilderTest : public testing::Test {
 protected:
  GraphBuilderTest() {
    ScenarioOptions options;
    options.landmarks = 25;
    scenario_ = std::make_unique<Scenario>(*Scenario::Create(options));
    passage_ = scenario_->MakePassage(3);
  }
  std::unique_ptr<Scenario> scenario_;
  Passage passage_;
};

TEST_F(GraphBuilderTest, NodesAreTheUnionOfGnssAndUsedDetectionTimes) {
  const PassageGraph g = *BuildPassageGraph(passage_, GraphOptions());
  EXPECT_TRUE(std::is_sorted(g.node_times_s.begin(), g.node_times_s.end()));
  EXPECT_EQ(g.motions.size(), g.node_times_s.size() - 1);
  for (const GnssObservation& o : g.gnss) EXPECT_NEAR(g.node_times_s[o.node], passage_.gnss[&o - g.gnss.data()].t_s, 1e-9);
  std::map<LandmarkId, int> per_landmark;
  for (const CameraObservation& d : g.detections) ++per_landmark[d.landmark_id];
  for (const auto& [id, count] : per_landmark) EXPECT_EQ(count, 5) << id;
  EXPECT_EQ(g.detections.size() + g.detections_dropped, passage_.detections.size());
  // Every node carries a fix or a used detection.
  std::vector<bool> used(g.node_count(), false);
  for (const GnssObservation& o : g.gnss) used[o.node] = true;
  for (const CameraObservation& d : g.detections) used[d.node] = true;
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0);
}

TEST_F(GraphBuilderTest, KeepsTheLastDetectionsOfEachLandmark) {
  GraphOptions all;
  all.detections_per_landmark = 0;
  EXPECT_EQ(BuildPassageGraph(passage_, all)->detections.size(), passage_.detections.size());
  const PassageGraph g = *BuildPassageGraph(passage_, GraphOptions());
  std::map<LandmarkId, double> last_time;
  for (const Detection& d : passage_.detections) last_time[d.landmark_id] = d.t_s;
  for (const CameraObservation& d : g.detections) {
    EXPECT_GE(g.node_times_s[d.node], last_time[d.landmark_id] - 2.0 - 1e-9) << "5 detections at 2 Hz span 2 s";
  }
}

TEST_F(GraphBuilderTest, InitialPosesAreCloseToTheTruth) {
  const PassageGraph g = *BuildPassageGraph(passage_, GraphOptions());
  double worst_position = 0.0, worst_heading = 0.0;
  for (int k = 0; k < g.node_count(); ++k) {
    const Pose2 truth = scenario_->TruePoseAt(g.node_times_s[k]);
    const Eigen::Vector2d truth_local = g.frame.ToLocal(scenario_->frame().ToGeo(truth.head<2>()));
    worst_position = std::max(worst_position, (truth_local - g.initial_poses[k].head<2>()).norm());
    worst_heading = std::max(worst_heading, std::abs(WrapAngle(truth.z() - g.initial_poses[k].z())));
  }
  // GNSS sigma 10 m: the odometry + GNSS pose graph is good to metres and about a tenth of a radian.
  EXPECT_LT(worst_position, 20.0);
  EXPECT_LT(worst_heading, 0.35);
}

}  // namespace
}  // namespace crowdmap
