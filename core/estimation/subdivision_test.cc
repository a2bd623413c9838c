#include "core/estimation/subdivision.h"

#include <algorithm>
#include <limits>
#include <set>
#include <vector>

#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

PassageGraph SimulatedGraph(int landmarks) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  GraphOptions graph_options;
  graph_options.refine_initial_poses = false;  // subdivision reads only the graph's structure
  return *BuildPassageGraph(Scenario::Create(options)->MakePassage(0), graph_options);
}

// The fewest contiguous ranges of dimension <= max_dim, by dynamic programming over all split
// points (no greedy argument needed). A single node above the bound may stand alone.
int MinimalRangeCount(const PassageGraph& graph, int max_dim) {
  const int n = graph.node_count();
  std::vector<std::vector<LandmarkId>> by_node(n);
  for (const CameraObservation& d : graph.detections) by_node[d.node].push_back(d.landmark_id);
  const int kInf = std::numeric_limits<int>::max() / 2;
  std::vector<int> best(n + 1, kInf);  // best[k]: fewest ranges covering nodes [0, k)
  best[0] = 0;
  for (int first = 0; first < n; ++first) {
    if (best[first] == kInf) continue;
    std::set<LandmarkId> landmarks;
    for (int last = first; last < n; ++last) {
      landmarks.insert(by_node[last].begin(), by_node[last].end());
      const int dim = 3 * (last - first + 1) + 2 * static_cast<int>(landmarks.size());
      if (dim > max_dim && last > first) break;  // dimension only grows with the range
      best[last + 1] = std::min(best[last + 1], best[first] + 1);
    }
  }
  return best[n];
}

class SubdivisionTest : public testing::Test {
 protected:
  static void SetUpTestSuite() { graph_ = new PassageGraph(SimulatedGraph(100)); }
  static void TearDownTestSuite() { delete graph_; }
  static PassageGraph* graph_;
};
PassageGraph* SubdivisionTest::graph_ = nullptr;

TEST_F(SubdivisionTest, SubgraphDimensionCountsPosesAndDistinctLandmarks) {
  const PassageGraph& g = *graph_;
  std::set<LandmarkId> all;
  for (const CameraObservation& d : g.detections) all.insert(d.landmark_id);
  EXPECT_EQ(SubgraphDimension(g, {0, g.node_count() - 1}), 3 * g.node_count() + 2 * static_cast<int>(all.size()));
  // The first node alone: 3 plus 2 per landmark detected at it.
  std::set<LandmarkId> first;
  for (const CameraObservation& d : g.detections) {
    if (d.node == 0) first.insert(d.landmark_id);
  }
  EXPECT_EQ(SubgraphDimension(g, {0, 0}), 3 + 2 * static_cast<int>(first.size()));
}

TEST_F(SubdivisionTest, RangesAreContiguousCoverAllNodesAndRespectTheBound) {
  const PassageGraph& g = *graph_;
  ASSERT_GT(g.node_count(), 100);
  for (int max_dim : {100, 200, 333, 500, 800, 5000}) {
    const std::vector<NodeRange> ranges = SubdivideGraph(g, max_dim);
    ASSERT_FALSE(ranges.empty()) << max_dim;
    EXPECT_EQ(ranges.front().first, 0) << max_dim;
    EXPECT_EQ(ranges.back().last, g.node_count() - 1) << max_dim;
    for (size_t i = 0; i < ranges.size(); ++i) {
      EXPECT_LE(ranges[i].first, ranges[i].last) << max_dim << " range " << i;
      if (i > 0) {
        EXPECT_EQ(ranges[i].first, ranges[i - 1].last + 1) << max_dim << " range " << i;
      }
      EXPECT_LE(SubgraphDimension(g, ranges[i]), max_dim) << max_dim << " range " << i;
    }
  }
}

TEST_F(SubdivisionTest, UsesTheFewestRangesPossible) {
  const PassageGraph& g = *graph_;
  for (int max_dim : {100, 200, 333, 500, 800, 5000}) {
    const int minimal = MinimalRangeCount(g, max_dim);
    EXPECT_EQ(static_cast<int>(SubdivideGraph(g, max_dim).size()), minimal) << max_dim;
  }
  EXPECT_EQ(SubdivideGraph(g, 5000).size(), 1u) << "the whole passage fits";
  EXPECT_GT(MinimalRangeCount(g, 500), 1) << "the thesis bound must actually split this graph";
}

