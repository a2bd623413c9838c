#include "server/map_worker.h"

#include <malloc.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <optional>
#include <set>
#include <thread>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "core/estimation/passage_exclusion.h"
#include "server/request_log.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

PassageResult ResultFromSummary(const PassageUpdateSummary& s, UpdateStrategy strategy) {
  PassageResult r;
  r.nodes = s.nodes;
  r.subgraphs = s.subgraphs;
  r.landmarks_updated = s.landmarks_updated;
  r.landmarks_created = s.landmarks_created;
  r.landmarks_conditioned = s.landmarks_conditioned;
  r.detections_used = s.detections_used;
  r.detections_dropped = s.detections_dropped;
  r.solver_iterations = s.solver_iterations;
  r.final_cost = s.final_cost;
  r.solve_ms = s.solve_ms;
  r.covariance_ms = s.covariance_ms;
  r.total_ms = s.total_ms;
  r.map_version = s.map_version;
  r.strategy = absl::StrCat(UpdateStrategyName(strategy), s.joint_passages > 0 ? "+joint" : "");
  return r;
}

// A queued passage's payload (the serialized wire Passage) as a core passage.
absl::StatusOr<Passage> DecodeStoredPassage(const std::string& payload) {
  pb::Passage wire;
  if (!wire.ParseFromString(payload)) return absl::InvalidArgumentError("passage: stored payload does not parse");
  return PassageFromProto(wire);
}

}  // namespace

absl::Status MapWorkerOptions::Validate() const {
  // Each worker holds a passage's matrices (100-200 MB at 100k landmarks): more than the cores
  // only costs memory and computations done again.
  if (workers < 1 || workers > kMaxWorkers) {
    return absl::InvalidArgumentError(absl::StrCat("workers: must lie in [1, ", kMaxWorkers, "], got ", workers));
  }
  if (max_attempts < 1) return absl::InvalidArgumentError(absl::StrCat("max_attempts: must be >= 1, got ", max_attempts));
  if (sequential_after_interruptions < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("sequential_after_interruptions: must be >= 1, got ", sequential_after_interruptions));
  }
  if (max_interruptions < 1) {
    return absl::InvalidArgumentError(absl::StrCat("max_interruptions: must be >= 1, got ", max_interruptions));
  }
  if (nice < 0 || nice > 19) return absl::InvalidArgumentError(absl::StrCat("worker-nice: must lie in [0, 19], got ", nice));
  // (at most a hundred years: the retention is taken in milliseconds as a 64-bit integer)
  if (!(settled_upload_retention_days >= 0.0 && settled_upload_retention_days <= kMaxRetentionDays)) {
    return absl::InvalidArgumentError(absl::StrCat("settled-upload-retention-days: must lie in [0, ", kMaxRetentionDays,
                                                   "] (0 = keep for good), got ", settled_upload_retention_days));
  }
  return update.Validate();
}

absl::StatusOr<std::unique_ptr<MapWorker>> MapWorker::Create(MapStoreInterface* store,
                                                             const MapWorkerOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  std::unique_ptr<MapWorker> worker(new MapWorker(store, options));
  auto requeued = store->RequeueProcessingPassages();
  if (!requeued.ok()) return requeued.status();
  if (*requeued > 0) spdlog::warn("event=requeue passages={} reason=\"processing at start-up\"", *requeued);
  if (auto s = worker->LoadUpdater(); !s.ok()) return s;
  return worker;
}

