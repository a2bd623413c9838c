#include "core/estimation/map_updater.h"

#include <algorithm>
#include <cstdio>
#include <functional>
#include <numeric>
#include <random>
#include <utility>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <gtest/gtest.h>

#include "absl/strings/str_cat.h"

#include "core/estimation/passage_exclusion.h"
#include "core/map/map_window.h"
#include "core/sim/city_scenario.h"
#include "core/sim/faults.h"
#include "core/sim/metrics.h"
#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

Scenario MakeScenario(int landmarks, uint64_t seed = 1) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.seed = seed;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok());
  return *std::move(scenario);
}

// The applied-passage line names the sensors a passage's own tests weighted down, and only then.
TEST(PassageUpdateSummary, SensorBriefNamesTheFactorsOnlyWhenASensorWasRaised) {
  PassageUpdateSummary summary;
  EXPECT_EQ(summary.SensorBrief(), "");
  summary.sensor_test_factors[2] = 3.91;
  EXPECT_EQ(summary.SensorBrief(), " odometry_factor=1.00 gnss_factor=1.00 camera_factor=3.91");
  EXPECT_NE(summary.Brief().find(" camera_factor=3.91"), std::string::npos) << summary.Brief();
}

TEST(MapUpdateOptions, RejectsOutOfRangeValuesNamingTheField) {
  {
    MapUpdateOptions negative;
    negative.sensor_test_sigmas = -1.0;
    EXPECT_NE(negative.Validate().message().find("sensor_test_sigmas"), std::string::npos);
  }
  MapUpdateOptions options;
  options.max_subgraph_dim = 5;
  EXPECT_NE(options.Validate().message().find("max_subgraph_dim"), std::string::npos);
  options = MapUpdateOptions();
  options.window_hops = -1;
  EXPECT_NE(options.Validate().message().find("window_hops"), std::string::npos);
  options = MapUpdateOptions();
  options.detections_per_landmark = -1;
  EXPECT_NE(options.Validate().message().find("detections_per_landmark"), std::string::npos);
  options.detections_per_landmark = 1;  // no landmark could ever be created
  EXPECT_NE(options.Validate().message().find("detections_per_landmark"), std::string::npos);
  options.detections_per_landmark = 2;  // below min_new_landmark_detections: none created either
  EXPECT_NE(options.Validate().message().find("min_new_landmark_detections"), std::string::npos);
  options.min_new_landmark_detections = 2;
  EXPECT_TRUE(options.Validate().ok()) << options.Validate();
  options = MapUpdateOptions();
  options.max_new_landmark_bias_sigmas = -1.0;
  EXPECT_NE(options.Validate().message().find("max_new_landmark_bias_sigmas"), std::string::npos);
  options = MapUpdateOptions();
  options.edge_margin_sigmas = -1.0;
  EXPECT_NE(options.Validate().message().find("edge_margin_sigmas"), std::string::npos);
  options = MapUpdateOptions();
  options.max_joint_mahalanobis2 = 0.0;
  EXPECT_NE(options.Validate().message().find("max_joint_mahalanobis2"), std::string::npos);
  options = MapUpdateOptions();
  options.warmup_passages = -1;
  EXPECT_NE(options.Validate().message().find("warmup_passages"), std::string::npos);
  options = MapUpdateOptions();
  options.relinearize_until_passages = -1;
  EXPECT_NE(options.Validate().message().find("relinearize_until_passages"), std::string::npos);
  options = MapUpdateOptions();
  options.relinearize_area_passages = -1;
  EXPECT_NE(options.Validate().message().find("relinearize_area_passages"), std::string::npos);
  for (double sigma : {-0.01, 0.5, static_cast<double>(NAN)}) {
    options = MapUpdateOptions();
    options.speed_scale_prior_sigma = sigma;
    EXPECT_NE(options.Validate().message().find("speed_scale_prior_sigma"), std::string::npos) << sigma;
  }
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

TEST(ComputePassageUpdate, YieldPointIsCalledThroughoutAndChangesNothing) {
  const Scenario scenario = MakeScenario(10);
  MapState map;
  map.Apply(ComputePassageUpdate(scenario.MakePassage(0), MapUpdateOptions(), map)->delta);
  absl::StatusOr<PassageUpdate> plain = ComputePassageUpdate(scenario.MakePassage(1), MapUpdateOptions(), map);
  MapUpdateOptions options;
  int calls = 0;
  options.yield_point = [&calls] { ++calls; };
  absl::StatusOr<PassageUpdate> yielding = ComputePassageUpdate(scenario.MakePassage(1), options, map);
  ASSERT_TRUE(plain.ok() && yielding.ok());
  // At least once per solver iteration (two solves per subgraph) and per stage of each subgraph.
  EXPECT_GE(calls, yielding->summary.solver_iterations + 3 * yielding->summary.subgraphs);
  ASSERT_EQ(plain->delta.landmarks.size(), yielding->delta.landmarks.size());
  for (const auto& [id, landmark] : plain->delta.landmarks) {
    const Landmark& other = yielding->delta.landmarks.at(id);
    EXPECT_EQ(landmark.position.lat_deg, other.position.lat_deg);
    EXPECT_EQ(landmark.position.lon_deg, other.position.lon_deg);
    EXPECT_EQ(landmark.cov_en_m2, other.cov_en_m2);
  }
  ASSERT_EQ(plain->delta.added_factors.size(), yielding->delta.added_factors.size());
  for (const auto& [id, factor] : plain->delta.added_factors) {
    EXPECT_EQ(factor.information, yielding->delta.added_factors.at(id).information);
    EXPECT_EQ(factor.information_vector, yielding->delta.added_factors.at(id).information_vector);
  }
}

TEST(ComputePassageUpdate, BoundedWindowStaysConservative) {
  // With a window of one link the prior and the written marginals come from windows that do not
  // cover the map: no marginal the map stores may be smaller than the exact marginal of the
  // information it holds, and the estimate stays close to the exact update's. Partial drives (300
  // to 600 m of the 2 km loop), so that a passage's window leaves part of the map out. With the
  // last 5 detections per landmark and with all of them.
  ScenarioOptions scenario_options;
  scenario_options.landmarks = 50;
  scenario_options.piece_min_m = 300.0;
  scenario_options.piece_max_m = 600.0;
  const Scenario scenario = *Scenario::Create(scenario_options);
  for (const int detections : {5, 0}) {
    SCOPED_TRACE(absl::StrCat("detections per landmark ", detections));
    MapUpdateOptions exact, windowed;
    exact.detections_per_landmark = windowed.detections_per_landmark = detections;
    windowed.window_hops = 1;
    windowed.max_subgraph_dim = 60;  // several subgraphs, so that the map is not one clique
    exact.max_subgraph_dim = 60;
    MapState exact_map, windowed_map;
    for (int p = 0; p < 8; ++p) {
      absl::StatusOr<PassageUpdate> e = ComputePassageUpdate(scenario.MakePassage(p), exact, exact_map);
      absl::StatusOr<PassageUpdate> w = ComputePassageUpdate(scenario.MakePassage(p), windowed, windowed_map);
      ASSERT_TRUE(e.ok() && w.ok()) << e.status() << w.status();
      exact_map.Apply(e->delta);
      windowed_map.Apply(w->delta);
    }
    ASSERT_EQ(exact_map.landmark_count(), windowed_map.landmark_count());
    int less_confident = 0;
    for (LandmarkId id : windowed_map.LandmarkIds()) {
      absl::StatusOr<Eigen::MatrixXd> marginal = JointCovariance(windowed_map, {id});
      ASSERT_TRUE(marginal.ok()) << marginal.status();
      const Eigen::Matrix2d difference = windowed_map.FindLandmark(id)->cov_en_m2 - *marginal;
      // (to 1e-6 m^2: the graph's East/North frame at the landmark and the map's at its anchor
      // differ by a rotation of offset / earth radius)
      EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(difference).eigenvalues().minCoeff(), -1e-6) << id;
      less_confident += difference.trace() > 1e-9;
      // A landmark outside a passage's window keeps its estimate where the exact update moves it
      // through its correlation with what the passage saw: measured up to 0.05 of its sigma with
      // the last 5 detections, 0.46 with all of them (0.77 m on sigmas of 3 m in this young map).
      const Landmark& exact_landmark = *exact_map.FindLandmark(id);
      const Eigen::Vector2d offset = EastNorthOffset(exact_landmark.position, windowed_map.FindLandmark(id)->position);
      EXPECT_LT(std::sqrt(offset.dot(exact_landmark.cov_en_m2.ldlt().solve(offset))), 0.75)
          << id << ": " << offset.norm() << " m";
    }
    EXPECT_GT(less_confident, 0) << "the windows lost some information";
  }
}

