#include "client/api/map_client.h"

#include <Eigen/Cholesky>

#include <algorithm>
#include <condition_variable>
#include <mutex>
#include <random>
#include <thread>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

bool IsTransient(absl::StatusCode code) {
  return code == absl::StatusCode::kUnavailable || code == absl::StatusCode::kResourceExhausted;
}

// gRPC's cap on a retry policy's attempts.
constexpr int kMaxGrpcAttempts = 5;

// The server's grpc-retry-pushback-ms, read as gRPC's retry policy reads it: absent = nullopt
// (the policy's own backoff), a non-negative number = the pause, anything else = -1 (do not retry).
std::optional<std::chrono::milliseconds> Pushback(const grpc::ClientContext& ctx) {
  const auto& trailers = ctx.GetServerTrailingMetadata();
  auto it = trailers.find("grpc-retry-pushback-ms");
  if (it == trailers.end()) return std::nullopt;
  int64_t ms = 0;
  if (!absl::SimpleAtoi(absl::string_view(it->second.data(), it->second.size()), &ms) || ms < 0) {
    return std::chrono::milliseconds(-1);
  }
  return std::chrono::milliseconds(ms);
}

// gRPC's duration syntax: seconds with a fraction.
std::string Seconds(std::chrono::milliseconds d) { return absl::StrFormat("%.3fs", d.count() / 1000.0); }

}  // namespace

absl::Status MapClientOptions::Validate() const {
  if (server.empty()) return absl::InvalidArgumentError("server: empty address");
  if (call_deadline.count() <= 0) return absl::InvalidArgumentError("call_deadline: must be > 0");
  if (max_attempts < 1 || max_attempts > kMaxGrpcAttempts) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_attempts: must lie in [1, ", kMaxGrpcAttempts, "] (gRPC's retry policy), got ", max_attempts));
  }
  if (initial_backoff.count() <= 0 || max_backoff < initial_backoff) {
    return absl::InvalidArgumentError("backoff: need 0 < initial_backoff <= max_backoff");
  }
  if (max_message_mb < 1) return absl::InvalidArgumentError("max_message_mb: must be >= 1");
  if (upload_chunk_bytes < 1 || upload_chunk_bytes > (static_cast<size_t>(max_message_mb) << 20) - 1024) {
    return absl::InvalidArgumentError("upload_chunk_bytes: must lie in [1, max_message_mb MiB - 1 KiB]");
  }
  return absl::OkStatus();
}

std::string RetryServiceConfig(const MapClientOptions& options) {
  if (options.max_attempts < 2) return "{}";
  const nlohmann::ordered_json policy = {
      {"maxAttempts", options.max_attempts},
      {"initialBackoff", Seconds(options.initial_backoff)},
      {"maxBackoff", Seconds(options.max_backoff)},
      {"backoffMultiplier", 2},
      {"retryableStatusCodes", {"UNAVAILABLE", "RESOURCE_EXHAUSTED"}}};
  // Uploads are idempotent; so are the map reads and localisations, whose covariance reads the
  // server caps (--max-covariance-reads) and answers RESOURCE_EXHAUSTED beyond.
  nlohmann::ordered_json names = nlohmann::ordered_json::array();
  for (const char* rpc : {"UploadPassage", "GetTile", "QueryRegion", "LocalizePassage"}) {
    names.push_back({{"service", "mapservice.v1.MapService"}, {"method", rpc}});
  }
  const nlohmann::ordered_json method = {{"name", names}, {"retryPolicy", policy}};
  return nlohmann::ordered_json{{"methodConfig", {method}}}.dump();
}

pb::BoundingBox WorldBox() {
  pb::BoundingBox box;
  box.set_min_lat_deg(-90);
  box.set_max_lat_deg(90);
  box.set_min_lon_deg(-180);
  box.set_max_lon_deg(180);
  return box;
}

absl::StatusOr<std::unique_ptr<MapClient>> MapClient::Create(const MapClientOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>> credentials = MakeChannelCredentials(options.security);
  if (!credentials.ok()) return credentials.status();
  return std::unique_ptr<MapClient>(new MapClient(options, *std::move(credentials)));
}

