// Uploads whose bytes are not a well-formed request (garbage, truncation, invalid UTF-8 in a
// string field), sent by a raw client: INVALID_ARGUMENT with a message naming the field, and
// nothing stored. gRPC's own deserialization would answer INTERNAL with an empty message.
#include <grpcpp/impl/client_unary_call.h>
#include <grpcpp/impl/rpc_method.h>
#include <grpcpp/support/sync_stream.h>

#include <string>
#include <vector>

#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "server/wire_parse.h"
#include "tests/support/mock_vehicle.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

const std::string kUploadPath = "/mapservice.v1.MapService/UploadPassage";
const std::string kChunkedPath = "/mapservice.v1.MapService/UploadPassageChunked";

grpc::ByteBuffer ToBuffer(const std::string& bytes) {
  grpc::Slice slice(bytes);
  return grpc::ByteBuffer(&slice, 1);
}

// `bytes` with the first occurrence of `from` replaced by `to` (same length, so no length prefix
// changes).
std::string Patch(std::string bytes, const std::string& from, const std::string& to) {
  const size_t at = bytes.find(from);
  EXPECT_NE(at, std::string::npos);
  EXPECT_EQ(from.size(), to.size());
  if (at != std::string::npos) bytes.replace(at, from.size(), to);
  return bytes;
}

class MalformedRequest : public ::testing::Test {
 protected:
  void SetUp() override {
    server_ = StartTestServer(TestServerOptions(dir_.File("map.db"), /*start_worker=*/false));
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<MockVehicle>(server_->address());
    Passage passage = ShortScenario().MakePassage(0);
    passage.vehicle_id = "veh-XX";
    PassageToProto(passage, &valid_);
  }

  grpc::Status UploadRaw(const std::string& bytes) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    grpc::ByteBuffer request = ToBuffer(bytes), response;
    return grpc::internal::BlockingUnaryCall<grpc::ByteBuffer, grpc::ByteBuffer>(
        client_->channel().get(), grpc::internal::RpcMethod(kUploadPath.c_str(), grpc::internal::RpcMethod::NORMAL_RPC),
        &ctx, request, &response);
  }

  // Each element of `chunks` is sent as one raw message of the stream.
  grpc::Status UploadChunksRaw(const std::vector<std::string>& chunks) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    pb::UploadPassageResponse response;
    std::unique_ptr<grpc::ClientWriter<grpc::ByteBuffer>> writer(grpc::internal::ClientWriterFactory<grpc::ByteBuffer>::Create(
        client_->channel().get(), grpc::internal::RpcMethod(kChunkedPath.c_str(), grpc::internal::RpcMethod::CLIENT_STREAMING),
        &ctx, &response));
    for (const std::string& chunk : chunks) {
      if (!writer->Write(ToBuffer(chunk))) break;
    }
    writer->WritesDone();
    return writer->Finish();
  }

  static std::string Chunk(const std::string& data) {
    pb::UploadPassageChunk chunk;
    chunk.set_data(data);
    return chunk.SerializeAsString();
  }

  std::string ValidRequest() const {
    pb::UploadPassageRequest request;
    *request.mutable_passage() = valid_;
    return request.SerializeAsString();
  }

  void ExpectInvalid(const grpc::Status& status, const std::string& message_start) {
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
    EXPECT_EQ(status.error_message().substr(0, message_start.size()), message_start) << status.error_message();
    auto listed = server_->store()->ListPassages(PassageQuery{});
    ASSERT_TRUE(listed.ok());
    EXPECT_TRUE(listed->empty()) << "a malformed upload was stored";
  }

  TempDir dir_;
  std::unique_ptr<MapServer> server_;
  std::unique_ptr<MockVehicle> client_;
  pb::Passage valid_;
};

