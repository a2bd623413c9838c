#include "core/estimation/subdivision.h"

#include <algorithm>

#include <gtest/gtest.h>

#include "core/sim/scenario.h"

namespace crowdmap {
namespace {

PassageGraph SimulatedGraph(int landmarks) {
  ScenarioOptions options;
  options.landmarks = landmarks;
  return *BuildPassageGraph(Scenario::Create(options)->MakePassage(0), GraphOptions());
}

TEST(SubdivideGraph, RangesCoverAllNodesInOrderWithinTheBound) {
  const PassageGraph graph = SimulatedGraph(100);
  for (int max_dim : {200, 500, 800}) {
    const std::vector<NodeRange> ranges = SubdivideGraph(graph, max_dim);
    ASSERT_FALSE(ranges.empty());
    EXPECT_EQ(ranges.front().first, 0);
    EXPECT_EQ(ranges.back().last, graph.node_count() - 1);
    int smallest = max_dim, largest = 0;
    for (size_t i = 0; i < ranges.size(); ++i) {
      if (i > 0) EXPECT_EQ(ranges[i].first, ranges[i - 1].last + 1);
      const int dim = SubgraphDimension(graph, ranges[i]);
      EXPECT_LE(dim, max_dim) << "range " << i;
      smallest = std::min(smallest, dim);
      largest = std::max(largest, dim);
    }
    // Balanced, and no more pieces than needed: merging any two neighbours would exceed the bound.
    if (ranges.size() > 1) EXPECT_LT(largest, 1.5 * smallest) << max_dim;
    EXPECT_GT(SubgraphDimension(graph, {0, graph.node_count() - 1}), max_dim * (static_cast<int>(ranges.size()) - 1) / 2);
  }
}

TEST(SubdivideGraph, TheThesisGraphSplitsIntoTwoOrThreeAtFiveHundred) {
  const std::vector<NodeRange> ranges = SubdivideGraph(SimulatedGraph(50), 500);
  EXPECT_GE(ranges.size(), 2u);
  EXPECT_LE(ranges.size(), 3u);
}

TEST(SubdivideGraph, NonPositiveBoundGivesOneRange) {
  const PassageGraph graph = SimulatedGraph(25);
  const std::vector<NodeRange> ranges = SubdivideGraph(graph, 0);
  ASSERT_EQ(ranges.size(), 1u);
  EXPECT_EQ(ranges[0].last, graph.node_count() - 1);
}

}  // namespace
}  // namespace crowdmap
