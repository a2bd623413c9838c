#include "server/map_worker.h"

#include <malloc.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <chrono>
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
  if (workers < 1) return absl::InvalidArgumentError(absl::StrCat("workers: must be >= 1, got ", workers));
  if (max_attempts < 1) return absl::InvalidArgumentError(absl::StrCat("max_attempts: must be >= 1, got ", max_attempts));
  if (sequential_after_interruptions < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("sequential_after_interruptions: must be >= 1, got ", sequential_after_interruptions));
  }
  if (max_interruptions < 1) {
    return absl::InvalidArgumentError(absl::StrCat("max_interruptions: must be >= 1, got ", max_interruptions));
  }
  if (nice < 0 || nice > 19) return absl::InvalidArgumentError(absl::StrCat("worker-nice: must lie in [0, 19], got ", nice));
  return update.Validate();
}

absl::StatusOr<std::unique_ptr<MapWorker>> MapWorker::Create(MapStoreInterface* store,
                                                             const MapWorkerOptions& options,
                                                             VersionNotifier* notifier) {
  if (auto s = options.Validate(); !s.ok()) return s;
  std::unique_ptr<MapWorker> worker(new MapWorker(store, options, notifier));
  auto requeued = store->RequeueProcessingPassages();
  if (!requeued.ok()) return requeued.status();
  if (*requeued > 0) spdlog::warn("event=requeue passages={} reason=\"processing at start-up\"", *requeued);
  if (auto s = worker->LoadMirror(); !s.ok()) return s;
  notifier->Publish(worker->map_->version());
  spdlog::info("event=map_loaded landmarks={} factors={} map_version={} warming_up={} next_joint_solve={}",
               worker->map_->landmark_count(), worker->map_->factor_count(), worker->map_->version(),
               worker->updater_->warming_up(), worker->updater_->joint_next());
  return worker;
}

absl::Status MapWorker::LoadMirror() {
  map_ = store_->CommittedMap();
  if (map_ == nullptr) {
    if (auto s = store_->LoadMap(&own_map_); !s.ok()) return s;
    map_ = &own_map_;
  }
  absl::StatusOr<MapStats> stats = store_->GetStats();
  if (!stats.ok()) return stats.status();
  const int64_t applied_count = stats->passages_by_state[static_cast<int>(PassageState::kApplied)];
  // The joint solves take the map's first passages; passages are applied in arrival (id) order.
  std::vector<Passage> kept;
  const int needed = JointSolvePassages(options_.update);
  if (applied_count <= needed) {
    PassageQuery query;
    query.state = PassageState::kApplied;
    query.limit = needed;
    absl::StatusOr<std::vector<StoredPassage>> applied = store_->ListPassages(query);
    if (!applied.ok()) return applied.status();
    for (const StoredPassage& record : *applied) {
      absl::StatusOr<std::string> payload = store_->GetPassagePayload(record.id);
      if (!payload.ok()) return payload.status();
      absl::StatusOr<Passage> passage = DecodeStoredPassage(*payload);
      if (!passage.ok()) return absl::DataLossError(absl::StrCat("applied passage ", record.id, ": ", passage.status().message()));
      kept.push_back(*std::move(passage));
    }
  }
  MapUpdateOptions update = options_.update;
  if (options_.yield) update.yield_point = [this] { Yield(); };
  updater_ = std::make_unique<MapUpdater>(update, std::move(kept), applied_count, map_);
  return absl::OkStatus();
}

void MapWorker::Follow(const MapDelta& delta) {
  if (map_ == &own_map_) own_map_.Apply(delta);
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
  wake_cv_.notify_one();
}

void MapWorker::Stop() {
  stopping_ = true;
  wake_cv_.notify_all();
  turn_cv_.notify_all();
  for (std::thread& t : threads_) t.join();
  threads_.clear();
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
    std::optional<ClaimedPassage> claimed;
    uint64_t ticket = 0;
    {
      std::lock_guard<std::mutex> lock(claim_mu_);
      if (stopping_) break;
      auto next = store_->ClaimNextPassage();
      if (!next.ok()) {
        spdlog::error("event=claim_failed error=\"{}\"", next.status().ToString());
      } else if (next->has_value()) {
        claimed = std::move(*next);
        ticket = next_ticket_++;
      }
    }
    if (!claimed) {
      if (!WaitForWork()) break;
      continue;
    }
    Process(std::move(*claimed), ticket);
  }
}

