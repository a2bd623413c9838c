// MapService handlers for uploads and the passage queue.
#include <grpcpp/support/method_handler.h>
#include <google/protobuf/descriptor.h>
#include <spdlog/spdlog.h>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "core/model/passage.h"
#include "server/map_service.h"
#include "server/request_log.h"
#include "server/wire_parse.h"

namespace crowdmap {
namespace {

// A passage's idempotency key as a request names it: checked as an upload's (ValidateId).
absl::Status ValidateKey(const std::string& vehicle_id, const std::string& passage_id) {
  if (absl::Status s = ValidateId("vehicle_id", vehicle_id); !s.ok()) return s;
  return ValidateId("passage_id", passage_id);
}

constexpr char kPageTokenPrefix[] = "after";
constexpr int kDefaultPassagePage = 100;
constexpr int kMaxPassagePage = 1000;

// 64-bit FNV-1a: stable across processes and builds, so tokens survive a server restart.
uint64_t Fingerprint(std::string_view text) {
  uint64_t h = 1469598103934665603ull;
  for (unsigned char c : text) {
    h ^= c;
    h *= 1099511628211ull;
  }
  return h;
}

// A full queue or disk (RESOURCE_EXHAUSTED): clients' retry policies wait this long before the
// next attempt (gRPC reads grpc-retry-pushback-ms) instead of their own short backoff.
constexpr char kUploadPushbackMs[] = "1000";

// A refusal with its own retry time (a quota) says so (AddRetryTrailers); other refusals of an
// upload with RESOURCE_EXHAUSTED (queue or disk full) get kUploadPushbackMs.
void AddPushback(grpc::ServerContextBase* ctx, const absl::Status& s) {
  if (s.code() != absl::StatusCode::kResourceExhausted) return;
  if (RetryAfter(s).count() > 0) {
    AddRetryTrailers(s, ctx);
  } else {
    ctx->AddTrailingMetadata("grpc-retry-pushback-ms", kUploadPushbackMs);
  }
}

std::string PassageListQuery(const pb::ListPassagesRequest& request) {
  return absl::StrCat("passages|", request.state(), "|", request.vehicle_id());
}

constexpr char kMalformedToken[] = "page_token: malformed; pass the next_page_token of a previous response";

// "after:<key>:<fingerprint of the query>", `key` free of ':'.
std::string MakeToken(const std::string& key, std::string_view query) {
  return absl::StrCat(kPageTokenPrefix, ":", key, ":", absl::Hex(Fingerprint(query), absl::kZeroPad16));
}

// The key of a token MakeToken made for `query`.
absl::StatusOr<std::string> ParseToken(const std::string& token, std::string_view query) {
  const std::vector<absl::string_view> parts = absl::StrSplit(token, ':');
  uint64_t fingerprint = 0;
  if (parts.size() != 3 || parts[0] != kPageTokenPrefix || parts[2].size() != 16 ||
      !absl::SimpleHexAtoi(parts[2], &fingerprint)) {
    return absl::InvalidArgumentError(kMalformedToken);
  }
  if (fingerprint != Fingerprint(query)) {
    return absl::InvalidArgumentError(
        "page_token: issued for a request with other filters; repeat them unchanged, or start again without a token");
  }
  return std::string(parts[1]);
}

}  // namespace

std::string MakePageToken(int64_t last_id, std::string_view query) { return MakeToken(absl::StrCat(last_id), query); }

absl::StatusOr<int64_t> ParsePageToken(const std::string& token, std::string_view query) {
  if (token.empty()) return 0;
  absl::StatusOr<std::string> key = ParseToken(token, query);
  if (!key.ok()) return key.status();
  int64_t id = 0;
  if (!absl::SimpleAtoi(*key, &id) || id < 0) {
    return absl::InvalidArgumentError(kMalformedToken);
  }
  return id;
}

std::string MakeKeyPageToken(std::string_view last_key, std::string_view query) {
  return MakeToken(absl::BytesToHexString(absl::string_view(last_key.data(), last_key.size())), query);
}

absl::StatusOr<std::string> ParseKeyPageToken(const std::string& token, std::string_view query) {
  if (token.empty()) return std::string();
  absl::StatusOr<std::string> key = ParseToken(token, query);
  if (!key.ok()) return key.status();
  if (key->size() % 2 != 0 || !std::all_of(key->begin(), key->end(), absl::ascii_isxdigit)) {
    return absl::InvalidArgumentError(kMalformedToken);
  }
  return absl::HexStringToBytes(*key);
}

absl::Status MapService::AcceptUpload(const Principal& who, const pb::Passage& wire, size_t wire_bytes,
                                      std::string payload, pb::UploadPassageResponse* response) {
  if (!context_->accepting_uploads) return absl::UnavailableError("server is shutting down; retry on another replica or later");
  if (auto s = CheckPassageSize(wire_bytes, context_->limits); !s.ok()) return s;
  // The idempotency key (vehicle_id, passage_id) is the authenticated vehicle's own: nobody else
  // can take it first.
  if (auto s = who.MayActFor(wire.vehicle_id()); !s.ok()) return s;
  if (auto s = context_->quotas->Admit(wire.vehicle_id(), wire_bytes); !s.ok()) return s;
  absl::StatusOr<Passage> passage = PassageFromProto(wire);
  if (!passage.ok()) return passage.status();
  NewPassage upload{passage->vehicle_id, passage->passage_id, std::move(payload), NowUnixMs(),
                    PassageContentDigest(*passage)};
  absl::StatusOr<EnqueueOutcome> outcome = context_->committer->Commit(std::move(upload));
  if (!outcome.ok()) return outcome.status();
  if (!outcome->duplicate && context_->worker != nullptr) context_->worker->Wake();
  if (context_->metrics != nullptr) context_->metrics->ObserveUpload(wire_bytes, outcome->duplicate);
  StoredPassageToProto(outcome->record, response->mutable_status());
  response->set_duplicate(outcome->duplicate);
  return absl::OkStatus();
}

MapService::MapService(MapServiceContext* context) : context_(context) {
  SetMessageAllocatorFor_GetTile(&tile_allocator_);
  SetMessageAllocatorFor_QueryRegion(&region_allocator_);
  // The chunked upload gets a handler that receives the request messages as raw bytes (the unary
  // one is a raw callback method). gRPC serves a method given its own handler as a stream
  // (MarkMethodStreamed); the clients see the same RPC.
  const google::protobuf::ServiceDescriptor* service =
      google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(pb::MapService::service_full_name());
  using Response = pb::UploadPassageResponse;
  MarkMethodStreamed(service->FindMethodByName("UploadPassageChunked")->index(),
                     new grpc::internal::BidiStreamingHandler<MapService, grpc::ByteBuffer, Response>(
                         [](MapService* self, grpc::ServerContext* ctx,
                            grpc::ServerReaderWriter<Response, grpc::ByteBuffer>* stream) {
                           Response response;
                           grpc::Status status = self->UploadPassageChunkedRaw(ctx, stream, &response);
                           if (status.ok()) stream->Write(response);
                           return status;
                         },
                         this));
}

grpc::ServerUnaryReactor* MapService::UploadPassage(grpc::CallbackServerContext* ctx, const grpc::ByteBuffer* request,
                                                   grpc::ByteBuffer* response) {
  pb::UploadPassageResponse reply;
  grpc::Status status = UploadPassageRaw(ctx, request, &reply);
  if (status.ok()) {
    bool own = false;
    status = grpc::GenericSerialize<grpc::ProtoBufferWriter, pb::UploadPassageResponse>(reply, response, &own);
  }
  grpc::ServerUnaryReactor* reactor = ctx->DefaultReactor();
  reactor->Finish(status);
  return reactor;
}

grpc::Status MapService::UploadPassageRaw(grpc::ServerContextBase* ctx, const grpc::ByteBuffer* raw,
                                          pb::UploadPassageResponse* response) {
  RequestLog log("UploadPassage", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kUpload, &log);
  if (!who.ok()) return log.Done(who.status());
  InflightBytes::Lease held(context_->inflight);
  absl::Status s = held.GrowTo(raw->Length());
  if (!s.ok()) {
    AddPushback(ctx, s);
    return log.Done(s);
  }
  pb::UploadPassageRequest request;
  if (s = ParseWireMessage(FlattenByteBuffer(*raw), "", &request); !s.ok()) return log.Done(s);
  const pb::Passage& wire = request.passage();
  // Checked before the log line or a message can echo them.
  if (s = ValidateKey(wire.vehicle_id(), wire.passage_id()); !s.ok()) return log.Done(s);
  log.Add(absl::StrCat("passage=", wire.passage_id(), " vehicle=", wire.vehicle_id()));
  s = AcceptUpload(*who, wire, wire.ByteSizeLong(), wire.SerializeAsString(), response);
  if (s.ok()) {
    log.Add(absl::StrCat("id=", response->status().id(), " duplicate=", response->duplicate() ? "true" : "false"));
  }
  AddPushback(ctx, s);
  return log.Done(s);
}

grpc::Status MapService::UploadPassageChunkedRaw(grpc::ServerContext* ctx,
                                                 grpc::ServerReaderWriterInterface<pb::UploadPassageResponse, grpc::ByteBuffer>* reader,
                                                 pb::UploadPassageResponse* response) {
  RequestLog log("UploadPassageChunked", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kUpload, &log);
  if (!who.ok()) return log.Done(who.status());
  absl::StatusOr<std::unique_ptr<StreamLimiter::Lease>> stream = context_->streams->OpenUpload(ctx, who->stream_identity());
  if (!stream.ok()) {
    AddRetryTrailers(stream.status(), ctx);
    return log.Done(stream.status());
  }
  InflightBytes::Lease held(context_->inflight);
  std::string bytes;
  grpc::ByteBuffer raw;
  pb::UploadPassageChunk chunk;
  int chunks = 0;
  while (reader->Read(&raw)) {
    if (absl::Status s = ParseWireMessage(FlattenByteBuffer(raw), absl::StrCat("chunk[", chunks, "]"), &chunk);
        !s.ok()) {
      return log.Done(s);
    }
    (*stream)->Touch(chunk.data().size());
    ++chunks;
    const size_t total = bytes.size() + chunk.data().size();
    if (absl::Status s = CheckPassageSize(total, context_->limits); !s.ok()) return log.Done(s);
    if (absl::Status s = held.GrowTo(total); !s.ok()) {
      AddRetryTrailers(s, ctx);
      return log.Done(s);
    }
    bytes += chunk.data();
  }
  log.Add(absl::StrCat("chunks=", chunks, " bytes=", bytes.size()));
  if ((*stream)->timed_out()) {
    return log.Done(absl::DeadlineExceededError(absl::StrCat(
        "upload: no bytes within --upload-idle-timeout-s, or fewer than ", StreamLimiter::kMinUploadBytesPerS,
        " bytes/s on average once open that long; call cancelled")));
  }
  if (bytes.empty()) return log.Done(absl::InvalidArgumentError("passage: no chunk carried any bytes"));
  pb::Passage wire;
  if (absl::Status s = ParseWireMessage(bytes, "passage", &wire); !s.ok()) {
    return log.Done(absl::InvalidArgumentError(
        absl::StrCat(s.message(), " (the chunks, joined in order, must form one serialized Passage)")));
  }
  if (absl::Status s = ValidateKey(wire.vehicle_id(), wire.passage_id()); !s.ok()) return log.Done(s);
  log.Add(absl::StrCat("passage=", wire.passage_id(), " vehicle=", wire.vehicle_id()));
  const size_t size = bytes.size();
  absl::Status s = AcceptUpload(*who, wire, size, std::move(bytes), response);
  if (s.ok()) {
    log.Add(absl::StrCat("id=", response->status().id(), " duplicate=", response->duplicate() ? "true" : "false"));
  }
  AddPushback(ctx, s);
  return log.Done(s);
}

absl::StatusOr<StoredPassage> MapService::FindRecord(int64_t id, const std::string& vehicle_id,
                                                     const std::string& passage_id, const Principal* own_reader,
                                                     RequestLog* log) {
  const bool keyed = !vehicle_id.empty() || !passage_id.empty();
  if (keyed) {
    if (absl::Status s = ValidateKey(vehicle_id, passage_id); !s.ok()) return s;
  }
  if (id != 0) {
    log->Add(absl::StrCat("id=", id));
    absl::StatusOr<StoredPassage> record = context_->store->GetPassage(id);
    // Another vehicle's passage answers as a missing one, before anything else is told of it.
    if (record.ok() && own_reader != nullptr && !own_reader->MayActFor(record->vehicle_id).ok()) {
      return PassageIdNotFoundError(id);
    }
    // Both given: they must name the same passage (an exclusion must not take the one the caller
    // did not mean).
    if (record.ok() && keyed && (record->vehicle_id != vehicle_id || record->passage_id != passage_id)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "id: passage ", id, " is not vehicle_id '", vehicle_id, "' passage_id '", passage_id,
          "'; give the id, or vehicle_id and passage_id, or both of one passage"));
    }
    return record;
  }
  if (keyed) {
    log->Add(absl::StrCat("passage=", passage_id, " vehicle=", vehicle_id));
    return context_->store->FindPassage(vehicle_id, passage_id);
  }
  return absl::InvalidArgumentError("id: give the passage id, or vehicle_id and passage_id");
}

