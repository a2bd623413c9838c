#ifndef CROWDMAP_CLIENT_API_MAP_CLIENT_H_
#define CROWDMAP_CLIENT_API_MAP_CLIENT_H_

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <grpcpp/grpcpp.h>

#include "absl/status/statusor.h"
#include "client/api/client_security.h"
#include "core/map/map_state.h"
#include "mapservice/v1/map_service.grpc.pb.h"
#include "server/grpc_status.h"

namespace crowdmap {

namespace pb = ::mapservice::v1;

struct MapClientOptions {
  std::string server = "127.0.0.1:50051";         // host:port
  // Deadline of every unary call; an upload's retries (below) all fit in it.
  std::chrono::milliseconds call_deadline{10000};
  // Uploads, GetTile, QueryRegion and LocalizePassage failing with UNAVAILABLE or
  // RESOURCE_EXHAUSTED (a full queue, the server's cap on reads with covariances) are retried up
  // to this many attempts in all (1..5; gRPC's retry policy allows at most 5), after a random
  // pause of up to initial_backoff, doubled after each retry up to max_backoff; a server's
  // pushback (grpc-retry-pushback-ms, sent with a full queue or a full cap) replaces the pause.
  int max_attempts = 5;
  std::chrono::milliseconds initial_backoff{50};
  std::chrono::milliseconds max_backoff{2000};
  int max_message_mb = 64;  // receive and send limit of the channel
  // Passages whose serialized size exceeds this go through UploadPassageChunked in pieces of
  // upload_chunk_bytes; the default stays under mapd's default 4 MiB receive limit.
  size_t unary_upload_limit_bytes = (4u << 20) - (64u << 10);
  size_t upload_chunk_bytes = 1u << 20;
  ClientSecurityOptions security;  // TLS, client certificate, bearer token

  absl::Status Validate() const;
};

// Every landmark of a region (all pages), and on request the joint covariance of each page's.
struct RegionMap {
  std::vector<pb::Landmark> landmarks;
  // Page by page, the joint covariance of the page's landmarks (metres^2, East and North rows of
  // each landmark in the order of `landmarks`); empty without covariances. Landmarks of two pages
  // are read apart: their cross blocks are not known.
  std::vector<Eigen::MatrixXd> page_covariances;
  // For each of page_covariances, how it relates to the map's exact covariance (UNSPECIFIED from
  // a server that predates the field).
  std::vector<pb::CovarianceBound> page_covariance_bounds;
  int64_t map_version = 0;  // highest version seen over the pages
};

// The channel's service config: the retry policy of UploadPassage from `options` (none with
// max_attempts 1).
std::string RetryServiceConfig(const MapClientOptions& options);

// A whole-world bounding box.
pb::BoundingBox WorldBox();

// Client of mapservice.v1: a deadline on every call; uploads (idempotent on passage_id) retried
// with jittered exponential backoff on UNAVAILABLE and RESOURCE_EXHAUSTED, by gRPC's retry policy
// (the channel's service config; RetryServiceConfig). Thread-safe.
// A passage named by its server id (non-zero), or by vehicle_id and passage_id.
struct PassageKey {
  int64_t id = 0;
  std::string vehicle_id;
  std::string passage_id;
};

class MapClient {
 public:
  static absl::StatusOr<std::unique_ptr<MapClient>> Create(const MapClientOptions& options);

