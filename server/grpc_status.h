#ifndef CROWDMAP_SERVER_GRPC_STATUS_H_
#define CROWDMAP_SERVER_GRPC_STATUS_H_

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace crowdmap {

// The one conversion from module errors to gRPC status; codes map one to one.
grpc::Status ToGrpcStatus(const absl::Status& status);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_GRPC_STATUS_H_
