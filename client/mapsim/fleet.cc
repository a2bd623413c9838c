#include "client/mapsim/fleet.h"

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <thread>
#include <unordered_map>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/geojson.h"
#include "client/api/passage_files.h"
#include "client/mapsim/simulated_passages.h"
#include "core/geo/local_frame.h"
#include "core/estimation/map_updater.h"
#include "core/sim/metrics.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double>(b - a).count(); }

double Median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

bool Finished(pb::PassageState s) {
  return s == pb::PASSAGE_STATE_APPLIED || s == pb::PASSAGE_STATE_REJECTED || s == pb::PASSAGE_STATE_FAILED;
}

int64_t FinishedCount(const pb::MapInfo& info) {
  return info.passages_applied() + info.passages_rejected() + info.passages_failed();
}

// Uploads of all vehicles; vehicle v sends passages v, v+V, ... in order.
class FleetUploader {
 public:
  FleetUploader(const FleetOptions& options, const std::vector<Passage>& passages)
      : options_(options), passages_(passages) {}

  void Start() {
    for (int v = 0; v < options_.vehicles; ++v) threads_.emplace_back([this, v] { RunVehicle(v); });
  }
  void Join() {
    for (std::thread& t : threads_) t.join();
    threads_.clear();
  }
  int uploaded() const { return uploaded_.load(); }
  int duplicates() const { return duplicates_.load(); }
  bool done() const { return finished_vehicles_.load() == options_.vehicles; }
  absl::Status error() {
    std::lock_guard<std::mutex> lock(mu_);
    return error_;
  }
  // Server passage id -> scenario passage index, for every acknowledged upload.
  std::unordered_map<int64_t, int> server_ids() {
    std::lock_guard<std::mutex> lock(mu_);
    return server_ids_;
  }

 private:
  void RunVehicle(int vehicle) {
    MapClientOptions client_options = options_.client;
    client_options.server = options_.server;
    absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(client_options);
    for (int i = vehicle; client.ok() && i < options_.passages && !failed_.load(); i += options_.vehicles) {
      pb::Passage wire;
      PassageToProto(passages_[i], &wire);
      absl::StatusOr<pb::UploadPassageResponse> response = (*client)->Upload(wire);
      if (!response.ok()) {
        Fail(absl::Status(response.status().code(), absl::StrCat("passage ", i, ": ", response.status().message())));
        break;
      }
      if (response->duplicate()) ++duplicates_;
      {
        std::lock_guard<std::mutex> lock(mu_);
        server_ids_[response->status().id()] = i;
      }
      ++uploaded_;
    }
    if (!client.ok()) Fail(client.status());
    ++finished_vehicles_;
  }
  void Fail(const absl::Status& status) {
    std::lock_guard<std::mutex> lock(mu_);
    if (error_.ok()) error_ = status;
    failed_ = true;
  }

  const FleetOptions& options_;
  const std::vector<Passage>& passages_;
  std::vector<std::thread> threads_;
  std::atomic<int> uploaded_{0}, duplicates_{0}, finished_vehicles_{0};
  std::atomic<bool> failed_{false};
  std::mutex mu_;
  absl::Status error_;
  std::unordered_map<int64_t, int> server_ids_;
};

// Fills solve_ms / subgraphs of each sampled record from the server's per-passage results, the
// experiment-level figures from the records, and the arrival order.
absl::Status Summarize(MapClient& client, const std::unordered_map<int64_t, int>& ids, FleetResult* result) {
  absl::StatusOr<std::vector<pb::PassageStatus>> all = client.ListPassages(std::nullopt);
  if (!all.ok()) return all.status();
  std::vector<pb::PassageStatus> ours;
  for (const pb::PassageStatus& p : *all) {
    if (ids.count(p.id()) && Finished(p.state())) ours.push_back(p);
  }
  std::sort(ours.begin(), ours.end(), [](const auto& a, const auto& b) { return a.id() < b.id(); });
  ExperimentResult& e = result->experiment;
  std::vector<double> all_ms;
  size_t next = 0;
  for (PassageRecord& r : e.records) {
    std::vector<double> ms;
    for (; next < ours.size() && static_cast<int>(next) < r.passage; ++next) {
      if (ours[next].state() != pb::PASSAGE_STATE_APPLIED) continue;
      ms.push_back(ours[next].result().total_ms());
      all_ms.push_back(ours[next].result().total_ms());
      r.subgraphs += ours[next].result().subgraphs();
    }
    r.solve_ms = Median(ms);
  }
  for (const pb::PassageStatus& p : ours) {
    if (p.state() != pb::PASSAGE_STATE_APPLIED) ++e.failed_passages;
    result->arrival_order.push_back(ids.at(p.id()));
  }
  e.median_passage_ms = Median(all_ms);
  if (!e.records.empty()) {
    e.final_mean_dist_err_m = e.records.back().metrics.mean_dist_err_m;
    e.final_nees_per_dof = e.records.back().metrics.nees_per_dof;
    e.final_joint_nees_per_dof = e.records.back().metrics.joint_nees_per_dof;
  }
  return absl::OkStatus();
}

