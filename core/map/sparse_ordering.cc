#include "core/map/sparse_ordering.h"

#include <algorithm>

#include <cholmod.h>

namespace crowdmap {

std::vector<int> PostorderedFillReducingOrder(const std::vector<std::vector<int>>& above, cholmod_common* common) {
  const int n = static_cast<int>(above.size());
  if (n == 0) return {};
  size_t links = 0;
  for (const auto& rows : above) links += rows.size();
  // Everything allocated before CHOLMOD's matrix, which nothing frees if an allocation throws.
  std::vector<int> order(n), position(n), next(n), parent(n), post(n);
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
  if (!cholmod_amd(pattern, nullptr, 0, order.data(), common)) {
    cholmod_free_sparse(&pattern, common);
    return {};
  }
  // The same pattern in that order (its upper triangle), for its elimination tree.
  for (int k = 0; k < n; ++k) position[order[k]] = k;
  std::fill(p, p + n + 1, 0);
  for (int j = 0; j < n; ++j) {
    for (int row : above[j]) ++p[std::max(position[row], position[j]) + 1];
  }
  for (int k = 0; k < n; ++k) p[k + 1] += p[k];
  std::copy(p, p + n, next.begin());
  for (int j = 0; j < n; ++j) {
    for (int row : above[j]) {
      const auto [first, column] = std::minmax(position[row], position[j]);
      i[next[column]++] = first;
    }
  }
  const bool postordered = cholmod_etree(pattern, parent.data(), common) &&
                           cholmod_postorder(parent.data(), n, nullptr, post.data(), common) == n;
  cholmod_free_sparse(&pattern, common);
  if (!postordered) return order;
  std::vector<int> out(n);
  for (int k = 0; k < n; ++k) out[k] = order[post[k]];
  return out;
}

}  // namespace crowdmap
