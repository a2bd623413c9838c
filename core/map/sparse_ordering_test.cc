#include "core/map/sparse_ordering.h"

#include <algorithm>
#include <random>
#include <set>

#include <cholmod.h>
#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// A map-like graph: `factors` cliques, each over a few vertices near a random place along a line
// of `n` (a street's landmarks seen by one passage's subgraph). above[j] lists the i < j linked.
std::vector<std::vector<int>> StreetGraph(int n, int factors, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> start(0, n - 1), size(2, 10), spread(0, 25);
  std::vector<std::set<int>> above(n);
  for (int f = 0; f < factors; ++f) {
    const int at = start(rng);
    std::vector<int> members;
    for (int k = size(rng); k > 0; --k) members.push_back(std::min(n - 1, at + spread(rng)));
    for (int a : members) {
      for (int b : members) {
        if (a < b) above[b].insert(a);
      }
    }
  }
  std::vector<std::vector<int>> out(n);
  for (int j = 0; j < n; ++j) out[j].assign(above[j].begin(), above[j].end());
  return out;
}

struct Elimination {
  std::vector<int> parent;  // by position; -1 for a root
  long long factor_entries = 0;
};

// The elimination tree and the entries of the Cholesky factor of the graph with its vertices in
// `order`, by eliminating them one after the other (each leaves its later neighbours a clique).
Elimination Eliminate(const std::vector<std::vector<int>>& above, const std::vector<int>& order) {
  const int n = static_cast<int>(above.size());
  std::vector<int> position(n);
  for (int k = 0; k < n; ++k) position[order[k]] = k;
  std::vector<std::set<int>> later(n);  // by position
  for (int j = 0; j < n; ++j) {
    for (int i : above[j]) {
      const int a = position[i], b = position[j];
      later[std::min(a, b)].insert(std::max(a, b));
    }
  }
  Elimination e;
  e.parent.assign(n, -1);
  for (int k = 0; k < n; ++k) {
    e.factor_entries += 1 + static_cast<long long>(later[k].size());
    if (later[k].empty()) continue;
    const int p = *later[k].begin();
    e.parent[k] = p;
    for (int m : later[k]) {
      if (m != p) later[p].insert(m);
    }
  }
  return e;
}

// Whether every subtree of the tree (parents after their children) is a range of positions.
bool Postordered(const std::vector<int>& parent) {
  const int n = static_cast<int>(parent.size());
  std::vector<int> first(n), size(n, 1);
  for (int k = 0; k < n; ++k) first[k] = k;
  for (int k = 0; k < n; ++k) {
    if (parent[k] < 0) continue;
    first[parent[k]] = std::min(first[parent[k]], first[k]);
    size[parent[k]] += size[k];
  }
  for (int k = 0; k < n; ++k) {
    if (size[k] != k - first[k] + 1) return false;
  }
  return true;
}

class SparseOrderingTest : public ::testing::Test {
 protected:
  SparseOrderingTest() { cholmod_start(&common_); }
  ~SparseOrderingTest() override { cholmod_finish(&common_); }

  // CHOLMOD's AMD order of the graph, as it is (its upper triangle from triplets).
  std::vector<int> AmdOrder(const std::vector<std::vector<int>>& above) {
    const int n = static_cast<int>(above.size());
    size_t links = 0;
    for (const auto& rows : above) links += rows.size();
    cholmod_triplet* t = cholmod_allocate_triplet(n, n, links, /*stype=*/1, CHOLMOD_PATTERN, &common_);
    for (int j = 0; j < n; ++j) {
      for (int i : above[j]) {
        static_cast<int*>(t->i)[t->nnz] = i;
        static_cast<int*>(t->j)[t->nnz++] = j;
      }
    }
    cholmod_sparse* a = cholmod_triplet_to_sparse(t, links, &common_);
    std::vector<int> order(n);
    EXPECT_TRUE(cholmod_amd(a, nullptr, 0, order.data(), &common_));
    cholmod_free_sparse(&a, &common_);
    cholmod_free_triplet(&t, &common_);
    return order;
  }

  cholmod_common common_;
};

TEST_F(SparseOrderingTest, TheOrderIsAmdsFillPostordered) {
  int amd_not_postordered = 0;
  for (uint64_t seed = 1; seed <= 40; ++seed) {
    SCOPED_TRACE(seed);
    const std::vector<std::vector<int>> graph = StreetGraph(200, 60, seed);
    const std::vector<int> order = PostorderedFillReducingOrder(graph, &common_);
    ASSERT_EQ(order.size(), graph.size());
    std::vector<int> sorted = order;
    std::sort(sorted.begin(), sorted.end());
    for (int k = 0; k < static_cast<int>(sorted.size()); ++k) ASSERT_EQ(sorted[k], k);

    const Elimination ours = Eliminate(graph, order);
    const Elimination amd = Eliminate(graph, AmdOrder(graph));
    EXPECT_TRUE(Postordered(ours.parent));
    EXPECT_EQ(ours.factor_entries, amd.factor_entries);
    amd_not_postordered += Postordered(amd.parent) ? 0 : 1;
  }
  // The graphs exercise the postorder: AMD alone leaves some of them unordered.
  EXPECT_GT(amd_not_postordered, 0);
}

TEST_F(SparseOrderingTest, AnEmptyGraphHasAnEmptyOrderAndOneVertexItself) {
  EXPECT_TRUE(PostorderedFillReducingOrder({}, &common_).empty());
  EXPECT_EQ(common_.status, CHOLMOD_OK);
  EXPECT_EQ(PostorderedFillReducingOrder(std::vector<std::vector<int>>(1), &common_), std::vector<int>{0});
}

TEST_F(SparseOrderingTest, AGraphWithoutLinksIsOrdered) {
  const std::vector<int> order = PostorderedFillReducingOrder(std::vector<std::vector<int>>(5), &common_);
  std::vector<int> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  EXPECT_EQ(sorted, (std::vector<int>{0, 1, 2, 3, 4}));
}

}  // namespace
}  // namespace crowdmap
