#ifndef CROWDMAP_SERVER_STORAGE_MAP_STORE_H_
#define CROWDMAP_SERVER_STORAGE_MAP_STORE_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "core/geo/tiles.h"
#include "core/map/map_state.h"
#include "core/map/map_window.h"

namespace crowdmap {

enum class PassageState {
  kQueued = 1,
  kProcessing = 2,
  kApplied = 3,
  kRejected = 4,
  kFailed = 5,
  kExcluded = 6,
  kQuarantined = 7,  // refused by the map's checks (the estimator's FailedPrecondition); map unchanged
  kDiscarded = 8,    // an operator discarded it (ResolvePassage); never applied
};
constexpr int kPassageStateCount = 9;  // 0 (none) and 1..8

const char* PassageStateName(PassageState state);

// Wall-clock time, milliseconds since the Unix epoch.
int64_t NowUnixMs();

// What applying a passage did (stored with the passage in the same transaction as the map change).
struct PassageResult {
  int nodes = 0;
  int subgraphs = 0;
  int landmarks_updated = 0;
  int landmarks_created = 0;
  int landmarks_conditioned = 0;
  int detections_used = 0;
  int detections_dropped = 0;
  int solver_iterations = 0;
  double final_cost = 0.0;
  double solve_ms = 0.0;
  double covariance_ms = 0.0;
  double total_ms = 0.0;
  int64_t map_version = 0;
  std::string strategy;
};

// The store's record of one upload. `id` increases with arrival order.
struct StoredPassage {
  int64_t id = 0;
  std::string vehicle_id;
  std::string passage_id;
  PassageState state = PassageState::kQueued;
  int attempts = 0;       // times the worker started applying it, less those a restart interrupted
  int interruptions = 0;  // times a restart or crash interrupted it (RequeueProcessingPassages)
  bool released = false;  // an operator released it from quarantine: applied with the map's checks off
  // When its upload was deleted, its factors folded into the map's base (PrunePassagePayloads);
  // 0 while the store holds it.
  int64_t payload_pruned_unix_ms = 0;
  std::string error;
  int64_t received_unix_ms = 0;
  int64_t finished_unix_ms = 0;
  int64_t size_bytes = 0;
  std::optional<PassageResult> result;  // set when applied
};

// An upload to put on the queue: the idempotency key and the serialized passage.
struct NewPassage {
  std::string vehicle_id;
  std::string passage_id;
  std::string payload;
  int64_t received_unix_ms = 0;
  // PassageContentDigest of the passage: an upload under a new key whose digest the queue already
  // holds is refused (AlreadyExists). Empty: not compared.
  std::string content_digest = {};
};

struct EnqueueOutcome {
  StoredPassage record;
  bool duplicate = false;  // the key existed: `record` is the original upload
};

// A passage the worker has taken off the queue (state processing, attempts incremented).
struct ClaimedPassage {
  StoredPassage record;
  std::string payload;
};

struct PassageQuery {
  int64_t after_id = 0;  // exclusive lower bound on the id (paging)
  int limit = 100;
  std::optional<PassageState> state;
  std::string vehicle_id;  // empty = any
};

struct LandmarkPage {
  std::vector<Landmark> landmarks;            // increasing id
  // On request, the joint covariance of `landmarks`, recovered from the map's information:
  // metres^2, rows 2i and 2i + 1 the East and North axes at landmarks[i]. Empty otherwise.
  Eigen::MatrixXd covariance;
  // How `covariance` relates to the exact one (meaningful only with a covariance).
  CovarianceBound covariance_bound = CovarianceBound::kExact;
  int64_t map_version = 0;
  bool more = false;  // further landmarks match after the last one returned
  // ChangedLandmarks only: the landmarks removed from the box since its version (increasing id).
  std::vector<LandmarkId> removed;
};

// A landmark the map no longer holds (an exclusion or a re-linearisation left it without
// factors): where it last was and the map version that removed it. Kept so that a watcher whose
// copy holds it learns of its removal; a landmark that comes back loses its record.
struct RemovedLandmark {
  LandmarkId id = 0;
  LatLon position;
  int64_t version = 0;
};

// One landmark and the passages that shaped it: those whose factors the map still keeps apart
// (passages older than the retention were folded into the base and are counted by
// landmark.passages_seen only). Passages in the order their factors were made.
struct LandmarkProvenance {
  Landmark landmark;
  std::vector<std::pair<std::string, std::string>> passages;  // vehicle_id, passage_id
  int64_t map_version = 0;
};

struct MapStats {
  int64_t map_version = 0;
  int64_t landmark_count = 0;
  int64_t factor_count = 0;
  int64_t passages_by_state[kPassageStateCount] = {};  // indexed by PassageState
  int64_t queue_depth() const { return passages_by_state[1] + passages_by_state[2]; }
};

// Persistent map and passage queue. Thread-safe: reads may run concurrently with one another and
// with writes; writes are serialized. Every write is one durable transaction.
// GetPassage's answer for an id it does not hold (also the answer to a vehicle asking for another
// vehicle's passage, which must not tell the two apart).
inline absl::Status PassageIdNotFoundError(int64_t id) {
  return absl::NotFoundError(absl::StrCat("passage id ", id, " not found"));
}

class MapStoreInterface {
 public:
  virtual ~MapStoreInterface() = default;

