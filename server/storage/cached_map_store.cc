#include "server/storage/cached_map_store.h"

#include <algorithm>
#include <cstdint>
#include <iterator>
#include <set>

#include "server/storage/map_reads.h"

namespace crowdmap {
namespace {

bool Inside(const BoundingBox& box, const LatLon& p) {
  return p.lat_deg >= box.min_lat_deg && p.lat_deg <= box.max_lat_deg && p.lon_deg >= box.min_lon_deg &&
         p.lon_deg <= box.max_lon_deg;
}

bool ById(const Landmark& a, const Landmark& b) { return a.id < b.id; }
bool RemovedById(const RemovedLandmark& a, const RemovedLandmark& b) { return a.id < b.id; }

}  // namespace

absl::StatusOr<std::unique_ptr<CachedMapStore>> CachedMapStore::Create(std::unique_ptr<MapStoreInterface> inner,
                                                                       int covariance_window_hops,
                                                                       int covariance_cache_landmarks) {
  if (inner == nullptr) return absl::InvalidArgumentError("CachedMapStore needs a store to wrap");
  if (covariance_cache_landmarks < 0) {
    return absl::InvalidArgumentError("covariance_cache_landmarks: must be >= 0");
  }
  std::unique_ptr<CachedMapStore> store(
      new CachedMapStore(std::move(inner), covariance_window_hops, covariance_cache_landmarks));
  MapState& map = store->map_;
  if (auto s = store->inner_->LoadMap(&map); !s.ok()) return s;
  if (auto s = CheckStoredMap(map); !s.ok()) return s;
  std::unordered_map<TileKey, Bucket> buckets;
  map.ForEachLandmark([&](const Landmark& l) {
    const TileKey key = KeyOf(TileContaining(l.position));
    buckets[key].push_back(l);
    store->tile_of_[l.id] = key;
  });
  auto view = std::make_shared<View>();
  view->version = map.version();
  absl::StatusOr<std::vector<RemovedLandmark>> removed = store->inner_->RemovedLandmarks();
  if (!removed.ok()) return removed.status();
  view->removed = std::make_shared<const std::vector<RemovedLandmark>>(std::move(*removed));
  for (auto& [key, bucket] : buckets) {
    std::sort(bucket.begin(), bucket.end(), ById);
    view->tiles.emplace(key, std::make_shared<const Bucket>(std::move(bucket)));
  }
  store->view_ = std::move(view);
  return store;
}

std::shared_ptr<const CachedMapStore::View> CachedMapStore::CurrentView() const {
  std::lock_guard<std::mutex> lock(view_mu_);
  return view_;
}

absl::Status CachedMapStore::CommitAndPublish(const MapDelta& delta, const std::function<absl::Status()>& commit) {
  std::lock_guard<std::mutex> lock(writer_mu_);
  if (auto s = commit(); !s.ok()) return s;
  Publish(delta);
  return absl::OkStatus();
}

absl::Status CachedMapStore::CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) {
  return CommitAndPublish(delta, [&] { return inner_->CommitPassageApplied(id, delta, result); });
}

absl::Status CachedMapStore::CommitPassageExcluded(int64_t id, const MapDelta& delta) {
  return CommitAndPublish(delta, [&] { return inner_->CommitPassageExcluded(id, delta); });
}

absl::Status CachedMapStore::CommitPassageRelinearized(int64_t id, const MapDelta& delta) {
  return CommitAndPublish(delta, [&] { return inner_->CommitPassageRelinearized(id, delta); });
}

bool CachedMapStore::ReadCommittedMap(const std::function<void(const MapState&)>& read) {
  std::shared_lock<WriterPreferringMutex> lock(map_mu_);
  read(map_);
  return true;
}

void CachedMapStore::SetPublishedCallback(std::function<void(int64_t)> fn) {
  std::lock_guard<std::mutex> lock(writer_mu_);
  on_published_ = std::move(fn);
}

void CachedMapStore::Publish(const MapDelta& delta) {
  std::shared_ptr<const View> next = ApplyToView(delta);
  int64_t version = 0;
  {
    std::unique_lock<WriterPreferringMutex> map_lock(map_mu_);
    map_.Apply(delta);
    version = map_.version();
    std::lock_guard<std::mutex> publish(view_mu_);
    view_ = std::move(next);
  }
  if (on_published_) on_published_(version);
}

absl::StatusOr<LandmarkProvenance> CachedMapStore::GetLandmarkProvenance(LandmarkId id) {
  std::shared_lock<WriterPreferringMutex> lock(map_mu_);
  return ProvenanceOf(map_, id);
}

