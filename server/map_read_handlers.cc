// MapService handlers that read the map.
#include <algorithm>
#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/map_service.h"
#include "server/metrics.h"
#include "server/request_log.h"

namespace crowdmap {
namespace {

// The request's box, which it must give: an absent one would read as the box (0, 0) to (0, 0).
template <typename Request>
absl::StatusOr<BoundingBox> RequiredBox(const Request& request) {
  if (!request.has_box()) return absl::InvalidArgumentError("box: required");
  return BoundingBoxFromProto(request.box(), "box");
}

constexpr int kDefaultRegionPage = 1000;
constexpr int kMaxRegionPage = 10000;
// With covariances a page's joint covariance is (2n)^2 doubles, read whole: 128 MB at 2,000
// landmarks, and 64 MB packed on the wire (MapClientOptions::max_message_mb).
constexpr int kMaxCovariancePage = 2000;
// Landmarks per WatchRegion message: a large change (the whole box, from since_version 0) comes in
// parts that fit a client's default 4 MiB message limit.
constexpr size_t kWatchMessageLandmarks = 1000;
constexpr std::chrono::milliseconds kWatchPoll{500};
// How long a watch from a version the map has not reached waits for it before it is refused.
constexpr std::chrono::milliseconds kWatchAheadWait{2000};

void CountCovarianceRead(ServerMetrics* metrics, const LandmarkPage& page) {
  if (metrics != nullptr && page.covariance.size() > 0) metrics->ObserveCovarianceRead(page.covariance_bound);
}

// " covariance_bound=..." for the request log of a read with covariances, "" otherwise.
std::string CovarianceBoundField(const LandmarkPage& page) {
  if (page.covariance.size() == 0) return "";
  return absl::StrCat(" covariance_bound=", CovarianceBoundName(page.covariance_bound));
}

}  // namespace

absl::Status ReadMapInfo(MapStoreInterface& store, const MapUpdateOptions& update, const MapWorker* worker,
                         pb::MapInfo* info) {
  auto due = [worker] { return worker != nullptr ? worker->relinearizations_due() : int64_t{0}; };
  const int64_t due_before = due();
  absl::StatusOr<MapStats> read = store.GetStats();
  if (!read.ok()) return read.status();
  const MapStats& stats = *read;
  info->set_relinearizations_due(std::max(due_before, due()));
  info->set_map_version(stats.map_version);
  info->set_landmark_count(stats.landmark_count);
  info->set_factor_count(stats.factor_count);
  info->set_queue_depth(stats.queue_depth());
  info->set_passages_queued(stats.passages_by_state[static_cast<int>(PassageState::kQueued)]);
  info->set_passages_processing(stats.passages_by_state[static_cast<int>(PassageState::kProcessing)]);
  info->set_passages_applied(stats.passages_by_state[static_cast<int>(PassageState::kApplied)]);
  info->set_passages_rejected(stats.passages_by_state[static_cast<int>(PassageState::kRejected)]);
  info->set_passages_failed(stats.passages_by_state[static_cast<int>(PassageState::kFailed)]);
  info->set_passages_quarantined(stats.passages_by_state[static_cast<int>(PassageState::kQuarantined)]);
  info->set_passages_discarded(stats.passages_by_state[static_cast<int>(PassageState::kDiscarded)]);
  info->set_strategy(UpdateStrategyName(update.strategy));
  info->set_server_version(CROWDMAP_VERSION);
  info->set_warmup_passages(update.warmup_passages);
  info->set_relinearize_until_passages(update.relinearize_until_passages);
  info->set_max_subgraph_dim(update.max_subgraph_dim);
  info->set_window_hops(update.window_hops);
  info->set_relinearize_sigmas(update.relinearize_sigmas);
  info->set_detections_per_landmark(update.detections_per_landmark);
  info->set_spread_detections(update.spread_detections);
  info->set_estimate_camera_yaw(update.estimate_camera_yaw);
  info->set_fleet_camera_yaw_prior_vehicles(update.fleet_camera_yaw_prior_vehicles);
  return absl::OkStatus();
}

namespace {

// A unary call's reactor that holds a lease until the call is done: a read's response (hundreds of
// MB for a page of 2,000 landmarks with covariances) lives until a client has taken it all, which
// a slow one draws out long after the handler returned.
class LeaseHoldingReactor final : public grpc::ServerUnaryReactor {
 public:
  // Finishes the call with `status`, holding `lease` until the call is done.
  void FinishHolding(const grpc::Status& status, std::unique_ptr<ConcurrentCalls::Lease> lease) {
    lease_ = std::move(lease);
    Finish(status);
  }
  void OnDone() override { delete this; }

