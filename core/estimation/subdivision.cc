#include "core/estimation/subdivision.h"

#include <algorithm>
#include <cmath>
#include <unordered_set>

namespace crowdmap {
namespace {

// Landmarks detected at each node.
std::vector<std::vector<LandmarkId>> LandmarksByNode(const PassageGraph& graph) {
  std::vector<std::vector<LandmarkId>> by_node(graph.node_count());
  for (const CameraObservation& d : graph.detections) by_node[d.node].push_back(d.landmark_id);
  return by_node;
}

// Greedy packing with dimension cap `cap`.
std::vector<NodeRange> Pack(const std::vector<std::vector<LandmarkId>>& by_node, int cap) {
  std::vector<NodeRange> ranges;
  const int n = static_cast<int>(by_node.size());
  int first = 0;
  while (first < n) {
    std::unordered_set<LandmarkId> landmarks;
    int last = first;
    for (int k = first; k < n; ++k) {
      size_t added = 0;
      for (LandmarkId id : by_node[k]) added += landmarks.count(id) ? 0 : 1;
      const int dim = 3 * (k - first + 1) + 2 * static_cast<int>(landmarks.size() + added);
      if (k > first && dim > cap) break;
      landmarks.insert(by_node[k].begin(), by_node[k].end());
      last = k;
    }
    ranges.push_back({first, last});
    first = last + 1;
  }
  return ranges;
}

}  // namespace

int SubgraphDimension(const PassageGraph& graph, const NodeRange& range) {
  std::unordered_set<LandmarkId> landmarks;
  for (const CameraObservation& d : graph.detections) {
    if (d.node >= range.first && d.node <= range.last) landmarks.insert(d.landmark_id);
  }
  return 3 * (range.last - range.first + 1) + 2 * static_cast<int>(landmarks.size());
}

std::vector<NodeRange> SubdivideGraph(const PassageGraph& graph, int max_dim) {
  if (graph.node_count() == 0) return {};
  if (max_dim <= 0) return {{0, graph.node_count() - 1}};
  const auto by_node = LandmarksByNode(graph);
  size_t pieces = Pack(by_node, max_dim).size();
  int hi = max_dim;
  if (graph.gnss_correlation_time_s > 0.0) {
    const double span_s = graph.node_times_s.back() - graph.node_times_s.front();
    const double most = std::floor(span_s / (kMinSubgraphCorrelationTimes * graph.gnss_correlation_time_s));
    pieces = std::min(pieces, static_cast<size_t>(std::max(1.0, most)));
    if (pieces == 1) return {{0, graph.node_count() - 1}};
    hi = std::max(max_dim, SubgraphDimension(graph, {0, graph.node_count() - 1}));  // one piece at most
  }
  // The smallest cap that still needs no more pieces gives the most even split.
  int lo = 1;
  while (lo < hi) {
    const int mid = lo + (hi - lo) / 2;
    if (Pack(by_node, mid).size() <= pieces) {
      hi = mid;
    } else {
      lo = mid + 1;
    }
  }
  return Pack(by_node, lo);
}

}  // namespace crowdmap
