#ifndef CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_
#define CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_

#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "server/storage/map_store.h"
#include "server/storage/sqlite_db.h"

namespace crowdmap {

// SQLite implementation of the map store, in two files: the map (`path`) and the passage queue
// (SqliteQueuePath(path)). Each has one writer connection behind a mutex (every write is a BEGIN
// IMMEDIATE transaction) and a pool of reader connections (WAL lets them read a consistent
// snapshot while the writer commits).
class SqliteMapStore : public MapStoreInterface {
 public:
  static absl::StatusOr<std::unique_ptr<SqliteMapStore>> Open(const std::string& path,
                                                              const SqliteMapStoreOptions& options);

  absl::StatusOr<std::vector<absl::StatusOr<EnqueueOutcome>>> EnqueuePassages(const std::vector<NewPassage>& passages,
                                                                              int64_t max_queue) override;
  absl::StatusOr<StoredPassage> GetPassage(int64_t id) override;
  absl::StatusOr<StoredPassage> FindPassage(const std::string& vehicle_id, const std::string& passage_id) override;
  absl::StatusOr<std::vector<StoredPassage>> ListPassages(const PassageQuery& query) override;
  absl::StatusOr<std::string> GetPassagePayload(int64_t id) override;
  absl::StatusOr<int> PrunePassagePayloads(const std::vector<std::pair<std::string, std::string>>& passages) override;
  absl::StatusOr<int> PruneSettledPayloads(int64_t finished_before_unix_ms, int limit) override;
  absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassage() override { return Claim(/*started=*/true); }
  absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassageAhead() override { return Claim(/*started=*/false); }
  absl::Status MarkPassageStarted(int64_t id) override;
  absl::Status CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) override;
  absl::Status CommitPassageExcluded(int64_t id, const MapDelta& delta) override;
  absl::Status CommitPassageRelinearized(int64_t id, const MapDelta& delta) override;
  absl::Status FinishPassageWithoutChange(int64_t id, PassageState state, const std::string& reason) override;
  absl::StatusOr<StoredPassage> MovePassage(int64_t id, const std::vector<PassageState>& from,
                                            PassageState to, bool released) override;
  absl::StatusOr<int> RecordFailedAttempt(int64_t id, const std::string& reason) override;
  absl::StatusOr<int> RequeueProcessingPassages() override;
  absl::Status ReleaseClaimedPassage(int64_t id) override;

  absl::Status LoadMap(MapState* map) override;
  absl::StatusOr<LandmarkPage> QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                           bool include_cross) override;
  absl::StatusOr<LandmarkPage> GetTile(const TileId& tile, bool include_cross) override;
  absl::StatusOr<LandmarkPage> GetLandmarks(const std::vector<LandmarkId>& ids, bool include_cross) override;
  absl::StatusOr<LandmarkPage> ChangedLandmarks(const BoundingBox& box, int64_t since_version) override;
  absl::StatusOr<std::vector<RemovedLandmark>> RemovedLandmarks() override;
  absl::StatusOr<MapStats> GetStats() override;
  absl::StatusOr<LandmarkProvenance> GetLandmarkProvenance(LandmarkId id) override;
  absl::StatusOr<VehicleCalibration> GetVehicle(const std::string& vehicle_id) override;
  absl::StatusOr<std::vector<VehicleCalibration>> ListVehicles(const std::string& after, int limit) override;

 private:
  SqliteMapStore(const SqliteMapStoreOptions& options, std::unique_ptr<SqliteFile> map,
                 std::unique_ptr<SqliteFile> queue, std::string version_mark_path)
      : options_(options), map_(std::move(map)), queue_(std::move(queue)),
        version_mark_path_(std::move(version_mark_path)) {}


  // Helpers running on a connection the caller holds (inside its transaction when needed).
  static absl::StatusOr<std::optional<StoredPassage>> ReadPassage(SqliteConnection* db, int64_t id);
  // ClaimNextPassage (started) and ClaimNextPassageAhead (not).
  absl::StatusOr<std::optional<ClaimedPassage>> Claim(bool started);
  // Sets `set` (an SQL SET list) on processing passage `id`, in a transaction of its own;
  // FailedPrecondition when it is not processing.
  absl::Status UpdateProcessingPassage(int64_t id, const char* set);
  static absl::StatusOr<std::optional<StoredPassage>> ReadPassageByKey(SqliteConnection* db,
                                                                      const std::string& vehicle_id,
                                                                      const std::string& passage_id);
  // The earliest upload with this content digest (NewPassage::content_digest).
  static absl::StatusOr<std::optional<StoredPassage>> ReadPassageByContent(SqliteConnection* db,
                                                                           const std::string& digest);
  static absl::StatusOr<int64_t> ReadMapVersion(SqliteConnection* db);
  // Where the map file has a landmark: its R*Tree box and the tile on its row. The writer looks
  // them up here rather than in the file, and rewrites neither while the landmark stays inside
  // both (a passage moves some 2,500 landmarks of a city map by millimetres).
  struct StoredPlacement {
    double min_lat = 0.0, max_lat = 0.0, min_lon = 0.0, max_lon = 0.0;
    TileId tile;
  };
  using Placements = absl::flat_hash_map<LandmarkId, StoredPlacement>;
  // Every stored landmark's placement (in the caller's transaction).
  static absl::StatusOr<Placements> ReadPlacements(SqliteConnection* db);
  // Writes the landmark; `stored` is its placement in the file before (null for a landmark the
  // file does not hold), `written` receives its placement after.
  static absl::Status WriteLandmark(SqliteConnection* db, const Landmark& landmark, const StoredPlacement* stored,
                                    StoredPlacement* written);
  static absl::Status WriteVehicle(SqliteConnection* db, const VehicleCalibration& vehicle);
  // The vehicles selected by `where` (after the column list), bound by `bind`.
  static absl::StatusOr<std::vector<VehicleCalibration>> ReadVehicles(SqliteConnection* db, const std::string& where,
                                                                      const std::function<void(SqliteStatement&)>& bind);
  // In the writer's transaction: the stored version is delta.base_version; passage `id` is in `state`.
  static absl::Status CheckBaseVersion(SqliteConnection* db, const MapDelta& delta);
  static absl::Status CheckPassageState(SqliteConnection* db, int64_t id, PassageState state);
  // Checks that passage `id` is `from`; then in the map file's transaction checks the base version,
  // writes the delta and records the passage as `to` with its result (map_passages); then, in the
  // queue file's, sets the passage to `to` with the result. When the queue's commit fails the map's
  // stands: the passage is recorded in the queue by the next queue write (ConfirmPending) or at the
  // next start (ReconcileQueueWithMap).
  absl::Status CommitMapChange(int64_t id, const MapDelta& delta, PassageState from, PassageState to,
                               const std::optional<PassageResult>& result);
  // A map change the queue has still to record.
  struct PendingConfirmation {
    int64_t id = 0;
    PassageState from = PassageState::kProcessing;
    PassageState to = PassageState::kApplied;
    int64_t finished_unix_ms = 0;
    std::optional<PassageResult> result;
    int64_t map_version = 0;  // the map's version after the change
  };
  // In the queue writer's transaction: records one map change, and the highest map version the
  // queue has seen (queue_meta 'map_version_seen').
  static absl::Status RecordMapChange(SqliteConnection* queue, const PendingConfirmation& change);
  static absl::Status RecordMapVersionSeen(SqliteConnection* queue, int64_t version);
  // At start, after the reconciliation: a restored map is at a version clients may have seen with
  // other contents. When the queue recorded a later version, or the version mark `marked`
  // (VersionMarkPath; 0 without one) holds one, the map's version is raised to the next multiple of
  // kRestoredVersionStep above it (clients may have seen later ones still), and each landmark
  // stamped with it, so that a client watching from any version it saw gets every landmark again.
  // Returns the map's version afterwards, raised or not.
  static constexpr int64_t kRestoredVersionStep = int64_t{1} << 32;
  static absl::StatusOr<int64_t> RaiseRestoredMapVersion(SqliteConnection* map, SqliteConnection* queue,
                                                         int64_t marked);
  // "<db>.version": the last version committed, written after each map commit (not synced: a
  // hint that can only be behind the map, never ahead of it). A map restored in place of a newer
  // one finds the newer one's last version there, even when its queue was backed up with it.
  static std::string VersionMarkPath(const std::string& map_path) { return map_path + ".version"; }
  static int64_t ReadVersionMark(const std::string& path);  // 0 when absent or unreadable
  void WriteVersionMark(int64_t version) const;             // logged, not returned, on failure
  // With the queue writer held: records the pending changes (each in its own transaction); those
  // that fail stay pending.
  void ConfirmPending(SqliteConnection* queue);
  // The result of an applied passage: into passage_results (queue) or map_passages (map), in the
  // caller's transaction.
  static absl::Status WriteResult(SqliteConnection* db, const std::string& table, int64_t id,
                                  const PassageResult& result);
  // Moves a stored factor into the base tables (in the writer's transaction).
  static absl::Status FoldFactor(SqliteConnection* db, int64_t id);
  // Writes the delta's landmarks, removals and factors and its version (in the writer's transaction),
  // the landmarks against their `stored` placements; the placements written go to `written`.
  static absl::Status WriteMapDelta(SqliteConnection* db, const MapDelta& delta, const Placements& stored,
                                    Placements* written);
  // Reads landmarks, factors and version (in the caller's transaction).
  static absl::Status ReadMap(SqliteConnection* db, MapState* map);
  // Landmarks selected by `where` (after the common column list), bound by `bind`, read in one
  // snapshot with the map version; limit 0 = all.
  // `read_more`, when given, adds to the page from the same snapshot.
  absl::StatusOr<LandmarkPage> ReadPage(
      const std::string& where, const std::function<void(SqliteStatement&)>& bind, int limit, bool include_cross,
      const std::function<absl::Status(SqliteConnection*, LandmarkPage*)>& read_more = nullptr);

  const SqliteMapStoreOptions options_;
  // The map (landmarks, factors, base, version, map_passages) and the passage queue, in two files
  // with a writer each, so that an upload's commit never waits for a map commit.
  const std::unique_ptr<SqliteFile> map_;
  const std::unique_ptr<SqliteFile> queue_;
  std::vector<PendingConfirmation> pending_;  // guarded by the queue's writer lock
  // The map file's placements as of its last commit, read at the first commit and dropped when a
  // commit fails (read again at the next); guarded by the map's writer lock.
  std::optional<Placements> placements_;
  const std::string version_mark_path_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_