std::shared_ptr<const CachedMapStore::View> CachedMapStore::ApplyToView(const MapDelta& delta) {
  const std::shared_ptr<const View> current = CurrentView();
  auto next = std::make_shared<View>(*current);  // copies tile pointers, not landmarks
  next->version = std::max(delta.version, delta.base_version);

  // Per touched tile: the landmarks that leave it and the records to insert or replace.
  struct Change {
    std::set<LandmarkId> leaving;
    std::vector<const Landmark*> upserts;
  };
  std::unordered_map<TileKey, Change> changes;
  std::vector<RemovedLandmark> removed;  // this delta's, in increasing id
  for (LandmarkId lid : delta.removed_landmarks) {
    auto old = tile_of_.find(lid);
    if (old == tile_of_.end()) continue;
    const Bucket& bucket = *current->tiles.at(old->second);
    auto record = std::lower_bound(bucket.begin(), bucket.end(), lid,
                                   [](const Landmark& l, LandmarkId id) { return l.id < id; });
    if (record != bucket.end() && record->id == lid) removed.push_back({lid, record->position, next->version});
    changes[old->second].leaving.insert(lid);
    tile_of_.erase(old);
  }
  std::sort(removed.begin(), removed.end(), RemovedById);
  // A landmark that comes back is no longer removed; one removed again gets its new record. The
  // records are copied only when the delta touches them (looked up by id: they are never pruned).
  const std::vector<RemovedLandmark>& records = *current->removed;
  const auto recorded = [&](LandmarkId id) {
    return std::binary_search(records.begin(), records.end(), RemovedLandmark{id, {}, 0}, RemovedById);
  };
  const bool returns = std::any_of(delta.landmarks.begin(), delta.landmarks.end(),
                                   [&](const auto& entry) { return recorded(entry.first); });
  auto removed_again = [&](const RemovedLandmark& r) {
    return delta.landmarks.count(r.id) > 0 || std::binary_search(removed.begin(), removed.end(), r, RemovedById);
  };
  if (!removed.empty() || returns) {
    std::vector<RemovedLandmark> all;
    all.reserve(records.size() + removed.size());
    std::remove_copy_if(records.begin(), records.end(), std::back_inserter(all), removed_again);
    const size_t kept = all.size();
    all.insert(all.end(), removed.begin(), removed.end());
    std::inplace_merge(all.begin(), all.begin() + static_cast<std::ptrdiff_t>(kept), all.end(), RemovedById);
    next->removed = std::make_shared<const std::vector<RemovedLandmark>>(std::move(all));
  }
  for (const auto& [lid, landmark] : delta.landmarks) {
    const TileKey key = KeyOf(TileContaining(landmark.position));
    changes[key].upserts.push_back(&landmark);
    auto old = tile_of_.find(lid);
    if (old != tile_of_.end() && old->second != key) changes[old->second].leaving.insert(lid);
    tile_of_[lid] = key;
  }
  for (auto& [key, change] : changes) {
    Bucket bucket;
    if (auto it = current->tiles.find(key); it != current->tiles.end()) bucket = *it->second;
    for (const Landmark* l : change.upserts) change.leaving.insert(l->id);  // replaced records go too
    bucket.erase(std::remove_if(bucket.begin(), bucket.end(),
                                [&](const Landmark& l) { return change.leaving.count(l.id) > 0; }),
                 bucket.end());
    for (const Landmark* l : change.upserts) bucket.push_back(*l);
    std::sort(bucket.begin(), bucket.end(), ById);
    if (bucket.empty()) {
      next->tiles.erase(key);
    } else {
      next->tiles[key] = std::make_shared<const Bucket>(std::move(bucket));
    }
  }
  return next;
}

template <typename Keep>
std::vector<Landmark> CachedMapStore::Select(const View& view, const BoundingBox& box, const Keep& keep,
                                             size_t limit) {
  // The records stay in their tiles until the page is known: a page of a large box copies and
  // orders only what it returns.
  std::vector<const Landmark*> found;
  auto scan = [&](const Bucket& bucket) {
    for (const Landmark& l : bucket) {
      if (Inside(box, l.position) && keep(l)) found.push_back(&l);
    }
  };
  // Tiles grow southwards: the north-west corner has the smallest x and y.
  const TileId nw = TileContaining({box.max_lat_deg, box.min_lon_deg});
  const TileId se = TileContaining({box.min_lat_deg, box.max_lon_deg});
  const int64_t range = (static_cast<int64_t>(se.x) - nw.x + 1) * (static_cast<int64_t>(se.y) - nw.y + 1);
  if (range > static_cast<int64_t>(view.tiles.size())) {
    for (const auto& [key, bucket] : view.tiles) scan(*bucket);
  } else {
    for (int x = nw.x; x <= se.x; ++x) {
      for (int y = nw.y; y <= se.y; ++y) {
        auto it = view.tiles.find(KeyOf(TileId{kStorageZoom, x, y}));
        if (it != view.tiles.end()) scan(*it->second);
      }
    }
  }
  const size_t n = std::min(limit, found.size());
  const auto by_id = [](const Landmark* a, const Landmark* b) { return a->id < b->id; };
  std::partial_sort(found.begin(), found.begin() + static_cast<std::ptrdiff_t>(n), found.end(), by_id);
  std::vector<Landmark> out;
  out.reserve(n);
  for (size_t k = 0; k < n; ++k) out.push_back(*found[k]);
  return out;
}