MapClient::MapClient(const MapClientOptions& options, std::shared_ptr<grpc::ChannelCredentials> credentials)
    : options_(options) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(options.max_message_mb << 20);
  args.SetMaxSendMessageSize(options.max_message_mb << 20);
  args.SetServiceConfigJSON(RetryServiceConfig(options));
  // gRPC retries a call only while what it sent fits this buffer (256 KiB by default, under
  // which a 1 MiB upload was tried once): a whole unary message.
  args.SetInt(GRPC_ARG_PER_RPC_RETRY_BUFFER_SIZE, options.max_message_mb << 20);
  if (!options.security.tls_server_name.empty()) args.SetSslTargetNameOverride(options.security.tls_server_name);
  channel_ = grpc::CreateCustomChannel(options.server, credentials, args);
  stub_ = pb::MapService::NewStub(channel_);
}

void MapClient::SetDeadline(grpc::ClientContext* ctx) const {
  ctx->set_deadline(std::chrono::system_clock::now() + options_.call_deadline);
  Authorize(ctx);
}

// Sent as plain metadata, not as call credentials: gRPC sends those over TLS only, and mapd on
// loopback may run without it.
void MapClient::Authorize(grpc::ClientContext* ctx) const {
  if (!options_.security.token.empty()) ctx->AddMetadata("authorization", "Bearer " + options_.security.token);
}

grpc::Status MapClient::UploadUnary(const pb::UploadPassageRequest& request, pb::UploadPassageResponse* response) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  return stub_->UploadPassage(&ctx, request, response);
}

grpc::Status MapClient::UploadChunked(const std::string& serialized, pb::UploadPassageResponse* response,
                                      std::optional<std::chrono::milliseconds>* pushback) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  std::unique_ptr<grpc::ClientWriter<pb::UploadPassageChunk>> writer = stub_->UploadPassageChunked(&ctx, response);
  pb::UploadPassageChunk chunk;
  for (size_t offset = 0; offset < serialized.size(); offset += options_.upload_chunk_bytes) {
    chunk.set_data(serialized.substr(offset, options_.upload_chunk_bytes));
    if (!writer->Write(chunk)) break;  // the server ended the call; Finish() says why
  }
  writer->WritesDone();
  grpc::Status status = writer->Finish();
  *pushback = Pushback(ctx);
  return status;
}

absl::StatusOr<pb::UploadPassageResponse> MapClient::UploadChunkedWithRetries(const std::string& serialized) {
  // gRPC's policy (A6, "Retry design"): a pause drawn uniformly from [0, backoff), the backoff
  // doubled after each retry up to its maximum; a pushback replaces the pause and resets it.
  thread_local std::mt19937_64 random(std::random_device{}());
  std::chrono::milliseconds backoff = options_.initial_backoff;
  absl::Status last;
  for (int attempt = 1; attempt <= options_.max_attempts; ++attempt) {
    pb::UploadPassageResponse response;
    std::optional<std::chrono::milliseconds> pushback;
    last = FromGrpcStatus(UploadChunked(serialized, &response, &pushback));
    if (last.ok()) return response;
    if (!IsTransient(last.code()) || attempt == options_.max_attempts) break;
    if (pushback && pushback->count() < 0) break;
    if (pushback) {
      std::this_thread::sleep_for(*pushback);
      backoff = options_.initial_backoff;
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(
          std::uniform_int_distribution<int64_t>(0, std::max<int64_t>(0, backoff.count() - 1))(random)));
      backoff = std::min(backoff * 2, options_.max_backoff);
    }
  }
  return last;
}