absl::Status MapWorker::LoadUpdater() {
  // The counts, the passages and the map at one version: no commit in between (a reload while
  // other workers run).
  std::lock_guard<std::mutex> no_commit(commit_mu_);
  absl::StatusOr<MapStats> stats = store_->GetStats();
  if (!stats.ok()) return stats.status();
  const int64_t applied_count = stats->passages_by_state[static_cast<int>(PassageState::kApplied)];
  // The joint solves take the map's first passages, in the order of their ids (with several
  // workers the order of their commits may differ; a joint solve takes them all at once).
  std::vector<Passage> kept;
  const int needed = JointSolvePassages(options_.update);
  // A map that took more passages than that, exclusions included, has no joint solve left
  // (MapUpdater::joint_next), and the uploads of its first passages may be gone.
  const int64_t taken_count = applied_count + stats->passages_by_state[static_cast<int>(PassageState::kExcluded)];
  if (taken_count <= needed) {
    PassageQuery query;
    query.state = PassageState::kApplied;
    query.limit = needed;
    absl::StatusOr<std::vector<StoredPassage>> applied = store_->ListPassages(query);
    if (!applied.ok()) return applied.status();
    for (const StoredPassage& record : *applied) {
      absl::StatusOr<std::string> payload = store_->GetPassagePayload(record.id);
      if (absl::IsNotFound(payload.status()) && record.payload_pruned_unix_ms > 0) {
        // An applied passage without its upload: a map restored from a backup brought back one
        // that was excluded and whose upload was deleted since. The joint solves need every
        // passage: the map goes on with sequential updates (MapUpdater takes none with fewer
        // passages kept than applied).
        spdlog::warn("event=joint_solves_given_up passage={} reason=\"{}\"", record.id,
                     std::string(payload.status().message()));
        kept.clear();
        break;
      }
      if (!payload.ok()) return payload.status();
      absl::StatusOr<Passage> passage = DecodeStoredPassage(*payload);
      if (!passage.ok()) return absl::DataLossError(absl::StrCat("applied passage ", record.id, ": ", passage.status().message()));
      kept.push_back(*std::move(passage));
    }
  }
  MapUpdateOptions update = options_.update;
  if (options_.yield) update.yield_point = [this] { Yield(); };
  std::lock_guard<std::mutex> lock(state_mu_);
  const bool kept_in_memory = store_->ReadCommittedMap([&](const MapState& map) {
    updater_ = std::make_unique<MapUpdater>(update, std::move(kept), applied_count, &map);
    committed_.clear();
    committed_version_ = map.version();
    committed_last_factor_id_ = map.last_factor_id();
    spdlog::info("event=map_loaded landmarks={} factors={} map_version={} warming_up={} next_joint_solve={}",
                 map.landmark_count(), map.factor_count(), map.version(), updater_->warming_up(),
                 updater_->joint_next());
  });
  if (!kept_in_memory) return absl::InternalError("the map worker needs a store that keeps its map in memory");
  return absl::OkStatus();
}

MapWorker::~MapWorker() { Stop(); }

void MapWorker::Start() {
  for (int i = 0; i < options_.workers; ++i) threads_.emplace_back([this] { Run(); });
}

void MapWorker::Yield() const {
  if (options_.yield) sched_yield();
}

void MapWorker::Wake() {
  {
    std::lock_guard<std::mutex> lock(wake_mu_);
    wake_pending_ = true;
  }
  wake_cv_.notify_all();
}

void MapWorker::Stop() {
  stopping_ = true;
  wake_cv_.notify_all();
  for (std::thread& t : threads_) t.join();
  threads_.clear();
  std::lock_guard<std::mutex> lock(claim_mu_);
  for (const Claimed& c : lookahead_) Release(c.record, "not started");
  lookahead_.clear();
}

bool MapWorker::WaitForWork() {
  std::unique_lock<std::mutex> lock(wake_mu_);
  wake_cv_.wait_for(lock, options_.idle_poll, [this] { return wake_pending_ || stopping_.load(); });
  wake_pending_ = false;
  return !stopping_;
}

void MapWorker::Run() {
  // Per-thread niceness: on Linux a thread id is a valid PRIO_PROCESS target.
  if (options_.nice > 0 && setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), options_.nice) != 0) {
    spdlog::warn("event=worker_nice_failed nice={} errno={}", options_.nice, errno);
  }
  while (!stopping_) {
    std::optional<Claimed> next;
    {
      std::lock_guard<std::mutex> lock(claim_mu_);
      if (stopping_) break;
      next = TakeNext();
    }
    if (!next) {
      PruneWhileIdle();
      if (RelinearizeOneWhileIdle()) continue;
      if (!WaitForWork()) break;
      continue;
    }
    const int64_t id = next->record.id;
    Process(*std::move(next));
    std::lock_guard<std::mutex> lock(claim_mu_);
    in_flight_.erase(id);
  }
}