// The second-order bias correction of a well-conditioned passage moves its new landmarks by a
// small part of their sigmas: the default bound (1 sigma) holds none back, and the map is the one
// without the test. A bound below every correction holds them all back: the first passage of a
// map then has nothing it could estimate, and is refused as one whose rays pin nothing down.
TEST(ComputePassageUpdate, NewLandmarksTheBiasCorrectionMovesBeyondTheirSigmaAreHeldBack) {
  const Scenario scenario = MakeScenario(10);
  const Passage passage = scenario.MakePassage(0);
  const MapState empty;
  MapUpdateOptions options;
  options.max_new_landmark_bias_sigmas = 0.0;
  absl::StatusOr<PassageUpdate> untested = ComputePassageUpdate(passage, options, empty);
  ASSERT_TRUE(untested.ok()) << untested.status();
  ASSERT_GT(untested->summary.landmarks_created, 0);
  ASSERT_GT(untested->summary.max_bias_correction_m, 0.0);
  absl::StatusOr<PassageUpdate> by_default = ComputePassageUpdate(passage, MapUpdateOptions(), empty);
  ASSERT_TRUE(by_default.ok()) << by_default.status();
  EXPECT_EQ(by_default->summary.landmarks_created, untested->summary.landmarks_created);
  EXPECT_EQ(by_default->summary.landmarks_held_back, untested->summary.landmarks_held_back);
  for (const auto& [id, record] : untested->delta.landmarks) {
    ASSERT_EQ(by_default->delta.landmarks.count(id), 1u) << id;
    EXPECT_EQ(by_default->delta.landmarks.at(id).position.lat_deg, record.position.lat_deg) << id;
  }
  options.max_new_landmark_bias_sigmas = 1e-9;
  absl::StatusOr<PassageUpdate> strict = ComputePassageUpdate(passage, options, empty);
  ASSERT_FALSE(strict.ok());
  EXPECT_EQ(strict.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(strict.status().message().find("no landmark of the passage could be estimated"), std::string::npos)
      << strict.status();
  // What set them aside, for the operator.
  EXPECT_NE(strict.status().message().find("landmark(s) not pinned down by its rays"), std::string::npos)
      << strict.status();
}

TEST(ComputePassageUpdate, NewLandmarksNeedRaysSpanningTheMinimumParallax) {
  const Scenario scenario = MakeScenario(10);
  const Passage passage = scenario.MakePassage(0);
  MapUpdateOptions options;
  const MapState empty;
  absl::StatusOr<PassageUpdate> normal = ComputePassageUpdate(passage, options, empty);
  ASSERT_TRUE(normal.ok()) << normal.status();
  // The widest angle between a landmark's rays differs from landmark to landmark (0.4 rad leaves
  // 6 of these 10): a bound between the smallest and the largest leaves some of them out.
  options.min_new_landmark_parallax_rad = 0.4;
  absl::StatusOr<PassageUpdate> strict = ComputePassageUpdate(passage, options, empty);
  ASSERT_TRUE(strict.ok()) << strict.status();
  EXPECT_LT(strict->summary.landmarks_created, normal->summary.landmarks_created);
  EXPECT_GT(strict->summary.landmarks_created, 0);
  EXPECT_GT(strict->summary.detections_dropped, normal->summary.detections_dropped);
  options.min_new_landmark_parallax_rad = 1.49;  // no pair of rays of a forward camera spans this
  EXPECT_EQ(ComputePassageUpdate(passage, options, empty).status().code(), absl::StatusCode::kInvalidArgument);
  options.min_new_landmark_parallax_rad = -0.1;
  EXPECT_NE(options.Validate().message().find("min_new_landmark_parallax_rad"), std::string::npos);
}

TEST(MapUpdater, FoldsTheFactorsOfPassagesBeyondTheRetentionWithoutChangingTheMap) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions keep_all, retain;
  keep_all.warmup_passages = retain.warmup_passages = 0;
  keep_all.retain_passages = 0;
  retain.retain_passages = 2;
  MapState kept_map, folded_map;
  MapUpdater keeping(keep_all), folding(retain);
  for (int p = 0; p < 6; ++p) {
    const Passage passage = scenario.MakePassage(p);
    absl::StatusOr<PassageUpdate> a = keeping.Compute(passage, kept_map);
    absl::StatusOr<PassageUpdate> b = folding.Compute(passage, folded_map);
    ASSERT_TRUE(a.ok() && b.ok()) << a.status() << b.status();
    EXPECT_TRUE(a->delta.folded_factors.empty());
    EXPECT_EQ(b->delta.folded_factors.empty(), p < 2) << p;
    kept_map.Apply(a->delta);
    keeping.Applied(passage, a->delta);
    folded_map.Apply(b->delta);
    folding.Applied(passage, b->delta);
  }
  // Only the last two passages keep their factors; the estimate is the same to the last bit.
  std::vector<int64_t> ids;
  for (int p = 0; p < 6; ++p) {
    ids.clear();
    folded_map.AppendPassageFactorIds(scenario.MakePassage(p).vehicle_id, scenario.MakePassage(p).passage_id, &ids);
    EXPECT_EQ(ids.empty(), p < 4) << p;
  }
  for (LandmarkId id : kept_map.LandmarkIds()) {
    EXPECT_EQ(folded_map.FindLandmark(id)->position.lat_deg, kept_map.FindLandmark(id)->position.lat_deg);
    EXPECT_EQ(folded_map.FindLandmark(id)->position.lon_deg, kept_map.FindLandmark(id)->position.lon_deg);
  }
  // A map loaded with its factors: the updater knows which passages it retains.
  MapUpdater reloaded(retain, {}, 6, &folded_map);
  absl::StatusOr<PassageUpdate> next = reloaded.Compute(scenario.MakePassage(6), folded_map);
  ASSERT_TRUE(next.ok());
  ids.clear();
  folded_map.AppendPassageFactorIds(scenario.MakePassage(4).vehicle_id, scenario.MakePassage(4).passage_id, &ids);
  EXPECT_EQ(next->delta.folded_factors, ids) << "passage 4, the oldest retained, is folded next";
  retain.retain_passages = 1;
  retain.warmup_passages = 8;  // its joint solves need the first 127 passages again
  EXPECT_NE(retain.Validate().message().find("retain_passages"), std::string::npos);
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

// Applies the scenario's passages in `order` through a MapUpdater.
MapState ApplyInOrder(const Scenario& scenario, const std::vector<int>& order, const MapUpdateOptions& options,
                      std::vector<PassageUpdateSummary>* summaries = nullptr) {
  MapState map;
  MapUpdater updater(options);
  for (int i : order) {
    const Passage passage = scenario.MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok()) continue;
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
    if (summaries != nullptr) summaries->push_back(update->summary);
  }
  return map;
}

// Largest East/North distance between the two maps' estimates of a landmark.
double LargestOffsetM(const MapState& a, const MapState& b) {
  double largest = 0.0;
  for (LandmarkId id : a.LandmarkIds()) {
    EXPECT_NE(b.FindLandmark(id), nullptr) << id;
    if (b.FindLandmark(id) == nullptr) continue;
    largest = std::max(largest, EastNorthOffset(a.FindLandmark(id)->position, b.FindLandmark(id)->position).norm());
  }
  return largest;
}

TEST(ComputeBatchUpdate, SolvesThePassagesJointlyAndCountsWhoSawEachLandmark) {
  const Scenario scenario = MakeScenario(10);
  MapState map;
  absl::StatusOr<PassageUpdate> update =
      ComputeBatchUpdate({scenario.MakePassage(0), scenario.MakePassage(1)}, MapUpdateOptions(), map);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_EQ(update->summary.subgraphs, 1);
  EXPECT_EQ(update->summary.landmarks_created, 10);
  EXPECT_EQ(update->delta.base_version, 0);
  EXPECT_EQ(update->delta.version, 1);
  map.Apply(update->delta);
  map.ForEachLandmark([](const Landmark& l) {
    EXPECT_EQ(l.passages_seen, 2) << l.id;
    EXPECT_EQ(l.version, 1) << l.id;
    EXPECT_EQ(Eigen::LLT<Eigen::Matrix2d>(l.cov_en_m2).info(), Eigen::Success) << l.id;
  });
  EXPECT_EQ(map.factor_count(), 2u) << "one factor per passage";

  // Against a map that holds the first passage's result, the same solve replaces those records. It
  // starts elsewhere (from that map), so it matches to the solver's convergence: well under a
  // millimetre, against about a metre of uncertainty after two passages.
  MapState first;
  first.Apply(ComputeBatchUpdate({scenario.MakePassage(0)}, MapUpdateOptions(), first)->delta);
  absl::StatusOr<PassageUpdate> again =
      ComputeBatchUpdate({scenario.MakePassage(0), scenario.MakePassage(1)}, MapUpdateOptions(), first);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->summary.landmarks_updated, 10);
  EXPECT_EQ(again->delta.base_version, first.version());
  EXPECT_EQ(again->delta.version, first.version() + 1);
  first.Apply(again->delta);
  EXPECT_LT(LargestOffsetM(map, first), 1e-3);
}

TEST(MapUpdater, WarmUpIsJointThenUpdatesGoOnePassageAtATime) {
  const Scenario scenario = MakeScenario(25);
  MapUpdateOptions options;
  options.warmup_passages = 2;
  std::vector<PassageUpdateSummary> summaries;
  const MapState map = ApplyInOrder(scenario, {0, 1, 2}, options, &summaries);
  ASSERT_EQ(summaries.size(), 3u);
  EXPECT_EQ(summaries[0].subgraphs, 1);
  EXPECT_EQ(summaries[1].subgraphs, 1);
  EXPECT_GE(summaries[2].subgraphs, 2);  // cc-gsd subdivides a whole passage
  EXPECT_EQ(summaries[0].joint_passages, 1);
  EXPECT_EQ(summaries[1].joint_passages, 2);
  EXPECT_EQ(summaries[2].joint_passages, 0);
  EXPECT_EQ(map.FindLandmark(1)->passages_seen, 3);
}

TEST(MapUpdater, WarmUpMapDoesNotDependOnThePassageOrder) {
  // Passages applied one at a time to a young map each enter it as a Gaussian taken at a
  // still-poor estimate, so their order shows in the map; the joint warm-up solve removes that.
  const Scenario scenario = MakeScenario(10);
  const std::vector<int> forward = {0, 1, 2, 3}, shuffled = {2, 0, 3, 1};
  MapUpdateOptions joint;
  joint.warmup_passages = 8;
  const double joint_offset = LargestOffsetM(ApplyInOrder(scenario, forward, joint),
                                             ApplyInOrder(scenario, shuffled, joint));
  MapUpdateOptions sequential;
  sequential.warmup_passages = 0;
  const double sequential_offset = LargestOffsetM(ApplyInOrder(scenario, forward, sequential),
                                                  ApplyInOrder(scenario, shuffled, sequential));
  EXPECT_LT(joint_offset, 1e-4) << "sequential: " << sequential_offset;
  EXPECT_GT(sequential_offset, 1e-3) << "the scenario must be one where the order matters";
}

TEST(MapUpdater, ReSolvesAllPassagesJointlyAtEachDoublingOfTheirCount) {
  MapUpdateOptions options;  // warm-up 8, re-solves up to 128 passages
  std::vector<int64_t> joint;
  for (int64_t count = 1; count <= 300; ++count) {
    if (IsJointSolvePassage(count, options)) joint.push_back(count);
  }
  EXPECT_EQ(joint, (std::vector<int64_t>{1, 2, 3, 4, 5, 6, 7, 8, 16, 32, 64, 128}));
  EXPECT_EQ(JointSolvePassages(options), 127);
  options.relinearize_until_passages = 100;
  EXPECT_FALSE(IsJointSolvePassage(128, options));
  EXPECT_EQ(JointSolvePassages(options), 63);
  options.strategy = UpdateStrategy::kDecorrelated;
  EXPECT_TRUE(IsJointSolvePassage(8, options));
  EXPECT_FALSE(IsJointSolvePassage(16, options));
  EXPECT_EQ(JointSolvePassages(options), 7);
  options.strategy = UpdateStrategy::kCorrelated;
  options.relinearize_until_passages = 0;
  EXPECT_FALSE(IsJointSolvePassage(16, options));
  EXPECT_EQ(JointSolvePassages(options), 7);
  options.warmup_passages = 0;
  options.relinearize_until_passages = 128;
  EXPECT_FALSE(IsJointSolvePassage(1, options));
  EXPECT_EQ(JointSolvePassages(options), 0);
}

