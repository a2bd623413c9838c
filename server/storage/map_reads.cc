#include "server/storage/map_reads.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "core/map/map_window.h"

namespace crowdmap {

namespace {

std::vector<LandmarkId> IdsOf(const LandmarkPage& page) {
  std::vector<LandmarkId> ids;
  ids.reserve(page.landmarks.size());
  for (const Landmark& l : page.landmarks) ids.push_back(l.id);
  return ids;
}

// Puts the joint covariance `cov` of the page's landmarks (in page order) into the page.
void PutCovariance(const std::vector<LandmarkId>& ids, const Eigen::MatrixXd& cov, LandmarkPage* page);

}  // namespace

absl::Status AppendCrossCovariances(const MapReaderInterface& map, int window_hops, LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  const std::vector<LandmarkId> ids = IdsOf(*page);
  MapWindowOptions options;
  options.hops = window_hops;
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, ids, options);
  if (!cov.ok()) return cov.status();
  PutCovariance(ids, *cov, page);
  return absl::OkStatus();
}

absl::Status AppendCrossCovariances(const MapWindow& window, LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  const std::vector<LandmarkId> ids = IdsOf(*page);
  absl::StatusOr<Eigen::MatrixXd> cov = window.Covariance(ids);
  if (!cov.ok()) return cov.status();
  PutCovariance(ids, *cov, page);
  return absl::OkStatus();
}

absl::Status AppendCrossCovariances(const MapWindow& window, const Eigen::MatrixXd& window_covariance,
                                    LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  const std::vector<LandmarkId> ids = IdsOf(*page);
  std::vector<int> rows;
  rows.reserve(2 * ids.size());
  for (LandmarkId id : ids) {
    const int k = window.index(id);
    if (k < 0) return absl::InternalError(absl::StrCat("covariance read: landmark ", id, " is not in the window"));
    rows.push_back(2 * k);
    rows.push_back(2 * k + 1);
  }
  PutCovariance(ids, window_covariance(rows, rows), page);
  return absl::OkStatus();
}

namespace {

void PutCovariance(const std::vector<LandmarkId>& ids, const Eigen::MatrixXd& cov_matrix, LandmarkPage* page) {
  const Eigen::MatrixXd* cov = &cov_matrix;
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
}

}  // namespace

absl::StatusOr<LandmarkProvenance> ProvenanceOf(const MapReaderInterface& map, LandmarkId id) {
  const Landmark* landmark = map.FindLandmark(id);
  if (landmark == nullptr) return absl::NotFoundError(absl::StrCat("landmark ", id, ": not in the map"));
  LandmarkProvenance out;
  out.landmark = *landmark;
  out.map_version = map.version();
  std::vector<int64_t> factor_ids;
  map.AppendFactorIds(id, &factor_ids);
  std::sort(factor_ids.begin(), factor_ids.end());
  for (int64_t f : factor_ids) {
    const MapFactor* factor = map.FindFactor(f);
    if (factor == nullptr) continue;
    const std::pair<std::string, std::string> key{factor->vehicle_id, factor->passage_id};
    if (std::find(out.passages.begin(), out.passages.end(), key) == out.passages.end()) out.passages.push_back(key);
  }
  return out;
}

}  // namespace crowdmap
