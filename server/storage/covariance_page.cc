#include "server/storage/covariance_page.h"

#include "core/map/map_window.h"

namespace crowdmap {

absl::Status AppendCrossCovariances(const MapReaderInterface& map, int window_hops, LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  std::vector<LandmarkId> ids;
  ids.reserve(page->landmarks.size());
  for (const Landmark& l : page->landmarks) ids.push_back(l.id);
  MapWindowOptions options;
  options.hops = window_hops;
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, ids, options);
  if (!cov.ok()) return cov.status();
  const size_t n = ids.size();
  page->cross.reserve(page->cross.size() + n * (n - 1) / 2);
  for (size_t i = 0; i < n; ++i) {
    page->landmarks[i].cov_en_m2 = cov->block<2, 2>(2 * i, 2 * i);
    for (size_t j = i + 1; j < n; ++j) {
      const bool ordered = ids[i] < ids[j];
      const Eigen::Matrix2d block = ordered ? Eigen::Matrix2d(cov->block<2, 2>(2 * i, 2 * j))
                                            : Eigen::Matrix2d(cov->block<2, 2>(2 * j, 2 * i));
      page->cross.emplace_back(ordered ? LandmarkPair{ids[i], ids[j]} : LandmarkPair{ids[j], ids[i]}, block);
    }
  }
  return absl::OkStatus();
}

}  // namespace crowdmap