// Exclusions that bring the count of a map's passages back to a joint solve's bring no joint
// solve once the map has taken more passages than the joint solves need: the oldest may be folded
// into the base by then (retain_passages), and a joint solve of them would count them twice. In
// a young map they still do.
TEST(MapUpdater, ExclusionsBringNoJointSolveBackOnceTheMapOutgrewThem) {
  MapUpdateOptions options;
  options.warmup_passages = 2;
  options.relinearize_until_passages = 4;  // joint solves at passages 1, 2 and 4
  ASSERT_EQ(JointSolvePassages(options), 3);
  const auto passage = [](int i) {
    Passage p;
    p.vehicle_id = "v";
    p.passage_id = std::to_string(i);
    return p;
  };
  MapUpdater young(options);
  young.Applied(passage(1), MapDelta());
  young.Applied(passage(2), MapDelta());
  EXPECT_FALSE(young.joint_next()) << "passage 3 is sequential";
  young.Excluded("v", "2");
  EXPECT_TRUE(young.joint_next()) << "passage 2 again, in a young map";

  MapUpdater grown(options);
  for (int i = 1; i <= 6; ++i) grown.Applied(passage(i), MapDelta());
  EXPECT_FALSE(grown.joint_next());
  for (int i = 4; i <= 6; ++i) grown.Excluded("v", std::to_string(i));
  EXPECT_EQ(grown.applied_count(), 3);
  EXPECT_FALSE(grown.joint_next()) << "passage 4 again, but the map took 6";
}

TEST(MapUpdater, ReSolvedMapDoesNotDependOnWhichPassagesCameFirst) {
  // After a two-passage warm-up the third passage is applied on its own; the fourth re-solves all
  // four. Which two passages formed the warm-up then no longer matters.
  const Scenario scenario = MakeScenario(10);
  const std::vector<int> forward = {0, 1, 2, 3}, other = {2, 3, 1, 0};
  MapUpdateOptions resolved;
  resolved.warmup_passages = 2;
  resolved.relinearize_until_passages = 4;
  std::vector<PassageUpdateSummary> summaries;
  const double resolved_offset = LargestOffsetM(ApplyInOrder(scenario, forward, resolved, &summaries),
                                                ApplyInOrder(scenario, other, resolved));
  ASSERT_EQ(summaries.size(), 4u);
  EXPECT_GE(summaries[2].subgraphs, 2) << "applied on its own, subdivided";
  EXPECT_EQ(summaries[3].subgraphs, 1) << "the joint solve";
  EXPECT_EQ(summaries[3].joint_passages, 4);
  MapUpdateOptions warmup_only = resolved;
  warmup_only.relinearize_until_passages = 0;
  const double warmup_only_offset = LargestOffsetM(ApplyInOrder(scenario, forward, warmup_only),
                                                   ApplyInOrder(scenario, other, warmup_only));
  // The two joint solves start from maps up to 0.8 m apart and stop at the solver's tolerance.
  EXPECT_LT(resolved_offset, 1e-3) << "warm-up only: " << warmup_only_offset;
  EXPECT_GT(warmup_only_offset, 0.1) << "the scenario must be one where the order matters";
}

TEST(ComputePassageUpdate, LeavesOutDetectionsOfMapLandmarksPredictedNearTheImageBorder) {
  const Scenario scenario = MakeScenario(50);
  MapUpdateOptions all, margin;
  all.edge_margin_sigmas = 0.0;
  all.warmup_passages = margin.warmup_passages = 0;
  const Passage first = scenario.MakePassage(0);
  MapState map;
  absl::StatusOr<PassageUpdate> a = ComputePassageUpdate(first, all, map);
  absl::StatusOr<PassageUpdate> b = ComputePassageUpdate(first, margin, map);
  ASSERT_TRUE(a.ok() && b.ok());
  // New landmarks are placed from these very detections, so their predictions would select on
  // the detections' noise: the margin leaves them alone.
  EXPECT_EQ(a->summary.detections_used, b->summary.detections_used);
  map.Apply(a->delta);
  int used = 0, left_out = 0;
  for (int i = 1; i <= 20; ++i) {
    a = ComputePassageUpdate(scenario.MakePassage(i), all, map);
    b = ComputePassageUpdate(scenario.MakePassage(i), margin, map);
    ASSERT_TRUE(a.ok() && b.ok());
    used += a->summary.detections_used;
    left_out += a->summary.detections_used - b->summary.detections_used;
    EXPECT_EQ(b->summary.detections_dropped - a->summary.detections_dropped,
              a->summary.detections_used - b->summary.detections_used);
  }
  // Rare (10 of about 5000 here), but the same landmarks on every passage.
  EXPECT_GT(left_out, 0) << "the last detections of some roadside landmarks come close to the border";
  EXPECT_LT(left_out, used / 100);
}

TEST(ComputeBatchUpdate, LocalisesThePosesAgainstTheMapNotAgainstItsOwnGuess) {
  // The first passage of this scenario places one landmark 78 m off (nearly parallel rays). When
  // the joint solve localised the passage's poses against its own starting guess, that landmark
  // held as an exact anchor turned the poses of a sharp turn by 1.6 rad and the solve diverged
  // (most landmarks tens of metres off, some kilometres).
  const Scenario scenario = MakeScenario(75, 3);
  MapState map;
  absl::StatusOr<PassageUpdate> joint = ComputeBatchUpdate({scenario.MakePassage(0)}, MapUpdateOptions(), map);
  ASSERT_TRUE(joint.ok()) << joint.status();
  EXPECT_FALSE(joint->summary.joint_rejected);
  map.Apply(joint->delta);
  EXPECT_LT(EvaluateMap(map, scenario.landmarks()).mean_dist_err_m, 5.0);
}

TEST(ComputeBatchUpdate, FallsBackToTheSequentialUpdateWhenTheJointSolutionLeavesItsConfidenceRegion) {
  const Scenario scenario = MakeScenario(25);
  MapState map;
  MapUpdater updater(MapUpdateOptions{});
  const std::vector<Passage> passages = {scenario.MakePassage(0), scenario.MakePassage(1)};
  map.Apply(updater.Compute(passages[0], map)->delta);
  MapUpdateOptions strict;
  strict.max_joint_mahalanobis2 = 1e-12;  // no two solutions agree that closely
  strict.inflation_test_sigmas = 0.0;     // and nothing tells whether the joint solution fits its passages
  absl::StatusOr<PassageUpdate> guarded = ComputeBatchUpdate(passages, strict, map);
  absl::StatusOr<PassageUpdate> sequential = ComputePassageUpdate(passages[1], strict, map);
  ASSERT_TRUE(guarded.ok() && sequential.ok());
  EXPECT_TRUE(guarded->summary.joint_rejected);
  EXPECT_EQ(guarded->delta.version, sequential->delta.version);
  MapState a = map, b = map;
  a.Apply(guarded->delta);
  b.Apply(sequential->delta);
  EXPECT_LT(LargestOffsetM(a, b), 1e-7);
  absl::StatusOr<PassageUpdate> joint = ComputeBatchUpdate(passages, MapUpdateOptions(), map);
  ASSERT_TRUE(joint.ok());
  EXPECT_FALSE(joint->summary.joint_rejected);
  EXPECT_EQ(joint->delta.version, map.version() + 1);
}

// The guard judges joint solutions that do not fit their passages (a solve in a wrong minimum): one
// that fits every passage's measurements is used even where it moves the map beyond the guard, and
// one that leaves a passage's residuals far beyond its noise is not.
TEST(ComputeBatchUpdate, TheGuardJudgesOnlyJointSolutionsThatDoNotFitTheirPassages) {
  const Scenario scenario = MakeScenario(25);
  MapState map;
  MapUpdater updater(MapUpdateOptions{});
  map.Apply(updater.Compute(scenario.MakePassage(0), map)->delta);
  MapUpdateOptions strict;
  strict.max_joint_mahalanobis2 = 1e-12;
  const std::vector<Passage> clean = {scenario.MakePassage(0), scenario.MakePassage(1)};
  absl::StatusOr<PassageUpdate> fits = ComputeBatchUpdate(clean, strict, map);
  ASSERT_TRUE(fits.ok()) << fits.status();
  EXPECT_FALSE(fits->summary.joint_rejected);
  EXPECT_EQ(fits->summary.max_variance_factor, 1.0);
  EXPECT_EQ(fits->summary.joint_passages, 2);

  // The second passage's fixes 40 m north for a minute, declared as usual.
  Passage burst = scenario.MakePassage(1);
  const double t0 = burst.gnss.front().t_s;
  for (GnssFix& fix : burst.gnss) {
    if (fix.t_s > t0 + 30.0 && fix.t_s < t0 + 90.0) fix.lat_deg += 40.0 / 111320.0;
  }
  absl::StatusOr<PassageUpdate> misfit = ComputeBatchUpdate({clean[0], burst}, strict, map);
  ASSERT_TRUE(misfit.ok()) << misfit.status();
  EXPECT_TRUE(misfit->summary.joint_rejected);
}

TEST(MapUpdater, RestoredFromTheAppliedPassagesItContinuesExactlyAsBefore) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options;
  options.warmup_passages = 2;
  options.relinearize_until_passages = 4;  // the fourth passage re-solves the first three with it
  MapState map;
  MapUpdater original(options);
  std::vector<Passage> applied;
  for (int i = 0; i < 3; ++i) {
    applied.push_back(scenario.MakePassage(i));
    const MapDelta delta = original.Compute(applied.back(), map)->delta;
    map.Apply(delta);
    original.Applied(applied.back(), delta);
  }
  const MapUpdater restored(options, applied, 3);
  EXPECT_FALSE(restored.warming_up());
  EXPECT_TRUE(restored.joint_next());
  absl::StatusOr<PassageUpdate> a = original.Compute(scenario.MakePassage(3), map);
  absl::StatusOr<PassageUpdate> b = restored.Compute(scenario.MakePassage(3), map);
  ASSERT_TRUE(a.ok() && b.ok());
  MapState from_a = map, from_b = map;
  from_a.Apply(a->delta);
  from_b.Apply(b->delta);
  // The same arithmetic up to summation order (Ceres orders some blocks by address), which can move
  // where the solver stops within its tolerance: 1e-10 relative on coordinates of up to 1 km.
  EXPECT_LT(LargestOffsetM(from_a, from_b), 1e-7);
  // A map past its last joint solve needs none of its passages back.
  EXPECT_FALSE(MapUpdater(options, {}, 4).joint_next());
  // One restored without the passages it needs applies the next passage on its own rather than
  // re-solving without them.
  EXPECT_FALSE(MapUpdater(options, {}, 3).joint_next());
  EXPECT_TRUE(MapUpdater(MapUpdateOptions()).warming_up()) << "on by default";
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// The defaults without the young map's joint solves: every passage is applied on its own.
MapUpdateOptions SequentialUpdatesOnly() {
  MapUpdateOptions options;
  options.warmup_passages = 0;
  options.relinearize_until_passages = 0;
  return options;
}