std::optional<MapWorker::Claimed> MapWorker::TakeNext() {
  const size_t lookahead = options_.workers > 1 ? static_cast<size_t>(kLookaheadPerWorker * options_.workers) : 1;
  while (lookahead_.size() < lookahead) {
    // One worker applies what it claims; several choose among the passages claimed ahead, and
    // mark the one taken as started below.
    auto next = lookahead == 1 ? store_->ClaimNextPassage() : store_->ClaimNextPassageAhead();
    if (!next.ok()) {
      spdlog::error("event=claim_failed error=\"{}\"", next.status().ToString());
      break;
    }
    if (!next->has_value()) break;
    Claimed& c = lookahead_.emplace_back();
    c.record = std::move((*next)->record);
    c.passage = DecodeStoredPassage((*next)->payload);
    if (c.passage.ok()) c.schedule.route = FootprintOf(*c.passage);
  }
  if (lookahead_.empty()) return std::nullopt;
  std::vector<ScheduleCandidate> candidates;
  for (const Claimed& c : lookahead_) candidates.push_back(c.schedule);
  std::vector<const RouteFootprint*> in_flight;
  for (const auto& [id, route] : in_flight_) in_flight.push_back(&route);
  const size_t pick = PickNextPassage(candidates, in_flight, kMaxPassedOver);
  if (lookahead > 1) {
    // Before it is applied: a crash while it is counts as its interruption.
    if (absl::Status s = store_->MarkPassageStarted(lookahead_[pick].record.id); !s.ok()) {
      spdlog::error("event=mark_started_failed id={} error=\"{}\"", lookahead_[pick].record.id, s.ToString());
      return std::nullopt;  // taken again at the next poll
    }
  }
  for (size_t i = 0; i < pick; ++i) ++lookahead_[i].schedule.passed_over;
  Claimed taken = std::move(lookahead_[pick]);
  lookahead_.erase(lookahead_.begin() + static_cast<std::ptrdiff_t>(pick));
  if (taken.schedule.route) in_flight_[taken.record.id] = *taken.schedule.route;
  return taken;
}

void MapWorker::Process(Claimed claimed) {
  const absl::StatusOr<Passage>& passage = claimed.passage;
  const StoredPassage& record = claimed.record;
  if (stopping_) {
    Release(record, "not started");
  } else if (!passage.ok()) {
    Finish(record, PassageState::kRejected, std::string(passage.status().message()));
  } else if (record.interruptions >= options_.max_interruptions) {
    Finish(record, PassageState::kFailed,
           absl::StrCat("interrupted ", record.interruptions,
                        " times while being applied (the server stopped or crashed each time); last error: ",
                        record.error.empty() ? "none" : record.error));
  } else if (record.attempts > options_.max_attempts) {
    Finish(record, PassageState::kFailed,
           absl::StrCat("gave up after ", record.attempts - 1, " attempts; last: ", record.error));
  } else {
    Apply(record, *passage);
  }
}

namespace {

// A storage error that says nothing about the passage (a full disk, an I/O error, a busy
// database): its commit is retried after a pause, and no attempt is counted.
bool IsTransientStorageError(const absl::Status& s) {
  return s.code() == absl::StatusCode::kResourceExhausted || s.code() == absl::StatusCode::kUnavailable;
}

// The passages that `folded` (factor ids of `map`) fold wholly into the map's base: all their
// factors are among them.
std::vector<MapUpdater::PassageKey> WhollyFolded(const MapReaderInterface& map, const std::vector<int64_t>& folded) {
  std::set<MapUpdater::PassageKey> keys;
  for (int64_t id : folded) {
    if (const MapFactor* f = map.FindFactor(id); f != nullptr) keys.insert({f->vehicle_id, f->passage_id});
  }
  const std::set<int64_t> folding(folded.begin(), folded.end());
  std::vector<MapUpdater::PassageKey> out;
  std::vector<int64_t> ids;
  for (const MapUpdater::PassageKey& key : keys) {
    ids.clear();
    map.AppendPassageFactorIds(key.first, key.second, &ids);
    if (std::all_of(ids.begin(), ids.end(), [&](int64_t id) { return folding.count(id) > 0; })) out.push_back(key);
  }
  return out;
}

}  // namespace

