// MapClient against a real in-process mapd: passages above the unary message limit go through
// the chunked upload on their own.
#include "client/api/map_client.h"

#include <atomic>

#include <grpcpp/server_builder.h>
#include <nlohmann/json.hpp>

#include "server/testing/temp_dir.h"
#include "server/wire_convert.h"
#include "tests/support/test_server.h"

namespace crowdmap {
namespace {

// A valid passage of more than 4 MiB: a short scenario passage followed by a long stop.
// A passage padded with standing-still odometry to about 20 bytes times `extra_samples` more.
pb::Passage LargePassage(int extra_samples = 240000) {
  pb::Passage wire;
  PassageToProto(ShortScenario().MakePassage(0), &wire);
  const pb::OdometrySample last = wire.odometry(wire.odometry_size() - 1);
  for (int i = 1; i <= extra_samples; ++i) {
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

// Answers the first `failures` uploads with `code` (and a pushback when `pushback_ms` is set),
// then acknowledges.
class FlakyUploads final : public pb::MapService::Service {
 public:
  FlakyUploads(int failures, grpc::StatusCode code, std::string pushback_ms = "")
      : failures_(failures), code_(code), pushback_ms_(std::move(pushback_ms)) {}

  grpc::Status UploadPassage(grpc::ServerContext* ctx, const pb::UploadPassageRequest*,
                             pb::UploadPassageResponse* response) override {
    if (calls_.fetch_add(1) < failures_) {
      if (!pushback_ms_.empty()) ctx->AddTrailingMetadata("grpc-retry-pushback-ms", pushback_ms_);
      return grpc::Status(code_, "try again");
    }
    response->mutable_status()->set_id(7);
    return grpc::Status::OK;
  }
  grpc::Status UploadPassageChunked(grpc::ServerContext* ctx, grpc::ServerReader<pb::UploadPassageChunk>* reader,
                                    pb::UploadPassageResponse* response) override {
    pb::UploadPassageChunk chunk;
    while (reader->Read(&chunk)) {
    }
    return UploadPassage(ctx, nullptr, response);
  }
  int calls() const { return calls_.load(); }

 private:
  const int failures_;
  const grpc::StatusCode code_;
  const std::string pushback_ms_;
  std::atomic<int> calls_{0};
};

struct FakeServer {
  explicit FakeServer(grpc::Service* service) {
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(service);
    server = builder.BuildAndStart();
  }
  ~FakeServer() { server->Shutdown(std::chrono::system_clock::now()); }
  std::string address() const { return "127.0.0.1:" + std::to_string(port); }
  int port = 0;
  std::unique_ptr<grpc::Server> server;
};

std::unique_ptr<MapClient> RetryingClient(const std::string& address, int max_attempts, bool chunked = false) {
  MapClientOptions options;
  if (chunked) options.unary_upload_limit_bytes = 0;
  options.server = address;
  options.max_attempts = max_attempts;
  options.initial_backoff = std::chrono::milliseconds(20);
  options.max_backoff = std::chrono::milliseconds(40);
  auto client = MapClient::Create(options);
  EXPECT_TRUE(client.ok()) << client.status();
  return client.ok() ? std::move(*client) : nullptr;
}

pb::Passage SmallPassage() {
  pb::Passage wire;
  PassageToProto(ShortScenario().MakePassage(0), &wire);
  return wire;
}

TEST(MapClientRetries, GrpcRetriesATransientUploadFailureUpToMaxAttempts) {
  FlakyUploads service(2, grpc::StatusCode::UNAVAILABLE);
  FakeServer server(&service);
  auto client = RetryingClient(server.address(), 3);
  auto r = client->Upload(SmallPassage());
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->status().id(), 7);
  EXPECT_EQ(service.calls(), 3);

  FlakyUploads always(100, grpc::StatusCode::RESOURCE_EXHAUSTED);
  FakeServer full(&always);
  auto gives_up = RetryingClient(full.address(), 4)->Upload(SmallPassage());
  EXPECT_EQ(gives_up.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(always.calls(), 4);
}

// gRPC retries a call only while what it sent fits its per-call retry buffer (256 KiB by default):
// a unary upload of 1 MiB was tried once. The client's buffer holds a whole unary message.
TEST(MapClientRetries, AUnaryUploadAboveGrpcsDefaultRetryBufferIsRetriedToo) {
  const pb::Passage passage = LargePassage(50000);
  ASSERT_GT(passage.ByteSizeLong(), 512u << 10);
  ASSERT_LT(passage.ByteSizeLong(), MapClientOptions().unary_upload_limit_bytes);
  FlakyUploads service(2, grpc::StatusCode::UNAVAILABLE);
  FakeServer server(&service);
  auto r = RetryingClient(server.address(), 3)->Upload(passage);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(service.calls(), 3);
}

TEST(MapClientRetries, NoRetryOfPermanentErrorsOrWithOneAttempt) {
  FlakyUploads invalid(1, grpc::StatusCode::INVALID_ARGUMENT);
  FakeServer server(&invalid);
  EXPECT_EQ(RetryingClient(server.address(), 5)->Upload(SmallPassage()).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(invalid.calls(), 1);

  FlakyUploads unavailable(1, grpc::StatusCode::UNAVAILABLE);
  FakeServer once(&unavailable);
  EXPECT_EQ(RetryingClient(once.address(), 1)->Upload(SmallPassage()).status().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(unavailable.calls(), 1);
}

TEST(MapClientRetries, TheServersPushbackSetsThePauseAndANegativeOneStopsRetrying) {
  FlakyUploads pushback(1, grpc::StatusCode::RESOURCE_EXHAUSTED, "400");
  FakeServer server(&pushback);
  auto client = RetryingClient(server.address(), 3);
  const auto start = std::chrono::steady_clock::now();
  ASSERT_TRUE(client->Upload(SmallPassage()).ok());
  const auto waited = std::chrono::steady_clock::now() - start;
  EXPECT_EQ(pushback.calls(), 2);
  // Without the pushback the pause is under the 20 ms backoff.
  EXPECT_GE(waited, std::chrono::milliseconds(400));

  FlakyUploads refuse(1, grpc::StatusCode::RESOURCE_EXHAUSTED, "-1");
  FakeServer refusing(&refuse);
  EXPECT_EQ(RetryingClient(refusing.address(), 3)->Upload(SmallPassage()).status().code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(refuse.calls(), 1);
}

TEST(MapClientRetries, ChunkedUploadsFollowTheSamePolicy) {
  FlakyUploads flaky(2, grpc::StatusCode::UNAVAILABLE);
  FakeServer server(&flaky);
  ASSERT_TRUE(RetryingClient(server.address(), 3, /*chunked=*/true)->Upload(SmallPassage()).ok());
  EXPECT_EQ(flaky.calls(), 3);

  FlakyUploads pushback(1, grpc::StatusCode::RESOURCE_EXHAUSTED, "400");
  FakeServer pushing(&pushback);
  const auto start = std::chrono::steady_clock::now();
  ASSERT_TRUE(RetryingClient(pushing.address(), 3, /*chunked=*/true)->Upload(SmallPassage()).ok());
  EXPECT_GE(std::chrono::steady_clock::now() - start, std::chrono::milliseconds(400));
  EXPECT_EQ(pushback.calls(), 2);

  FlakyUploads refuse(1, grpc::StatusCode::RESOURCE_EXHAUSTED, "-1");
  FakeServer refusing(&refuse);
  EXPECT_FALSE(RetryingClient(refusing.address(), 3, /*chunked=*/true)->Upload(SmallPassage()).ok());
  EXPECT_EQ(refuse.calls(), 1);
}

// A server from before the packed layout: QueryRegion answers with a block per pair whatever
// layout is asked for.
class BlocksOnlyRegions final : public pb::MapService::Service {
 public:
  grpc::Status QueryRegion(grpc::ServerContext*, const pb::QueryRegionRequest* request,
                           pb::QueryRegionResponse* response) override {
    response->set_map_version(3);
    for (int id : {4, 9}) {
      pb::Landmark* l = response->add_landmarks();
      l->set_id(id);
      l->mutable_cov_en_m2()->set_ee(id);
      l->mutable_cov_en_m2()->set_nn(id + 1);
    }
    if (request->include_cross_covariance()) {
      pb::CrossCovariance* c = response->add_cross_covariances();
      c->set_first_id(4);
      c->set_second_id(9);
      c->mutable_cov_m2()->set_en(0.5);
      response->set_covariance_bound(pb::COVARIANCE_BOUND_MAY_BE_NARROWER);
    }
    return grpc::Status::OK;
  }
};

TEST(MapClient, ReadsTheCovarianceOfAServerWithoutThePackedLayout) {
  BlocksOnlyRegions service;
  FakeServer server(&service);
  auto client = Client(server.address(), MapClientOptions().unary_upload_limit_bytes);
  ASSERT_NE(client, nullptr);
  absl::StatusOr<RegionMap> region = client->QueryRegion(WorldBox(), /*include_cross=*/true);
  ASSERT_TRUE(region.ok()) << region.status();
  ASSERT_EQ(region->page_covariances.size(), 1u);
  Eigen::MatrixXd expected = Eigen::MatrixXd::Zero(4, 4);
  expected.diagonal() << 4, 5, 9, 10;
  expected(0, 3) = expected(3, 0) = 0.5;  // landmark 4's East with landmark 9's North
  EXPECT_EQ(region->page_covariances[0], expected);
  EXPECT_EQ(region->page_covariance_bounds, std::vector<pb::CovarianceBound>{pb::COVARIANCE_BOUND_MAY_BE_NARROWER});
}

TEST(MapClientRetries, ServiceConfigCarriesThePolicyAndOptionsAreChecked) {
  MapClientOptions options;
  options.max_attempts = 4;
  options.initial_backoff = std::chrono::milliseconds(50);
  options.max_backoff = std::chrono::milliseconds(2000);
  const nlohmann::json config = nlohmann::json::parse(RetryServiceConfig(options));
  const nlohmann::json& method = config["methodConfig"][0];
  EXPECT_EQ(method["name"][0]["method"], "UploadPassage") << config;
  EXPECT_EQ(method["name"][1]["method"], "GetTile") << config;      // the reads: the server caps those
  EXPECT_EQ(method["name"][2]["method"], "QueryRegion") << config;  // with covariances
  EXPECT_EQ(method["retryPolicy"]["maxAttempts"], 4) << config;
  EXPECT_EQ(method["retryPolicy"]["initialBackoff"], "0.050s") << config;
  EXPECT_EQ(method["retryPolicy"]["maxBackoff"], "2.000s") << config;
  EXPECT_EQ(method["retryPolicy"]["retryableStatusCodes"], nlohmann::json::array({"UNAVAILABLE", "RESOURCE_EXHAUSTED"}))
      << config;
  options.max_attempts = 1;
  EXPECT_EQ(RetryServiceConfig(options), "{}");
  options.max_attempts = 6;
  EXPECT_FALSE(options.Validate().ok()) << "gRPC caps a retry policy at 5 attempts";
}

}  // namespace
}  // namespace crowdmap
