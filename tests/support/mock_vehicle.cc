#include "tests/support/mock_vehicle.h"

#include <thread>

#include "absl/strings/str_cat.h"
#include "server/wire_convert.h"

namespace crowdmap {
namespace {

constexpr std::chrono::seconds kCallDeadline{20};

void SetDeadline(grpc::ClientContext* ctx) { ctx->set_deadline(std::chrono::system_clock::now() + kCallDeadline); }

}  // namespace

absl::Status FromGrpcStatus(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()), status.error_message());
}

MockVehicle::MockVehicle(const std::string& address, int max_message_mb) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(max_message_mb << 20);
  args.SetMaxSendMessageSize(max_message_mb << 20);
  channel_ = grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
  stub_ = pb::MapService::NewStub(channel_);
}

pb::BoundingBox MockVehicle::World() {
  pb::BoundingBox box;
  box.set_min_lat_deg(-90);
  box.set_max_lat_deg(90);
  box.set_min_lon_deg(-180);
  box.set_max_lon_deg(180);
  return box;
}

absl::StatusOr<pb::UploadPassageResponse> MockVehicle::UploadOnce(const pb::Passage& passage) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::UploadPassageRequest request;
  *request.mutable_passage() = passage;
  pb::UploadPassageResponse response;
  grpc::Status s = stub_->UploadPassage(&ctx, request, &response);
  if (!s.ok()) return FromGrpcStatus(s);
  return response;
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
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::UploadPassageResponse response;
  auto writer = stub_->UploadPassageChunked(&ctx, &response);
  const std::string bytes = passage.SerializeAsString();
  for (size_t offset = 0; offset < bytes.size(); offset += chunk_bytes) {
    pb::UploadPassageChunk chunk;
    chunk.set_data(bytes.substr(offset, chunk_bytes));
    if (!writer->Write(chunk)) break;
  }
  writer->WritesDone();
  grpc::Status s = writer->Finish();
  if (!s.ok()) return FromGrpcStatus(s);
  return response;
}

absl::StatusOr<pb::MapInfo> MockVehicle::GetMapInfo() {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::MapInfo info;
  grpc::Status s = stub_->GetMapInfo(&ctx, pb::GetMapInfoRequest(), &info);
  if (!s.ok()) return FromGrpcStatus(s);
  return info;
}

absl::StatusOr<pb::PassageStatus> MockVehicle::GetPassage(const std::string& vehicle_id,
                                                         const std::string& passage_id) {
  grpc::ClientContext ctx;
  SetDeadline(&ctx);
  pb::GetPassageRequest request;
  request.set_vehicle_id(vehicle_id);
  request.set_passage_id(passage_id);
  pb::PassageStatus status;
  grpc::Status s = stub_->GetPassage(&ctx, request, &status);
  if (!s.ok()) return FromGrpcStatus(s);
  return status;
}

absl::StatusOr<pb::MapInfo> MockVehicle::WaitUntilIdle(std::chrono::milliseconds timeout) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (true) {
    auto info = GetMapInfo();
    if (!info.ok() || info->queue_depth() == 0) return info;
    if (std::chrono::steady_clock::now() > end) {
      return absl::DeadlineExceededError(absl::StrCat("queue still holds ", info->queue_depth(), " passages"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

absl::StatusOr<MapState> MockVehicle::DownloadMap(const pb::BoundingBox& box) {
  MapState map;
  std::string token;
  int64_t version = 0;
  do {
    grpc::ClientContext ctx;
    SetDeadline(&ctx);
    pb::QueryRegionRequest request;
    *request.mutable_box() = box;
    request.set_page_size(10000);
    request.set_page_token(token);
    request.set_include_cross_covariance(true);
    pb::QueryRegionResponse response;
    grpc::Status s = stub_->QueryRegion(&ctx, request, &response);
    if (!s.ok()) return FromGrpcStatus(s);
    if (!token.empty() && response.map_version() != version) {
      return absl::AbortedError("map changed between pages; download again when idle");
    }
    version = response.map_version();
    for (const pb::Landmark& l : response.landmarks()) map.PutLandmark(LandmarkFromProto(l));
    for (const pb::CrossCovariance& c : response.cross_covariances()) {
      Eigen::Matrix2d block;
      block << c.cov_m2().ee(), c.cov_m2().en(), c.cov_m2().ne(), c.cov_m2().nn();
      map.PutCrossCovariance(c.first_id(), c.second_id(), block);
    }
    token = response.next_page_token();
  } while (!token.empty());
  map.set_version(version);
  return map;
}

}  // namespace crowdmap
