#include "core/estimation/graph_builder.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <set>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

using DetectionKey = std::tuple<double, LandmarkId, double>;  // (t_s, landmark, u_px)

// The last `per_landmark` detections of each landmark (all when 0), computed independently of
// the builder: group by landmark in upload order and keep the tail.
std::multiset<DetectionKey> LastDetections(const Passage& p, int per_landmark) {
  std::map<LandmarkId, std::vector<const Detection*>> by_landmark;
  for (const Detection& d : p.detections) by_landmark[d.landmark_id].push_back(&d);
  std::multiset<DetectionKey> kept;
  for (const auto& [id, list] : by_landmark) {
    const size_t keep = per_landmark > 0 ? std::min<size_t>(per_landmark, list.size()) : list.size();
    for (size_t i = list.size() - keep; i < list.size(); ++i) kept.insert({list[i]->t_s, id, list[i]->u_px});
  }
  return kept;
}

std::multiset<DetectionKey> GraphDetections(const PassageGraph& g) {
  std::multiset<DetectionKey> out;
  for (const CameraObservation& d : g.detections) out.insert({g.node_times_s[d.node], d.landmark_id, d.u_px});
  return out;
}

// The thesis's rule, the default: the last five detections of each landmark.
GraphOptions LastFive() {
  GraphOptions options;
  options.detections_per_landmark = 5;
  return options;
}

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

TEST_F(GraphBuilderTest, NodeTimesAreTheSortedUnionOfGnssAndUsedDetectionTimes) {
  const PassageGraph g = *BuildPassageGraph(passage_, LastFive());
  std::set<double> expected;
  for (const GnssFix& f : passage_.gnss) expected.insert(f.t_s);
  for (const DetectionKey& d : LastDetections(passage_, 5)) expected.insert(std::get<0>(d));
  EXPECT_EQ(g.node_times_s, std::vector<double>(expected.begin(), expected.end()));
  // Some detection times are not GNSS times (2 Hz vs 1 Hz), so the union is larger than either.
  EXPECT_GT(g.node_times_s.size(), passage_.gnss.size());
}

TEST_F(GraphBuilderTest, KeepsTheLastFiveDetectionsOfEachLandmark) {
  const PassageGraph g = *BuildPassageGraph(passage_, LastFive());
  const std::multiset<DetectionKey> expected = LastDetections(passage_, 5);
  EXPECT_EQ(GraphDetections(g), expected);
  EXPECT_EQ(g.detections_dropped, static_cast<int>(passage_.detections.size() - expected.size()));
  EXPECT_GT(g.detections_dropped, 0) << "the scenario sees landmarks more than 5 times";
  EXPECT_TRUE(std::is_sorted(g.detections.begin(), g.detections.end(),
                             [](const CameraObservation& a, const CameraObservation& b) { return a.node < b.node; }));
}

TEST_F(GraphBuilderTest, KeepsAllDetectionsWithZeroAndTheLastTwoWithTwo) {
  GraphOptions all;
  all.detections_per_landmark = 0;
  const PassageGraph g_all = *BuildPassageGraph(passage_, all);
  EXPECT_EQ(GraphDetections(g_all), LastDetections(passage_, 0));
  EXPECT_EQ(g_all.detections.size(), passage_.detections.size());
  EXPECT_EQ(g_all.detections_dropped, 0);

  GraphOptions two;
  two.detections_per_landmark = 2;
  EXPECT_EQ(GraphDetections(*BuildPassageGraph(passage_, two)), LastDetections(passage_, 2));
}

// Spread over the track: each landmark keeps min(n, 5) of its n detections, its first and its last
// among them, the kept ones evenly apart (their gaps in the landmark's detections differ by at most
// one).
TEST_F(GraphBuilderTest, SpreadsTheFiveDetectionsOverEachLandmarksTrack) {
  GraphOptions spread = LastFive();
  spread.spread_detections = true;
  const std::multiset<DetectionKey> kept = GraphDetections(*BuildPassageGraph(passage_, spread));
  std::map<LandmarkId, std::vector<DetectionKey>> track;
  for (const Detection& d : passage_.detections) track[d.landmark_id].push_back({d.t_s, d.landmark_id, d.u_px});
  int longer = 0;
  for (const auto& [id, detections] : track) {
    std::vector<int> positions;
    for (size_t i = 0; i < detections.size(); ++i) {
      if (kept.count(detections[i])) positions.push_back(static_cast<int>(i));
    }
    ASSERT_EQ(positions.size(), std::min<size_t>(5, detections.size())) << "landmark " << id;
    EXPECT_EQ(positions.front(), 0) << "landmark " << id;
    EXPECT_EQ(positions.back(), static_cast<int>(detections.size()) - 1) << "landmark " << id;
    int min_gap = 1 << 30, max_gap = 0;
    for (size_t k = 1; k < positions.size(); ++k) {
      min_gap = std::min(min_gap, positions[k] - positions[k - 1]);
      max_gap = std::max(max_gap, positions[k] - positions[k - 1]);
    }
    EXPECT_LE(max_gap - min_gap, 1) << "landmark " << id;
    longer += detections.size() > 5;
  }
  EXPECT_GT(longer, 0) << "the scenario sees landmarks more than 5 times";
  EXPECT_NE(kept, LastDetections(passage_, 5));
}

