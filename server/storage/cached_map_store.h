#ifndef CROWDMAP_SERVER_STORAGE_CACHED_MAP_STORE_H_
#define CROWDMAP_SERVER_STORAGE_CACHED_MAP_STORE_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <unordered_map>
#include <vector>

#include "core/map/map_window.h"
#include "server/storage/map_store.h"
#include "server/storage/writer_preferring_mutex.h"

namespace crowdmap {

// A MapStoreInterface that answers the map reads (QueryRegion, GetTile, ChangedLandmarks) from an
// in-memory copy of the map, and forwards everything else to the store it wraps, which stays the
// source of truth. Reads without covariances use immutable per-tile snapshots of the landmarks;
// reads with cross-covariances recover them from an in-memory copy of the map's factors.
//
// The copy is loaded from the inner store when the cache is created and is replaced after each
// successful map commit (an applied, excluded or re-linearised passage) by applying the same
// delta, so a read sees either the map before or after a commit, never a mixture, and never a
// change that is not yet durable. Readers take a reference to the current copy and never wait for
// the writer or for SQLite. A commit copies only the tiles it touches (plus the table of tile
// pointers).
class CachedMapStore : public MapStoreInterface {
 public:
  // Maps of at most this many landmarks keep their whole covariance (8 (2n)^2 bytes: 32 MiB at
  // 1,024) per version, for reads with covariances when covariance_window_hops is 0.
  static constexpr int kDefaultCovarianceCacheLandmarks = 1024;

  // `covariance_window_hops`: see SqliteMapStoreOptions::covariance_window_hops.
  // `covariance_cache_landmarks`: up to this map size (0: never), the first read with covariances
  // after a commit inverts the map's information once, and the version's later such reads copy
  // their blocks from it.
  static absl::StatusOr<std::unique_ptr<CachedMapStore>> Create(
      std::unique_ptr<MapStoreInterface> inner, int covariance_window_hops = 0,
      int covariance_cache_landmarks = kDefaultCovarianceCacheLandmarks);

  absl::StatusOr<std::vector<absl::StatusOr<EnqueueOutcome>>> EnqueuePassages(const std::vector<NewPassage>& passages,
                                                                              int64_t max_queue) override {
    return inner_->EnqueuePassages(passages, max_queue);
  }
  absl::StatusOr<StoredPassage> GetPassage(int64_t id) override { return inner_->GetPassage(id); }
  absl::StatusOr<StoredPassage> FindPassage(const std::string& vehicle_id, const std::string& passage_id) override {
    return inner_->FindPassage(vehicle_id, passage_id);
  }
  absl::StatusOr<std::vector<StoredPassage>> ListPassages(const PassageQuery& query) override {
    return inner_->ListPassages(query);
  }
  absl::StatusOr<std::string> GetPassagePayload(int64_t id) override { return inner_->GetPassagePayload(id); }
  absl::StatusOr<int> PrunePassagePayloads(const std::vector<std::pair<std::string, std::string>>& passages) override {
    return inner_->PrunePassagePayloads(passages);
  }
  absl::StatusOr<int> PruneSettledPayloads(int64_t finished_before_unix_ms, int limit) override {
    return inner_->PruneSettledPayloads(finished_before_unix_ms, limit);
  }
  absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassage() override { return inner_->ClaimNextPassage(); }
  absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassageAhead() override {
    return inner_->ClaimNextPassageAhead();
  }
  absl::Status MarkPassageStarted(int64_t id) override { return inner_->MarkPassageStarted(id); }
  absl::Status FinishPassageWithoutChange(int64_t id, PassageState state, const std::string& reason) override {
    return inner_->FinishPassageWithoutChange(id, state, reason);
  }
  absl::StatusOr<StoredPassage> MovePassage(int64_t id, const std::vector<PassageState>& from,
                                            PassageState to, bool released) override {
    return inner_->MovePassage(id, from, to, released);
  }
  absl::StatusOr<int> RecordFailedAttempt(int64_t id, const std::string& reason) override {
    return inner_->RecordFailedAttempt(id, reason);
  }
  absl::StatusOr<int> RequeueProcessingPassages() override { return inner_->RequeueProcessingPassages(); }
  absl::Status ReleaseClaimedPassage(int64_t id) override { return inner_->ReleaseClaimedPassage(id); }
  absl::Status LoadMap(MapState* map) override { return inner_->LoadMap(map); }
  bool ReadCommittedMap(const std::function<void(const MapState&)>& read) override;
  // Called with the map's version each time a commit reaches the map's reads (by the committing
  // thread, in commit order).
  void SetPublishedCallback(std::function<void(int64_t)> fn);
  absl::StatusOr<MapStats> GetStats() override { return inner_->GetStats(); }
  // From the in-memory map.
  absl::StatusOr<LandmarkProvenance> GetLandmarkProvenance(LandmarkId id) override;
  absl::StatusOr<VehicleCalibration> GetVehicle(const std::string& vehicle_id) override {
    return inner_->GetVehicle(vehicle_id);
  }
  absl::StatusOr<std::vector<VehicleCalibration>> ListVehicles(const std::string& after, int limit) override {
    return inner_->ListVehicles(after, limit);
  }

