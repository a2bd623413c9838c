#include "core/map/sparse_ordering.h"

#include <algorithm>

namespace crowdmap {

std::vector<int> PostorderedFillReducingOrder(const std::vector<std::vector<int>>& above, cholmod_common* common) {
  const int n = static_cast<int>(above.size());
  size_t links = 0;
  for (const auto& rows : above) links += rows.size();
  cholmod_sparse* pattern =
      cholmod_allocate_sparse(n, n, links, /*sorted=*/0, /*packed=*/1, /*stype=*/1, CHOLMOD_PATTERN, common);
  if (pattern == nullptr) return {};
  int* p = static_cast<int*>(pattern->p);
  int* i = static_cast<int*>(pattern->i);
  int at = 0;
  for (int j = 0; j < n; ++j) {
    p[j] = at;
    for (int row : above[j]) i[at++] = row;
  }
  p[n] = at;
  std::vector<int> order(n);
  if (!cholmod_amd(pattern, nullptr, 0, order.data(), common)) {
    cholmod_free_sparse(&pattern, common);
    return {};
  }
  // The same pattern in that order (its upper triangle), for its elimination tree.
  std::vector<int> position(n);
  for (int k = 0; k < n; ++k) position[order[k]] = k;
  std::vector<int> fill(n + 1, 0);
  for (int j = 0; j < n; ++j) {
    for (int row : above[j]) ++fill[std::max(position[row], position[j]) + 1];
  }
  for (int k = 0; k < n; ++k) fill[k + 1] += fill[k];
  std::copy(fill.begin(), fill.end(), p);
  for (int j = 0; j < n; ++j) {
    for (int row : above[j]) {
      const auto [first, column] = std::minmax(position[row], position[j]);
      i[fill[column]++] = first;
    }
  }
  std::vector<int> parent(n), post(n);
  const bool postordered = cholmod_etree(pattern, parent.data(), common) &&
                           cholmod_postorder(parent.data(), n, nullptr, post.data(), common) == n;
  cholmod_free_sparse(&pattern, common);
  if (!postordered) return order;
  std::vector<int> out(n);
  for (int k = 0; k < n; ++k) out[k] = order[post[k]];
  return out;
}

}  // namespace crowdmap