// From a 25 Hz camera the last five frames of a landmark are 0.16 s apart. With a spacing of
// 0.5 s only "grid frames" count, the first frame in each half second, so that the five kept span
// two seconds, as the thesis's 2 Hz frames did, and every landmark keeps the same frames: the
// graph has about as many nodes as from a 2 Hz camera.
TEST(GraphBuilder, KeepsTheLastDetectionsOfFramesOnAGridOfTheSpacing) {
  ScenarioOptions options;
  options.landmarks = 25;
  options.camera_rate_hz = 25.0;
  const Passage passage = Scenario::Create(options)->MakePassage(3);
  // Expected independently: the grid frames, then each landmark's last five detections on them.
  std::set<double> frames;
  for (const Detection& d : passage.detections) frames.insert(d.t_s);
  std::set<double> grid;
  long bucket = -1;
  for (double t : frames) {
    const long b = static_cast<long>(std::floor((t + 1e-3) / 0.5));
    if (b > bucket) grid.insert(t);
    bucket = std::max(bucket, b);
  }
  std::map<LandmarkId, std::vector<const Detection*>> on_grid;
  for (const Detection& d : passage.detections) {
    if (grid.count(d.t_s) > 0) on_grid[d.landmark_id].push_back(&d);
  }
  std::multiset<DetectionKey> expected;
  for (const auto& [id, list] : on_grid) {
    for (size_t i = list.size() - std::min<size_t>(5, list.size()); i < list.size(); ++i) {
      expected.insert({list[i]->t_s, id, list[i]->u_px});
    }
  }
  GraphOptions spaced = LastFive();
  spaced.detection_spacing_s = 0.5;
  const PassageGraph g = *BuildPassageGraph(passage, spaced);
  EXPECT_EQ(GraphDetections(g), expected);
  // About as many nodes as from a 2 Hz camera.
  ScenarioOptions slow = options;
  slow.camera_rate_hz = 2.0;
  const PassageGraph g2 = *BuildPassageGraph(Scenario::Create(slow)->MakePassage(3), spaced);
  EXPECT_LT(g.node_count(), 1.1 * g2.node_count());
  // Without the spacing: the last five frames.
  const PassageGraph last = *BuildPassageGraph(passage, LastFive());
  EXPECT_EQ(GraphDetections(last), LastDetections(passage, 5));
}

// A vehicle that stops for a minute with a landmark in view: with a spacing in metres the stop
// adds one frame, the first after arriving, and none after it until the vehicle has moved on.
TEST(GraphBuilder, AVehicleStandingStillAddsNoFrames) {
  Passage p;
  p.vehicle_id = "v";
  p.passage_id = "stop";
  // 10 m/s for 10 s, standing from 10 s to 70 s, 10 m/s again until 80 s; a 2 Hz camera sees one
  // landmark all along.
  for (int i = 0; i <= 800; ++i) {
    const double t = 0.1 * i;
    p.odometry.push_back({t, t >= 10.0 - 1e-9 && t < 70.0 - 1e-9 ? 0.0 : 10.0, 0.0});
  }
  for (int i = 0; i <= 80; ++i) {
    GnssFix f;
    f.t_s = i;
    f.lat_deg = 48.0;
    f.lon_deg = 2.0 + (i <= 10 ? i : i <= 70 ? 10 : i - 60) * 10.0 / 74500.0;
    p.gnss.push_back(f);
  }
  for (int i = 0; i < 160; ++i) p.detections.push_back({0.5 * i, 7, 900.0});
  GraphOptions options;
  options.detections_per_landmark = 0;
  options.detection_spacing_s = 0.5;
  EXPECT_EQ(BuildPassageGraph(p, options)->detections.size(), 160u) << "by time alone, every frame";
  options.detection_spacing_m = 1.0;
  const PassageGraph g = *BuildPassageGraph(p, options);
  std::vector<double> times, expected;
  for (const CameraObservation& d : g.detections) times.push_back(g.node_times_s[d.node]);
  for (int i = 0; i < 160; ++i) {
    const double t = 0.5 * i;
    if (t <= 10.0 || t >= 70.5) expected.push_back(t);  // 5 m apart while moving; t = 10 arrives
  }
  EXPECT_EQ(times, expected);
  // With the last five: those of the drive on, not five views of the stop.
  options.detections_per_landmark = 5;
  const PassageGraph last = *BuildPassageGraph(p, options);
  ASSERT_EQ(last.detections.size(), 5u);
  EXPECT_EQ(last.node_times_s[last.detections.front().node], 77.5);
  // Encoders that read noise while the wheels stand still (+-0.5 m/s, zero-mean): no travel.
  for (OdometrySample& o : p.odometry) {
    if (o.speed_mps == 0.0) o.speed_mps = (std::lround(o.t_s * 10.0) % 2 == 0) ? 0.5 : -0.5;
  }
  options.detections_per_landmark = 0;
  const PassageGraph noisy = *BuildPassageGraph(p, options);
  std::vector<double> noisy_times;
  for (const CameraObservation& d : noisy.detections) noisy_times.push_back(noisy.node_times_s[d.node]);
  EXPECT_EQ(noisy_times, expected);
}

