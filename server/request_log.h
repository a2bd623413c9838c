#ifndef CROWDMAP_SERVER_REQUEST_LOG_H_
#define CROWDMAP_SERVER_REQUEST_LOG_H_

#include <chrono>
#include <string>

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include "absl/status/status.h"
#include "server/grpc_status.h"

namespace crowdmap {

// Times one RPC and logs one key=value line when it ends; Done() converts the status.
class RequestLog {
 public:
  RequestLog(const char* rpc, const grpc::ServerContextBase* ctx)
      : rpc_(rpc), peer_(ctx->peer()), start_(std::chrono::steady_clock::now()) {}

  // Extra key=value pairs, e.g. "passage=p1 vehicle=v1".
  void Add(const std::string& fields) {
    fields_ += ' ';
    fields_ += fields;
  }

  grpc::Status Done(const absl::Status& status) {
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start_).count();
    const auto level = status.ok() || status.code() == absl::StatusCode::kNotFound ? spdlog::level::info
                                                                                   : spdlog::level::warn;
    if (status.ok()) {
      spdlog::log(level, "rpc={} peer={} code=OK ms={:.2f}{}", rpc_, peer_, ms, fields_);
    } else {
      spdlog::log(level, "rpc={} peer={} code={} ms={:.2f}{} error=\"{}\"", rpc_, peer_,
                  absl::StatusCodeToString(status.code()), ms, fields_, std::string(status.message()));
    }
    return ToGrpcStatus(status);
  }

 private:
  const char* rpc_;
  std::string peer_;
  std::chrono::steady_clock::time_point start_;
  std::string fields_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_REQUEST_LOG_H_