  // Commits new uploads in one transaction, in order. Per item: the outcome, or
  // ResourceExhausted when the queue already holds `max_queue` passages (0 = unbounded).
  // Duplicates of existing keys (or of earlier items) return the original record; an upload under
  // a new key with the content digest of an earlier one (the same drive sent again under other
  // ids) is AlreadyExists, naming the earlier upload.
  virtual absl::StatusOr<std::vector<absl::StatusOr<EnqueueOutcome>>> EnqueuePassages(
      const std::vector<NewPassage>& passages, int64_t max_queue) = 0;

  virtual absl::StatusOr<StoredPassage> GetPassage(int64_t id) = 0;
  virtual absl::StatusOr<StoredPassage> FindPassage(const std::string& vehicle_id, const std::string& passage_id) = 0;
  virtual absl::StatusOr<std::vector<StoredPassage>> ListPassages(const PassageQuery& query) = 0;
  // NotFound for an unknown id and for a pruned payload (saying so).
  virtual absl::StatusOr<std::string> GetPassagePayload(int64_t id) = 0;
  // Deletes the uploads of applied passages (vehicle_id, passage_id) whose factors were all folded
  // into the map's base: nothing takes them again. Other passages are left as they are. Returns
  // how many were deleted.
  virtual absl::StatusOr<int> PrunePassagePayloads(const std::vector<std::pair<std::string, std::string>>& passages) = 0;
  // Deletes the uploads of passages that ended rejected, excluded or discarded (nothing takes
  // them again; failed and quarantined ones keep theirs, which an operator may requeue) and
  // finished before `finished_before_unix_ms`, at most `limit` of them, in the order they were
  // uploaded. Their records stay. Returns how many were deleted.
  virtual absl::StatusOr<int> PruneSettledPayloads(int64_t finished_before_unix_ms, int limit) = 0;

  // Takes the oldest queued passage to apply it: state processing, attempts + 1, started. nullopt
  // when none is queued.
  virtual absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassage() = 0;
  // The same for a worker's look-ahead (several workers choose among a few claimed passages):
  // claimed but not started, so that a crash does not count it as interrupted.
  virtual absl::StatusOr<std::optional<ClaimedPassage>> ClaimNextPassageAhead() = 0;
  // A passage claimed ahead is about to be applied (durably, before it is). FailedPrecondition
  // when it is not processing.
  virtual absl::Status MarkPassageStarted(int64_t id) = 0;
  // In one transaction: writes the map change, sets the map version to delta.version and marks
  // the passage applied with its result. FailedPrecondition when the stored map version is not
  // delta.base_version or the passage is not processing.
  virtual absl::Status CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) = 0;
  // In one transaction: writes the map change that takes an applied passage out of the map (see
  // ComputePassageExclusion) and marks it excluded. FailedPrecondition when the stored map version
  // is not delta.base_version or the passage is not applied.
  virtual absl::Status CommitPassageExcluded(int64_t id, const MapDelta& delta) = 0;
  // In one transaction: writes the map change that takes an applied passage's factors again at the
  // map's current estimate (see ComputePassageRelinearization); the passage stays applied, its
  // result unchanged. FailedPrecondition as for CommitPassageExcluded.
  virtual absl::Status CommitPassageRelinearized(int64_t id, const MapDelta& delta) = 0;
  // Ends a processing passage without a map change: state `final_state` (rejected or failed)
  // or queued (to retry), with the reason.
  virtual absl::Status FinishPassageWithoutChange(int64_t id, PassageState state, const std::string& reason) = 0;
  // Puts a processing passage that was claimed but not started back on the queue, its claim not
  // counted as an attempt (a worker stopping with passages claimed ahead). FailedPrecondition when
  // it is not processing.
  virtual absl::Status ReleaseClaimedPassage(int64_t id) = 0;
  // Records a failed attempt of a processing passage that stays processing (retried in place):
  // attempts + 1 and the reason. Returns the new attempt count.
  virtual absl::StatusOr<int> RecordFailedAttempt(int64_t id, const std::string& reason) = 0;
  // An operator's decision on a finished passage: moves it from one of `from` to `to` (queued:
  // with its attempts and error cleared, and marked `released` or not). FailedPrecondition when it
  // is in none of `from`; NotFound for an unknown id. Returns the updated record.
  virtual absl::StatusOr<StoredPassage> MovePassage(int64_t id, const std::vector<PassageState>& from,
                                                    PassageState to, bool released) = 0;
  // Start-up recovery: every processing passage goes back to queued, its interrupted attempt
  // uncounted and, if it was started, counted as an interruption instead. Returns how many.
  virtual absl::StatusOr<int> RequeueProcessingPassages() = 0;