MapWorker::Computation MapWorker::ComputeOnCommittedMap(
    const std::function<absl::StatusOr<PassageUpdate>(const MapReaderInterface&)>& compute,
    const std::function<void()>& plan) {
  std::optional<MapReadRecorder> recorder;
  {
    // The plan and the version it is computed against, together. A commit under way (between
    // its validation and RecordCommitted, without state_mu_) may already show in the store's map:
    // the computation still counts as made against the version before it, and is checked against
    // that commit's changes like any computation that began before a commit.
    std::lock_guard<std::mutex> lock(state_mu_);
    if (plan) plan();
    recorder.emplace(
        [this](const std::function<void(const MapReaderInterface&)>& read) {
          store_->ReadCommittedMap([&](const MapState& map) { read(map); });
        },
        committed_version_, committed_last_factor_id_);
  }
  Computation c;
  c.base_version = recorder->version();
  c.last_factor_id = recorder->last_factor_id();
  c.update = compute(*recorder);
  c.read = recorder->TakeRead();
  return c;
}

bool MapWorker::StillValid(const Computation& c) const {
  if (c.base_version == committed_version_) return true;
  // A joint solve takes all the map's passages: it is valid only if none came in since.
  if (c.plan && (c.plan->joint || updater_->joint_next()) && c.plan->applied_count != updater_->applied_count()) {
    return false;
  }
  // The changes since its base must all be known, and none may touch what it read.
  if (committed_.empty() || committed_.front().base_version > c.base_version) return false;
  for (const CommittedChange& change : committed_) {
    if (change.version > c.base_version && Overlaps(c.read, change.written)) return false;
  }
  return true;
}

void MapWorker::RebaseOntoCommitted(Computation* c) {
  RebaseDelta(c->last_factor_id, committed_version_, committed_last_factor_id_, &c->update->delta);
  c->last_factor_id = committed_last_factor_id_;
  c->update->summary.map_version = c->update->delta.version;
}

void MapWorker::RecordCommitted(const MapDelta& delta, MapWriteSet written) {
  committed_.push_back({delta.base_version, delta.version, std::move(written)});
  if (committed_.size() > kCommittedChangesKept) committed_.pop_front();
  committed_version_ = std::max(delta.version, delta.base_version);
  for (const auto& [id, factor] : delta.added_factors) {
    committed_last_factor_id_ = std::max(committed_last_factor_id_, id);
  }
}

void MapWorker::PrunePayloads(const std::vector<MapUpdater::PassageKey>& folded) {
  if (folded.empty()) return;
  absl::StatusOr<int> pruned = store_->PrunePassagePayloads(folded);
  if (!pruned.ok()) {  // the uploads stay (nothing is lost, the queue file is only larger) until a retry
    spdlog::warn("event=payload_prune_failed passages={} error=\"{}\" retry=\"while idle\"", folded.size(),
                 pruned.status().ToString());
    std::lock_guard<std::mutex> lock(prune_mu_);
    prune_failed_.insert(prune_failed_.end(), folded.begin(), folded.end());
    return;
  }
  spdlog::info("event=payloads_pruned passages={} reason=\"factors folded into the map's base\"", *pruned);
}

