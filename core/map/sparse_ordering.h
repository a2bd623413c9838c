#ifndef CROWDMAP_CORE_MAP_SPARSE_ORDERING_H_
#define CROWDMAP_CORE_MAP_SPARSE_ORDERING_H_

#include <vector>

struct cholmod_common_struct;  // CHOLMOD's cholmod_common

namespace crowdmap {

// A fill-reducing order of the vertices of a graph for a Cholesky factorisation (AMD), postordered:
// every subtree of the elimination tree is a range of consecutive positions. The postorder
// changes no fill. It lets a solve with a few unit columns carry, at each supernode, only the
// columns its subtree reaches (MapWindow's covariance reads); AMD's own order is not always
// postordered: 2 of 60 read windows of a 100k city were not.
//
// `above[j]` lists the vertices i < j linked to vertex j, each link once. order[k] is the vertex
// put k-th. Empty for an empty graph or when AMD fails (out of memory); AMD's order as it is when
// the postorder fails.
std::vector<int> PostorderedFillReducingOrder(const std::vector<std::vector<int>>& above,
                                              cholmod_common_struct* common);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_SPARSE_ORDERING_H_