// The in-process experiment with the passages in the server's arrival order, compared with the
// server's final map.
absl::Status Replay(const FleetOptions& options, FleetResult* result) {
  ExperimentOptions experiment;
  experiment.scenario = options.scenario;
  experiment.passages = options.passages;
  experiment.strategy = result->server_strategy;
  experiment.update = result->server_update;
  experiment.order = result->arrival_order;
  absl::StatusOr<ExperimentResult> replay = RunExperiment(experiment);
  if (!replay.ok()) return replay.status();
  FleetReplay& r = result->replay.emplace();
  r.final_mean_dist_err_m = replay->final_mean_dist_err_m;
  const MapState& server = result->experiment.final_map;
  const LocalFrame frame(options.scenario.origin);
  replay->final_map.ForEachLandmark([&](const Landmark& mine) {
    const Landmark* theirs = server.FindLandmark(mine.id);
    if (theirs == nullptr) {
      ++r.missing_landmarks;
      return;
    }
    r.max_position_diff_m =
        std::max(r.max_position_diff_m, (frame.ToLocal(mine.position) - frame.ToLocal(theirs->position)).norm());
    r.max_cov_diff_m2 = std::max(r.max_cov_diff_m2, (mine.cov_en_m2 - theirs->cov_en_m2).cwiseAbs().maxCoeff());
  });
  r.missing_landmarks += static_cast<int>(server.landmark_count()) - static_cast<int>(replay->final_map.landmark_count());
  return absl::OkStatus();
}

}  // namespace

absl::Status FleetOptions::Validate() const {
  if (absl::Status s = city ? city_scenario.Validate() : scenario.Validate(); !s.ok()) return s;
  if (city && replay) {
    return absl::InvalidArgumentError("replay: the in-process replay takes the loop's passages only; turn it off with city");
  }
  if (passages < 1) return absl::InvalidArgumentError("passages: must be >= 1");
  if (vehicles < 1) return absl::InvalidArgumentError("vehicles: must be >= 1");
  if (!strategy.empty() && strategy != "cc" && strategy != "dc" && strategy != "cc-gsd") {
    return absl::InvalidArgumentError(absl::StrCat("strategy: '", strategy, "' is not cc, dc or cc-gsd"));
  }
  if (sample_interval.count() <= 0) return absl::InvalidArgumentError("sample_interval: must be > 0");
  MapClientOptions c = client;
  c.server = server;
  return c.Validate();
}

std::string FleetResult::Brief() const {
  std::string brief = absl::StrFormat(
      "strategy=%s passages=%d duplicates=%d failed=%d final_mean_dist_err_m=%.4f final_nees_per_dof=%.3f "
      "final_joint_nees_per_dof=%.3f landmarks=%d map_version=%d upload_s=%.2f apply_s=%.2f median_passage_ms=%.2f",
      server_strategy, experiment.records.empty() ? 0 : experiment.records.back().passage, duplicates,
      experiment.failed_passages, experiment.final_mean_dist_err_m, experiment.final_nees_per_dof,
      experiment.final_joint_nees_per_dof, landmarks.size(), map_version, upload_s, apply_s,
      experiment.median_passage_ms);
  if (replay) {
    absl::StrAppendFormat(&brief,
                          " arrival_order_experiment_err_m=%.4f max_position_diff_vs_arrival_order_m=%.2g "
                          "max_cov_diff_m2=%.2g",
                          replay->final_mean_dist_err_m, replay->max_position_diff_m, replay->max_cov_diff_m2);
  }
  return brief;
}

