#ifndef CROWDMAP_SERVER_GRPC_STATUS_H_
#define CROWDMAP_SERVER_GRPC_STATUS_H_

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace crowdmap {

// The one conversion between module errors and gRPC status, both ways (the server answers with
// ToGrpcStatus, clients read answers with FromGrpcStatus); codes and messages map one to one.
grpc::Status ToGrpcStatus(const absl::Status& status);
absl::Status FromGrpcStatus(const grpc::Status& status);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_GRPC_STATUS_H_