// A camera of 2 Hz or slower: every frame is a grid frame, so the spacing changes nothing.
TEST_F(GraphBuilderTest, TheSpacingKeepsEveryFrameOfATwoHertzCamera) {
  GraphOptions spaced = LastFive();
  spaced.detection_spacing_s = 0.5;
  EXPECT_EQ(GraphDetections(*BuildPassageGraph(passage_, spaced)), LastDetections(passage_, 5));
}

TEST_F(GraphBuilderTest, EveryObservationPointsAtTheNodeOfItsTime) {
  const PassageGraph g = *BuildPassageGraph(passage_, LastFive());
  ASSERT_EQ(g.gnss.size(), passage_.gnss.size());
  for (size_t j = 0; j < g.gnss.size(); ++j) {
    const GnssObservation& o = g.gnss[j];
    ASSERT_GE(o.node, 0);
    ASSERT_LT(o.node, g.node_count());
    EXPECT_EQ(g.node_times_s[o.node], passage_.gnss[j].t_s) << j;
    const Eigen::Vector2d local = g.frame.ToLocal({passage_.gnss[j].lat_deg, passage_.gnss[j].lon_deg});
    EXPECT_LT((o.position_m - local).norm(), 1e-9) << j;
    // 100 m^2 isotropic stays isotropic under the (nearly orthogonal) frame change.
    EXPECT_LT((o.cov_m2 - passage_.gnss[j].cov_en_m2).norm(), 1e-3) << j;
  }
  for (const CameraObservation& d : g.detections) {
    ASSERT_GE(d.node, 0);
    ASSERT_LT(d.node, g.node_count());
  }
  // GraphDetections pairs each observation with its node's time; equality with the kept
  // (time, id, pixel) triples says each one points at the node of its own time.
  EXPECT_EQ(GraphDetections(g), LastDetections(passage_, 5));
  // Every node carries a fix or a used detection.
  std::vector<bool> used(g.node_count(), false);
  for (const GnssObservation& o : g.gnss) used[o.node] = true;
  for (const CameraObservation& d : g.detections) used[d.node] = true;
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0);
}

TEST_F(GraphBuilderTest, HasOneMotionBetweenConsecutiveNodesInTheFirstFixFrame) {
  const PassageGraph g = *BuildPassageGraph(passage_, GraphOptions());
  EXPECT_EQ(g.frame.origin().lat_deg, passage_.gnss[0].lat_deg);
  EXPECT_EQ(g.frame.origin().lon_deg, passage_.gnss[0].lon_deg);
  ASSERT_EQ(g.motions.size(), g.node_times_s.size() - 1);
  ASSERT_EQ(g.initial_poses.size(), g.node_times_s.size());
  for (size_t k = 0; k + 1 < g.node_times_s.size(); ++k) {
    EXPECT_NEAR(g.motions[k].duration_s, g.node_times_s[k + 1] - g.node_times_s[k], 1e-12) << k;
    EXPECT_GT(g.motions[k].duration_s, 0.0) << k;
  }
  // A 0.5 s step at about 12 m/s moves about 6 m forward.
  const RelativeMotion& m = g.motions[g.motions.size() / 2];
  EXPECT_NEAR(m.delta.x() / m.duration_s, 12.0, 3.0);
}

TEST_F(GraphBuilderTest, RejectsAPassageWithFewerThanTwoFixes) {
  passage_.gnss.resize(1);
  EXPECT_EQ(BuildPassageGraph(passage_, GraphOptions()).status().code(), absl::StatusCode::kInvalidArgument);
}