void MapWorker::PruneWhileIdle() {
  std::vector<MapUpdater::PassageKey> retry;
  {
    std::lock_guard<std::mutex> lock(prune_mu_);
    const auto now = std::chrono::steady_clock::now();
    if (now < next_idle_prune_) return;
    next_idle_prune_ = now + options_.idle_prune_every;
    retry.swap(prune_failed_);
  }
  if (!retry.empty()) PrunePayloads(retry);  // a failure queues them again
  if (options_.settled_upload_retention_days <= 0.0) return;
  const auto retention_ms = static_cast<int64_t>(options_.settled_upload_retention_days * 86400e3);
  absl::StatusOr<int> pruned = store_->PruneSettledPayloads(NowUnixMs() - retention_ms, kSettledPruneBatch);
  if (!pruned.ok()) {
    spdlog::warn("event=payload_prune_failed error=\"{}\" retry=\"while idle\"", pruned.status().ToString());
    return;
  }
  if (*pruned == 0) return;
  spdlog::info("event=payloads_pruned passages={} reason=\"settled (rejected, excluded or discarded) {} days ago\"",
               *pruned, options_.settled_upload_retention_days);
  if (*pruned == kSettledPruneBatch) {  // more to do: at the next idle moment
    std::lock_guard<std::mutex> lock(prune_mu_);
    next_idle_prune_ = std::chrono::steady_clock::now();
  }
}