  // Loads the whole map (landmarks, factors, version) into `map`.
  virtual absl::Status LoadMap(MapState* map) = 0;
  // Calls `read` with the map as last committed, when the store keeps it in memory
  // (CachedMapStore), and returns true; false otherwise. The map updater reads it this way instead
  // of keeping a copy of its own (at city scale the map's information is the process's largest
  // structure). `read` runs under the store's read lock, which commits wait for: keep it short,
  // copy what must outlive it (MapReadRecorder), and do not call the store from it.
  virtual bool ReadCommittedMap(const std::function<void(const MapState&)>& read) { return false; }
  // Landmarks inside `box` with id > after_id, at most `limit` (0 = all), with their cross-covariances on request.
  virtual absl::StatusOr<LandmarkPage> QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                                   bool include_cross) = 0;
  // Landmarks stored in the storage-zoom tile, with cross blocks on request.
  virtual absl::StatusOr<LandmarkPage> GetTile(const TileId& tile, bool include_cross) = 0;
  // The landmarks of `ids` that the map holds (increasing id; the others are left out), with their
  // cross-covariances on request, as QueryRegion gives them for the landmarks of a box.
  virtual absl::StatusOr<LandmarkPage> GetLandmarks(const std::vector<LandmarkId>& ids, bool include_cross) = 0;
  // Landmarks inside `box` whose version is greater than `since_version`, and in `removed` those
  // removed from it after that version.
  virtual absl::StatusOr<LandmarkPage> ChangedLandmarks(const BoundingBox& box, int64_t since_version) = 0;
  // Every removed landmark's record (RemovedLandmark), in increasing id.
  virtual absl::StatusOr<std::vector<RemovedLandmark>> RemovedLandmarks() = 0;
  virtual absl::StatusOr<MapStats> GetStats() = 0;
  // Landmark `id` and the passages that shaped it. NotFound when it is not mapped.
  virtual absl::StatusOr<LandmarkProvenance> GetLandmarkProvenance(LandmarkId id) = 0;
  // The camera calibration estimated for `vehicle_id` (written with the map's changes). NotFound
  // when none of its passages estimated one.
  virtual absl::StatusOr<VehicleCalibration> GetVehicle(const std::string& vehicle_id) = 0;
  // The vehicles' with vehicle_id > `after`, in increasing vehicle_id, at most `limit` (0 = all).
  virtual absl::StatusOr<std::vector<VehicleCalibration>> ListVehicles(const std::string& after = "", int limit = 0) = 0;
};

struct SqliteMapStoreOptions {
  int busy_timeout_ms = 5000;
  // Upper bound on pooled read connections kept open (more may be opened under load).
  int max_idle_readers = 32;
  // Writes give the CPU to other threads (sched_yield) about every this many SQLite virtual
  // machine steps (4000 is some 0.1 ms of a passage's commit), so that a large commit does not
  // hold a core for milliseconds while requests wait. 0: never.
  int write_yield_vm_steps = 0;
  // Cross-covariances of a read are recovered within this many links of the landmarks read
  // (MapWindowOptions::hops; 0 = the whole connected map, exact).
  int covariance_window_hops = 0;

  absl::Status Validate() const;
};

// The passage queue's file beside the map's: `<path>.queue`. Back both up together.
std::string SqliteQueuePath(const std::string& map_path);

// Opens (creating and migrating when needed) the SQLite map store at `path` with its queue file.
// A map file of schema 4 or older (queue and map in one file) has its queue moved to the queue
// file. FailedPrecondition when the map file exists at a later schema and its queue file does not.
absl::StatusOr<std::unique_ptr<MapStoreInterface>> CreateSqliteMapStore(const std::string& path,
                                                                        const SqliteMapStoreOptions& options = {});

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_MAP_STORE_H_
