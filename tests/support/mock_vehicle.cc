#include "tests/support/mock_vehicle.h"

#include <algorithm>
#include <thread>

#include "gtest/gtest.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

MapClientOptions SingleAttempt(const std::string& address, int max_message_mb) {
  MapClientOptions options;
  options.server = address;
  options.call_deadline = std::chrono::seconds(20);
  options.max_attempts = 1;
  options.max_message_mb = max_message_mb;
  return options;
}

std::unique_ptr<MapClient> CreateClient(const MapClientOptions& options) {
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(options);
  EXPECT_TRUE(client.ok()) << client.status();
  return client.ok() ? std::move(*client) : nullptr;
}

}  // namespace

MockVehicle::MockVehicle(const std::string& address, int max_message_mb)
    : options_(SingleAttempt(address, max_message_mb)), client_(CreateClient(options_)) {}

absl::StatusOr<pb::UploadPassageResponse> MockVehicle::UploadOnce(const pb::Passage& passage) {
  return client_->Upload(passage);
}

absl::StatusOr<pb::UploadPassageResponse> MockVehicle::Upload(const Passage& passage,
                                                             std::chrono::milliseconds give_up_after) {
  pb::Passage wire;
  PassageToProto(passage, &wire);
  const auto end = std::chrono::steady_clock::now() + give_up_after;
  std::chrono::milliseconds backoff(10);
  while (true) {
    auto response = UploadOnce(wire);
    const absl::StatusCode code = response.status().code();
    const bool transient = code == absl::StatusCode::kUnavailable || code == absl::StatusCode::kResourceExhausted ||
                           code == absl::StatusCode::kDeadlineExceeded;
    if (response.ok() || !transient || std::chrono::steady_clock::now() > end) return response;
    std::this_thread::sleep_for(backoff);
    backoff = std::min(backoff * 2, std::chrono::milliseconds(500));
  }
}

absl::StatusOr<pb::UploadPassageResponse> MockVehicle::UploadChunked(const pb::Passage& passage, size_t chunk_bytes) {
  MapClientOptions options = options_;
  options.unary_upload_limit_bytes = 0;
  options.upload_chunk_bytes = chunk_bytes;
  std::unique_ptr<MapClient> chunking = CreateClient(options);
  if (chunking == nullptr) return absl::InternalError("chunking client: bad options");
  return chunking->Upload(passage);
}

}  // namespace crowdmap