struct CityMapErrors {
  double max_m = 0.0;
  double max_mahalanobis = 0.0;  // of the error, in the landmark's marginal covariance
  double mean_nees_per_dof = 0.0;  // marginal, mean over the mapped landmarks
  int held_back = 0;
  int disagreeing = 0;
  int outliers = 0;
};

// Applies the first `passages` city passages one at a time to an empty map; errors against the
// truth. `after_each` sees the map after every passage.
CityMapErrors ApplyCityPassages(const CityScenarioOptions& city, int passages, const MapUpdateOptions& options,
                                const std::function<void(const MapState&)>& after_each = nullptr,
                                const FaultOptions& faults = FaultOptions()) {
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  MapState map;
  CityMapErrors out;
  for (int i = 0; i < passages; ++i) {
    Passage passage = scenario->MakePassage(i);
    InjectFaults(faults, i, scenario->frame(), &passage);
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(passage, options, map);
    EXPECT_TRUE(update.ok()) << i << ": " << update.status();
    if (!update.ok()) continue;
    out.outliers += update->summary.detections_outliers;
    out.held_back += update->summary.landmarks_held_back;
    out.disagreeing += update->summary.landmarks_disagreeing;
    map.Apply(update->delta);
    if (after_each) after_each(map);
  }
  map.ForEachLandmark([&](const Landmark& l) {
    const Eigen::Vector2d truth = scenario->landmarks()[l.id - 1].position_m;
    const Eigen::Vector2d error = scenario->frame().ToLocal(l.position) - truth;
    const double mahalanobis2 = error.dot(l.cov_en_m2.ldlt().solve(error));
    out.max_m = std::max(out.max_m, error.norm());
    out.max_mahalanobis = std::max(out.max_mahalanobis, std::sqrt(mahalanobis2));
    out.mean_nees_per_dof += 0.5 * mahalanobis2 / map.landmark_count();
  });
  return out;
}

TEST(ComputePassageUpdate, EveryCommittedMapHasPositiveDefiniteInformationAndItsStoredEstimate) {
  CityScenarioOptions city;
  city.route_length_m = 600.0;
  MapUpdateOptions options = SequentialUpdatesOnly();
  int checked = 0;
  ApplyCityPassages(city, 8, options, [&](const MapState& map) {
    // The whole map in one window: its factorisation fails unless the information is positive
    // definite.
    absl::StatusOr<MapWindow> window = MapWindow::Build(map, map.LandmarkIds(), MapWindowOptions());
    ASSERT_TRUE(window.ok()) << "after passage " << checked << ": " << window.status();
    ASSERT_TRUE(window->offsets().allFinite());
    for (size_t i = 0; i < window->landmarks().size(); ++i) {
      const Landmark& l = *map.FindLandmark(window->landmarks()[i]);
      EXPECT_LT((window->offsets().segment<2>(2 * i) - l.Offset()).norm(), 1e-5) << l.id;
    }
    ++checked;
  });
  EXPECT_EQ(checked, 8);
}

// Applies the first `passages` city passages through a MapUpdater (its joint solves included) to
// an empty map; `after_each` sees the map after every passage.
MapState ApplyCityPassagesThroughUpdater(const CityScenarioOptions& city, int passages, const MapUpdateOptions& options,
                                         const std::function<void(int, const MapState&)>& after_each = nullptr) {
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  MapState map;
  if (!scenario.ok()) return map;
  MapUpdater updater(options);
  for (int i = 0; i < passages; ++i) {
    const Passage passage = scenario->MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << "passage " << i << ": " << update.status();
    if (!update.ok()) continue;
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
    if (after_each) after_each(i, map);
  }
  return map;
}

// The young map's joint solves replace the factors of the passages they re-solve: a landmark one
// of those factors reached, but whose detections the joint solve cannot use, must not be left
// without information (the map could no longer be factorised around it).
TEST(MapUpdater, JointSolvesOfAYoungCityMapLeaveItsInformationPositiveDefinite) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  city.vehicle_yaw_bias_sigma_rad = 0.0087;
  MapUpdateOptions options;
  options.estimate_camera_yaw = true;
  ApplyCityPassagesThroughUpdater(city, 8, options, [](int i, const MapState& map) {
    absl::StatusOr<MapWindow> window = MapWindow::Build(map, map.LandmarkIds(), MapWindowOptions());
    ASSERT_TRUE(window.ok()) << "after passage " << i << ": " << window.status();
    ASSERT_TRUE(window->offsets().allFinite());
  });
}

// The mean and the largest distance of `map`'s landmarks from the truth (m).
std::pair<double, double> MeanAndWorstError(const CityScenario& scenario, const MapState& map) {
  double worst = 0.0, sum = 0.0;
  map.ForEachLandmark([&](const Landmark& l) {
    const double error = (scenario.frame().ToLocal(l.position) - scenario.landmarks()[l.id - 1].position_m).norm();
    worst = std::max(worst, error);
    sum += error;
  });
  return {sum / map.landmark_count(), worst};
}

// The young map's joint solves on the street grid, vehicles with their own sensor rates: before
// they estimated only what the sequential updates had created and checked every landmark they
// moved, a few landmarks (placed by two nearly parallel rays) ended kilometres off
// (here: worst 13,951 m, mean 19.6 m; measured after: worst 12.8 m, mean 1.27 m).
TEST(MapUpdater, JointSolvesOfAYoungCityMapPlaceNoLandmarkFarOff) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  city.rate_variation = 0.2;
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  const MapState map = ApplyCityPassagesThroughUpdater(city, 16, MapUpdateOptions{});
  const auto [mean, worst] = MeanAndWorstError(*scenario, map);
  std::printf("city, 16 passages with joint solves: %zu landmarks, mean error %.3f m, worst %.2f m\n",
              map.landmark_count(), mean, worst);
  EXPECT_LT(mean, 2.0);
  EXPECT_LT(worst, 30.0);
}

// The default city driven on routes of 1 km, its layout and fleet drawn from `seed`.
CityScenarioOptions OneKilometreRoutes(uint64_t seed, NoiseConfig noise) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  city.seed = seed;
  city.layout_seed = seed;
  city.noise = noise;
  return city;
}

// Two nearly parallel rays fit a landmark anywhere along them. The joint solve of this young map's
// first two passages (AR(1) GNSS) moved one 98 km along its rays, fitting every passage's
// measurements, and the guard took it on that ground: after 60 passages the map's mean error was
// 98.9 m. A joint solution that leaves a landmark undetermined is not taken.
TEST(MapUpdater, AJointSolveThatLeavesALandmarkUndeterminedIsNotTaken) {
  const CityScenarioOptions city = OneKilometreRoutes(2, NoiseConfig::kGnssAr1);
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  const MapState map = ApplyCityPassagesThroughUpdater(city, 2, MapUpdateOptions{});
  const auto [mean, worst] = MeanAndWorstError(*scenario, map);
  std::printf("AR(1) city, 2 passages: mean error %.3f m, worst %.2f m\n", mean, worst);
  EXPECT_LT(worst, 100.0);
  map.ForEachLandmark([](const Landmark& l) {
    EXPECT_LT(std::sqrt(l.cov_en_m2.trace()), 150.0) << l.id;
  });
}

// A fleet of several car models, AR(1) GNSS: the joint solve of the young map's first 8 passages
// fitted every passage's measurements but slid landmark 687 264 m along its rays from the
// sequential estimate, where no passage's rays pin it down, and the guard took it on that ground
// (after 60 passages it was still 18 m off; here worst 252.7 m after 8). Such a landmark is held
// back and the passages solved again without it; here each of three rounds leaves another one
// unpinned and the sequential update is kept (worst 20.4 m).
TEST(MapUpdater, AJointSolveHoldsBackLandmarksItsRaysDoNotPinDown) {
  CityScenarioOptions city = OneKilometreRoutes(8, NoiseConfig::kGnssAr1);
  city.vary_calibration = true;
  city.vehicle_yaw_bias_sigma_rad = 0.0087;
  city.rate_variation = 0.2;
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  MapUpdateOptions options;
  options.estimate_camera_yaw = true;
  const MapState map = ApplyCityPassagesThroughUpdater(city, 8, options);
  const auto [mean, worst] = MeanAndWorstError(*scenario, map);
  std::printf("varied fleet, AR(1) city, 8 passages: mean error %.3f m, worst %.2f m\n", mean, worst);
  EXPECT_LT(worst, 50.0);
}

// Every passage loses its GNSS for 20 to 60 s. A subgraph cut inside the outage was tied by
// odometry to fixes at one end only, its heading nearly free: in this seed the 12th passage placed
// a street 100 m and more off with sigmas of 1.5 m (mean error 4.4 m after 13 passages, and 2.2 m,
// NEES/dof 55, after 60).
TEST(MapUpdater, PassagesThroughGnssOutagesPlaceNoLandmarkFarOff) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  city.seed = 4;
  city.layout_seed = 4;
  city.gnss_outage_probability = 1.0;
  city.gnss_outage_min_s = 20.0;
  city.gnss_outage_max_s = 60.0;
  absl::StatusOr<CityScenario> scenario = CityScenario::Create(city);
  ASSERT_TRUE(scenario.ok()) << scenario.status();
  const MapState map = ApplyCityPassagesThroughUpdater(city, 13, MapUpdateOptions{});
  const auto [mean, worst] = MeanAndWorstError(*scenario, map);
  std::printf("city with GNSS outages, 13 passages: %zu landmarks, mean error %.3f m, worst %.2f m\n",
              map.landmark_count(), mean, worst);
  EXPECT_LT(mean, 2.0);
  EXPECT_LT(worst, 20.0);
}