 private:
  std::unique_ptr<ConcurrentCalls::Lease> lease_;
};

// Serves a map read through `serve` (ServeTile or ServeRegion, told whether the read got its place).
// A read with covariances takes its place among the capped ones here and, with it, is computed on
// a thread of its own: on gRPC's callback threads (two on a 2-core machine) it kept every other
// call waiting, uploads included (0.3 to 1 s behind four 2,000-landmark reads). Any other read,
// and one refused its place, is served on the callback thread.
template <typename Serve>
grpc::ServerUnaryReactor* ServeRead(grpc::CallbackServerContext* ctx, bool include_cross, ConcurrentCalls* cap,
                                    Serve serve) {
  absl::StatusOr<std::unique_ptr<ConcurrentCalls::Lease>> place = std::unique_ptr<ConcurrentCalls::Lease>();
  if (include_cross && cap != nullptr) place = cap->Enter();
  if (include_cross && place.ok()) {
    auto* reactor = new LeaseHoldingReactor();
    std::thread([reactor, serve, lease = *std::move(place)]() mutable {
      reactor->FinishHolding(serve(absl::OkStatus()), std::move(lease));
    }).detach();
    return reactor;
  }
  grpc::ServerUnaryReactor* reactor = ctx->DefaultReactor();
  reactor->Finish(serve(place.status()));
  return reactor;
}

}  // namespace

grpc::ServerUnaryReactor* MapService::GetTile(grpc::CallbackServerContext* ctx, const pb::GetTileRequest* request,
                                              pb::GetTileResponse* response) {
  return ServeRead(ctx, request->include_cross_covariance(), context_->covariance_reads,
                   [this, ctx, request, response](const absl::Status& place) {
                     return ServeTile(ctx, request, response, place);
                   });
}

grpc::ServerUnaryReactor* MapService::QueryRegion(grpc::CallbackServerContext* ctx,
                                                  const pb::QueryRegionRequest* request,
                                                  pb::QueryRegionResponse* response) {
  return ServeRead(ctx, request->include_cross_covariance(), context_->covariance_reads,
                   [this, ctx, request, response](const absl::Status& place) {
                     return ServeRegion(ctx, request, response, place);
                   });
}

grpc::Status MapService::ServeTile(grpc::ServerContextBase* ctx, const pb::GetTileRequest* request,
                                   pb::GetTileResponse* response, const absl::Status& place) {
  RequestLog log("GetTile", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log); !who.ok()) return log.Done(who.status());
  const TileId tile{request->tile().z(), request->tile().x(), request->tile().y()};
  log.Add(absl::StrCat("tile=", tile.z, "/", tile.x, "/", tile.y));
  if (tile.z != kStorageZoom) {
    return log.Done(absl::InvalidArgumentError(
        absl::StrCat("tile.z: tiles are served at the storage zoom ", kStorageZoom, ", got ", tile.z)));
  }
  if (!IsValidTile(tile)) {
    return log.Done(absl::InvalidArgumentError(absl::StrCat("tile: x and y must lie in [0, ", (1 << kStorageZoom) - 1,
                                                            "] at zoom ", kStorageZoom, ", got ", tile.x, "/", tile.y)));
  }
  absl::StatusOr<pb::CovarianceFormat> format = CovarianceFormatFromProto(
      request->covariance_format(), request->include_cross_covariance(), "covariance_format");
  if (!format.ok()) return log.Done(format.status());
  if (!place.ok()) {  // refused its place among the reads with covariances
    AddRetryTrailers(place, ctx);
    return log.Done(place);
  }
  absl::StatusOr<LandmarkPage> page = context_->store->GetTile(tile, request->include_cross_covariance());
  if (!page.ok()) return log.Done(page.status());
  *response->mutable_tile() = request->tile();
  int64_t tile_version = 0;
  for (const Landmark& l : page->landmarks) tile_version = std::max(tile_version, l.version);
  response->set_tile_version(tile_version);
  response->set_map_version(page->map_version);
  LandmarkPageToProto(*page, *format, response);
  CountCovarianceRead(context_->metrics, *page);
  log.Add(absl::StrCat("landmarks=", page->landmarks.size(), CovarianceBoundField(*page)));
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::ServeRegion(grpc::ServerContextBase* ctx, const pb::QueryRegionRequest* request,
                                     pb::QueryRegionResponse* response,
                                     const absl::Status& place) {
  RequestLog log("QueryRegion", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log); !who.ok()) return log.Done(who.status());
  absl::StatusOr<BoundingBox> box = RequiredBox(*request);
  if (!box.ok()) return log.Done(box.status());
  if (request->page_size() < 0 || request->page_size() > kMaxRegionPage) {
    return log.Done(absl::InvalidArgumentError(absl::StrCat("page_size: must lie in [0, ", kMaxRegionPage, "]")));
  }
  // %a prints the exact doubles: a token is valid only for the same box.
  const std::string query =
      absl::StrFormat("region|%a|%a|%a|%a|%d", request->box().min_lat_deg(), request->box().min_lon_deg(),
                      request->box().max_lat_deg(), request->box().max_lon_deg(), request->include_cross_covariance());
  absl::StatusOr<pb::CovarianceFormat> format = CovarianceFormatFromProto(
      request->covariance_format(), request->include_cross_covariance(), "covariance_format");
  if (!format.ok()) return log.Done(format.status());
  absl::StatusOr<int64_t> after = ParsePageToken(request->page_token(), query);
  if (!after.ok()) return log.Done(after.status());
  const int limit = request->page_size() == 0 ? kDefaultRegionPage : request->page_size();
  if (request->include_cross_covariance() && limit > kMaxCovariancePage) {
    return log.Done(absl::InvalidArgumentError(absl::StrCat("page_size: at most ", kMaxCovariancePage,
                                                            " with include_cross_covariance, got ", limit)));
  }
  if (!place.ok()) {  // refused its place among the reads with covariances
    AddRetryTrailers(place, ctx);
    return log.Done(place);
  }
  absl::StatusOr<LandmarkPage> page =
      context_->store->QueryRegion(*box, *after, limit, request->include_cross_covariance());
  if (!page.ok()) return log.Done(page.status());
  response->set_map_version(page->map_version);
  LandmarkPageToProto(*page, *format, response);
  CountCovarianceRead(context_->metrics, *page);
  if (page->more) response->set_next_page_token(MakePageToken(page->landmarks.back().id, query));
  log.Add(absl::StrCat("landmarks=", page->landmarks.size(), " covariance_dim=", page->covariance.rows(),
                       CovarianceBoundField(*page)));
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::WatchRegion(grpc::ServerContext* ctx, const pb::WatchRegionRequest* request,
                                     grpc::ServerWriter<pb::WatchRegionResponse>* writer) {
  RequestLog log("WatchRegion", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log);
  if (!who.ok()) return log.Done(who.status());
  absl::StatusOr<std::unique_ptr<StreamLimiter::Lease>> stream =
      context_->streams->OpenWatch(ctx, who->stream_identity());
  if (!stream.ok()) {
    AddRetryTrailers(stream.status(), ctx);
    return log.Done(stream.status());
  }
  absl::StatusOr<BoundingBox> box = RequiredBox(*request);
  if (!box.ok()) return log.Done(box.status());
  if (request->since_version() < 0) return log.Done(absl::InvalidArgumentError("since_version: must be >= 0"));
  int64_t since = request->since_version();
  int messages = 0;
  // The first message is always sent (it tells the client the current version); later ones only
  // when landmarks in the box changed.
  while (!ctx->IsCancelled()) {
    absl::StatusOr<LandmarkPage> page = context_->store->ChangedLandmarks(*box, since);
    if (!page.ok()) return log.Done(page.status());
    if (messages == 0 && since > page->map_version) {
      // A version just committed may not be served yet (the client read it from GetMapInfo or its
      // passage's result): wait for it a moment.
      context_->notifier->WaitAbove(since - 1, kWatchAheadWait);
      page = context_->store->ChangedLandmarks(*box, since);
      if (!page.ok()) return log.Done(page.status());
    }
    if (messages == 0 && since > page->map_version) {
      // Versions this map has not reached: the client's come from another map, or from one since
      // restored from a backup. Its copy cannot be brought up to date.
      return log.Done(absl::FailedPreconditionError(absl::StrCat(
          "since_version: ", since, " is ahead of the map's version ", page->map_version,
          " (another map, or one restored from a backup): read the region again and watch from its map_version")));
    }
    if (messages == 0 || !page->landmarks.empty() || !page->removed.empty()) {
      // Only a change's last part carries its version: a client that resumes from the version of
      // an earlier part is sent the whole change again.
      const size_t n = page->landmarks.size();
      bool written = true;
      size_t at = 0;
      do {
        const size_t end = std::min(n, at + kWatchMessageLandmarks);
        pb::WatchRegionResponse response;
        response.set_map_version(end == n ? page->map_version : since);
        for (size_t k = at; k < end; ++k) LandmarkToProto(page->landmarks[k], response.add_landmarks());
        if (end == n) {
          for (LandmarkId id : page->removed) response.add_removed_landmark_ids(id);
        }
        written = writer->Write(response);
        ++messages;
        at = end;
      } while (written && at < n);
      if (!written) break;
    }
    since = std::max(since, page->map_version);
    if (context_->notifier->closed()) {
      log.Add(absl::StrCat("messages=", messages));
      return log.Done(absl::UnavailableError("server is shutting down"));
    }
    context_->notifier->WaitAbove(since, kWatchPoll);
  }
  log.Add(absl::StrCat("messages=", messages));
  return log.Done(absl::CancelledError("client cancelled"));
}

grpc::Status MapService::GetLandmark(grpc::ServerContext* ctx, const pb::GetLandmarkRequest* request,
                                     pb::GetLandmarkResponse* response) {
  RequestLog log("GetLandmark", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log);
  if (!who.ok()) return log.Done(who.status());
  log.Add(absl::StrCat("id=", request->id()));
  absl::StatusOr<LandmarkProvenance> provenance = context_->store->GetLandmarkProvenance(request->id());
  if (!provenance.ok()) return log.Done(provenance.status());
  LandmarkToProto(provenance->landmark, response->mutable_landmark());
  // Which vehicles drove where is passage data: operators and admins only.
  for (const auto& [vehicle_id, passage_id] : provenance->passages) {
    if (!who->MayReadAllPassages()) break;
    pb::PassageKey* key = response->add_passages();
    key->set_vehicle_id(vehicle_id);
    key->set_passage_id(passage_id);
  }
  response->set_map_version(provenance->map_version);
  log.Add(absl::StrCat("passages=", provenance->passages.size()));
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::GetMapInfo(grpc::ServerContext* ctx, const pb::GetMapInfoRequest* request,
                                    pb::MapInfo* response) {
  RequestLog log("GetMapInfo", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kReadMap, &log); !who.ok()) return log.Done(who.status());
  if (absl::Status s = ReadMapInfo(*context_->store, context_->update, context_->worker, response); !s.ok()) {
    return log.Done(s);
  }
  log.Add(absl::StrCat("map_version=", response->map_version(), " queue_depth=", response->queue_depth(),
                       " relinearizations_due=", response->relinearizations_due()));
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