TEST_F(SubdivisionTest, BalancesTheRangeSizes) {
  const PassageGraph& g = *graph_;
  for (int max_dim : {100, 200, 333, 500, 800}) {
    const std::vector<NodeRange> ranges = SubdivideGraph(g, max_dim);
    ASSERT_GT(ranges.size(), 1u) << max_dim;
    int smallest = std::numeric_limits<int>::max(), largest = 0;
    for (const NodeRange& r : ranges) {
      smallest = std::min(smallest, SubgraphDimension(g, r));
      largest = std::max(largest, SubgraphDimension(g, r));
    }
    EXPECT_LT(largest, 1.5 * smallest) << max_dim << ": no weakly anchored remainder at the end";
  }
}

TEST_F(SubdivisionTest, NonPositiveBoundGivesOneRange) {
  const PassageGraph& g = *graph_;
  for (int max_dim : {0, -1}) {
    const std::vector<NodeRange> ranges = SubdivideGraph(g, max_dim);
    ASSERT_EQ(ranges.size(), 1u) << max_dim;
    EXPECT_EQ(ranges[0].first, 0);
    EXPECT_EQ(ranges[0].last, g.node_count() - 1);
  }
}

TEST(SubdivideGraph, ABoundBelowOneNodeGivesOneRangePerGnssNode) {
  // Every node alone, but a range without a fix is no anchored piece: the nodes of detections
  // alone join the range of the fix before them (the first ones the fix after them).
  const PassageGraph g = SimulatedGraph(4);
  const std::vector<NodeRange> ranges = SubdivideGraph(g, 2);
  std::set<int> gnss_nodes;
  for (const GnssObservation& fix : g.gnss) gnss_nodes.insert(fix.node);
  ASSERT_LT(gnss_nodes.size(), static_cast<size_t>(g.node_count())) << "the graph has nodes without a fix";
  ASSERT_EQ(ranges.size(), gnss_nodes.size());
  for (size_t k = 0; k < ranges.size(); ++k) {
    if (k > 0) {
      EXPECT_EQ(ranges[k].first, ranges[k - 1].last + 1);
    }
    int fixes = 0;
    for (int node = ranges[k].first; node <= ranges[k].last; ++node) fixes += gnss_nodes.count(node);
    EXPECT_EQ(fixes, 1) << k;
  }
}

TEST(SubdivideGraph, TheThesisGraphSplitsIntoTwoOrThreeAtFiveHundred) {
  const std::vector<NodeRange> ranges = SubdivideGraph(SimulatedGraph(50), 500);
  EXPECT_GE(ranges.size(), 2u);
  EXPECT_LE(ranges.size(), 3u);
}

// A passage of the thesis's loop with 100 landmarks, and graph options that keep the initial
// poses as built (the tests below change the passage's fixes and build its graph again).
Passage HundredLandmarkPassage() {
  ScenarioOptions options;
  options.landmarks = 100;
  return Scenario::Create(options)->MakePassage(0);
}
GraphOptions UnrefinedGraph() {
  GraphOptions graph_options;
  graph_options.refine_initial_poses = false;
  return graph_options;
}