// Every vehicle's encoders off by its own 2% (sigma) of the speed. Taken as exact, the errors
// stretch and shrink each vehicle's streets; with the scale of the distance travelled estimated in
// every subgraph the map stays consistent.
TEST(ComputePassageUpdate, WheelSpeedScaleErrorsAreEstimated) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  city.vehicle_speed_scale_sigma = 0.02;
  MapUpdateOptions options = SequentialUpdatesOnly();
  const CityMapErrors ignored = ApplyCityPassages(city, 16, options);
  options.speed_scale_prior_sigma = 0.03;
  const CityMapErrors estimated = ApplyCityPassages(city, 16, options);
  std::printf("wheel-speed scale errors, 16 passages: NEES/dof %.2f ignored, %.2f estimated\n",
              ignored.mean_nees_per_dof, estimated.mean_nees_per_dof);
  EXPECT_GT(ignored.mean_nees_per_dof, 2.0);
  EXPECT_LT(estimated.mean_nees_per_dof, 1.3);
  EXPECT_LT(estimated.max_mahalanobis, ignored.max_mahalanobis);
}

TEST(ComputePassageUpdate, DetectionsReportedUnderANeighboursIdAreSetAsideAsOutliers) {
  CityScenarioOptions city;
  city.route_length_m = 1000.0;
  MapUpdateOptions options = SequentialUpdatesOnly();
  const CityMapErrors clean = ApplyCityPassages(city, 12, options);
  EXPECT_EQ(clean.outliers, 0) << "no honest detection is 5 sigma off";
  FaultOptions faults;
  faults.mislabel_rate = 0.02;
  const CityMapErrors mislabelled = ApplyCityPassages(city, 12, options, nullptr, faults);
  EXPECT_GT(mislabelled.outliers, 0);
  options.max_detection_residual_sigmas = 0.0;
  const CityMapErrors unprotected = ApplyCityPassages(city, 12, options, nullptr, faults);
  // Measured: NEES/dof 0.76 clean, 1.49 with 2% of the detections mislabelled, 3.59 without the test.
  EXPECT_LT(mislabelled.mean_nees_per_dof, unprotected.mean_nees_per_dof);
}

TEST(ComputePassageUpdate, ShortCityDrivesLeaveNoLandmarkFarOff) {
  // Pieces of 600 m: landmarks approached head-on at a turn, seen by two or three frames, which
  // once were created tens to thousands of metres off and then dragged their neighbours along.
  CityScenarioOptions city;
  city.route_length_m = 600.0;
  MapUpdateOptions options = SequentialUpdatesOnly();
  const CityMapErrors errors = ApplyCityPassages(city, 20, options);
  EXPECT_GT(errors.held_back, 0) << "the scenario has weak new landmarks";
  // Measured: at most 12.8 m, 4.9 sigma, NEES/dof 1.19; without the creation and disagreement
  // rules 43 km, 105 sigma, NEES/dof 25.
  EXPECT_LT(errors.max_m, 50.0);
  EXPECT_LT(errors.max_mahalanobis, 8.0);
  EXPECT_LT(errors.mean_nees_per_dof, 1.5);
}


}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// The map after `passages` loop passages through a MapUpdater (its defaults: warm-up and
// re-solves), with passage `bad` (if >= 0) spoilt by `spoil`. `joint`, when given, receives the
// indices of the passages applied by a joint solve.
MapState LoopMapWithFaultyPassage(int passages, int bad, const std::function<void(Passage*)>& spoil,
                                  std::vector<int>* joint = nullptr, const MapUpdateOptions& options = {}) {
  const Scenario scenario = MakeScenario(25);
  MapUpdater updater(options, {}, 0);
  MapState map;
  for (int i = 0; i < passages; ++i) {
    Passage passage = scenario.MakePassage(i);
    if (i == bad) spoil(&passage);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    EXPECT_TRUE(update.ok()) << i << ": " << update.status();
    if (!update.ok()) continue;
    if (joint != nullptr && update->summary.joint_passages > 0) joint->push_back(i);
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
  }
  return map;
}

// The same with passage `bad` reporting landmark `from`'s detections as `to`'s.
MapState LoopMapWithMislabelledPassage(int passages, int bad, LandmarkId from, LandmarkId to,
                                       std::vector<int>* joint = nullptr) {
  return LoopMapWithFaultyPassage(
      passages, bad,
      [&](Passage* passage) {
        for (Detection& d : passage->detections) {
          if (d.landmark_id == from) d.landmark_id = to;
        }
      },
      joint);
}

// With the subgraph-level defences off (outliers, disagreeing landmarks, the consistency tests), a
// passage that reports one landmark's detections under a neighbour's id drags the neighbour metres
// away; the whole-update gate refuses it, naming the landmark, and nothing of it is applied. (The
// camera's own consistency test alone weights such a passage's rays down enough that the
// neighbour moves by 0.2 of its sigmas.)
TEST(ComputePassageUpdate, AnUpdateMovingAnEstablishedLandmarkBeyondTheGateIsRefusedWhole) {
  constexpr LandmarkId kFrom = 5, kTo = 6;
  const Scenario scenario = MakeScenario(25);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.max_detection_residual_sigmas = 0.0;
  options.max_landmark_shift_mahalanobis2 = 0.0;
  options.inflation_test_sigmas = 0.0;
  options.sensor_test_sigmas = 0.0;
  MapState map;
  for (int i = 0; i < 12; ++i) {
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(scenario.MakePassage(i), options, map);
    ASSERT_TRUE(update.ok()) << i << ": " << update.status();
    map.Apply(update->delta);
  }
  Passage bad = scenario.MakePassage(12);
  for (Detection& d : bad.detections) {
    if (d.landmark_id == kFrom) d.landmark_id = kTo;
  }
  MapUpdateOptions unguarded = options;
  unguarded.max_update_shift_mahalanobis2 = 0.0;
  absl::StatusOr<PassageUpdate> applied = ComputePassageUpdate(bad, unguarded, map);
  ASSERT_TRUE(applied.ok()) << applied.status();
  const Landmark& before = *map.FindLandmark(kTo);
  const Eigen::Vector2d shift = EastNorthOffset(before.position, applied->delta.landmarks.at(kTo).position);
  ASSERT_GT(shift.dot(before.cov_en_m2.ldlt().solve(shift)), 9.0) << "the passage is not hostile enough to test";

  absl::StatusOr<PassageUpdate> refused = ComputePassageUpdate(bad, options, map);
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition) << refused.status();
  // It names the landmarks that would have moved furthest (the whole stretch is dragged along).
  EXPECT_NE(refused.status().message().find("established landmark(s) further than 3.0 of their sigmas: landmark "),
            std::string::npos)
      << refused.status();
  EXPECT_NE(refused.status().message().find("the map is unchanged"), std::string::npos);
  // An honest passage passes the same gate.
  EXPECT_TRUE(ComputePassageUpdate(scenario.MakePassage(12), options, map).ok());
}

TEST(MapUpdater, AMislabelledPassageDoesNotMoveTheLandmarkItNamesWrongly) {
  constexpr LandmarkId kFrom = 5, kTo = 6;
  // Right after the mislabelled passage, and (the 4th of the map) once the map went on to 40
  // passages through its joint solves at 8, 16 and 32 passages.
  for (const auto& [bad, passages] : std::vector<std::pair<int, int>>{{3, 4}, {15, 16}, {39, 40}, {3, 40}}) {
    const MapState clean = LoopMapWithMislabelledPassage(passages, -1, kFrom, kTo);
    std::vector<int> joint;
    const MapState map = LoopMapWithMislabelledPassage(passages, bad, kFrom, kTo, &joint);
    if (passages == 40) {  // the re-solves at 8, 16 and 32 passages still run (measured: only the
                           // mislabelled passage itself is then taken sequentially)
      for (int i : {7, 15, 31}) EXPECT_NE(std::find(joint.begin(), joint.end(), i), joint.end()) << i;
    }
    const Landmark& a = *clean.FindLandmark(kTo);
    const Landmark& b = *map.FindLandmark(kTo);
    const Eigen::Vector2d difference = EastNorthOffset(a.position, b.position);
    const double sigmas = std::sqrt(difference.dot(a.cov_en_m2.ldlt().solve(difference)));
    // Measured: 0.18, 0.32 and 0.28 sigma (the solve's consistency test down-weights the passage).
    EXPECT_LT(sigmas, 3.0) << "mislabelled passage " << bad << " of " << passages << ": " << difference.norm()
                           << " m";
    std::printf("mislabelled passage %d of %d: landmark %lld %.3f m, %.2f sigma from the clean map's\n", bad,
                passages, static_cast<long long>(kTo), difference.norm(), sigmas);
  }
}

// A young map's passage whose camera reports, beside each true detection, two of landmarks picked
// at random at random pixels (a hostile upload), and whose arrival re-solves the map's first 32
// passages jointly. Its sequential update sets them aside as outliers; the joint solve took them
// in, down-weighted by the camera's consistency test, and its solution was used: the 40-passage
// map ended 2.19 sigmas from the clean one at the worst landmark. The joint solve now sets aside
// what lies beyond 5 pixel sigmas at its solution too; here what is left still moves a landmark
// beyond the guard, which keeps the sequential update (measured: 0.54 sigma). With two thirds of
// its detections false the passage is now refused whole (the next test); here that rule is off.
TEST(MapUpdater, AYoungMapsJointSolveDoesNotTakeInAPassagesFalseDetections) {
  const auto garbage = [](Passage* passage) {
    std::mt19937 rng(7);
    std::uniform_int_distribution<LandmarkId> any(1, 25);
    std::uniform_real_distribution<double> pixel(0.0, passage->calibration.image_width_px);
    std::vector<Detection> spoilt;
    for (const Detection& d : passage->detections) {
      spoilt.push_back(d);
      for (int k = 0; k < 2; ++k) spoilt.push_back({d.t_s, any(rng), pixel(rng)});
    }
    passage->detections = spoilt;
  };
  MapUpdateOptions options;
  options.max_unfit_detection_fraction = 0.0;
  const MapState clean = LoopMapWithFaultyPassage(40, -1, garbage, nullptr, options);
  const MapState map = LoopMapWithFaultyPassage(40, 31, garbage, nullptr, options);
  double worst = 0.0;
  clean.ForEachLandmark([&](const Landmark& a) {
    const Landmark* b = map.FindLandmark(a.id);
    ASSERT_NE(b, nullptr) << a.id;
    const Eigen::Vector2d difference = EastNorthOffset(a.position, b->position);
    worst = std::max(worst, std::sqrt(difference.dot(a.cov_en_m2.ldlt().solve(difference))));
  });
  std::printf("a young map's passage with false detections: the map at most %.2f sigma from the clean one\n", worst);
  EXPECT_LT(worst, 1.0);
}

