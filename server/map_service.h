#ifndef CROWDMAP_SERVER_MAP_SERVICE_H_
#define CROWDMAP_SERVER_MAP_SERVICE_H_

#include <atomic>
#include <string>

#include <google/protobuf/arena.h>
#include <grpcpp/support/byte_buffer.h>
#include <grpcpp/support/message_allocator.h>
#include <grpcpp/support/sync_stream.h>

#include "core/estimation/map_updater.h"
#include "mapservice/v1/map_service.grpc.pb.h"
#include "server/auth.h"
#include "server/map_worker.h"
#include "server/metrics.h"
#include "server/quotas.h"
#include "server/request_log.h"
#include "server/storage/map_store.h"
#include "server/upload_committer.h"
#include "server/version_notifier.h"
#include "server/wire_convert.h"

namespace crowdmap {

// What the RPC handlers share. Pointers are borrowed; the server owns them.
struct MapServiceContext {
  MapStoreInterface* store = nullptr;
  UploadCommitter* committer = nullptr;
  MapWorker* worker = nullptr;  // woken after each new upload
  VersionNotifier* notifier = nullptr;
  ServerMetrics* metrics = nullptr;  // nullptr without --metrics-listen
  WireLimits limits;
  MapUpdateOptions update;  // the worker's estimator settings, reported by GetMapInfo
  std::atomic<bool> accepting_uploads{true};
  const Authenticator* auth = nullptr;  // null: authentication off
  VehicleQuotas* quotas = nullptr;
  InflightBytes* inflight = nullptr;
  StreamLimiter* streams = nullptr;
  ConcurrentCalls* covariance_reads = nullptr;  // null: no limit
};

// GetMapInfo's answer (also the map viewer's): the store's counts, the estimator's settings and the
// re-linearisations `worker` (null: none) owes, read before and after the stats and the larger
// taken: a re-linearisation is committed before it stops being owed, and a passage's owed ones
// are counted before its commit, so an answer with nothing queued and nothing owed carries the
// map's final version. The store's error when it cannot answer.
absl::Status ReadMapInfo(MapStoreInterface& store, const MapUpdateOptions& update, const MapWorker* worker,
                         pb::MapInfo* info);

// mapservice.v1.MapService: one thin handler per RPC; conversion in wire_convert, errors through
// ToGrpcStatus, one log line per request.
// Allocates a callback call's request and response on one protobuf arena, freed with the call.
template <typename Request, typename Response>
class ArenaMessageAllocator : public grpc::MessageAllocator<Request, Response> {
 public:
  grpc::MessageHolder<Request, Response>* AllocateMessages() override { return new Holder(); }

 private:
  static constexpr size_t kFirstBlockBytes = 32 << 10;  // a 1000-landmark page fits in a few blocks
  class Holder : public grpc::MessageHolder<Request, Response> {
   public:
    Holder() : arena_(Options()) {
      this->set_request(google::protobuf::Arena::CreateMessage<Request>(&arena_));
      this->set_response(google::protobuf::Arena::CreateMessage<Response>(&arena_));
    }
    void Release() override { delete this; }

   private:
    static google::protobuf::ArenaOptions Options() {
      google::protobuf::ArenaOptions options;
      options.start_block_size = kFirstBlockBytes;
      return options;
    }
    google::protobuf::Arena arena_;
  };
};

// The map reads (GetTile, QueryRegion) are served from memory and never block, so they use the
// callback API and run on gRPC's own threads without a hand-off; those with covariances, which
// take milliseconds to seconds, on threads of their own (map_read_handlers.cc, ServeRead). UploadPassage does too: its
// handler waits only for the queue's group commit (a few ms), and with the synchronous API gRPC
// 1.51 left 1-2% of the requests unread in the socket for 40-100 ms before any thread took them
// (acknowledgement p99 85 ms, 8.8 ms as a callback; docs/results.md). The other RPCs are
// synchronous.
using MapServiceBase = pb::MapService::WithRawCallbackMethod_UploadPassage<
    pb::MapService::WithCallbackMethod_GetTile<pb::MapService::WithCallbackMethod_QueryRegion<pb::MapService::Service>>>;

// The two upload RPCs are served raw (their request bytes parsed in the handler, see wire_parse.h),
// so that a malformed upload gets INVALID_ARGUMENT naming the field.
class MapService final : public MapServiceBase {
 public:
  explicit MapService(MapServiceContext* context);

