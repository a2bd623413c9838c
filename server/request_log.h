#ifndef CROWDMAP_SERVER_REQUEST_LOG_H_
#define CROWDMAP_SERVER_REQUEST_LOG_H_

#include <chrono>
#include <string>
#include <string_view>

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include "absl/status/status.h"
#include "server/grpc_status.h"
#include "server/log_format.h"

namespace crowdmap {

// `text` with every byte a log line must not carry raw (control characters, the backslash, bytes
// outside printable ASCII) written as \xNN: a client-supplied value cannot start a line of its own.
inline std::string EscapeForLog(const std::string& text) {
  static constexpr char kHex[] = "0123456789abcdef";
  std::string out;
  out.reserve(text.size());
  for (unsigned char c : text) {
    if (c >= 0x20 && c < 0x7f && c != '\\') {
      out += static_cast<char>(c);
    } else {
      out += "\\x";
      out += kHex[c >> 4];
      out += kHex[c & 15];
    }
  }
  return out;
}

// The response metadata key of the request id. It travels in the trailing metadata: a server that
// sends initial metadata commits the call, and gRPC's retry policy would no longer retry it (gRFC A6).
inline constexpr char kRequestIdKey[] = "x-request-id";

// Times one RPC and logs one key=value line when it ends; Done() converts the status. Each RPC gets
// a request id, returned to the client as x-request-id (trailing metadata) and written in the line. Successful
// reads are logged at debug level (they come by the thousand per second), everything else at info,
// failures at warn. Every client-supplied value is escaped (EscapeForLog).
class RequestLog {
 public:
  RequestLog(const char* rpc, grpc::ServerContextBase* ctx)
      : rpc_(rpc), ctx_(ctx), id_(NewRequestId()), peer_(ctx->peer()), start_(std::chrono::steady_clock::now()),
        read_(IsRead(rpc)) {}

  const std::string& request_id() const { return id_; }

  // Extra key=value pairs, e.g. "passage=p1 vehicle=v1".
  void Add(const std::string& fields) {
    fields_ += ' ';
    fields_ += fields;
  }

  grpc::Status Done(const absl::Status& status) {
    ctx_->AddTrailingMetadata(kRequestIdKey, id_);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_).count();
    const bool quiet = status.ok() || status.code() == absl::StatusCode::kNotFound;
    const auto level = !quiet ? spdlog::level::warn : read_ ? spdlog::level::debug : spdlog::level::info;
    if (status.ok()) {
      spdlog::log(level, "rpc={} request_id={} peer={} code=OK ms={:.2f}{}", rpc_, id_, EscapeForLog(peer_), ms,
                  EscapeForLog(fields_));
    } else {
      spdlog::log(level, "rpc={} request_id={} peer={} code={} ms={:.2f}{} error=\"{}\"", rpc_, id_, EscapeForLog(peer_),
                  absl::StatusCodeToString(status.code()), ms, EscapeForLog(fields_),
                  EscapeForLog(std::string(status.message())));
    }
    return ToGrpcStatus(status);
  }

 private:
  static bool IsRead(std::string_view rpc) {
    for (std::string_view read : {"GetLandmark", "GetMapInfo", "GetPassage", "GetTile", "ListPassages",
                                  "LocalizePassage", "QueryRegion", "WatchRegion", "GetVehicle", "ListVehicles"}) {
      if (rpc == read) return true;
    }
    return false;
  }

  const char* rpc_;
  grpc::ServerContextBase* ctx_;
  std::string id_;
  std::string peer_;
  std::chrono::steady_clock::time_point start_;
  bool read_;
  std::string fields_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_REQUEST_LOG_H_