// A passage whose camera reports every detection under a landmark id picked at random (a hostile
// or broken upload). It arrived in the young map's warm-up (its 4th passage: the joint solve of the
// first 4 took it in, moving landmarks by 2 to 3 sigmas from the map without it) and at the 16th
// (a re-solve; 2 sigmas). Most of its detections do not fit, so it is refused whole wherever it
// arrives, in a mature map too, and the map is the one its passages give without it.
TEST(MapUpdater, APassageMostOfWhoseDetectionsDoNotFitIsRefusedWhole) {
  const auto random_ids = [](Passage* passage) {
    std::mt19937 rng(2);
    std::uniform_int_distribution<LandmarkId> any(1, 25);
    for (Detection& d : passage->detections) d.landmark_id = any(rng);
  };
  const Scenario scenario = MakeScenario(25);
  for (int bad : {3, 15, 40}) {
    MapUpdater updater(MapUpdateOptions(), {}, 0);
    MapUpdater reference_updater(MapUpdateOptions(), {}, 0);
    MapState map, reference;
    for (int i = 0; i <= bad + 2; ++i) {
      Passage passage = scenario.MakePassage(i);
      if (i == bad) {
        random_ids(&passage);
        absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
        ASSERT_TRUE(absl::IsFailedPrecondition(update.status())) << bad << ": " << update.status();
        EXPECT_NE(update.status().message().find("detections do not fit"), absl::string_view::npos)
            << update.status();
        continue;
      }
      for (auto [u, m] : {std::pair{&updater, &map}, std::pair{&reference_updater, &reference}}) {
        absl::StatusOr<PassageUpdate> update = u->Compute(passage, *m);
        ASSERT_TRUE(update.ok()) << i << ": " << update.status();
        m->Apply(update->delta);
        u->Applied(passage, update->delta);
      }
    }
    ASSERT_EQ(map.landmark_count(), reference.landmark_count());
    reference.ForEachLandmark([&](const Landmark& a) {
      const Landmark* b = map.FindLandmark(a.id);
      ASSERT_NE(b, nullptr) << a.id;
      EXPECT_LT(EastNorthOffset(a.position, b->position).norm(), 1e-9) << bad << ": landmark " << a.id;
    });
  }
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

TEST(ComputePassageRelinearization, TakenAtTheEstimateItWasTakenAtItChangesTheMapOnlyBySolverTolerance) {
  const Scenario scenario = MakeScenario(25);
  MapUpdateOptions options = SequentialUpdatesOnly();
  MapState map;
  for (int i = 0; i < 4; ++i) map.Apply(ComputePassageUpdate(scenario.MakePassage(i), options, map)->delta);
  const Passage last = scenario.MakePassage(3);
  absl::StatusOr<PassageUpdate> again = ComputePassageRelinearization(last, options, map);
  ASSERT_TRUE(again.ok()) << again.status();
  MapState relinearized = map;
  relinearized.Apply(again->delta);
  EXPECT_EQ(relinearized.landmark_count(), map.landmark_count());
  double largest_m = 0.0;
  map.ForEachLandmark([&](const Landmark& l) {
    largest_m = std::max(largest_m, EastNorthOffset(l.position, relinearized.FindLandmark(l.id)->position).norm());
  });
  EXPECT_LT(largest_m, 1e-8);  // measured: 9e-11 m
  std::vector<int64_t> factors;
  relinearized.AppendPassageFactorIds(last.vehicle_id, last.passage_id, &factors);
  EXPECT_FALSE(factors.empty());
  for (int64_t id : factors) EXPECT_GT(id, map.last_factor_id()) << "the passage's factors are new ones";
}

// On a young street grid a landmark may be known mostly from one passage: without it, what is left
// fixes it worse than a new landmark must be, and the passage cannot be excluded. Its
// re-linearisation gives that information back in the same change, so it goes ahead there: the
// young streets are where the map has moved most since their factors were taken.
TEST(ComputePassageRelinearization, GoesAheadWhereExcludingThePassageWouldLeaveALandmarkUndetermined) {
  CityScenarioOptions city_options;
  city_options.route_length_m = 600.0;
  const CityScenario city = *CityScenario::Create(city_options);
  const MapUpdateOptions options = SequentialUpdatesOnly();
  MapState map;
  std::vector<Passage> applied;
  for (int i = 0; i < 8; ++i) {
    applied.push_back(city.MakePassage(i));
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(applied.back(), options, map);
    ASSERT_TRUE(update.ok()) << update.status();
    map.Apply(update->delta);
  }
  int refused = 0, relinearized = 0;
  double largest_move_m = 0.0;
  for (const Passage& passage : applied) {
    absl::StatusOr<PassageUpdate> exclusion =
        ComputePassageExclusion(passage.vehicle_id, passage.passage_id, options, map);
    if (exclusion.ok()) continue;
    ASSERT_TRUE(absl::IsFailedPrecondition(exclusion.status())) << exclusion.status();
    ASSERT_NE(exclusion.status().message().find("left undetermined"), absl::string_view::npos) << exclusion.status();
    ++refused;
    absl::StatusOr<PassageUpdate> again = ComputePassageRelinearization(passage, options, map);
    if (!again.ok()) {
      // Only where what is left is numerically singular (a landmark free along a ray).
      EXPECT_NE(again.status().message().find("left undetermined"), absl::string_view::npos) << again.status();
      continue;
    }
    ++relinearized;
    MapState after = map;
    after.Apply(again->delta);
    after.ForEachLandmark([&](const Landmark& l) {
      if (const Landmark* before = map.FindLandmark(l.id)) {
        largest_move_m = std::max(largest_move_m, EastNorthOffset(before->position, l.position).norm());
      }
      EXPECT_TRUE(l.Offset().allFinite() && l.cov_en_m2.allFinite()) << "landmark " << l.id;
      EXPECT_GT(Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(l.cov_en_m2).eigenvalues()(0), 0.0)
          << "landmark " << l.id;
    });
    // The whole map in one window: its factorisation fails unless the information is positive
    // definite, and its solve is the stored estimate.
    absl::StatusOr<MapWindow> window = MapWindow::Build(after, after.LandmarkIds(), MapWindowOptions());
    ASSERT_TRUE(window.ok()) << passage.passage_id << ": " << window.status();
    for (size_t i = 0; i < window->landmarks().size(); ++i) {
      const Landmark& l = *after.FindLandmark(window->landmarks()[i]);
      EXPECT_LT((window->offsets().segment<2>(2 * i) - l.Offset()).norm(), 1e-5) << l.id;
    }
  }
  std::printf("%d of 8 passages cannot be excluded; %d of them re-linearised, moving a landmark by %.3f m at most\n",
              refused, relinearized, largest_move_m);
  EXPECT_GT(relinearized, 0) << "a re-linearisation goes ahead where the exclusion is refused";
}

// A map built through a MapUpdater, re-linearising in memory as `mapsim` does.
struct RelinearizingMap {
  explicit RelinearizingMap(const MapUpdateOptions& options) : updater(options) {}
  // Applies `passage` to the map; false (with a test failure) when it could not be.
  bool Take(Passage passage) {
    applied.push_back(std::move(passage));
    absl::StatusOr<PassageUpdate> update = updater.Compute(applied.back(), map);
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok()) return false;
    map.Apply(update->delta);
    updater.Applied(applied.back(), update->delta);
    return true;
  }
  // The updater's re-linearisations of the stale passages; how many were applied.
  int Relinearize() {
    return RelinearizeStaleInMemory([this](const MapUpdater::PassageKey& key) { return PassageOf(key); }, &updater,
                                    &map);
  }
  absl::StatusOr<Passage> PassageOf(const MapUpdater::PassageKey& key) const {
    for (const Passage& p : applied) {
      if (p.vehicle_id == key.first && p.passage_id == key.second) return p;
    }
    return absl::NotFoundError("not applied");
  }

  MapUpdater updater;
  MapState map;
  std::vector<Passage> applied;
};

// A re-linearisation may go ahead where the map without the passage fixes a landmark less than an
// exclusion requires, but only if the passage taken again fixes it as required: on this young grid
// (seed 5, the eastern district not yet driven) one set such a landmark aside, left it free along
// a ray (9.5 m sigma), and later passages dragged it 703 m off within 10 passages (measured with
// the check: worst 11.7 m; 13.6 m when such passages were not re-linearised at all).
TEST(MapUpdater, RelinearizingAYoungCityMapMovesNoLandmarkFarOff) {
  CityScenarioOptions city_options;
  city_options.route_length_m = 1000.0;
  city_options.seed = city_options.layout_seed = 5;
  city_options.late_blocks_x = 2;
  city_options.late_from_passage = 150;
  const CityScenario city = *CityScenario::Create(city_options);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.relinearize_sigmas = 0.5;
  RelinearizingMap run(options);
  int relinearized = 0;
  for (int i = 0; i < 10; ++i) {
    ASSERT_TRUE(run.Take(city.MakePassage(i)));
    relinearized += run.Relinearize();
  }
  double worst_m = 0.0;
  run.map.ForEachLandmark([&](const Landmark& l) {
    worst_m = std::max(worst_m, (city.frame().ToLocal(l.position) - city.landmarks()[l.id - 1].position_m).norm());
  });
  std::printf("10 city passages, %d re-linearisations: worst landmark %.1f m off\n", relinearized, worst_m);
  EXPECT_GT(relinearized, 2);
  EXPECT_LT(worst_m, 30.0);
  EXPECT_TRUE(MapWindow::Build(run.map, run.map.LandmarkIds(), MapWindowOptions()).ok())
      << "the map's information is positive definite";
}

TEST(MapUpdater, RelinearizesTheStalestPassageOnceTheMapHasMovedAwayFromIt) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.relinearize_sigmas = 0.5;
  RelinearizingMap run(options);
  int relinearized = 0;
  for (int i = 0; i < 4; ++i) {
    ASSERT_TRUE(run.Take(scenario.MakePassage(i)));
    if (i == 0) {
      EXPECT_FALSE(run.updater.StalestPassage(run.map).has_value()) << "nothing moved since the first passage";
    }
    relinearized += run.Relinearize();
  }
  // The first passages' landmarks move by about a sigma with each of the next ones.
  EXPECT_GT(relinearized, 0);
  options.relinearize_sigmas = 0.0;
  EXPECT_FALSE(MapUpdater(options).StalestPassage(run.map).has_value());
}