absl::StatusOr<pb::UploadPassageResponse> MapClient::Upload(const pb::Passage& passage) {
  if (passage.ByteSizeLong() > options_.unary_upload_limit_bytes) return UploadChunkedWithRetries(passage.SerializeAsString());
  pb::UploadPassageRequest request;
  *request.mutable_passage() = passage;
  pb::UploadPassageResponse response;
  if (absl::Status s = FromGrpcStatus(UploadUnary(request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<pb::PassageStatus> MapClient::GetPassage(int64_t id) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetPassageRequest request;
  request.set_id(id);
  pb::PassageStatus status;
  if (absl::Status s = FromGrpcStatus(stub_->GetPassage(&ctx, request, &status)); !s.ok()) return s;
  return status;
}

absl::StatusOr<pb::GetLandmarkResponse> MapClient::GetLandmark(int64_t id) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetLandmarkRequest request;
  request.set_id(id);
  pb::GetLandmarkResponse response;
  if (absl::Status s = FromGrpcStatus(stub_->GetLandmark(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<pb::Vehicle> MapClient::GetVehicle(const std::string& vehicle_id) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetVehicleRequest request;
  request.set_vehicle_id(vehicle_id);
  pb::Vehicle response;
  if (absl::Status s = FromGrpcStatus(stub_->GetVehicle(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<pb::ListVehiclesResponse> MapClient::ListVehicles() {
  pb::ListVehiclesResponse all;
  std::string token;
  do {
    grpc::ClientContext ctx;
    SetDeadline(&ctx);
    pb::ListVehiclesRequest request;
    request.set_page_size(1000);
    request.set_page_token(token);
    pb::ListVehiclesResponse response;
    if (absl::Status s = FromGrpcStatus(stub_->ListVehicles(&ctx, request, &response)); !s.ok()) return s;
    all.mutable_vehicles()->MergeFrom(response.vehicles());
    token = response.next_page_token();
  } while (!token.empty());
  return all;
}

absl::StatusOr<pb::LocalizePassageResponse> MapClient::LocalizePassage(const pb::Passage& passage) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::LocalizePassageRequest request;
  *request.mutable_passage() = passage;
  pb::LocalizePassageResponse response;
  if (absl::Status s = FromGrpcStatus(stub_->LocalizePassage(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

namespace {

// Requests that name a passage by id, or by vehicle_id and passage_id.
template <typename Request>
Request NamingPassage(const PassageKey& key) {
  Request request;
  request.set_id(key.id);
  request.set_vehicle_id(key.vehicle_id);
  request.set_passage_id(key.passage_id);
  return request;
}

}  // namespace

absl::StatusOr<pb::ExcludePassageResponse> MapClient::ExcludePassage(const PassageKey& key) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  const auto request = NamingPassage<pb::ExcludePassageRequest>(key);
  pb::ExcludePassageResponse response;
  if (absl::Status s = FromGrpcStatus(stub_->ExcludePassage(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<pb::PassageStatus> MapClient::ResolvePassage(const PassageKey& key,
                                                           pb::ResolvePassageRequest::Action action) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  auto request = NamingPassage<pb::ResolvePassageRequest>(key);
  request.set_action(action);
  pb::PassageStatus response;
  if (absl::Status s = FromGrpcStatus(stub_->ResolvePassage(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<pb::PassageStatus> MapClient::GetPassage(const std::string& vehicle_id,
                                                       const std::string& passage_id) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetPassageRequest request;
  request.set_vehicle_id(vehicle_id);
  request.set_passage_id(passage_id);
  pb::PassageStatus status;
  if (absl::Status s = FromGrpcStatus(stub_->GetPassage(&ctx, request, &status)); !s.ok()) return s;
  return status;
}

absl::StatusOr<std::vector<pb::PassageStatus>> MapClient::ListPassages(std::optional<pb::PassageState> state) {
  std::vector<pb::PassageStatus> out;
  std::string token;
  do {
    grpc::ClientContext ctx;
    SetDeadline(&ctx);
    pb::ListPassagesRequest request;
    request.set_page_size(1000);
    request.set_page_token(token);
    if (state) request.set_state(*state);
    pb::ListPassagesResponse response;
    if (absl::Status s = FromGrpcStatus(stub_->ListPassages(&ctx, request, &response)); !s.ok()) return s;
    out.insert(out.end(), response.passages().begin(), response.passages().end());
    token = response.next_page_token();
  } while (!token.empty());
  return out;
}

absl::StatusOr<pb::MapInfo> MapClient::GetMapInfo() {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::MapInfo info;
  if (absl::Status s = FromGrpcStatus(stub_->GetMapInfo(&ctx, pb::GetMapInfoRequest(), &info)); !s.ok()) return s;
  return info;
}

absl::StatusOr<pb::GetTileResponse> MapClient::GetTile(int z, int x, int y, bool include_cross) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetTileRequest request;
  request.mutable_tile()->set_z(z);
  request.mutable_tile()->set_x(x);
  request.mutable_tile()->set_y(y);
  request.set_include_cross_covariance(include_cross);
  if (include_cross) request.set_covariance_format(pb::COVARIANCE_FORMAT_PACKED);
  pb::GetTileResponse response;
  if (absl::Status s = FromGrpcStatus(stub_->GetTile(&ctx, request, &response)); !s.ok()) return s;
  return response;
}

absl::StatusOr<RegionMap> MapClient::QueryRegion(const pb::BoundingBox& box, bool include_cross) {
  RegionMap region;
  std::string token;
  do {
    grpc::ClientContext ctx;
    SetDeadline(&ctx);
    pb::QueryRegionRequest request;
    *request.mutable_box() = box;
    request.set_page_size(include_cross ? 2000 : 10000);  // the server's largest pages
    request.set_page_token(token);
    request.set_include_cross_covariance(include_cross);
    if (include_cross) request.set_covariance_format(pb::COVARIANCE_FORMAT_PACKED);
    pb::QueryRegionResponse response;
    if (absl::Status s = FromGrpcStatus(stub_->QueryRegion(&ctx, request, &response)); !s.ok()) return s;
    if (!token.empty() && response.map_version() != region.map_version) {
      return absl::AbortedError("map changed between pages; query again");
    }
    region.map_version = response.map_version();
    region.landmarks.insert(region.landmarks.end(), response.landmarks().begin(), response.landmarks().end());
    if (include_cross && response.landmarks_size() > 0) {
      absl::StatusOr<Eigen::MatrixXd> cov = CovarianceFromProto(response);
      if (!cov.ok()) return absl::DataLossError(absl::StrCat("QueryRegion response: ", cov.status().message()));
      region.page_covariances.push_back(*std::move(cov));
      region.page_covariance_bounds.push_back(response.covariance_bound());
    }
    token = response.next_page_token();
  } while (!token.empty());
  return region;
}

absl::StatusOr<MapState> MapClient::DownloadMap(const pb::BoundingBox& box) {
  absl::StatusOr<RegionMap> region = QueryRegion(box, /*include_cross=*/true);
  if (!region.ok()) return region.status();
  // The region's Gaussian in information form: one factor with the inverse of its joint
  // covariance, the landmarks anchored at their positions.
  MapState map;
  MapFactor factor;
  factor.id = 1;
  for (const pb::Landmark& l : region->landmarks) {
    Landmark record = LandmarkFromProto(l);
    record.anchor = record.position;
    factor.landmarks.push_back(record.id);
    map.PutLandmark(record);
  }
  const int n = 2 * static_cast<int>(factor.landmarks.size());
  Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(n, n);
  int at = 0;
  for (const Eigen::MatrixXd& page : region->page_covariances) {
    cov.block(at, at, page.rows(), page.rows()) = page;
    at += static_cast<int>(page.rows());
  }
  if (n > 0) {
    Eigen::LLT<Eigen::MatrixXd> llt(0.5 * (cov + cov.transpose()));
    if (llt.info() != Eigen::Success) return absl::DataLossError("the region's joint covariance is not positive definite");
    factor.information = llt.solve(Eigen::MatrixXd::Identity(n, n));
    factor.information_vector = Eigen::VectorXd::Zero(n);
    map.PutFactor(std::move(factor));
  }
  map.set_version(region->map_version);
  return map;
}

absl::Status MapClient::WatchOnce(const pb::BoundingBox& box, int64_t* since, bool wait_for_server,
                                  const std::function<bool(const pb::WatchRegionResponse&)>& on_change,
                                  std::optional<std::chrono::system_clock::time_point> end, bool* answered,
                                  bool* stopped) {
  grpc::ClientContext ctx;
  if (end) ctx.set_deadline(*end);
  ctx.set_wait_for_ready(wait_for_server);
  Authorize(&ctx);
  pb::WatchRegionRequest request;
  *request.mutable_box() = box;
  request.set_since_version(*since);
  // A stream has no deadline of its own; a watchdog cancels the call when its first message is
  // late by call_deadline.
  std::mutex mu;
  std::condition_variable cv;
  bool first = false, done = false, first_late = false;
  std::thread watchdog([&] {
    std::unique_lock<std::mutex> lock(mu);
    if (!cv.wait_for(lock, options_.call_deadline, [&] { return first || done; })) {
      first_late = true;
      ctx.TryCancel();
    }
  });
  auto wake = [&](bool* flag) {
    std::lock_guard<std::mutex> lock(mu);
    *flag = true;
    cv.notify_all();
  };
  std::unique_ptr<grpc::ClientReader<pb::WatchRegionResponse>> reader = stub_->WatchRegion(&ctx, request);
  pb::WatchRegionResponse response;
  while (reader->Read(&response)) {
    if (!first) wake(&first);
    *answered = true;
    *since = std::max(*since, response.map_version());
    if (!on_change(response)) {
      *stopped = true;
      ctx.TryCancel();
      break;
    }
  }
  const grpc::Status status = reader->Finish();
  wake(&done);
  watchdog.join();
  if (*stopped || (end && status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED)) return absl::OkStatus();
  bool late = false;
  {
    std::lock_guard<std::mutex> lock(mu);
    late = first_late && !first;
  }
  if (late) {
    return absl::DeadlineExceededError(absl::StrFormat("WatchRegion: no answer within the call deadline (%.3g s)",
                                                       options_.call_deadline.count() / 1000.0));
  }
  return FromGrpcStatus(status);
}

absl::Status MapClient::WatchRegion(const pb::BoundingBox& box, int64_t since_version,
                                    const std::function<bool(const pb::WatchRegionResponse&)>& on_change,
                                    const WatchOptions& options) {
  std::optional<std::chrono::system_clock::time_point> end;
  if (options.duration) end = std::chrono::system_clock::now() + *options.duration;
  int64_t since = since_version;
  bool wait_for_server = false;
  bool answered = false;  // the watch has been live: some stream answered
  while (true) {
    bool stopped = false;
    absl::Status status = WatchOnce(box, &since, wait_for_server, on_change, end, &answered, &stopped);
    if (status.ok() || stopped) return status;
    // Reconnect only a watch that was live: a server unreachable from the start is an error at once,
    // and a reconnection that got no answer within call_deadline ends the watch. A stream this
    // client did not cancel that ends CANCELLED was cut by the server (a shutdown): lost as well.
    const bool lost = status.code() == absl::StatusCode::kUnavailable || status.code() == absl::StatusCode::kCancelled;
    if (!options.reconnect || !answered || !lost) return status;
    if (options.on_reconnect) options.on_reconnect(status, since);
    wait_for_server = true;
  }
}

absl::StatusOr<pb::MapInfo> MapClient::WaitUntilIdle(std::chrono::milliseconds timeout,
                                                     const std::function<void(const pb::MapInfo&)>& on_poll) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (true) {
    absl::StatusOr<pb::MapInfo> info = GetMapInfo();
    if (!info.ok()) return info;
    if (on_poll) on_poll(*info);
    if (info->queue_depth() == 0 && info->relinearizations_due() == 0) return info;
    if (std::chrono::steady_clock::now() > end) {
      return absl::DeadlineExceededError(absl::StrCat("queue still holds ", info->queue_depth(), " passages, ",
                                                      info->relinearizations_due(), " re-linearisations due"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
}

}  // namespace crowdmap