  // UploadPassage, or UploadPassageChunked above unary_upload_limit_bytes; retried as above. gRPC
  // retries a call only while what it sent fits its retry buffer (the channel's is set to hold a
  // whole unary message), and a chunked passage is larger than any, so chunked uploads are retried
  // here, with the same policy (jitter, backoff, pushback).
  absl::StatusOr<pb::UploadPassageResponse> Upload(const pb::Passage& passage);
  absl::StatusOr<pb::PassageStatus> GetPassage(int64_t id);
  // One landmark and the passages that shaped it.
  absl::StatusOr<pb::GetLandmarkResponse> GetLandmark(int64_t id);
  // A vehicle's estimated camera calibration; every vehicle's (operators), all pages of them.
  absl::StatusOr<pb::Vehicle> GetVehicle(const std::string& vehicle_id);
  absl::StatusOr<pb::ListVehiclesResponse> ListVehicles();
  // Localises a passage against the map (read-only); retried as above.
  absl::StatusOr<pb::LocalizePassageResponse> LocalizePassage(const pb::Passage& passage);
  // Takes an applied passage out of the map (administration).
  absl::StatusOr<pb::ExcludePassageResponse> ExcludePassage(const PassageKey& key);
  // An operator's decision on a failed or quarantined passage (ResolvePassage).
  absl::StatusOr<pb::PassageStatus> ResolvePassage(const PassageKey& key, pb::ResolvePassageRequest::Action action);
  absl::StatusOr<pb::PassageStatus> GetPassage(const std::string& vehicle_id, const std::string& passage_id);
  // Every passage (all pages) in `state`; nullopt = all states.
  absl::StatusOr<std::vector<pb::PassageStatus>> ListPassages(std::optional<pb::PassageState> state);
  absl::StatusOr<pb::MapInfo> GetMapInfo();
  absl::StatusOr<pb::GetTileResponse> GetTile(int z, int x, int y, bool include_cross = false);
  absl::StatusOr<RegionMap> QueryRegion(const pb::BoundingBox& box, bool include_cross = false);
  // The region as a core map; Aborted when the map changed between pages.
  absl::StatusOr<MapState> DownloadMap(const pb::BoundingBox& box);
  // How a watch runs, beyond its box and first version.
  struct WatchOptions {
    // End the watch (OK) after this long; none: until on_change returns false.
    std::optional<std::chrono::milliseconds> duration;
    // When a stream that had answered breaks (UNAVAILABLE: the server restarted, the connection
    // dropped), call again from the last map version received, waiting up to call_deadline for
    // the server to answer; a server not back by then ends the watch with that error.
    bool reconnect = false;
    // Told before each reconnection: the error that broke the stream and the version resumed from.
    std::function<void(const absl::Status&, int64_t)> on_reconnect;
  };
  // Streams changes after `since_version` to `on_change` until it returns false, the duration
  // passes (OK then), or the server ends the stream. Each call's first message (the server sends
  // the current version at once) must come within call_deadline, else DEADLINE_EXCEEDED; later
  // messages come when the map changes and have no deadline.
  absl::Status WatchRegion(const pb::BoundingBox& box, int64_t since_version,
                           const std::function<bool(const pb::WatchRegionResponse&)>& on_change,
                           const WatchOptions& options);
  absl::Status WatchRegion(const pb::BoundingBox& box, int64_t since_version,
                           const std::function<bool(const pb::WatchRegionResponse&)>& on_change,
                           std::optional<std::chrono::milliseconds> duration) {
    WatchOptions options;
    options.duration = duration;
    return WatchRegion(box, since_version, on_change, options);
  }
  // Polls GetMapInfo until nothing is queued or processing and no re-linearisation is due (the map
  // changes no more); DeadlineExceeded after `timeout`.
  absl::StatusOr<pb::MapInfo> WaitUntilIdle(std::chrono::milliseconds timeout,
                                            const std::function<void(const pb::MapInfo&)>& on_poll = nullptr);

  pb::MapService::Stub* stub() { return stub_.get(); }
  const std::shared_ptr<grpc::Channel>& channel() const { return channel_; }

 private:
  // One WatchRegion call from `*since` (advanced as messages arrive) until `end`.
  absl::Status WatchOnce(const pb::BoundingBox& box, int64_t* since, bool wait_for_server,
                         const std::function<bool(const pb::WatchRegionResponse&)>& on_change,
                         std::optional<std::chrono::system_clock::time_point> end, bool* answered, bool* stopped);

  MapClient(const MapClientOptions& options, std::shared_ptr<grpc::ChannelCredentials> credentials);
  // The call deadline and the bearer token.
  void SetDeadline(grpc::ClientContext* ctx) const;
  void Authorize(grpc::ClientContext* ctx) const;
  // One attempt of each upload RPC.
  grpc::Status UploadUnary(const pb::UploadPassageRequest& request, pb::UploadPassageResponse* response);
  // `pushback` is set to the server's grpc-retry-pushback-ms when it sent one.
  grpc::Status UploadChunked(const std::string& serialized, pb::UploadPassageResponse* response,
                             std::optional<std::chrono::milliseconds>* pushback);
  absl::StatusOr<pb::UploadPassageResponse> UploadChunkedWithRetries(const std::string& serialized);

  MapClientOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<pb::MapService::Stub> stub_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_API_MAP_CLIENT_H_