// A map that is the joint solution of its passages is a fixed point of their joint solve: some of
// them taken again jointly, against the rest of the map as the prior, find the same solution (the
// rest's factors were taken there) and the same information. Without the bias correction, which
// the rest's factors carry from where they were taken, that holds to the solver's convergence.
TEST(ComputeAreaRelinearization, PassagesOfAJointSolutionTakenAgainChangeNothing) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.bias_correction = false;
  std::vector<Passage> passages;
  for (int i = 0; i < 6; ++i) passages.push_back(scenario.MakePassage(i));
  MapState map;
  map.Apply(ComputeBatchUpdate(passages, options, map)->delta);
  absl::StatusOr<PassageUpdate> again = ComputeAreaRelinearization({passages[1], passages[3]}, options, map);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->summary.joint_passages, 2);
  EXPECT_TRUE(again->delta.vehicles.empty()) << "the vehicles' records already hold the passages";
  MapState after = map;
  after.Apply(again->delta);
  ASSERT_EQ(after.landmark_count(), map.landmark_count());
  EXPECT_LT(LargestOffsetM(map, after), 1e-5);
  double largest_change = 0.0;  // of a marginal covariance, relative
  map.ForEachLandmark([&](const Landmark& l) {
    const Landmark& now = *after.FindLandmark(l.id);
    largest_change = std::max(largest_change, (now.cov_en_m2 - l.cov_en_m2).norm() / l.cov_en_m2.norm());
    EXPECT_EQ(now.passages_seen, l.passages_seen) << "the passages were counted when they were applied";
  });
  std::printf("landmarks moved by %.2e m at most, marginal covariances by %.2e of theirs\n",
              LargestOffsetM(map, after), largest_change);
  EXPECT_LT(largest_change, 1e-4);  // the poses re-solved from another start: the Jacobians differ a little
  for (int i = 0; i < 6; ++i) {
    std::vector<int64_t> factors;
    after.AppendPassageFactorIds(passages[i].vehicle_id, passages[i].passage_id, &factors);
    ASSERT_FALSE(factors.empty());
    const bool taken_again = i == 1 || i == 3;
    for (int64_t id : factors) EXPECT_EQ(id > map.last_factor_id(), taken_again) << "passage " << i;
  }
}

// A map made one passage at a time keeps each factor where its passage found the map. Every
// passage taken again jointly (nothing else in the map) is the joint solve of them all; its first
// passages alone, against the later ones as the prior, bring it most of the way there.
TEST(ComputeAreaRelinearization, BringsASequentialMapTowardsTheJointSolutionOfItsPassages) {
  const Scenario scenario = MakeScenario(25);
  const MapUpdateOptions options = SequentialUpdatesOnly();
  std::vector<Passage> passages;
  MapState sequential, before_last;
  for (int i = 0; i < 6; ++i) {
    passages.push_back(scenario.MakePassage(i));
    if (i == 5) before_last = sequential;
    sequential.Apply(ComputePassageUpdate(passages.back(), options, sequential)->delta);
  }
  MapState joint = before_last;
  joint.Apply(ComputeBatchUpdate(passages, options, before_last)->delta);

  absl::StatusOr<PassageUpdate> all = ComputeAreaRelinearization(passages, options, sequential);
  ASSERT_TRUE(all.ok()) << all.status();
  MapState all_again = sequential;
  all_again.Apply(all->delta);
  const std::vector<Passage> first(passages.begin(), passages.begin() + 3);
  absl::StatusOr<PassageUpdate> area = ComputeAreaRelinearization(first, options, sequential);
  ASSERT_TRUE(area.ok()) << area.status();
  MapState area_again = sequential;
  area_again.Apply(area->delta);

  const double sequential_m = LargestOffsetM(sequential, joint);
  const double all_m = LargestOffsetM(all_again, joint);
  const double area_m = LargestOffsetM(area_again, joint);
  std::printf("from the joint solution: sequential %.4f m, first 3 again %.4f m, all again %.2e m\n", sequential_m,
              area_m, all_m);
  EXPECT_LT(all_m, 1e-3);  // the same problem from another start
  EXPECT_LT(area_m, 0.5 * sequential_m);
}

TEST(ComputeAreaRelinearization, RefusesWhatItCannotSolveNamingTheField) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options = SequentialUpdatesOnly();
  MapState map;
  map.Apply(ComputePassageUpdate(scenario.MakePassage(0), options, map)->delta);
  absl::StatusOr<PassageUpdate> none = ComputeAreaRelinearization({}, options, map);
  EXPECT_TRUE(absl::IsInvalidArgument(none.status()));
  EXPECT_NE(none.status().message().find("passages"), absl::string_view::npos) << none.status();
  options.strategy = UpdateStrategy::kDecorrelated;
  absl::StatusOr<PassageUpdate> dc = ComputeAreaRelinearization({scenario.MakePassage(0)}, options, map);
  EXPECT_TRUE(absl::IsInvalidArgument(dc.status()));
  EXPECT_NE(dc.status().message().find("strategy"), absl::string_view::npos) << dc.status();
}

// After four passages, two of them leave the loop's landmarks fixed worse than a new landmark must
// be (3 m): a joint solve of the other two against that prior could slide one along its rays, so it
// is refused, and the stale passage is taken again alone.
TEST(ComputeAreaRelinearization, IsRefusedAgainstAPriorWeakerThanANewLandmarksAndTheStalePassageGoesAlone) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.relinearize_area_passages = 2;
  std::vector<Passage> passages;
  MapState map;
  for (int i = 0; i < 4; ++i) {
    passages.push_back(scenario.MakePassage(i));
    map.Apply(ComputePassageUpdate(passages.back(), options, map)->delta);
  }
  absl::StatusOr<PassageUpdate> joint = ComputeAreaRelinearization({passages[0], passages[1]}, options, map);
  EXPECT_TRUE(absl::IsFailedPrecondition(joint.status())) << joint.status();
  EXPECT_NE(joint.status().message().find("weakly determined"), absl::string_view::npos) << joint.status();
  absl::StatusOr<PassageUpdate> alone = ComputeRelinearization({passages[0], passages[1]}, options, map);
  ASSERT_TRUE(alone.ok()) << alone.status();
  EXPECT_EQ(alone->summary.joint_passages, 0);
  for (const auto& [id, factor] : alone->delta.added_factors) EXPECT_EQ(factor.passage_id, passages[0].passage_id);
}

TEST(MapUpdater, TakesTheStalestPassageAgainWithTheStalePassagesOfItsArea) {
  const Scenario scenario = MakeScenario(10);
  MapUpdateOptions options = SequentialUpdatesOnly();
  options.relinearize_sigmas = 0.5;
  options.relinearize_area_passages = 3;
  RelinearizingMap run(options);
  for (int i = 0; i < 7; ++i) ASSERT_TRUE(run.Take(scenario.MakePassage(i)));
  const std::optional<MapUpdater::PassageKey> stalest = run.updater.StalestPassage(run.map);
  ASSERT_TRUE(stalest.has_value());
  const std::vector<MapUpdater::PassageKey> area = run.updater.AreaOf(*stalest, run.map);
  ASSERT_EQ(area.size(), 3u) << "the first passages' landmarks, seen by all, moved by more than a sigma since";
  EXPECT_EQ(area.front(), *stalest);
  EXPECT_EQ(std::set<MapUpdater::PassageKey>(area.begin(), area.end()).size(), area.size());
  options.relinearize_area_passages = 1;
  EXPECT_EQ(MapUpdater(options, {}, 0, &run.map).AreaOf(*stalest, run.map).size(), 1u);
  const absl::StatusOr<Passage> stalest_passage = run.PassageOf(*stalest);
  ASSERT_TRUE(stalest_passage.ok()) << stalest_passage.status();
  absl::StatusOr<PassageUpdate> alone_jointly = ComputeRelinearization({*stalest_passage}, options, run.map);
  ASSERT_TRUE(alone_jointly.ok()) << alone_jointly.status();
  EXPECT_EQ(alone_jointly->summary.joint_passages, 1) << "with 1, the passage alone through the joint solve";
  options.relinearize_area_passages = 0;
  absl::StatusOr<PassageUpdate> by_subgraphs = ComputeRelinearization({*stalest_passage}, options, run.map);
  ASSERT_TRUE(by_subgraphs.ok()) << by_subgraphs.status();
  EXPECT_EQ(by_subgraphs->summary.joint_passages, 0) << "with 0, its subgraphs anew";

  const int64_t last_factor = run.map.last_factor_id();
  ASSERT_EQ(run.Relinearize(), 1);
  for (const Passage& passage : run.applied) {
    std::vector<int64_t> factors;
    run.map.AppendPassageFactorIds(passage.vehicle_id, passage.passage_id, &factors);
    const bool in_area = std::count(area.begin(), area.end(), MapUpdater::PassageKey{passage.vehicle_id,
                                                                                      passage.passage_id}) > 0;
    for (int64_t id : factors) EXPECT_EQ(id > last_factor, in_area) << passage.passage_id;
  }
  EXPECT_TRUE(MapWindow::Build(run.map, run.map.LandmarkIds(), MapWindowOptions()).ok())
      << "the map's information is positive definite";
}

}  // namespace
}  // namespace crowdmap