// GNSS residual blocks AddPoseGraphFactors puts on nodes first..last.
int GnssBlocks(const PassageGraph& g, int first, int last) {
  std::vector<Pose2> poses(g.initial_poses.begin() + first, g.initial_poses.begin() + last + 1);
  ceres::Problem problem;
  AddPoseGraphFactors(g, first, last, Eigen::Vector2d(0.5, 0.0), nullptr, nullptr, &poses, &problem);
  return problem.NumResidualBlocks() - (last - first);  // less the odometry between the nodes
}

TEST(AddPoseGraphFactors, CorrelatedGnssEntersAsInnovationsAndACutDropsTheOneAcrossIt) {
  ScenarioOptions options;
  options.landmarks = 25;
  options.noise = NoiseConfig::kGnssAr1;
  const Scenario scenario = *Scenario::Create(options);
  const Passage passage = scenario.MakePassage(0);
  const PassageGraph g = *BuildPassageGraph(passage, GraphOptions());
  EXPECT_NEAR(g.gnss_correlation_time_s, -1.0 / std::log(0.988), 1e-9);
  const int fixes = static_cast<int>(g.gnss.size());
  const int n = g.node_count();
  EXPECT_EQ(GnssBlocks(g, 0, n - 1), fixes);  // the first fix, then one innovation per fix
  // Cut after a node that holds a fix (with a later fix in the second range).
  const int cut = g.gnss[fixes / 2].node;
  EXPECT_EQ(GnssBlocks(g, 0, cut) + GnssBlocks(g, cut + 1, n - 1), fixes - 1);

  Passage white = passage;
  white.noise.gnss_correlation_time_s = 0.0;
  const PassageGraph w = *BuildPassageGraph(white, GraphOptions());
  EXPECT_EQ(GnssBlocks(w, 0, cut) + GnssBlocks(w, cut + 1, n - 1), fixes);  // white: every fix on its own
}

TEST(BuildPassageGraph, ADeclaredProcessSigmaReplacesTheFixCovariance) {
  ScenarioOptions options;
  options.landmarks = 5;
  Passage passage = Scenario::Create(options)->MakePassage(0);
  passage.noise.gnss_process_sigma_m = 4.0;
  const PassageGraph g = *BuildPassageGraph(passage, GraphOptions());
  for (const GnssObservation& o : g.gnss) EXPECT_LT((o.cov_m2 - 16.0 * Eigen::Matrix2d::Identity()).norm(), 1e-5);  // the frame's rotation
}

// Bounds set at about twice the worst seen over 4 scenario seeds x 8 passages (GNSS sigma 10 m,
// white): whole passage max 14.3 m / 0.21 rad (the ends, with fixes on one side only), interior
// (10 s from the ends) max 9.1 m / 0.17 rad, per-passage RMS at most 4.2 m / 0.059 rad.
TEST(BuildPassageGraph, InitialPosesAreWithinAFewMetresOfTheTruth) {
  for (uint64_t seed : {1, 2}) {
    ScenarioOptions options;
    options.landmarks = 25;
    options.seed = seed;
    const Scenario scenario = *Scenario::Create(options);
    for (int index : {0, 1, 2}) {
      const PassageGraph g = *BuildPassageGraph(scenario.MakePassage(index), GraphOptions());
      double worst_position = 0.0, worst_heading = 0.0, interior_position = 0.0, interior_heading = 0.0;
      double sum_position2 = 0.0, sum_heading2 = 0.0;
      for (int k = 0; k < g.node_count(); ++k) {
        const double t = g.node_times_s[k];
        const Pose2 truth = scenario.TruePoseAt(t);
        const Eigen::Vector2d truth_local = g.frame.ToLocal(scenario.frame().ToGeo(truth.head<2>()));
        const double position = (truth_local - g.initial_poses[k].head<2>()).norm();
        const double heading = std::abs(WrapAngle(truth.z() - g.initial_poses[k].z()));
        worst_position = std::max(worst_position, position);
        worst_heading = std::max(worst_heading, heading);
        if (t >= 10.0 && t <= 155.0) {
          interior_position = std::max(interior_position, position);
          interior_heading = std::max(interior_heading, heading);
        }
        sum_position2 += position * position;
        sum_heading2 += heading * heading;
      }
      SCOPED_TRACE(testing::Message() << "seed " << seed << " passage " << index);
      EXPECT_LT(worst_position, 30.0);
      EXPECT_LT(worst_heading, 0.45);
      EXPECT_LT(interior_position, 20.0);
      EXPECT_LT(interior_heading, 0.35);
      EXPECT_LT(std::sqrt(sum_position2 / g.node_count()), 8.0);
      EXPECT_LT(std::sqrt(sum_heading2 / g.node_count()), 0.12);
    }
  }
}

}  // namespace
}  // namespace crowdmap