int64_t JointSolveUnderWay(const pb::MapInfo& info) {
  MapUpdateOptions options;
  absl::StatusOr<UpdateStrategy> strategy = ParseUpdateStrategy(info.strategy());
  if (!strategy.ok()) return 0;
  options.strategy = *strategy;
  options.warmup_passages = info.warmup_passages();
  options.relinearize_until_passages = info.relinearize_until_passages();
  const int64_t next = info.passages_applied() + 1;
  return IsJointSolvePassage(next, options) ? next : 0;
}

absl::StatusOr<FleetResult> RunFleet(const FleetOptions& options,
                                     const std::function<void(const FleetProgress&)>& progress) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<SimulatedPassages> scenario =
      MakeSimulatedPassages(options.scenario, options.city ? &options.city_scenario : nullptr, options.passages);
  if (!scenario.ok()) return scenario.status();
  MapClientOptions client_options = options.client;
  client_options.server = options.server;
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(client_options);
  if (!client.ok()) return client.status();
  absl::StatusOr<pb::MapInfo> start_info = (*client)->GetMapInfo();
  if (!start_info.ok()) return start_info.status();
  FleetResult result;
  result.server_strategy = start_info->strategy();
  result.server_update.warmup_passages = start_info->warmup_passages();
  result.server_update.relinearize_until_passages = start_info->relinearize_until_passages();
  result.server_update.max_subgraph_dim = start_info->max_subgraph_dim();
  result.server_update.window_hops = start_info->window_hops();
  if (start_info->has_detections_per_landmark()) {
    result.server_update.detections_per_landmark = start_info->detections_per_landmark();
    result.server_update.spread_detections = start_info->spread_detections();
  }
  if (start_info->has_estimate_camera_yaw()) {
    result.server_update.estimate_camera_yaw = start_info->estimate_camera_yaw();
    result.server_update.fleet_camera_yaw_prior_vehicles = start_info->fleet_camera_yaw_prior_vehicles();
  }
  if (!options.strategy.empty() && options.strategy != result.server_strategy) {
    return absl::FailedPreconditionError(absl::StrCat("the server runs strategy '", result.server_strategy,
                                                      "', not '", options.strategy, "' (mapd --strategy)"));
  }
  if (start_info->landmark_count() > 0) {
    spdlog::warn("the server's map already holds {} landmarks: errors describe that map plus this fleet's passages",
                 start_info->landmark_count());
  }
  const int64_t finished_at_start = FinishedCount(*start_info);

  const Clock::time_point t0 = Clock::now();
  FleetUploader uploader(options, scenario->passages);
  uploader.Start();
  FleetProgress state;
  state.total = options.passages;
  int64_t last_sampled = 0;
  int64_t last_sampled_version = -1;
  Clock::time_point upload_end{};
  while (true) {
    std::this_thread::sleep_for(options.sample_interval);
    const bool uploads_done = uploader.done();
    if (uploads_done && upload_end == Clock::time_point{}) upload_end = Clock::now();
    if (!uploader.error().ok()) break;
    absl::StatusOr<pb::MapInfo> info = (*client)->GetMapInfo();
    if (!info.ok()) {
      uploader.Join();
      return info.status();
    }
    state.uploaded = uploader.uploaded();
    state.applied = static_cast<int>(FinishedCount(*info) - finished_at_start);
    state.joint_solve_of = info->queue_depth() > 0 ? JointSolveUnderWay(*info) : 0;
    // Idle: nothing queued and no re-linearisation owed (mapd --relinearize-sigmas does them once
    // the queue is empty), so the map sampled then is the final one.
    const bool idle = uploads_done && info->queue_depth() == 0 && info->relinearizations_due() == 0;
    if (state.applied > last_sampled || (idle && info->map_version() != last_sampled_version)) {
      absl::StatusOr<MapState> map = (*client)->DownloadMap(WorldBox());
      if (map.ok()) {
        PassageRecord record;
        record.passage = state.applied;
        record.metrics = EvaluateMap(*map, scenario->landmarks);
        result.experiment.records.push_back(record);
        state.mean_dist_err_m = record.metrics.mean_dist_err_m;
        last_sampled = state.applied;
        last_sampled_version = map->version();
      } else if (map.status().code() != absl::StatusCode::kAborted) {
        uploader.Join();
        return map.status();
      }
    }
    if (progress) progress(state);
    if (idle && last_sampled == state.applied && last_sampled_version == info->map_version()) break;
    if (Clock::now() - t0 > options.apply_timeout) {
      uploader.Join();
      return absl::DeadlineExceededError(absl::StrCat("passages still queued after ", options.apply_timeout.count(), " s"));
    }
  }
  uploader.Join();
  if (absl::Status s = uploader.error(); !s.ok()) return s;
  result.upload_s = Seconds(t0, upload_end);
  result.apply_s = Seconds(t0, Clock::now());
  result.duplicates = uploader.duplicates();

  absl::StatusOr<RegionMap> region = (*client)->QueryRegion(WorldBox(), /*include_cross=*/true);
  if (!region.ok()) return region.status();
  result.landmarks = region->landmarks;
  result.map_version = region->map_version;
  absl::StatusOr<MapState> final_map = (*client)->DownloadMap(WorldBox());
  if (!final_map.ok()) return final_map.status();
  result.experiment.final_map = *std::move(final_map);
  if (absl::Status s = Summarize(**client, uploader.server_ids(), &result); !s.ok()) return s;
  if (options.replay) {
    if (start_info->landmark_count() > 0 || result.duplicates > 0 ||
        static_cast<int>(result.arrival_order.size()) != options.passages) {
      spdlog::warn("no replay: the server's map did not start empty or not every passage was applied by this run");
    } else if (start_info->relinearize_sigmas() > 0.0) {
      spdlog::warn("no replay: the server re-linearises stale passages while its queue is empty (relinearize_sigmas "
                   "{}), at moments a replay cannot know (mapd --relinearize-sigmas 0 to compare)",
                   start_info->relinearize_sigmas());
    } else if (absl::Status s = Replay(options, &result); !s.ok()) {
      return s;
    }
  }
  return result;
}

