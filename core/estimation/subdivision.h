#ifndef CROWDMAP_CORE_ESTIMATION_SUBDIVISION_H_
#define CROWDMAP_CORE_ESTIMATION_SUBDIVISION_H_

#include <vector>

#include "core/estimation/graph_builder.h"

namespace crowdmap {

// Consecutive pose nodes [first, last] of a passage graph; the odometry factor between two
// ranges is cut (thesis section 4.4.3, graph subdivision).
struct NodeRange {
  int first = 0;
  int last = 0;
};

// State dimension of a range: 3 per pose plus 2 per landmark detected from it.
int SubgraphDimension(const PassageGraph& graph, const NodeRange& range);

// With coloured GNSS noise (PassageGraph::gnss_correlation_time_s), a range spans at least this
// many correlation times. A cut leaves out the GNSS innovation across it (AddPoseGraphFactors), and
// a range that starts within a correlation time of the cut is anchored only by its own
// innovations, weakly: on a 165 s loop passage (tau = 83 s) cut in two, the second half of a first
// passage was mapped 56 m off where the whole passage was 14 m off. Over three correlation times
// a range's innovations alone fix its position to about the stationary sigma.
constexpr double kMinSubgraphCorrelationTimes = 3.0;

// A cut between two ranges needs a GNSS fix within this many seconds (plus two of the passage's
// median fix intervals) on each side of it; otherwise the two ranges are one (a GNSS outage is not
// cut, see JoinUnanchoredCuts in subdivision.cc).
constexpr double kCutAnchorS = 5.0;
// The longest interval between fixes taken for a receiver's rate (JoinUnanchoredCuts).
constexpr double kSlowestFixIntervalS = 10.0;

// Splits the graph along time into the fewest ranges whose dimension is at most max_dim, with the
// sizes balanced (a small remainder at the end would be weakly anchored). A single node whose
// dimension already exceeds max_dim forms its own range. max_dim <= 0: one range. With coloured
// GNSS noise, at most as many ranges as the passage spans kMinSubgraphCorrelationTimes (at least
// one), balanced the same way. Ranges whose cut would fall in a GNSS outage are then joined (see
// kCutAnchorS), so a range can exceed max_dim there.
std::vector<NodeRange> SubdivideGraph(const PassageGraph& graph, int max_dim);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_SUBDIVISION_H_
