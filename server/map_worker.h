#ifndef CROWDMAP_SERVER_MAP_WORKER_H_
#define CROWDMAP_SERVER_MAP_WORKER_H_

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "core/estimation/map_updater.h"
#include "core/map/map_access.h"
#include "core/map/map_state.h"
#include "server/passage_schedule.h"
#include "server/storage/map_store.h"

namespace crowdmap {

// How long the steps of one applied passage took, milliseconds.
struct AppliedPassageTimings {
  double apply_ms = 0.0;       // the whole update: compute, commit, mirror
  double solve_ms = 0.0;       // the estimator's solves (PassageUpdateSummary::solve_ms)
  double covariance_ms = 0.0;  // its covariance recoveries (PassageUpdateSummary::covariance_ms)
  double commit_ms = 0.0;      // the durable transaction
  int recomputed = 0;          // times the update was computed again (MapWorkerOptions::workers)
  // The consistency tests that weighted the passage down: the whole subgraph's chi-square
  // (MapUpdateOptions::inflation_test_sigmas), and each sensor's own (odometry, GNSS, camera;
  // sensor_test_sigmas).
  bool inflated = false;
  bool sensor_inflated[kPassageSensors] = {false, false, false};
};

struct MapWorkerOptions {
  MapUpdateOptions update;
  // Worker threads. Each claims a passage and computes its update against the map as committed
  // when it began; an update is committed only if no change committed meanwhile touched what it
  // read (core/map/map_access.h), and is computed again otherwise. With one worker, passages are
  // applied in arrival order; with more, passages whose neighbourhoods do not overlap are applied
  // concurrently, and the map is the one the same passages applied one at a time in their commit
  // order would give; each worker takes, among the next few queued passages, the one furthest from
  // the passages being computed (passage_schedule.h). Each worker's computation holds its own copy
  // of the passage's matrices.
  int workers = 1;
  static constexpr int kMaxWorkers = 64;
  // Attempts (including start-ups interrupted while processing) before a passage is failed.
  int max_attempts = 3;
  // A passage interrupted this many times while being applied (restarts, crashes) is marked failed,
  // so that one that crashes the server cannot keep it from serving.
  int max_interruptions = 10;
  // A passage whose joint solve (the young map's warm-up and re-solves, seconds long) was
  // interrupted this many times is applied by a sequential update instead, which takes
  // milliseconds: restarts during a long solve must not end with the passage failed.
  int sequential_after_interruptions = 3;
  std::chrono::milliseconds idle_poll{200};
  // The uploads of passages that ended rejected, excluded or discarded are deleted this many days
  // after they finished (MapStoreInterface::PruneSettledPayloads), looked for while the queue is
  // empty, at most every idle_prune_every; their records stay. 0 = kept for good.
  double settled_upload_retention_days = 30.0;
  static constexpr double kMaxRetentionDays = 36525.0;
  std::chrono::milliseconds idle_prune_every{60000};
  // Scheduling niceness of the worker threads (Linux, 0..19). Applying passages is background
  // work: a positive value lets request handling preempt the solver, so reads stay fast while the
  // map is updated, and costs nothing when the CPU is otherwise idle.
  int nice = 10;
  // Yield the CPU (sched_yield) at each MapUpdateOptions::yield_point of an update. Niceness alone
  // does not keep reads fast: the kernel lets a running thread finish its time slice (over a
  // millisecond) before a woken request thread gets the core, whatever the priorities, so a solver
  // that computes without pause holds one of the cores for a slice at a time. Yielding every
  // millisecond or so hands the core to waiting requests at once and costs a system call when none
  // waits. See server/README.md for the measurements.
  bool yield = true;
  // Called on the worker's thread after each passage is applied (metrics); empty = nothing.
  std::function<void(const AppliedPassageTimings&)> on_applied;
  // Called on the worker's thread after each re-linearisation (MapUpdateOptions::relinearize_sigmas)
  // with whether it was committed (false: refused or failed, see the log); empty = nothing.
  std::function<void(bool committed)> on_relinearized;
  absl::Status Validate() const;
};

// Applies queued passages to the map. Computes each update against the store's committed map
// (MapStoreInterface::ReadCommittedMap, through a MapReadRecorder) and commits it with the
// passage's result and the new version in one transaction. While the map is young
// (MapUpdateOptions::warmup_passages, then at each doubling of its passage count up to
// relinearize_until_passages) an update re-solves the passages applied so far together with the
// new one; after a restart they are read back from the store.
class MapWorker {
 public:
  // Loads the map and puts passages left processing by an earlier run back on the queue. The store
  // must keep its committed map in memory (ReadCommittedMap).
  static absl::StatusOr<std::unique_ptr<MapWorker>> Create(MapStoreInterface* store, const MapWorkerOptions& options);
  ~MapWorker();
  MapWorker(const MapWorker&) = delete;
  MapWorker& operator=(const MapWorker&) = delete;