CachedMapStore::WholeMap CachedMapStore::WholeMapWindow() const {
  std::lock_guard<std::mutex> lock(window_mu_);
  if (whole_map_.window == nullptr || window_version_ != map_.version()) {
    whole_map_ = {};
    absl::StatusOr<MapWindow> window = MapWindow::Build(map_, map_.LandmarkIds(), MapWindowOptions());
    if (!window.ok()) return {};  // the caller falls back to a window of its own, with the error
    whole_map_.window = std::make_shared<const MapWindow>(*std::move(window));
    window_version_ = map_.version();
    if (static_cast<int>(whole_map_.window->landmarks().size()) <= covariance_cache_landmarks_) {
      // Without it (an error), each read recovers its own blocks and reports the error.
      if (absl::StatusOr<Eigen::MatrixXd> cov = whole_map_.window->FullCovariance(); cov.ok()) {
        whole_map_.covariance = std::make_shared<const Eigen::MatrixXd>(*std::move(cov));
      }
    }
  }
  return whole_map_;
}

absl::Status CachedMapStore::AppendCovariances(LandmarkPage* page) const {
  if (covariance_window_hops_ == 0 && !page->landmarks.empty()) {
    if (const WholeMap whole = WholeMapWindow(); whole.window != nullptr) {
      return whole.covariance != nullptr ? AppendCrossCovariances(*whole.window, *whole.covariance, page)
                                         : AppendCrossCovariances(*whole.window, page);
    }
  }
  return AppendCrossCovariances(map_, covariance_window_hops_, page);
}

absl::StatusOr<LandmarkPage> CachedMapStore::QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                                         bool include_cross) {
  // With covariances, the view and the map are read under the map's lock: the same version.
  std::shared_lock<WriterPreferringMutex> map_lock(map_mu_, std::defer_lock);
  if (include_cross) map_lock.lock();
  const std::shared_ptr<const View> view = CurrentView();
  LandmarkPage page;
  page.map_version = view->version;
  // One beyond the page tells whether there are more.
  const size_t wanted = limit > 0 ? static_cast<size_t>(limit) + 1 : SIZE_MAX;
  page.landmarks = Select(*view, box, [&](const Landmark& l) { return l.id > after_id; }, wanted);
  if (limit > 0 && static_cast<int>(page.landmarks.size()) > limit) {
    page.landmarks.resize(limit);
    page.more = true;
  }
  if (include_cross) {
    if (auto s = AppendCovariances(&page); !s.ok()) return s;
  }
  return page;
}

absl::StatusOr<LandmarkPage> CachedMapStore::GetTile(const TileId& tile, bool include_cross) {
  if (tile.z != kStorageZoom || !IsValidTile(tile)) return inner_->GetTile(tile, include_cross);
  std::shared_lock<WriterPreferringMutex> map_lock(map_mu_, std::defer_lock);
  if (include_cross) map_lock.lock();
  const std::shared_ptr<const View> view = CurrentView();
  LandmarkPage page;
  page.map_version = view->version;
  if (auto it = view->tiles.find(KeyOf(tile)); it != view->tiles.end()) page.landmarks = *it->second;
  if (include_cross) {
    if (auto s = AppendCovariances(&page); !s.ok()) return s;
  }
  return page;
}

absl::StatusOr<LandmarkPage> CachedMapStore::GetLandmarks(const std::vector<LandmarkId>& ids, bool include_cross) {
  std::vector<LandmarkId> sorted = ids;
  std::sort(sorted.begin(), sorted.end());
  sorted.erase(std::unique(sorted.begin(), sorted.end()), sorted.end());
  // The records and the covariances from the map, under its lock: one version.
  std::shared_lock<WriterPreferringMutex> map_lock(map_mu_);
  LandmarkPage page;
  page.map_version = map_.version();
  for (LandmarkId id : sorted) {
    if (const Landmark* l = map_.FindLandmark(id)) page.landmarks.push_back(*l);
  }
  if (include_cross) {
    if (auto s = AppendCovariances(&page); !s.ok()) return s;
  }
  return page;
}

absl::StatusOr<LandmarkPage> CachedMapStore::ChangedLandmarks(const BoundingBox& box, int64_t since_version) {
  const std::shared_ptr<const View> view = CurrentView();
  LandmarkPage page;
  page.map_version = view->version;
  page.landmarks = Select(*view, box, [&](const Landmark& l) { return l.version > since_version; }, SIZE_MAX);
  for (const RemovedLandmark& r : *view->removed) {
    if (r.version > since_version && Inside(box, r.position)) page.removed.push_back(r.id);
  }
  return page;
}

absl::StatusOr<std::vector<RemovedLandmark>> CachedMapStore::RemovedLandmarks() { return *CurrentView()->removed; }

}  // namespace crowdmap