absl::Status WriteFleetOutputs(const FleetOptions& options, const FleetResult& result, const std::string& dir) {
  ExperimentOptions experiment;
  experiment.scenario = options.scenario;
  experiment.passages = options.passages;
  experiment.strategy = result.server_strategy;
  experiment.update = result.server_update;  // the summary gives the server's settings
  std::vector<std::pair<std::string, double>> extra = {{"vehicles", options.vehicles}};
  if (options.city) {  // the summary's scenario fields are the loop's: say which passages these were
    extra.push_back({"city_blocks_x", options.city_scenario.blocks_x});
    extra.push_back({"city_blocks_y", options.city_scenario.blocks_y});
    extra.push_back({"city_route_m", options.city_scenario.route_length_m});
  }
  if (result.replay) {
    extra.push_back({"arrival_order_experiment_final_mean_dist_err_m", result.replay->final_mean_dist_err_m});
    extra.push_back({"max_position_diff_vs_arrival_order_experiment_m", result.replay->max_position_diff_m});
    extra.push_back({"max_cov_diff_vs_arrival_order_experiment_m2", result.replay->max_cov_diff_m2});
  }
  if (absl::Status s = WriteExperimentOutputs(experiment, result.experiment, dir, extra); !s.ok()) return s;
  if (absl::Status s = WriteOrderFile(result.arrival_order, dir + "/arrival_order.txt"); !s.ok()) return s;
  GeoJsonOptions geojson;
  geojson.ellipses = true;
  const std::string path = dir + "/map.geojson";
  std::ofstream out(path, std::ios::trunc);
  out << LandmarksToGeoJson(result.landmarks, result.map_version, geojson);
  out.close();
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": write failed"));
  return absl::OkStatus();
}

absl::Status ExportPassages(const ScenarioOptions& options, int passages, bool binary, const std::string& dir) {
  absl::StatusOr<Scenario> scenario = Scenario::Create(options);
  if (!scenario.ok()) return scenario.status();
  return ExportPassages([&](int i) { return scenario->MakePassage(i); }, passages, binary, dir);
}

absl::Status ExportPassages(const std::function<Passage(int)>& make_passage, int passages, bool binary,
                            const std::string& dir) {
  if (passages < 1) return absl::InvalidArgumentError("passages: must be >= 1");
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  for (int i = 0; i < passages; ++i) {
    pb::Passage wire;
    PassageToProto(make_passage(i), &wire);
    const std::string path = absl::StrFormat("%s/passage-%05d.%s", dir, i, binary ? "pb" : "json");
    if (absl::Status s = WritePassageFile(wire, binary ? PassageFileFormat::kBinary : PassageFileFormat::kJson, path);
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

}  // namespace crowdmap