void MapWorker::Apply(const StoredPassage& record, const Passage& passage) {
  int attempts = record.attempts;
  int recomputed = 0;
  std::chrono::milliseconds pause(500);
  MapUpdater::Mode mode;
  mode.vouched = record.released;
  mode.sequential = record.interruptions >= options_.sequential_after_interruptions;
  std::optional<Computation> computed;
  double commit_wait_ms = 0.0;  // waiting for other workers' commits
  const auto apply_start = std::chrono::steady_clock::now();
  while (true) {
    if (!computed) {
      MapUpdater::Plan plan;
      computed = ComputeOnCommittedMap(
          [&](const MapReaderInterface& map) { return MapUpdater::ComputePlanned(plan, passage, map); },
          [&] { plan = updater_->PlanFor(mode); });
      computed->plan = std::move(plan);
      Yield();
    }
    std::string error;
    bool transient = false;
    bool reload = false;
    {
      // Commits one at a time, from validation to RecordCommitted; state_mu_ only where the
      // worker's state is read or changed, so that other workers begin their next computations
      // while the durable transaction runs.
      const auto wait_start = std::chrono::steady_clock::now();
      std::unique_lock<std::mutex> commit(commit_mu_);
      std::unique_lock<std::mutex> state(state_mu_);
      commit_wait_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - wait_start).count();
      const auto unlock = [&] {
        state.unlock();
        commit.unlock();
      };
      if (!StillValid(*computed)) {
        // A change committed meanwhile touched what it read: computed again against the map with it.
        unlock();
        computed.reset();
        ++recomputed;
        if (stopping_) {
          Release(record, "stopping: its update was to be computed again");
          return;
        }
        continue;
      }
      const absl::Status& status = computed->update.status();
      const bool refused = status.code() == absl::StatusCode::kInvalidArgument ||
                           status.code() == absl::StatusCode::kFailedPrecondition;
      if (refused && computed->base_version != committed_version_) {
        // A refusal is final (a quarantined passage waits for an operator), so it must come from a
        // computation against one state of the map: one during which other changes were committed
        // is computed again, even when none of them wrote what it recorded as read. (In one CI run
        // of ParallelWorkers.CityPassagesGiveTheMapOfTheirCommitOrder a passage was quarantined for
        // "map information over 59 landmarks is not positive definite", while the same passages
        // applied one at a time in that commit order refused none, and 40 further runs of the test
        // none: not explained.)
        unlock();
        computed.reset();
        ++recomputed;
        continue;
      }
      if (status.code() == absl::StatusCode::kInvalidArgument) {
        unlock();
        Finish(record, PassageState::kRejected, std::string(status.message()));
        return;
      }
      if (status.code() == absl::StatusCode::kFailedPrecondition) {
        // The map's checks refused it (see ComputePassageUpdate): the same data would be refused
        // again, so it waits for an operator (ResolvePassage) instead of being retried.
        unlock();
        Finish(record, PassageState::kQuarantined, std::string(status.message()));
        return;
      }
      if (!status.ok()) {
        error = status.ToString();
        computed.reset();
      } else {
        RebaseOntoCommitted(&*computed);
        MapDelta& delta = computed->update->delta;
        const PassageUpdateSummary& summary = computed->update->summary;
        delta.folded_factors.clear();
        std::vector<MapUpdater::PassageKey> folded;
        MapWriteSet written;
        store_->ReadCommittedMap([&](const MapState& map) {  // as before this commit: commits hold commit_mu_
          updater_->AddFolding(map, &delta);
          folded = WhollyFolded(map, delta.folded_factors);
          written = WriteSetOf(delta, map);
        });
        // Owed before the passage shows as applied, so that a client that sees the queue empty sees
        // them; taken back if the commit fails.
        int64_t owed = 0;
        if (options_.update.relinearize_sigmas > 0.0) {
          const int64_t due = relinearizations_due_.load();
          owed = std::min(kMaxRelinearizationsDue - due, int64_t{options_.update.relinearizations_per_passage});
          relinearizations_due_ = due + owed;
        }
        state.unlock();
        const PassageResult result = ResultFromSummary(summary, options_.update.strategy);
        const auto commit_start = std::chrono::steady_clock::now();
        absl::Status committed = store_->CommitPassageApplied(record.id, delta, result);
        const double commit_ms =
            std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - commit_start).count();
        if (committed.ok()) {
          state.lock();
          RecordCommitted(delta, std::move(written));
          updater_->Applied(passage, delta);
          const bool trim = ++commits_since_trim_ >= kTrimEveryCommits;
          if (trim) commits_since_trim_ = 0;
          unlock();
          Yield();
          PrunePayloads(folded);
          // An update allocates and frees hundreds of MB of matrices, and glibc keeps freed pages
          // inside its heaps: at 100k landmarks mapd grew by 2.5 MB per passage (1.45 -> 1.94 GB
          // over 200 passages, 1.61 GB after a trim). Returning them every kTrimEveryCommits
          // commits keeps the resident memory near the map's size; a trim takes 14 to 26 ms there.
          // With tcmalloc as mapd's allocator (CMakeLists.txt, crowdmap_use_tcmalloc) glibc's heap
          // holds next to nothing and the trim takes no time: tcmalloc returns free memory itself
          // (peak 1.37 GB over those passages).
          double trim_ms = 0.0;
          if (trim) {
            const auto trim_start = std::chrono::steady_clock::now();
            malloc_trim(0);
            trim_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - trim_start).count();
          }
          if (options_.on_applied) {
            const auto ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - apply_start);
            AppliedPassageTimings timings{ms.count(), result.solve_ms, result.covariance_ms, commit_ms, recomputed};
            timings.inflated = summary.max_variance_factor > 1.0;
            for (int s = 0; s < kPassageSensors; ++s) {
              timings.sensor_inflated[s] = summary.sensor_test_factors[s] > 1.0;
            }
            options_.on_applied(timings);
          }
          spdlog::info(
              "event=applied passage={} vehicle={} id={} nodes={} subgraphs={} landmarks_updated={} "
              "landmarks_created={} landmarks_conditioned={} solve_ms={:.1f} total_ms={:.1f} commit_ms={:.1f} "
              "factors_added={} map_version={} recomputed={} commit_wait_ms={:.1f} trim_ms={:.1f}{}",
              record.passage_id, record.vehicle_id, record.id, result.nodes, result.subgraphs,
              result.landmarks_updated, result.landmarks_created, result.landmarks_conditioned, result.solve_ms,
              result.total_ms, commit_ms, delta.added_factors.size(), delta.version, recomputed, commit_wait_ms,
              trim_ms, summary.SpeedScaleBrief() + summary.GnssBrief() + summary.SensorBrief());
          return;
        }
        if (owed > 0) {  // not applied: nothing owed for it
          std::lock_guard<std::mutex> owing(state_mu_);
          relinearizations_due_ =
              std::max(relinearizations_due_.load() - owed, static_cast<int64_t>(relinearizing_.size()));
        }
        error = absl::StrCat("commit: ", committed.ToString());
        transient = IsTransientStorageError(committed);
        // The store's map is not at the version the worker counted on: read it again.
        reload = committed.code() == absl::StatusCode::kFailedPrecondition;
        if (!transient) computed.reset();
      }
    }
    if (reload) {
      if (absl::Status s = LoadUpdater(); !s.ok()) spdlog::error("event=reload_failed error=\"{}\"", s.ToString());
    }
    if (transient && stopping_) {  // says nothing about the passage: back to the queue, uncounted
      Release(record, "stopping: its commit was deferred by a storage error");
      return;
    }
    if (transient) {  // the same passage again, no attempt counted
      spdlog::warn("event=commit_deferred passage={} vehicle={} id={} retry_in_ms={} error=\"{}\"", record.passage_id,
                   record.vehicle_id, record.id, pause.count(), error);
      for (auto waited = std::chrono::milliseconds(0); waited < pause && !stopping_; waited += std::chrono::milliseconds(100)) {
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
      pause = std::min<std::chrono::milliseconds>(2 * pause, std::chrono::seconds(30));
      continue;
    }
    spdlog::warn("event=attempt_failed passage={} vehicle={} id={} attempt={} error=\"{}\"", record.passage_id,
                 record.vehicle_id, record.id, attempts, error);
    if (attempts >= options_.max_attempts) {
      Finish(record, PassageState::kFailed, absl::StrCat("failed ", attempts, " times; last: ", error));
      return;
    }
    if (stopping_) {
      Finish(record, PassageState::kQueued, error);
      return;
    }
    auto recorded = store_->RecordFailedAttempt(record.id, error);
    attempts = recorded.ok() ? *recorded : attempts + 1;
  }
}

