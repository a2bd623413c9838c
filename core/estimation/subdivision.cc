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

// Joins each range to the next where the cut between them is not anchored on both sides: no GNSS
// fix in the last kCutAnchorS (plus two of the passage's median fix intervals) of the range before
// it, or in the first of the range after. A cut inside a GNSS outage would leave a range whose
// poses only odometry ties to a fix at one end, or to none: the heading there is free (10 m fixes
// over 50 m leave it to 0.3 rad), the solve is far from linear, and the first passage through an
// outage placed a street 130 m off with sigmas of 1.5 m. With the cut moved out of the outage,
// the odometry across it is kept and the outage is bridged from both of its ends.
std::vector<NodeRange> JoinUnanchoredCuts(const PassageGraph& graph, const std::vector<NodeRange>& ranges) {
  if (ranges.size() < 2) return ranges;
  std::vector<double> fix_times;
  for (const GnssObservation& fix : graph.gnss) fix_times.push_back(graph.node_times_s[fix.node]);
  std::vector<double> intervals;
  for (size_t j = 1; j < fix_times.size(); ++j) intervals.push_back(fix_times[j] - fix_times[j - 1]);
  double median_interval_s = 0.0;
  if (!intervals.empty()) {
    std::nth_element(intervals.begin(), intervals.begin() + intervals.size() / 2, intervals.end());
    median_interval_s = intervals[intervals.size() / 2];
  }
  // A receiver's rate, not an outage: a passage with a fix only at each end has a median interval
  // as long as itself, which would call every cut anchored and leave ranges with one fix, their
  // heading free (the landmarks undetermined). Fixes come at 0.1 Hz at the slowest.
  const double reach_s = kCutAnchorS + 2.0 * std::min(median_interval_s, kSlowestFixIntervalS);
  // A fix at a node of [first, last] within reach_s of node `at`.
  auto fix_near = [&](int first, int last, int at) {
    for (const GnssObservation& fix : graph.gnss) {
      if (fix.node >= first && fix.node <= last &&
          std::abs(graph.node_times_s[fix.node] - graph.node_times_s[at]) <= reach_s) {
        return true;
      }
    }
    return false;
  };
  std::vector<NodeRange> joined = {ranges.front()};
  for (size_t i = 1; i < ranges.size(); ++i) {
    NodeRange& before = joined.back();
    const NodeRange& after = ranges[i];
    if (fix_near(before.first, before.last, before.last) && fix_near(after.first, after.last, after.first)) {
      joined.push_back(after);
    } else {
      before.last = after.last;
    }
  }
  return joined;
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
  return JoinUnanchoredCuts(graph, Pack(by_node, lo));
}

}  // namespace crowdmap