  void Start();
  // A new passage was queued.
  void Wake();
  // Finishes the passages being applied (a passage that must be computed again goes back to the
  // queue), joins.
  void Stop();
  // Takes an applied passage out of the map (ComputePassageExclusion, then CommitPassageExcluded),
  // like an update; runs on the calling thread. Unavailable when stopping.
  absl::StatusOr<PassageUpdateSummary> Exclude(const StoredPassage& record);
  // Re-linearisations owed (MapUpdateOptions::relinearize_sigmas): relinearizations_per_passage
  // for each passage applied, counted before its commit (taken back if it fails), until done or
  // until no retained passage qualifies; 0 when off. With the queue empty (GetMapInfo's
  // queue_depth) and this 0, the map changes no more until something arrives.
  int64_t relinearizations_due() const { return relinearizations_due_.load(); }

 private:
  MapWorker(MapStoreInterface* store, const MapWorkerOptions& options) : store_(store), options_(options) {}

  // One change computed against the committed map, with what it read there.
  struct Computation {
    absl::StatusOr<PassageUpdate> update = absl::UnknownError("not computed");
    MapReadSet read;
    int64_t base_version = 0;    // of the map it read
    int64_t last_factor_id = 0;  // of the map its delta's new factor ids follow
    std::optional<MapUpdater::Plan> plan;  // a passage's (an exclusion has none)
  };
  // What a commit changed, kept while computations begun before it may still commit.
  struct CommittedChange {
    int64_t base_version = 0;
    int64_t version = 0;
    MapWriteSet written;
  };
  static constexpr size_t kCommittedChangesKept = 64;

  // A claimed passage, decoded, waiting for a worker.
  struct Claimed {
    StoredPassage record;
    absl::StatusOr<Passage> passage = absl::UnknownError("not decoded");
    ScheduleCandidate schedule;
  };
  // Passages claimed ahead of the workers, among which each takes the one furthest from the
  // passages being computed (passage_schedule.h): kLookaheadPerWorker per worker when there are
  // several, one otherwise (arrival order).
  static constexpr int kLookaheadPerWorker = 2;
  static constexpr int kMaxPassedOver = 8;