void MapWorker::Process(ClaimedPassage claimed, uint64_t ticket) {
  // Decoding runs in parallel; the map update waits for this passage's turn.
  absl::StatusOr<Passage> passage = DecodeStoredPassage(claimed.payload);
  claimed.payload.clear();

  std::unique_lock<std::mutex> lock(turn_mu_);
  turn_cv_.wait(lock, [&] { return serving_ticket_ == ticket; });
  lock.unlock();
  const StoredPassage& record = claimed.record;
  if (stopping_ && record.attempts <= options_.max_attempts) {
    Finish(record, PassageState::kQueued, "");  // not started: back to the queue, in order
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
    Apply(claimed, *passage);
  }
  lock.lock();
  ++serving_ticket_;
  lock.unlock();
  turn_cv_.notify_all();
}

namespace {

// A storage error that says nothing about the passage (a full disk, an I/O error, a busy
// database): its commit is retried after a pause, and no attempt is counted.
bool IsTransientStorageError(const absl::Status& s) {
  return s.code() == absl::StatusCode::kResourceExhausted || s.code() == absl::StatusCode::kUnavailable;
}

// The passages (vehicle_id, passage_id) that `factors` of `map` came from, each once.
std::vector<MapUpdater::PassageKey> PassagesOf(const MapReaderInterface& map, const std::vector<int64_t>& factors) {
  std::set<MapUpdater::PassageKey> keys;
  for (int64_t id : factors) {
    if (const MapFactor* f = map.FindFactor(id); f != nullptr) keys.insert({f->vehicle_id, f->passage_id});
  }
  return {keys.begin(), keys.end()};
}

}  // namespace

void MapWorker::PrunePayloadsOfFolded(const std::vector<MapUpdater::PassageKey>& folding) {
  // Only passages with no factor left apart: wholly folded into the base.
  std::vector<MapUpdater::PassageKey> folded;
  std::vector<int64_t> left;
  for (const MapUpdater::PassageKey& key : folding) {
    left.clear();
    map_->AppendPassageFactorIds(key.first, key.second, &left);
    if (left.empty()) folded.push_back(key);
  }
  if (folded.empty()) return;
  absl::StatusOr<int> pruned = store_->PrunePassagePayloads(folded);
  if (!pruned.ok()) {  // the uploads stay: nothing is lost, the queue file is only larger
    spdlog::warn("event=payload_prune_failed passages={} error=\"{}\"", folded.size(), pruned.status().ToString());
    return;
  }
  spdlog::info("event=payloads_pruned passages={} reason=\"factors folded into the map's base\"", *pruned);
}