grpc::Status MapService::GetPassage(grpc::ServerContext* ctx, const pb::GetPassageRequest* request,
                                    pb::PassageStatus* response) {
  RequestLog log("GetPassage", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadPassages, &log);
  if (!who.ok()) return log.Done(who.status());
  // A vehicle reads its own passages. By ids it names its vehicle, checked first; by queue id
  // another vehicle's passage answers as a missing one does, so that walking the ids tells
  // neither which vehicles there are nor how many drives each uploaded.
  const bool own_only = !who->MayReadAllPassages();
  if (own_only && request->id() == 0) {
    if (absl::Status s = who->MayActFor(request->vehicle_id()); !s.ok()) return log.Done(s);
  }
  absl::StatusOr<StoredPassage> record = FindRecord(request->id(), request->vehicle_id(), request->passage_id(),
                                                    own_only ? &*who : nullptr, &log);
  if (!record.ok()) return log.Done(record.status());
  StoredPassageToProto(*record, response);
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::ExcludePassage(grpc::ServerContext* ctx, const pb::ExcludePassageRequest* request,
                                        pb::ExcludePassageResponse* response) {
  RequestLog log("ExcludePassage", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kAdministrate, &log); !who.ok()) return log.Done(who.status());
  absl::StatusOr<StoredPassage> record = FindRecord(request->id(), request->vehicle_id(), request->passage_id(), nullptr, &log);
  if (!record.ok()) return log.Done(record.status());
  if (record->state != PassageState::kApplied) {
    return log.Done(absl::FailedPreconditionError(absl::StrCat(
        "passage ", record->id, " is ", PassageStateName(record->state), ": only an applied passage can be excluded")));
  }
  absl::StatusOr<PassageUpdateSummary> summary = context_->worker->Exclude(*record);
  if (summary.status().code() == absl::StatusCode::kNotFound) {
    return log.Done(absl::FailedPreconditionError(absl::StrCat(
        "passage ", record->id, ": its factors were folded into the map's base (it is older than the last ",
        "--retain-passages applied passages) and can no longer be taken out")));
  }
  if (!summary.ok()) return log.Done(summary.status());
  absl::StatusOr<StoredPassage> now = context_->store->GetPassage(record->id);
  if (!now.ok()) return log.Done(now.status());
  StoredPassageToProto(*now, response->mutable_status());
  response->set_map_version(summary->map_version);
  response->set_landmarks_updated(summary->landmarks_updated);
  response->set_landmarks_removed(summary->landmarks_removed);
  response->set_landmarks_conditioned(summary->landmarks_conditioned);
  log.Add(absl::StrCat("map_version=", summary->map_version, " removed=", summary->landmarks_removed));
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::ResolvePassage(grpc::ServerContext* ctx, const pb::ResolvePassageRequest* request,
                                        pb::PassageStatus* response) {
  RequestLog log("ResolvePassage", ctx);
  if (auto who = CheckAccess(context_->auth, *ctx, Permission::kAdministrate, &log); !who.ok()) return log.Done(who.status());
  std::vector<PassageState> from = {PassageState::kFailed, PassageState::kQuarantined};
  PassageState to;
  bool released = false;
  switch (request->action()) {
    case pb::ResolvePassageRequest::REQUEUE:
      to = PassageState::kQueued;
      break;
    case pb::ResolvePassageRequest::RELEASE:
      to = PassageState::kQueued;
      released = true;
      from = {PassageState::kQuarantined};  // a failed passage failed for other reasons
      break;
    case pb::ResolvePassageRequest::DISCARD:
      to = PassageState::kDiscarded;
      break;
    default:
      return log.Done(absl::InvalidArgumentError("action: must be REQUEUE, RELEASE or DISCARD"));
  }
  absl::StatusOr<StoredPassage> record = FindRecord(request->id(), request->vehicle_id(), request->passage_id(), nullptr, &log);
  if (!record.ok()) return log.Done(record.status());
  absl::StatusOr<StoredPassage> moved = context_->store->MovePassage(record->id, from, to, released);
  if (!moved.ok()) return log.Done(moved.status());
  if (to == PassageState::kQueued && context_->worker != nullptr) context_->worker->Wake();
  StoredPassageToProto(*moved, response);
  log.Add(absl::StrCat("state=", PassageStateName(moved->state)));
  return log.Done(absl::OkStatus());
}

grpc::Status MapService::ListPassages(grpc::ServerContext* ctx, const pb::ListPassagesRequest* request,
                                      pb::ListPassagesResponse* response) {
  RequestLog log("ListPassages", ctx);
  absl::StatusOr<Principal> who = CheckAccess(context_->auth, *ctx, Permission::kReadPassages, &log);
  if (!who.ok()) return log.Done(who.status());
  if (!request->vehicle_id().empty()) {
    if (absl::Status s = ValidateId("vehicle_id", request->vehicle_id()); !s.ok()) return log.Done(s);
  }
  if (!who->MayReadAllPassages() && request->vehicle_id() != who->name) {
    return log.Done(absl::PermissionDeniedError(
        absl::StrCat("vehicle_id: a vehicle lists its own passages only; set it to '", who->name, "'")));
  }
  if (request->page_size() < 0 || request->page_size() > kMaxPassagePage) {
    return log.Done(absl::InvalidArgumentError(absl::StrCat("page_size: must lie in [0, ", kMaxPassagePage, "]")));
  }
  const std::string list_query = PassageListQuery(*request);
  absl::StatusOr<int64_t> after = ParsePageToken(request->page_token(), list_query);
  if (!after.ok()) return log.Done(after.status());
  absl::StatusOr<std::optional<PassageState>> state = PassageStateFromProto(request->state());
  if (!state.ok()) return log.Done(state.status());
  PassageQuery query;
  query.after_id = *after;
  query.limit = (request->page_size() == 0 ? kDefaultPassagePage : request->page_size()) + 1;
  query.state = *state;
  query.vehicle_id = request->vehicle_id();
  absl::StatusOr<std::vector<StoredPassage>> records = context_->store->ListPassages(query);
  if (!records.ok()) return log.Done(records.status());
  const bool more = static_cast<int>(records->size()) == query.limit;
  if (more) records->pop_back();
  for (const StoredPassage& r : *records) StoredPassageToProto(r, response->add_passages());
  if (more) response->set_next_page_token(MakePageToken(records->back().id, list_query));
  log.Add(absl::StrCat("returned=", records->size()));
  return log.Done(absl::OkStatus());
}

}  // namespace crowdmap