  grpc::ServerUnaryReactor* UploadPassage(grpc::CallbackServerContext* ctx, const grpc::ByteBuffer* request,
                                          grpc::ByteBuffer* response) override;
  grpc::Status UploadPassageRaw(grpc::ServerContextBase* ctx, const grpc::ByteBuffer* request,
                                pb::UploadPassageResponse* response);
  grpc::Status UploadPassageChunkedRaw(
      grpc::ServerContext* ctx, grpc::ServerReaderWriterInterface<pb::UploadPassageResponse, grpc::ByteBuffer>* reader,
      pb::UploadPassageResponse* response);
  grpc::Status GetPassage(grpc::ServerContext* ctx, const pb::GetPassageRequest* request,
                          pb::PassageStatus* response) override;
  grpc::Status ListPassages(grpc::ServerContext* ctx, const pb::ListPassagesRequest* request,
                            pb::ListPassagesResponse* response) override;
  grpc::ServerUnaryReactor* GetTile(grpc::CallbackServerContext* ctx, const pb::GetTileRequest* request,
                                    pb::GetTileResponse* response) override;
  grpc::ServerUnaryReactor* QueryRegion(grpc::CallbackServerContext* ctx, const pb::QueryRegionRequest* request,
                                        pb::QueryRegionResponse* response) override;
  grpc::Status WatchRegion(grpc::ServerContext* ctx, const pb::WatchRegionRequest* request,
                           grpc::ServerWriter<pb::WatchRegionResponse>* writer) override;
  grpc::Status GetMapInfo(grpc::ServerContext* ctx, const pb::GetMapInfoRequest* request,
                          pb::MapInfo* response) override;
  grpc::Status ExcludePassage(grpc::ServerContext* ctx, const pb::ExcludePassageRequest* request,
                              pb::ExcludePassageResponse* response) override;
  grpc::Status ResolvePassage(grpc::ServerContext* ctx, const pb::ResolvePassageRequest* request,
                              pb::PassageStatus* response) override;
  grpc::Status GetLandmark(grpc::ServerContext* ctx, const pb::GetLandmarkRequest* request,
                           pb::GetLandmarkResponse* response) override;
  grpc::Status LocalizePassage(grpc::ServerContext* ctx, const pb::LocalizePassageRequest* request,
                               pb::LocalizePassageResponse* response) override;
  grpc::Status GetVehicle(grpc::ServerContext* ctx, const pb::GetVehicleRequest* request,
                          pb::Vehicle* response) override;
  grpc::Status ListVehicles(grpc::ServerContext* ctx, const pb::ListVehiclesRequest* request,
                            pb::ListVehiclesResponse* response) override;

 private:
  // The record named by an id, or by vehicle_id and passage_id, or by both (InvalidArgument when
  // they name two passages). With `own_reader` (a caller who reads only its own vehicle's), another
  // vehicle's passage named by its id answers as a missing one, before the key is compared.
  absl::StatusOr<StoredPassage> FindRecord(int64_t id, const std::string& vehicle_id, const std::string& passage_id,
                                           const Principal* own_reader, RequestLog* log);
  // Validates, commits and acknowledges one upload (both upload RPCs end here).
  // `who` may upload only as itself (Principal::MayActFor); the upload counts against the quota of
  // its vehicle_id.
  absl::Status AcceptUpload(const Principal& who, const pb::Passage& wire, size_t wire_bytes, std::string payload,
                            pb::UploadPassageResponse* response);

  // `place`: whether a read with covariances got its place among those capped
  // (MapServiceContext::covariance_reads; the caller holds it until the response is sent). A
  // refused one is answered with it once the request is found valid.
  grpc::Status ServeTile(grpc::ServerContextBase* ctx, const pb::GetTileRequest* request,
                         pb::GetTileResponse* response, const absl::Status& place);
  grpc::Status ServeRegion(grpc::ServerContextBase* ctx, const pb::QueryRegionRequest* request,
                           pb::QueryRegionResponse* response, const absl::Status& place);

  MapServiceContext* const context_;
  // Map read responses hold a few hundred small messages: one arena per call instead.
  ArenaMessageAllocator<pb::GetTileRequest, pb::GetTileResponse> tile_allocator_;
  ArenaMessageAllocator<pb::QueryRegionRequest, pb::QueryRegionResponse> region_allocator_;
};

// Opaque page tokens: the last id of the previous page, bound to the query that issued them by a
// fingerprint of `query` (the request's filters, not its page size), so that a token passed with
// other filters is refused instead of silently continuing a different listing.
std::string MakePageToken(int64_t last_id, std::string_view query);
absl::StatusOr<int64_t> ParsePageToken(const std::string& token, std::string_view query);
// The same for listings in the order of a string key (vehicle_id); an empty token gives "".
std::string MakeKeyPageToken(std::string_view last_key, std::string_view query);
absl::StatusOr<std::string> ParseKeyPageToken(const std::string& token, std::string_view query);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAP_SERVICE_H_