void MapWorker::Apply(const ClaimedPassage& claimed, const Passage& passage) {
  const StoredPassage& record = claimed.record;
  int attempts = record.attempts;
  std::chrono::milliseconds pause(500);
  while (true) {
    std::string error;
    const auto apply_start = std::chrono::steady_clock::now();
    MapUpdater::Mode mode;
    mode.vouched = record.released;
    mode.sequential = record.interruptions >= options_.sequential_after_interruptions;
    auto update = updater_->Compute(passage, *map_, mode);
    if (update.ok()) {
      const PassageResult result = ResultFromSummary(update->summary, options_.update.strategy);
      // The passages whose factors the commit folds, read before it does.
      const std::vector<MapUpdater::PassageKey> folding = PassagesOf(*map_, update->delta.folded_factors);
      Yield();
      const auto commit_start = std::chrono::steady_clock::now();
      absl::Status committed = store_->CommitPassageApplied(record.id, update->delta, result);
      const double commit_ms =
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - commit_start).count();
      if (committed.ok()) {
        Follow(update->delta);
        updater_->Applied(passage, update->delta);
        Yield();
        notifier_->Publish(map_->version());
        PrunePayloadsOfFolded(folding);
        // An update allocates and frees hundreds of MB of matrices, and glibc keeps freed pages
        // inside its heaps: at 100k landmarks mapd grew by 2.5 MB per passage (1.45 -> 1.94 GB
        // over 200 passages, 1.61 GB after a trim). Returning them every kTrimEveryCommits commits
        // keeps the resident memory near the map's size; a trim takes 14 to 26 ms there.
        double trim_ms = 0.0;
        if (++commits_since_trim_ >= kTrimEveryCommits) {
          const auto trim_start = std::chrono::steady_clock::now();
          malloc_trim(0);
          trim_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - trim_start).count();
          commits_since_trim_ = 0;
        }
        if (options_.on_applied) {
          const auto ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - apply_start);
          options_.on_applied({ms.count(), result.solve_ms, result.covariance_ms, commit_ms});
        }
        spdlog::info(
            "event=applied passage={} vehicle={} id={} nodes={} subgraphs={} landmarks_updated={} "
            "landmarks_created={} landmarks_conditioned={} solve_ms={:.1f} total_ms={:.1f} commit_ms={:.1f} "
            "factors_added={} map_version={} trim_ms={:.1f}",
            record.passage_id, record.vehicle_id, record.id, result.nodes, result.subgraphs,
            result.landmarks_updated, result.landmarks_created, result.landmarks_conditioned, result.solve_ms,
            result.total_ms, commit_ms, update->delta.added_factors.size(), map_->version(), trim_ms);
        return;
      }
      error = absl::StrCat("commit: ", committed.ToString());
      if (IsTransientStorageError(committed) && !stopping_) {
        spdlog::warn("event=commit_deferred passage={} vehicle={} id={} retry_in_ms={} error=\"{}\"", record.passage_id,
                     record.vehicle_id, record.id, pause.count(), committed.ToString());
        for (auto waited = std::chrono::milliseconds(0); waited < pause && !stopping_; waited += std::chrono::milliseconds(100)) {
          std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
        pause = std::min<std::chrono::milliseconds>(2 * pause, std::chrono::seconds(30));
        continue;  // the same passage again, no attempt counted
      }
      if (committed.code() == absl::StatusCode::kFailedPrecondition) {
        // The mirror disagrees with the store: reload it before the next attempt.
        if (absl::Status s = LoadMirror(); !s.ok()) spdlog::error("event=reload_failed error=\"{}\"", s.ToString());
      }
    } else if (update.status().code() == absl::StatusCode::kInvalidArgument) {
      Finish(record, PassageState::kRejected, std::string(update.status().message()));
      return;
    } else if (update.status().code() == absl::StatusCode::kFailedPrecondition) {
      // The map's checks refused it (see ComputePassageUpdate): the same data would be refused
      // again, so it waits for an operator (ResolvePassage) instead of being retried.
      Finish(record, PassageState::kQuarantined, std::string(update.status().message()));
      return;
    } else {
      error = update.status().ToString();
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

absl::StatusOr<PassageUpdateSummary> MapWorker::Exclude(const StoredPassage& record) {
  uint64_t ticket = 0;
  {
    std::lock_guard<std::mutex> lock(claim_mu_);
    ticket = next_ticket_++;
  }
  std::unique_lock<std::mutex> lock(turn_mu_);
  turn_cv_.wait(lock, [&] { return serving_ticket_ == ticket || stopping_.load(); });
  lock.unlock();
  absl::StatusOr<PassageUpdateSummary> out = absl::UnavailableError("server is shutting down");
  if (!stopping_) {
    absl::StatusOr<PassageUpdate> exclusion =
        ComputePassageExclusion(record.vehicle_id, record.passage_id, options_.update, *map_);
    if (!exclusion.ok()) {
      out = exclusion.status();
    } else if (absl::Status s = store_->CommitPassageExcluded(record.id, exclusion->delta); !s.ok()) {
      out = s;
    } else {
      Follow(exclusion->delta);
      updater_->Excluded(record.vehicle_id, record.passage_id);
      notifier_->Publish(map_->version());
      spdlog::info("event=excluded passage={} vehicle={} id={} landmarks_updated={} landmarks_removed={} "
                   "landmarks_conditioned={} total_ms={:.1f} map_version={}",
                   record.passage_id, record.vehicle_id, record.id, exclusion->summary.landmarks_updated,
                   exclusion->summary.landmarks_removed, exclusion->summary.landmarks_conditioned,
                   exclusion->summary.total_ms, map_->version());
      out = exclusion->summary;
    }
  }
  lock.lock();
  if (serving_ticket_ == ticket) ++serving_ticket_;
  lock.unlock();
  turn_cv_.notify_all();
  return out;
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
