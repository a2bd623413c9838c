#include "core/map/map_state.h"

#include <algorithm>

namespace crowdmap {
namespace {

LandmarkPair OrderedPair(LandmarkId a, LandmarkId b) { return a < b ? LandmarkPair{a, b} : LandmarkPair{b, a}; }

}  // namespace

const Landmark* MapState::FindLandmark(LandmarkId id) const {
  auto it = entries_.find(id);
  return it == entries_.end() ? nullptr : &it->second.landmark;
}

bool MapState::CrossCovariance(LandmarkId a, LandmarkId b, Eigen::Matrix2d* cov) const {
  auto it = entries_.find(a);
  if (it == entries_.end()) return false;
  auto jt = it->second.cross.find(b);
  if (jt == it->second.cross.end()) return false;
  *cov = jt->second;
  return true;
}

void MapState::AppendNeighbors(LandmarkId id, std::vector<LandmarkId>* out) const {
  auto it = entries_.find(id);
  if (it == entries_.end()) return;
  for (const auto& [other, block] : it->second.cross) out->push_back(other);
}

void MapState::ForEachLandmark(const std::function<void(const Landmark&)>& fn) const {
  for (const auto& [id, entry] : entries_) fn(entry.landmark);
}

std::vector<LandmarkId> MapState::LandmarkIds() const {
  std::vector<LandmarkId> ids;
  ids.reserve(entries_.size());
  for (const auto& [id, entry] : entries_) ids.push_back(id);
  std::sort(ids.begin(), ids.end());
  return ids;
}

void MapState::PutLandmark(const Landmark& landmark) {
  entries_[landmark.id].landmark = landmark;
  version_ = std::max(version_, landmark.version);
}

void MapState::PutCrossCovariance(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& cov_ab) {
  auto& forward = entries_[a].cross;
  if (forward.find(b) == forward.end()) ++cross_block_count_;
  forward[b] = cov_ab;
  entries_[b].cross[a] = cov_ab.transpose();
}

void MapState::Apply(const MapDelta& delta) {
  for (const auto& [id, landmark] : delta.landmarks) PutLandmark(landmark);
  for (const auto& [pair, block] : delta.cross) PutCrossCovariance(pair.first, pair.second, block);
  version_ = std::max(version_, delta.version);
}

MapOverlay::MapOverlay(const MapReaderInterface& base) : base_(base) {
  delta_.base_version = base.version();
  delta_.version = base.version();
}

const Landmark* MapOverlay::FindLandmark(LandmarkId id) const {
  auto it = delta_.landmarks.find(id);
  return it != delta_.landmarks.end() ? &it->second : base_.FindLandmark(id);
}

bool MapOverlay::CrossCovariance(LandmarkId a, LandmarkId b, Eigen::Matrix2d* cov) const {
  auto it = delta_.cross.find(OrderedPair(a, b));
  if (it == delta_.cross.end()) return base_.CrossCovariance(a, b, cov);
  *cov = a < b ? it->second : Eigen::Matrix2d(it->second.transpose());
  return true;
}

void MapOverlay::AppendNeighbors(LandmarkId id, std::vector<LandmarkId>* out) const {
  base_.AppendNeighbors(id, out);
  // Only pairs the base lacks are recorded here, so nothing is reported twice.
  auto it = added_neighbors_.find(id);
  if (it != added_neighbors_.end()) out->insert(out->end(), it->second.begin(), it->second.end());
}

void MapOverlay::PutLandmark(const Landmark& landmark) { delta_.landmarks[landmark.id] = landmark; }

void MapOverlay::PutCrossCovariance(LandmarkId a, LandmarkId b, const Eigen::Matrix2d& cov_ab) {
  const LandmarkPair key = OrderedPair(a, b);
  auto [it, inserted] = delta_.cross.try_emplace(key);
  it->second = a < b ? cov_ab : Eigen::Matrix2d(cov_ab.transpose());
  if (inserted) {
    Eigen::Matrix2d unused;
    if (!base_.CrossCovariance(a, b, &unused)) {
      added_neighbors_[a].push_back(b);
      added_neighbors_[b].push_back(a);
    }
  }
}

}  // namespace crowdmap
