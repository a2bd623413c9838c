#ifndef CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_
#define CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_

#include <chrono>
#include <memory>
#include <string>

#include <grpcpp/grpcpp.h>

#include "absl/status/statusor.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"
#include "mapservice/v1/map_service.grpc.pb.h"

namespace crowdmap {

namespace pb = ::mapservice::v1;

absl::Status FromGrpcStatus(const grpc::Status& status);

// A vehicle (or operator) talking to mapd the way a production client would: deadlines on every
// call, retries of uploads on UNAVAILABLE / RESOURCE_EXHAUSTED (uploads are idempotent).
class MockVehicle {
 public:
  explicit MockVehicle(const std::string& address, int max_message_mb = 64);

  pb::MapService::Stub* stub() { return stub_.get(); }
  const std::shared_ptr<grpc::Channel>& channel() const { return channel_; }

  // One attempt, no retry.
  absl::StatusOr<pb::UploadPassageResponse> UploadOnce(const pb::Passage& passage);
  // Retries transient failures until acknowledged or `give_up_after` passes.
  absl::StatusOr<pb::UploadPassageResponse> Upload(const Passage& passage,
                                                  std::chrono::milliseconds give_up_after = std::chrono::seconds(30));
  absl::StatusOr<pb::UploadPassageResponse> UploadChunked(const pb::Passage& passage, size_t chunk_bytes);

  absl::StatusOr<pb::MapInfo> GetMapInfo();
  absl::StatusOr<pb::PassageStatus> GetPassage(const std::string& vehicle_id, const std::string& passage_id);
  // Polls until nothing is queued or processing.
  absl::StatusOr<pb::MapInfo> WaitUntilIdle(std::chrono::milliseconds timeout = std::chrono::seconds(120));
  // Every landmark in `box` (paged QueryRegion) and the cross blocks among them, as a MapState.
  absl::StatusOr<MapState> DownloadMap(const pb::BoundingBox& box);

  static pb::BoundingBox World();

 private:
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<pb::MapService::Stub> stub_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_
