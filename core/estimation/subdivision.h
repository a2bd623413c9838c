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

// Splits the graph along time into the fewest ranges whose dimension is at most max_dim, with the
// sizes balanced (a small remainder at the end would be weakly anchored). A single node whose
// dimension already exceeds max_dim forms its own range. max_dim <= 0: one range.
std::vector<NodeRange> SubdivideGraph(const PassageGraph& graph, int max_dim);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_ESTIMATION_SUBDIVISION_H_
