// MapClient against a real in-process mapd: passages above the unary message limit go through
// the chunked upload on their own.
#include "client/api/map_client.h"

#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// A valid passage of more than 4 MiB: a short scenario passage followed by a long stop.
pb::Passage LargePassage() {
  pb::Passage wire;
  PassageToProto(ShortScenario().MakePassage(0), &wire);
  const pb::OdometrySample last = wire.odometry(wire.odometry_size() - 1);
  for (int i = 1; i <= 240000; ++i) {  // about 20 bytes each
    pb::OdometrySample* o = wire.add_odometry();
    *o = last;
    o->set_t_s(last.t_s() + 0.001 * i);
    o->set_speed_mps(0.0);
  }
  return wire;
}

std::unique_ptr<MapClient> Client(const std::string& address, size_t unary_limit) {
  MapClientOptions options;
  options.server = address;
  options.max_attempts = 1;
  options.unary_upload_limit_bytes = unary_limit;
  auto client = MapClient::Create(options);
  EXPECT_TRUE(client.ok()) << client.status();
  return client.ok() ? std::move(*client) : nullptr;
}

TEST(MapClient, UploadsAPassageAboveTheServersMessageLimitInChunks) {
  TempDir dir;
  auto server = StartTestServer(TestServerOptions(dir.File("map.db"), /*start_worker=*/false));
  ASSERT_NE(server, nullptr);
  const pb::Passage big = LargePassage();
  ASSERT_GT(big.ByteSizeLong(), 4u << 20);

  // Sent whole, the server's 4 MiB receive limit refuses it...
  auto whole = Client(server->address(), SIZE_MAX);
  ASSERT_NE(whole, nullptr);
  EXPECT_EQ(whole->Upload(big).status().code(), absl::StatusCode::kResourceExhausted);

  // ...while the default client splits it and gets it queued, once.
  auto client = Client(server->address(), MapClientOptions().unary_upload_limit_bytes);
  ASSERT_NE(client, nullptr);
  auto response = client->Upload(big);
  ASSERT_TRUE(response.ok()) << response.status();
  EXPECT_FALSE(response->duplicate());
  EXPECT_EQ(response->status().state(), pb::PASSAGE_STATE_QUEUED);
  EXPECT_EQ(response->status().size_bytes(), static_cast<int64_t>(big.ByteSizeLong()));
  auto again = client->Upload(big);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->duplicate());
  EXPECT_EQ(again->status().id(), response->status().id());
}

TEST(MapClient, RejectsAChunkSizeAboveTheMessageLimit) {
  MapClientOptions options;
  options.max_message_mb = 4;
  options.upload_chunk_bytes = 4u << 20;
  EXPECT_EQ(MapClient::Create(options).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap
