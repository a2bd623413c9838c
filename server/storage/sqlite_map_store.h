#ifndef CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_
#define CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_

#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "server/storage/map_store.h"
#include "server/storage/sqlite_db.h"

namespace crowdmap {

// SQLite implementation of the map store: one writer connection behind a mutex (every write is a
// BEGIN IMMEDIATE transaction), and a pool of reader connections (WAL lets them read a consistent
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
  absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassage() override;
  absl::Status CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) override;
  absl::Status CommitPassageExcluded(int64_t id, const MapDelta& delta) override;
  absl::Status FinishPassageWithoutChange(int64_t id, PassageState state, const std::string& reason) override;
  absl::StatusOr<StoredPassage> MovePassage(int64_t id, const std::vector<PassageState>& from,
                                            PassageState to) override;
  absl::StatusOr<int> RecordFailedAttempt(int64_t id, const std::string& reason) override;
  absl::StatusOr<int> RequeueProcessingPassages() override;

  absl::Status LoadMap(MapState* map) override;
  absl::StatusOr<LandmarkPage> QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                           bool include_cross) override;
  absl::StatusOr<LandmarkPage> GetTile(const TileId& tile, bool include_cross) override;
  absl::StatusOr<LandmarkPage> ChangedLandmarks(const BoundingBox& box, int64_t since_version) override;
  absl::StatusOr<MapStats> GetStats() override;
  absl::StatusOr<LandmarkProvenance> GetLandmarkProvenance(LandmarkId id) override;

 private:
  // A pooled reader connection, returned to the pool when the lease ends.
  class ReaderLease {
   public:
    ReaderLease(SqliteMapStore* store, std::unique_ptr<SqliteConnection> db) : store_(store), db_(std::move(db)) {}
    ReaderLease(ReaderLease&&) = default;
    ~ReaderLease();
    SqliteConnection* operator->() { return db_.get(); }
    SqliteConnection* get() { return db_.get(); }

   private:
    SqliteMapStore* store_;
    std::unique_ptr<SqliteConnection> db_;
  };

  SqliteMapStore(std::string path, const SqliteMapStoreOptions& options, std::unique_ptr<SqliteConnection> writer)
      : path_(std::move(path)), options_(options), writer_(std::move(writer)) {}

  absl::StatusOr<ReaderLease> AcquireReader();
  void ReleaseReader(std::unique_ptr<SqliteConnection> db);

  // Helpers running on a connection the caller holds (inside its transaction when needed).
  static absl::StatusOr<std::optional<StoredPassage>> ReadPassage(SqliteConnection* db, int64_t id);
  static absl::StatusOr<std::optional<StoredPassage>> ReadPassageByKey(SqliteConnection* db,
                                                                      const std::string& vehicle_id,
                                                                      const std::string& passage_id);
  static absl::StatusOr<int64_t> ReadMapVersion(SqliteConnection* db);
  static absl::Status WriteLandmark(SqliteConnection* db, const Landmark& landmark);
  // In the writer's transaction: the stored version is delta.base_version; passage `id` is in `state`.
  static absl::Status CheckBaseVersion(SqliteConnection* db, const MapDelta& delta);
  static absl::Status CheckPassageState(SqliteConnection* db, int64_t id, PassageState state);
  // One write transaction: checks the base version and that passage `id` is `from`, writes the
  // delta, sets the passage to `to`, runs `also` (may be empty), commits.
  absl::Status CommitMapChange(int64_t id, const MapDelta& delta, PassageState from, PassageState to,
                               const std::function<absl::Status(SqliteConnection*)>& also);
  // The result of an applied passage (in the writer's transaction).
  static absl::Status WriteResult(SqliteConnection* db, int64_t id, const PassageResult& result);
  // Moves a stored factor into the base tables (in the writer's transaction).
  static absl::Status FoldFactor(SqliteConnection* db, int64_t id);
  // Writes the delta's landmarks, removals and factors and its version (in the writer's transaction).
  static absl::Status WriteMapDelta(SqliteConnection* db, const MapDelta& delta);
  // Reads landmarks, factors and version (in the caller's transaction).
  static absl::Status ReadMap(SqliteConnection* db, MapState* map);
  // Landmarks selected by `where` (after the common column list), bound by `bind`, read in one
  // snapshot with the map version; limit 0 = all.
  absl::StatusOr<LandmarkPage> ReadPage(const std::string& where, const std::function<void(SqliteStatement&)>& bind,
                                        int limit, bool include_cross);

  const std::string path_;
  const SqliteMapStoreOptions options_;
  std::mutex writer_mu_;
  std::unique_ptr<SqliteConnection> writer_;
  std::mutex readers_mu_;
  std::vector<std::unique_ptr<SqliteConnection>> idle_readers_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_SQLITE_MAP_STORE_H_