TEST(SubdivideGraph, NoCutFallsInAGnssOutage) {
  const GraphOptions graph_options = UnrefinedGraph();
  Passage passage = HundredLandmarkPassage();
  const PassageGraph whole = *BuildPassageGraph(passage, graph_options);
  const std::vector<NodeRange> cuts = SubdivideGraph(whole, 500);
  ASSERT_GE(cuts.size(), 2u);
  // A 40 s outage around where the first cut falls with every fix.
  const double cut_s = whole.node_times_s[cuts.front().last];
  passage.gnss.erase(std::remove_if(passage.gnss.begin(), passage.gnss.end(),
                                    [&](const GnssFix& f) { return std::abs(f.t_s - cut_s) < 20.0; }),
                     passage.gnss.end());
  const PassageGraph graph = *BuildPassageGraph(passage, graph_options);
  const std::vector<NodeRange> ranges = SubdivideGraph(graph, 500);
  ASSERT_GE(ranges.size(), 1u);
  EXPECT_LT(ranges.size(), cuts.size() + 1);
  EXPECT_EQ(ranges.front().first, 0);
  EXPECT_EQ(ranges.back().last, graph.node_count() - 1);
  // Fixes at 1 Hz: each side of every cut has one within kCutAnchorS + 2 s.
  auto fix_within = [&](const NodeRange& r, int at) {
    for (const GnssObservation& fix : graph.gnss) {
      if (fix.node >= r.first && fix.node <= r.last &&
          std::abs(graph.node_times_s[fix.node] - graph.node_times_s[at]) <= kCutAnchorS + 2.0) {
        return true;
      }
    }
    return false;
  };
  bool joined = false;
  for (size_t k = 1; k < ranges.size(); ++k) {
    EXPECT_EQ(ranges[k].first, ranges[k - 1].last + 1);
    EXPECT_TRUE(fix_within(ranges[k - 1], ranges[k - 1].last)) << k;
    EXPECT_TRUE(fix_within(ranges[k], ranges[k].first)) << k;
  }
  for (const NodeRange& r : ranges) {
    const double from_s = graph.node_times_s[r.first], to_s = graph.node_times_s[r.last];
    if (from_s < cut_s - 20.0 && to_s > cut_s + 20.0) joined = true;
  }
  EXPECT_TRUE(joined) << "one range bridges the outage";
}

// A passage with a fix only at its start and its end (a receiver that lost the sky between them)
// is one range: a cut would leave ranges with one fix, or none, their heading free.
TEST(SubdivideGraph, APassageFixedOnlyAtItsEndsIsNotCut) {
  const GraphOptions graph_options = UnrefinedGraph();
  Passage passage = HundredLandmarkPassage();
  ASSERT_GE(SubdivideGraph(*BuildPassageGraph(passage, graph_options), 500).size(), 2u);
  passage.gnss = {passage.gnss.front(), passage.gnss.back()};
  const PassageGraph graph = *BuildPassageGraph(passage, graph_options);
  ASSERT_GT(graph.node_times_s.back() - graph.node_times_s.front(), 60.0);
  const std::vector<NodeRange> ranges = SubdivideGraph(graph, 500);
  ASSERT_EQ(ranges.size(), 1u);
  EXPECT_EQ(ranges.front().first, 0);
  EXPECT_EQ(ranges.front().last, graph.node_count() - 1);
}

TEST(SubdivideGraph, CorrelatedGnssKeepsEveryRangeThreeCorrelationTimesLong) {
  ScenarioOptions options;
  options.landmarks = 50;
  options.noise = NoiseConfig::kGnssAr1;
  options.duration_s = 1000.0;
  options.repeat_route = true;
  GraphOptions graph_options;
  graph_options.refine_initial_poses = false;
  PassageGraph graph = *BuildPassageGraph(Scenario::Create(options)->MakePassage(0), graph_options);
  const double tau = graph.gnss_correlation_time_s;
  ASSERT_GT(tau, 80.0);
  // 1000 s over 3 x 83 s: at most 4 ranges, where the dimension bound alone asks for more.
  graph.gnss_correlation_time_s = 0.0;
  const size_t white = SubdivideGraph(graph, 500).size();
  graph.gnss_correlation_time_s = tau;
  const std::vector<NodeRange> ranges = SubdivideGraph(graph, 500);
  EXPECT_GT(white, 4u);
  EXPECT_EQ(ranges.size(), 4u);
  EXPECT_EQ(ranges.front().first, 0);
  EXPECT_EQ(ranges.back().last, graph.node_count() - 1);
  for (size_t k = 0; k < ranges.size(); ++k) {
    if (k > 0) {
      EXPECT_EQ(ranges[k].first, ranges[k - 1].last + 1);
    }
    const double span_s = graph.node_times_s[ranges[k].last] - graph.node_times_s[ranges[k].first];
    EXPECT_GT(span_s, 2.0 * tau) << k;  // balanced by dimension, so about 250 s each
  }
  // The 165 s loop passage stays whole.
  options.duration_s = 165.0;
  options.repeat_route = false;
  EXPECT_EQ(SubdivideGraph(*BuildPassageGraph(Scenario::Create(options)->MakePassage(0), graph_options), 500).size(),
            1u);
}

}  // namespace
}  // namespace crowdmap