namespace crowdmap {
namespace {

// Partial drives (300 to 1500 m pieces of the loop) from the map's first passage on, with the
// updater's defaults (warm-up and re-solves): none fails, and the map is as consistent as whole
// passages make it.
TEST(MapUpdater, PartialDrivesFromTheFirstPassageOnBuildAConsistentMap) {
  ScenarioOptions options;
  options.piece_min_m = 300.0;
  options.piece_max_m = 1500.0;
  const Scenario scenario = *Scenario::Create(options);
  MapUpdater updater(MapUpdateOptions(), {}, 0);
  MapState map;
  for (int i = 0; i < 24; ++i) {
    const Passage passage = scenario.MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    ASSERT_TRUE(update.ok()) << "passage " << i << ": " << update.status();
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
  }
  const MapErrorMetrics metrics = EvaluateMap(map, scenario.landmarks());
  std::printf("partial drives, 24 passages: %zu landmarks, mean error %.3f m, NEES/dof %.2f, joint %.2f\n",
              map.landmark_count(), metrics.mean_dist_err_m, metrics.nees_per_dof, metrics.joint_nees_per_dof);
  EXPECT_EQ(map.landmark_count(), scenario.landmarks().size());
  EXPECT_LT(metrics.nees_per_dof, 1.5);
  EXPECT_LT(metrics.joint_nees_per_dof, 1.5);
}

// Coloured GNSS (AR(1), 10 m, 83 s correlation time) puts whole passages tens of metres off for
// minutes. Localised from there against the map, a piece of a passage could wind through a full
// turn and stay there (a wrong minimum, chi2 15 times its degrees of freedom, the passage then
// inflated away); aligned to the map first, every passage of this run solves to a consistent chi2.
TEST(ComputePassageUpdate, ColouredGnssPassagesTensOfMetresOffReachTheRightMinimum) {
  ScenarioOptions options;
  options.landmarks = 50;
  options.noise = NoiseConfig::kGnssAr1;
  const Scenario scenario = *Scenario::Create(options);
  MapUpdater updater(MapUpdateOptions(), {}, 0);
  MapState map;
  int inflated = 0;
  for (int i = 0; i < 48; ++i) {
    const Passage passage = scenario.MakePassage(i);
    absl::StatusOr<PassageUpdate> update = updater.Compute(passage, map);
    ASSERT_TRUE(update.ok()) << "passage " << i << ": " << update.status();
    if (update->summary.max_variance_factor > 1.0) {
      ++inflated;
      ADD_FAILURE() << "passage " << i << " inflated by " << update->summary.max_variance_factor;
    }
    map.Apply(update->delta);
    updater.Applied(passage, update->delta);
  }
  EXPECT_EQ(inflated, 0);
  const MapErrorMetrics metrics = EvaluateMap(map, scenario.landmarks());
  EXPECT_LT(metrics.joint_nees_per_dof, 1.5);
}

// A fleet of three vehicles whose cameras are each turned by their own error (sigma 0.5 degrees).
Scenario MakeFleetScenario(int landmarks, int vehicles, uint64_t seed) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  options.seed = seed;
  options.vehicles = vehicles;
  options.vehicle_yaw_bias_sigma_rad = 0.5 * M_PI / 180.0;
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  EXPECT_TRUE(scenario.ok()) << scenario.status();
  return *std::move(scenario);
}

TEST(CameraYawEstimation, WithoutItAPassageLeavesNoVehicleRecord) {
  const Scenario scenario = MakeFleetScenario(25, 3, 1);
  MapState map;
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(scenario.MakePassage(0), MapUpdateOptions(), map);
  ASSERT_TRUE(update.ok()) << update.status();
  EXPECT_TRUE(update->delta.vehicles.empty());
  EXPECT_EQ(update->summary.camera_yaw_sigma_rad, 0.0);
}

TEST(CameraYawEstimation, AFirstPassageNarrowsTheDefaultPriorAndRecordsTheVehicle) {
  const Scenario scenario = MakeFleetScenario(25, 3, 1);
  MapUpdateOptions options;
  options.estimate_camera_yaw = true;
  MapState map;
  const Passage passage = scenario.MakePassage(0);
  absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(passage, options, map);
  ASSERT_TRUE(update.ok()) << update.status();
  ASSERT_EQ(update->delta.vehicles.count(passage.vehicle_id), 1u);
  const VehicleCalibration& v = update->delta.vehicles.at(passage.vehicle_id);
  EXPECT_EQ(v.passages, 1);
  EXPECT_EQ(v.version, update->delta.version);
  EXPECT_LT(std::sqrt(v.camera_yaw_variance_rad2), options.camera_yaw_prior_sigma_rad);
  EXPECT_GT(v.camera_yaw_variance_rad2, 0.0);
  map.Apply(update->delta);
  ASSERT_NE(map.FindVehicle(passage.vehicle_id), nullptr);
  EXPECT_EQ(map.FindVehicle(passage.vehicle_id)->camera_yaw_offset_rad, v.camera_yaw_offset_rad);
}

TEST(CameraYawEstimation, EachVehiclesBiasIsRecoveredWithinThreeSigmaAndTheMapIsMoreConsistentThanIgnoringIt) {
  const int vehicles = 3, passages = 24;
  const Scenario scenario = MakeFleetScenario(25, vehicles, 2);
  std::vector<int> order(passages);
  std::iota(order.begin(), order.end(), 0);
  auto run = [&](bool estimate) {
    MapUpdateOptions options;
    options.estimate_camera_yaw = estimate;
    return ApplyInOrder(scenario, order, options);
  };
  const MapState estimated = run(true);
  for (int v = 0; v < vehicles; ++v) {
    const VehicleCalibration* record = estimated.FindVehicle(absl::StrCat("sim-v", v));
    ASSERT_NE(record, nullptr) << v;
    EXPECT_EQ(record->passages, passages / vehicles) << v;
    const double truth = scenario.VehicleYawBiasRad(v), sigma = std::sqrt(record->camera_yaw_variance_rad2);
    EXPECT_LT(std::abs(record->camera_yaw_offset_rad - truth), 3.0 * sigma)
        << "vehicle " << v << " truth " << truth << " estimate " << record->camera_yaw_offset_rad << " sigma " << sigma;
    // From the 1 degree prior to about 0.2-0.25 degrees after 8 passages of a 24-passage map: the
    // young map's errors, shared by every passage of the vehicle, not the pixels, limit it
    // (ConsiderCameraYawSolve).
    EXPECT_LT(sigma, 0.3 * MapUpdateOptions().camera_yaw_prior_sigma_rad) << v;
  }
  // The biases ignored, their common errors are in no covariance: the map is more sure of itself
  // than with them estimated (joint NEES/dof 0.81 against 0.76 here; lower with them estimated in
  // all 12 runs of `mapsim experiment --landmarks 25 --passages 24 --vehicles 3
  // --vehicle-yaw-bias-sigma-rad 0.0087 --seed 2..7`, with the last 5 and with all detections).
  // After 24 passages the error is lower in only 6 of those 12 runs (0.514 against 0.532 m here),
  // up to 10% higher in one, and the marginal NEES in 7.
  const MapErrorMetrics with = EvaluateMap(estimated, scenario.landmarks());
  const MapErrorMetrics without = EvaluateMap(run(false), scenario.landmarks());
  EXPECT_LT(with.joint_nees_per_dof, without.joint_nees_per_dof);
  EXPECT_LT(with.mean_dist_err_m, 1.05 * without.mean_dist_err_m);
}

// The vehicle's record is the prior of its passage's yaw, not information its factor adds to the
// map: the record came from the vehicle's earlier passages, which the map holds already. The same
// passage applied to the same map with the record 10 times surer adds the same information (up to
// the slightly different point it is linearised at), where a factor that held the prior would
// differ by the record's weight.
TEST(CameraYawEstimation, AVehiclesRecordIsNotInTheInformationItsNextPassageAdds) {
  const Scenario scenario = MakeFleetScenario(25, 3, 4);
  MapUpdateOptions options;
  options.estimate_camera_yaw = true;
  options.strategy = UpdateStrategy::kCorrelated;  // one factor per passage
  options.warmup_passages = 0;
  options.relinearize_until_passages = 0;
  const MapState map = ApplyInOrder(scenario, {0, 1, 2, 3}, options);
  const Passage next = scenario.MakePassage(6);  // vehicle 0's third
  const VehicleCalibration* record = map.FindVehicle(next.vehicle_id);
  ASSERT_NE(record, nullptr);
  ASSERT_EQ(record->passages, 2);
  auto added_information = [&](double variance_scale) -> Eigen::MatrixXd {
    MapState copy = map;
    VehicleCalibration changed = *record;
    changed.camera_yaw_variance_rad2 *= variance_scale;
    copy.PutVehicle(changed);
    absl::StatusOr<PassageUpdate> update = ComputePassageUpdate(next, options, copy);
    EXPECT_TRUE(update.ok()) << update.status();
    if (!update.ok() || update->delta.added_factors.size() != 1) return Eigen::MatrixXd();
    return update->delta.added_factors.begin()->second.information;
  };
  const Eigen::MatrixXd as_recorded = added_information(1.0), surer = added_information(0.1);
  ASSERT_GT(as_recorded.rows(), 0);
  ASSERT_EQ(as_recorded.rows(), surer.rows());
  // 6e-4 here, from the point each is linearised at; 0.058 when the factor held the prior.
  const double relative = (surer - as_recorded).norm() / as_recorded.norm();
  EXPECT_LT(relative, 1e-3);
}

// Every passage a vehicle of its own, every camera turned by the same 0.009 rad (one model, one
// mount): with the fleet's prior the new vehicles start from what the earlier ones showed, and
// their records come closer to the common error than from the fixed prior around 0.
TEST(CameraYawEstimation, AFleetThatSharesOneCameraErrorTeachesItToNewVehicles) {
  ScenarioOptions scenario_options;
  scenario_options.noise = NoiseConfig::kYawBias;
  scenario_options.seed = 3;
  const Scenario scenario = *Scenario::Create(scenario_options);
  std::vector<int> order(120);
  std::iota(order.begin(), order.end(), 0);
  auto run = [&](int fleet_vehicles, double* record_error, double* record_nees) {
    MapUpdateOptions options;
    options.estimate_camera_yaw = true;
    options.fleet_camera_yaw_prior_vehicles = fleet_vehicles;
    const MapState map = ApplyInOrder(scenario, order, options);
    // The last 40 vehicles' records.
    std::vector<VehicleCalibration> records;
    map.ForEachVehicle([&](const VehicleCalibration& v) { records.push_back(v); });
    EXPECT_EQ(records.size(), order.size());
    *record_error = *record_nees = 0.0;
    for (int i = 80; i < 120; ++i) {
      const VehicleCalibration* v = map.FindVehicle(scenario.MakePassage(i).vehicle_id);
      if (v == nullptr) {
        ADD_FAILURE() << "no record for passage " << i;
        continue;
      }
      const double error = v->camera_yaw_offset_rad - scenario_options.camera_yaw_bias_rad;
      *record_error += std::abs(error) / 40;
      *record_nees += error * error / v->camera_yaw_variance_rad2 / 40;
    }
    return EvaluateMap(map, scenario.landmarks());
  };
  double fixed_error = 0.0, fixed_nees = 0.0, fleet_error = 0.0, fleet_nees = 0.0;
  const MapErrorMetrics fixed = run(0, &fixed_error, &fixed_nees);
  const MapErrorMetrics fleet = run(5, &fleet_error, &fleet_nees);
  // Measured: records 0.0056 -> 0.0052 rad off (NEES 1.36 -> 1.21); the maps 0.3395 and 0.3393 m
  // (NEES/dof 1.075 and 1.074, joint 1.014 and 1.013). The records' prior is not information the
  // map takes in (AVehiclesRecordIsNotInTheInformationItsNextPassageAdds), so neither prior steers
  // the map; when each passage's prior reached the map, the fixed prior's pull towards 0 was in
  // it: 0.384 m, joint NEES/dof 1.91 (0.363 m and 1.63 with the fleet's prior).
  EXPECT_LT(fleet_error, fixed_error);
  EXPECT_LT(fleet_nees, fixed_nees);
  EXPECT_LT(std::abs(fleet.mean_dist_err_m - fixed.mean_dist_err_m), 0.01 * fixed.mean_dist_err_m);
  EXPECT_LT(fixed.joint_nees_per_dof, 1.25);
}

}  // namespace
}  // namespace crowdmap