  void Run();
  // Waits for a wake-up or the idle poll; false when stopping.
  bool WaitForWork();
  // Under claim_mu_: the passage this worker applies next, its route recorded as in flight; none
  // when the queue is empty.
  std::optional<Claimed> TakeNext();
  void Process(Claimed claimed);
  void Apply(const StoredPassage& record, const Passage& passage);
  // Runs `compute` against the committed map, which other workers' commits may change meanwhile,
  // and records what it read; `plan`, if given, runs first, under state_mu_ and at the version
  // the computation starts from.
  Computation ComputeOnCommittedMap(
      const std::function<absl::StatusOr<PassageUpdate>(const MapReaderInterface&)>& compute,
      const std::function<void()>& plan = nullptr);
  // Under state_mu_: whether `c`'s outcome still holds (nothing committed since its base touched
  // what it read, and a joint solve's passages are still the map's).
  bool StillValid(const Computation& c) const;
  // Under state_mu_: moves `c`'s delta onto the committed map (RebaseDelta).
  void RebaseOntoCommitted(Computation* c);
  // Under state_mu_, after a commit of `delta`, which changed `written`.
  void RecordCommitted(const MapDelta& delta, MapWriteSet written);
  // Computes a change that is not a queued passage's update (an exclusion, a re-linearisation)
  // against the committed map, with the updater's options, until it still holds when committed;
  // commits it with `commit` and then, under state_mu_, calls `committed`. Unavailable when
  // stopping; the computation's or the commit's error otherwise.
  absl::StatusOr<PassageUpdate> CommitChange(
      const std::function<absl::StatusOr<PassageUpdate>(const MapReaderInterface&, const MapUpdateOptions&)>& compute,
      const std::function<absl::Status(const MapDelta&)>& commit, const std::function<void(const MapDelta&)>& committed);
  // Local re-linearisation (MapUpdateOptions::relinearize_sigmas) while the queue is empty: if a
  // re-linearisation is due, the retained passage whose landmarks moved furthest since its factors
  // were taken, beyond the threshold, is taken again at the map's current estimate
  // (ComputePassageRelinearization, CommitPassageRelinearized). False when none was due or none
  // qualified (then only those other workers are computing stay due). A failure is logged,
  // counted as done, and that passage left until it is applied anew. Queued passages come first:
  // a worker with a backlog applies it at full speed and catches up on its re-linearisations (up
  // to kMaxRelinearizationsDue) once it is idle.
  bool RelinearizeOneWhileIdle();
  absl::Status Relinearize(const MapUpdater::PassageKey& key);
  // Deletes the stored uploads of `folded` passages (MapStoreInterface::PrunePassagePayloads); a
  // failure is logged, never fatal.
  void PrunePayloads(const std::vector<MapUpdater::PassageKey>& folded);
  // While the queue is empty, at most every options_.idle_prune_every: the folded passages' uploads whose
  // deletion failed before, and those of settled passages past options_.settled_upload_retention_days.
  void PruneWhileIdle();
  void Finish(const StoredPassage& record, PassageState state, const std::string& reason);
  // A claimed passage back to the queue, its attempt not counted (MapStoreInterface::
  // ReleaseClaimedPassage): not started, or stopped by a stop before anything about it was learnt
  // (`reason`, logged).
  void Release(const StoredPassage& record, const char* reason);
  // sched_yield() when options_.yield.
  void Yield() const;
  // Loads updater_ (with the passages its joint solves still need) from the store.
  absl::Status LoadUpdater();

  MapStoreInterface* const store_;
  const MapWorkerOptions options_;

  // One commit at a time: held from a computation's validation until the commit is recorded.
  // Taken before state_mu_, never inside it.
  std::mutex commit_mu_;
  // The updater and what was committed; not held during a commit's durable transaction. Taken
  // before the store's map lock (ReadCommittedMap), never inside it.
  std::mutex state_mu_;
  std::unique_ptr<MapUpdater> updater_;
  std::deque<CommittedChange> committed_;
  int64_t committed_version_ = 0;
  int64_t committed_last_factor_id_ = 0;
  static constexpr int kTrimEveryCommits = 16;
  int commits_since_trim_ = 0;
  std::set<MapUpdater::PassageKey> relinearizing_;  // re-linearisations being computed
  // Owed, those being computed included; changed under state_mu_, read by GetMapInfo.
  std::atomic<int64_t> relinearizations_due_{0};
  static constexpr int64_t kMaxRelinearizationsDue = 256;

  std::atomic<bool> stopping_{false};
  std::mutex wake_mu_;
  std::condition_variable wake_cv_;
  bool wake_pending_ = false;
  std::mutex claim_mu_;  // one claim at a time; guards the two below
  std::deque<Claimed> lookahead_;
  std::map<int64_t, RouteFootprint> in_flight_;  // routes of the passages being computed, by id

  std::mutex prune_mu_;  // guards the two below
  std::vector<MapUpdater::PassageKey> prune_failed_;  // folded passages whose uploads are still stored
  std::chrono::steady_clock::time_point next_idle_prune_{};
  // Uploads deleted per transaction: the queue file's writer is the uploads' too, and their
  // acknowledgements must not wait behind a long deletion (the rest follows at the next idle step).
  static constexpr int kSettledPruneBatch = 64;

  std::vector<std::thread> threads_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAP_WORKER_H_
