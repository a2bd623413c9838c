#ifndef CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_
#define CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_

#include <chrono>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "client/api/map_client.h"
#include "core/map/map_state.h"
#include "core/model/passage.h"

namespace crowdmap {

// A vehicle (or operator) talking to mapd the way a production client would, through the client
// library (deadlines on every call), plus what the tests need around it: raw stub access, a single
// upload attempt, forced chunked uploads, and retries bounded by time rather than attempts.
class MockVehicle {
 public:
  explicit MockVehicle(const std::string& address, int max_message_mb = 64);

  pb::MapService::Stub* stub() { return client_->stub(); }
  MapClient* client() { return client_.get(); }
  const std::shared_ptr<grpc::Channel>& channel() const { return client_->channel(); }

  // One attempt, no retry.
  absl::StatusOr<pb::UploadPassageResponse> UploadOnce(const pb::Passage& passage);
  // Retries transient failures (and deadlines: the server may be restarting) until acknowledged
  // or `give_up_after` passes.
  absl::StatusOr<pb::UploadPassageResponse> Upload(const Passage& passage,
                                                  std::chrono::milliseconds give_up_after = std::chrono::seconds(30));
  // One attempt through UploadPassageChunked, whatever the size.
  absl::StatusOr<pb::UploadPassageResponse> UploadChunked(const pb::Passage& passage, size_t chunk_bytes);

  absl::StatusOr<pb::MapInfo> GetMapInfo() { return client_->GetMapInfo(); }
  absl::StatusOr<pb::PassageStatus> GetPassage(const std::string& vehicle_id, const std::string& passage_id) {
    return client_->GetPassage(vehicle_id, passage_id);
  }
  absl::StatusOr<pb::MapInfo> WaitUntilIdle(std::chrono::milliseconds timeout = std::chrono::seconds(120)) {
    return client_->WaitUntilIdle(timeout);
  }
  // Every landmark in `box` and the cross blocks among them, as a MapState.
  absl::StatusOr<MapState> DownloadMap(const pb::BoundingBox& box) { return client_->DownloadMap(box); }

  static pb::BoundingBox World() { return WorldBox(); }

 private:
  MapClientOptions options_;
  std::unique_ptr<MapClient> client_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_TESTS_SUPPORT_MOCK_VEHICLE_H_
