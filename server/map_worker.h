#ifndef CROWDMAP_SERVER_MAP_WORKER_H_
#define CROWDMAP_SERVER_MAP_WORKER_H_

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "core/estimation/map_updater.h"
#include "core/map/map_state.h"
#include "server/storage/map_store.h"
#include "server/version_notifier.h"

namespace crowdmap {

// How long the steps of one applied passage took, milliseconds.
struct AppliedPassageTimings {
  double apply_ms = 0.0;       // the whole update: compute, commit, mirror
  double solve_ms = 0.0;       // the estimator's solves (PassageUpdateSummary::solve_ms)
  double covariance_ms = 0.0;  // its covariance recoveries (PassageUpdateSummary::covariance_ms)
  double commit_ms = 0.0;      // the durable transaction
};

struct MapWorkerOptions {
  MapUpdateOptions update;
  // Worker threads. They claim and decode passages in parallel, but the map update itself is
  // serialized in arrival order, so any count gives exactly the sequential result.
  int workers = 1;
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
  absl::Status Validate() const;
};

// Applies queued passages to the map, in arrival order. Keeps an in-memory mirror of the stored
// map (this process owns the database): each passage's update is computed against the mirror,
// committed with the passage's result and the new version in one transaction, and only then
// applied to the mirror. While the map is young (MapUpdateOptions::warmup_passages, then at each
// doubling of its passage count up to relinearize_until_passages) an update re-solves the passages
// applied so far together with the new one; after a restart they are read back from the store.
class MapWorker {
 public:
  // Loads the map and puts passages left processing by an earlier run back on the queue.
  static absl::StatusOr<std::unique_ptr<MapWorker>> Create(MapStoreInterface* store, const MapWorkerOptions& options,
                                                          VersionNotifier* notifier);
  ~MapWorker();
  MapWorker(const MapWorker&) = delete;
  MapWorker& operator=(const MapWorker&) = delete;

  void Start();
  // A new passage was queued.
  void Wake();
  // Finishes the passages being applied, returns claimed but unstarted ones to the queue, joins.
  void Stop();
  // Takes an applied passage out of the map (ComputePassageExclusion, then CommitPassageExcluded),
  // after the passages already claimed; runs on the calling thread. Unavailable when stopping.
  absl::StatusOr<PassageUpdateSummary> Exclude(const StoredPassage& record);

 private:
  MapWorker(MapStoreInterface* store, const MapWorkerOptions& options, VersionNotifier* notifier)
      : store_(store), options_(options), notifier_(notifier) {}

  void Run();
  // Waits for a wake-up or the idle poll; false when stopping.
  bool WaitForWork();
  void Process(ClaimedPassage claimed, uint64_t ticket);
  void Apply(const ClaimedPassage& claimed, const Passage& passage);
  // Deletes the stored uploads of those of `folding` whose factors are now all folded into the
  // map's base (MapStoreInterface::PrunePassagePayloads); a failure is logged, never fatal.
  void PrunePayloadsOfFolded(const std::vector<MapUpdater::PassageKey>& folding);
  void Finish(const StoredPassage& record, PassageState state, const std::string& reason);
  // sched_yield() when options_.yield.
  void Yield() const;

  MapStoreInterface* const store_;
  const MapWorkerOptions options_;
  VersionNotifier* const notifier_;
  // Loads map_ and updater_ (with the passages its joint solves still need) from the store.
  absl::Status LoadMirror();
  // After a commit of `delta`: own_map_ follows it (the store's committed map already has).
  void Follow(const MapDelta& delta);

  // Touched only by the thread whose ticket is being served:
  // The map updates are computed against: the store's committed map when it keeps one
  // (MapStoreInterface::CommittedMap), otherwise own_map_, which follows each commit.
  const MapState* map_ = nullptr;
  MapState own_map_;
  std::unique_ptr<MapUpdater> updater_;
  static constexpr int kTrimEveryCommits = 16;
  int commits_since_trim_ = 0;


  std::atomic<bool> stopping_{false};
  std::mutex wake_mu_;
  std::condition_variable wake_cv_;
  bool wake_pending_ = false;

  std::mutex claim_mu_;  // claim + ticket assignment, so tickets follow arrival order
  uint64_t next_ticket_ = 0;
  std::mutex turn_mu_;
  std::condition_variable turn_cv_;
  uint64_t serving_ticket_ = 0;

  std::vector<std::thread> threads_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAP_WORKER_H_