absl::StatusOr<PassageUpdate> MapWorker::CommitChange(
    const std::function<absl::StatusOr<PassageUpdate>(const MapReaderInterface&, const MapUpdateOptions&)>& compute,
    const std::function<absl::Status(const MapDelta&)>& commit, const std::function<void(const MapDelta&)>& committed) {
  while (!stopping_) {
    MapUpdateOptions options;
    Computation c = ComputeOnCommittedMap([&](const MapReaderInterface& map) { return compute(map, options); },
                                          [&] { options = updater_->options(); });
    std::lock_guard<std::mutex> one_commit(commit_mu_);  // rare: held with state_mu_ for the whole commit
    std::lock_guard<std::mutex> state(state_mu_);
    if (!StillValid(c)) continue;
    if (!c.update.ok()) return c.update.status();
    RebaseOntoCommitted(&c);
    const MapDelta& delta = c.update->delta;
    MapWriteSet written;
    store_->ReadCommittedMap([&](const MapState& map) { written = WriteSetOf(delta, map); });
    if (absl::Status s = commit(delta); !s.ok()) return s;
    RecordCommitted(delta, std::move(written));
    committed(delta);
    return std::move(*c.update);
  }
  return absl::UnavailableError("server is shutting down");
}

absl::StatusOr<PassageUpdateSummary> MapWorker::Exclude(const StoredPassage& record) {
  absl::StatusOr<PassageUpdate> update = CommitChange(
      [&](const MapReaderInterface& map, const MapUpdateOptions& options) {
        return ComputePassageExclusion(record.vehicle_id, record.passage_id, options, map);
      },
      [&](const MapDelta& delta) { return store_->CommitPassageExcluded(record.id, delta); },
      [&](const MapDelta&) { updater_->Excluded(record.vehicle_id, record.passage_id); });
  if (!update.ok()) return update.status();
  const PassageUpdateSummary& summary = update->summary;
  spdlog::info("event=excluded passage={} vehicle={} id={} landmarks_updated={} landmarks_removed={} "
               "landmarks_conditioned={} total_ms={:.1f} map_version={}",
               record.passage_id, record.vehicle_id, record.id, summary.landmarks_updated, summary.landmarks_removed,
               summary.landmarks_conditioned, summary.total_ms, summary.map_version);
  return summary;
}