TEST_F(MalformedRequest, WellFormedRawUploadsAreAccepted) {
  // The raw client itself works: the same bytes, unchanged, are acknowledged on both RPCs.
  EXPECT_TRUE(UploadRaw(ValidRequest()).ok());
  valid_.set_passage_id(valid_.passage_id() + "-chunked");
  valid_.set_start_time_unix_ms(valid_.start_time_unix_ms() + 1);  // another drive: the same one is taken once
  const std::string passage = valid_.SerializeAsString();
  EXPECT_TRUE(UploadChunksRaw({Chunk(passage.substr(0, 1000)), Chunk(passage.substr(1000))}).ok());
  auto listed = server_->store()->ListPassages(PassageQuery{});
  ASSERT_TRUE(listed.ok());
  EXPECT_EQ(listed->size(), 2u);
}

TEST_F(MalformedRequest, GarbageUploadGetsInvalidArgument) {
  ExpectInvalid(UploadRaw(std::string("\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff\xff", 11)), "request: malformed field tag");
  ExpectInvalid(UploadRaw(std::string("\x0a\x7f\x01\x02", 4)), "passage: length 127 runs past the end");
}

TEST_F(MalformedRequest, InvalidUtf8InAStringFieldIsNamed) {
  ExpectInvalid(UploadRaw(Patch(ValidRequest(), "veh-XX", "veh-\xc3\x28")), "passage.vehicle_id: not valid UTF-8");
  // A surrogate code point (U+D800, encoded in three bytes) is not valid UTF-8 either.
  ExpectInvalid(UploadRaw(Patch(ValidRequest(), "veh-XX", "v\xed\xa0\x80-X")), "passage.vehicle_id: not valid UTF-8");
}

TEST_F(MalformedRequest, TruncatedUploadNamesTheFieldItStopsIn) {
  const std::string request = ValidRequest();
  // Cut in the middle of the passage: the outer length runs past the end.
  ExpectInvalid(UploadRaw(request.substr(0, request.size() / 2)), "passage: length");
}

TEST_F(MalformedRequest, GarbageChunkGetsInvalidArgumentNamingTheChunk) {
  const std::string passage = valid_.SerializeAsString();
  ExpectInvalid(UploadChunksRaw({Chunk(passage.substr(0, 100)), std::string("\x0a\xff\xff\xff\xff\x0f", 6)}),
                "chunk[1].data: length");
}

TEST_F(MalformedRequest, ChunksFormingAMalformedPassageAreNamed) {
  const std::string passage = Patch(valid_.SerializeAsString(), "veh-XX", "veh-\xc3\x28");
  ExpectInvalid(UploadChunksRaw({Chunk(passage.substr(0, 500)), Chunk(passage.substr(500))}),
                "passage.vehicle_id: not valid UTF-8");
  ExpectInvalid(UploadChunksRaw({Chunk(valid_.SerializeAsString().substr(0, 700))}), "passage.");
  ExpectInvalid(UploadChunksRaw({Chunk("")}), "passage: no chunk carried any bytes");
}

TEST(WireParse, Utf8ValidatorFollowsTheStandard) {
  EXPECT_TRUE(IsValidUtf8(""));
  EXPECT_TRUE(IsValidUtf8("veh-42"));
  EXPECT_TRUE(IsValidUtf8("\xc3\xa9t\xc3\xa9"));          // été
  EXPECT_TRUE(IsValidUtf8("\xf0\x9f\x9a\x97"));           // U+1F697
  EXPECT_FALSE(IsValidUtf8("\xc3"));                      // truncated
  EXPECT_FALSE(IsValidUtf8("\xc3\x28"));                  // bad continuation
  EXPECT_FALSE(IsValidUtf8("\xc0\xaf"));                  // overlong '/'
  EXPECT_FALSE(IsValidUtf8("\xed\xa0\x80"));              // surrogate
  EXPECT_FALSE(IsValidUtf8("\xf4\x90\x80\x80"));          // above U+10FFFF
  EXPECT_FALSE(IsValidUtf8("\xff"));
}

}  // namespace
}  // namespace crowdmap
