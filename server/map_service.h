#ifndef CROWDMAP_SERVER_MAP_SERVICE_H_
#define CROWDMAP_SERVER_MAP_SERVICE_H_

#include <atomic>
#include <string>

#include "mapservice/v1/map_service.grpc.pb.h"
#include "server/map_worker.h"
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
  WireLimits limits;
  std::string strategy;
  std::atomic<bool> accepting_uploads{true};
};

// mapservice.v1.MapService: one thin handler per RPC; conversion in wire_convert, errors through
// ToGrpcStatus, one log line per request.
class MapService final : public pb::MapService::Service {
 public:
  explicit MapService(MapServiceContext* context) : context_(context) {}

  grpc::Status UploadPassage(grpc::ServerContext* ctx, const pb::UploadPassageRequest* request,
                             pb::UploadPassageResponse* response) override;
  grpc::Status UploadPassageChunked(grpc::ServerContext* ctx, grpc::ServerReader<pb::UploadPassageChunk>* reader,
                                    pb::UploadPassageResponse* response) override;
  grpc::Status GetPassage(grpc::ServerContext* ctx, const pb::GetPassageRequest* request,
                          pb::PassageStatus* response) override;
  grpc::Status ListPassages(grpc::ServerContext* ctx, const pb::ListPassagesRequest* request,
                            pb::ListPassagesResponse* response) override;
  grpc::Status GetTile(grpc::ServerContext* ctx, const pb::GetTileRequest* request,
                       pb::GetTileResponse* response) override;
  grpc::Status QueryRegion(grpc::ServerContext* ctx, const pb::QueryRegionRequest* request,
                           pb::QueryRegionResponse* response) override;
  grpc::Status WatchRegion(grpc::ServerContext* ctx, const pb::WatchRegionRequest* request,
                           grpc::ServerWriter<pb::WatchRegionResponse>* writer) override;
  grpc::Status GetMapInfo(grpc::ServerContext* ctx, const pb::GetMapInfoRequest* request,
                          pb::MapInfo* response) override;

 private:
  // Validates, commits and acknowledges one upload (both upload RPCs end here).
  absl::Status AcceptUpload(const pb::Passage& wire, size_t wire_bytes, std::string payload,
                            pb::UploadPassageResponse* response);

  MapServiceContext* const context_;
};

// Opaque page tokens: the last id of the previous page.
std::string MakePageToken(int64_t last_id);
absl::StatusOr<int64_t> ParsePageToken(const std::string& token);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_MAP_SERVICE_H_