bool MapWorker::RelinearizeOneWhileIdle() {
  if (relinearizations_due_.load() == 0) return false;  // also when off: no lock taken
  std::optional<MapUpdater::PassageKey> key;
  {
    std::lock_guard<std::mutex> no_commit(commit_mu_);  // the map and the updater at one version
    std::lock_guard<std::mutex> state(state_mu_);
    if (relinearizations_due_.load() <= static_cast<int64_t>(relinearizing_.size())) return false;
    store_->ReadCommittedMap([&](const MapState& map) { key = updater_->StalestPassage(map, relinearizing_); });
    if (!key) {
      // Nothing qualifies; what other workers are computing stays due until it is done.
      relinearizations_due_ = static_cast<int64_t>(relinearizing_.size());
      return false;
    }
    relinearizing_.insert(*key);
  }
  absl::Status status = Relinearize(*key);
  {
    std::lock_guard<std::mutex> state(state_mu_);
    relinearizing_.erase(*key);
    if (relinearizations_due_.load() > 0) --relinearizations_due_;
    if (stopping_) return false;
    if (!status.ok()) {
      updater_->RelinearizationFailed(*key);
      spdlog::warn("event=relinearization_failed passage={} vehicle={} error=\"{}\"", key->second, key->first,
                   status.ToString());
    }
  }
  if (options_.on_relinearized) options_.on_relinearized(status.ok());
  return true;
}

absl::Status MapWorker::Relinearize(const MapUpdater::PassageKey& key) {
  absl::StatusOr<StoredPassage> record = store_->FindPassage(key.first, key.second);
  if (!record.ok()) return record.status();
  absl::StatusOr<std::string> payload = store_->GetPassagePayload(record->id);
  if (!payload.ok()) return payload.status();
  absl::StatusOr<Passage> passage = DecodeStoredPassage(*payload);
  if (!passage.ok()) return passage.status();
  absl::StatusOr<PassageUpdate> update = CommitChange(
      [&](const MapReaderInterface& map, const MapUpdateOptions& options) {
        return ComputePassageRelinearization(*passage, options, map);
      },
      [&](const MapDelta& delta) { return store_->CommitPassageRelinearized(record->id, delta); },
      [&](const MapDelta& delta) { updater_->Relinearized(delta); });
  if (!update.ok()) return update.status();
  const PassageUpdateSummary& summary = update->summary;
  spdlog::info("event=relinearized passage={} vehicle={} id={} landmarks_updated={} landmarks_conditioned={} "
               "total_ms={:.1f} map_version={}",
               record->passage_id, record->vehicle_id, record->id, summary.landmarks_updated,
               summary.landmarks_conditioned, summary.total_ms, summary.map_version);
  return absl::OkStatus();
}

void MapWorker::Release(const StoredPassage& record, const char* reason) {
  if (absl::Status s = store_->ReleaseClaimedPassage(record.id); !s.ok()) {
    // It stays processing: the next start queues it again, as after a crash.
    spdlog::error("event=release_failed passage={} id={} error=\"{}\"", record.passage_id, record.id, s.ToString());
    return;
  }
  spdlog::info("event=returned passage={} vehicle={} id={} reason=\"{}\"", record.passage_id, record.vehicle_id,
               record.id, reason);
}

void MapWorker::Finish(const StoredPassage& record, PassageState state, const std::string& reason) {
  absl::Status s = store_->FinishPassageWithoutChange(record.id, state, reason);
  if (!s.ok()) {
    spdlog::error("event=finish_failed passage={} id={} error=\"{}\"", record.passage_id, record.id, s.ToString());
    return;
  }
  if (state == PassageState::kQueued) {
    spdlog::info("event=returned passage={} vehicle={} id={}", record.passage_id, record.vehicle_id, record.id);
  } else {
    spdlog::warn("event={} passage={} vehicle={} id={} reason=\"{}\"", PassageStateName(state),
                 EscapeForLog(record.passage_id), EscapeForLog(record.vehicle_id), record.id, EscapeForLog(reason));
  }
}

}  // namespace crowdmap
