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

// Puts the joint covariance `cov` of the page's landmarks (in page order) into the page, its
// diagonal blocks as the landmarks' own.
void PutCovariance(const Eigen::MatrixXd& cov, CovarianceBound bound, LandmarkPage* page) {
  for (size_t i = 0; i < page->landmarks.size(); ++i) page->landmarks[i].cov_en_m2 = cov.block<2, 2>(2 * i, 2 * i);
  page->covariance = cov;
  page->covariance_bound = bound;
}

}  // namespace

absl::Status AppendCrossCovariances(const MapReaderInterface& map, int window_hops, LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  const std::vector<LandmarkId> ids = IdsOf(*page);
  MapWindowOptions options;
  options.hops = window_hops;
  CovarianceBound bound = CovarianceBound::kExact;
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, ids, options, &bound);
  if (!cov.ok()) return cov.status();
  PutCovariance(*cov, bound, page);
  return absl::OkStatus();
}

absl::Status AppendCrossCovariances(const MapWindow& window, LandmarkPage* page) {
  if (page->landmarks.empty()) return absl::OkStatus();
  const std::vector<LandmarkId> ids = IdsOf(*page);
  absl::StatusOr<Eigen::MatrixXd> cov = window.Covariance(ids);
  if (!cov.ok()) return cov.status();
  PutCovariance(*cov, window.covariance_bound(), page);
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
  PutCovariance(window_covariance(rows, rows), window.covariance_bound(), page);
  return absl::OkStatus();
}

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