  // Commits through the inner store, then publishes the new copy.
  absl::Status CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) override;
  absl::Status CommitPassageExcluded(int64_t id, const MapDelta& delta) override;
  absl::Status CommitPassageRelinearized(int64_t id, const MapDelta& delta) override;

  // Served from the copy; requests with cross covariances go to the inner store.
  absl::StatusOr<LandmarkPage> QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                           bool include_cross) override;
  absl::StatusOr<LandmarkPage> GetTile(const TileId& tile, bool include_cross) override;
  absl::StatusOr<LandmarkPage> GetLandmarks(const std::vector<LandmarkId>& ids, bool include_cross) override;
  absl::StatusOr<LandmarkPage> ChangedLandmarks(const BoundingBox& box, int64_t since_version) override;
  absl::StatusOr<std::vector<RemovedLandmark>> RemovedLandmarks() override;

 private:
  using TileKey = uint64_t;
  using Bucket = std::vector<Landmark>;  // increasing id
  // One published state of the map. Immutable once published.
  struct View {
    int64_t version = 0;
    std::unordered_map<TileKey, std::shared_ptr<const Bucket>> tiles;
    // The removed landmarks' records (increasing id), loaded from the inner store and kept as
    // commits remove landmarks or bring them back.
    std::shared_ptr<const std::vector<RemovedLandmark>> removed;
  };

  CachedMapStore(std::unique_ptr<MapStoreInterface> inner, int covariance_window_hops, int covariance_cache_landmarks)
      : inner_(std::move(inner)),
        covariance_window_hops_(covariance_window_hops),
        covariance_cache_landmarks_(covariance_cache_landmarks) {}

  static TileKey KeyOf(const TileId& tile) { return (static_cast<uint64_t>(tile.x) << 32) | static_cast<uint32_t>(tile.y); }
  std::shared_ptr<const View> CurrentView() const;
  // After a commit of `delta`: applies it to the map and publishes the new view (writer only).
  void Publish(const MapDelta& delta);
  // Runs `commit` (one of the inner store's map commits) under writer_mu_ and publishes `delta`
  // when it succeeded.
  absl::Status CommitAndPublish(const MapDelta& delta, const std::function<absl::Status()>& commit);
  // Builds the view that results from applying `delta` to the current one (writer only).
  std::shared_ptr<const View> ApplyToView(const MapDelta& delta);
  // The first `limit` landmarks of `view` inside `box` that pass `keep`, in increasing id order.
  template <typename Keep>
  static std::vector<Landmark> Select(const View& view, const BoundingBox& box, const Keep& keep, size_t limit);

  const std::unique_ptr<MapStoreInterface> inner_;
  const int covariance_window_hops_;
  const int covariance_cache_landmarks_;
  // The map with its factors, for covariance reads; written under an exclusive lock by commits,
  // together with the view's publication. Writer-preferring: reads with covariances hold it for a
  // whole recovery, and a stream of them must not hold a commit's publication back.
  mutable WriterPreferringMutex map_mu_;
  MapState map_;
  // Over the whole map at one version, for reads with covariances (covariance_window_hops_ 0): one
  // factorisation serves every such read until the next commit, and on a small map (up to
  // covariance_cache_landmarks_) its whole covariance too. Built by the first read that needs it,
  // under map_mu_ shared; window_mu_ orders its building.
  struct WholeMap {
    std::shared_ptr<const MapWindow> window;            // null when it cannot be built
    std::shared_ptr<const Eigen::MatrixXd> covariance;  // null on a larger map
  };
  WholeMap WholeMapWindow() const;
  absl::Status AppendCovariances(LandmarkPage* page) const;
  mutable std::mutex window_mu_;
  mutable WholeMap whole_map_;
  mutable int64_t window_version_ = -1;
  mutable std::mutex view_mu_;  // guards the pointer only; held for a copy of it
  std::shared_ptr<const View> view_;
  std::mutex writer_mu_;                             // orders commits and their publication
  std::unordered_map<LandmarkId, TileKey> tile_of_;  // writer's index: where each landmark is
  std::function<void(int64_t)> on_published_;        // set before the first commit
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_CACHED_MAP_STORE_H_
