#ifndef CROWDMAP_SERVER_WIRE_PARSE_H_
#define CROWDMAP_SERVER_WIRE_PARSE_H_

// Parsing of request bytes the handlers receive raw, so that a malformed request is answered
// INVALID_ARGUMENT naming the field, instead of gRPC's INTERNAL with an empty message.

#include <string_view>

#include <google/protobuf/message.h>
#include <grpcpp/support/byte_buffer.h>

#include "absl/status/status.h"

namespace crowdmap {

// Parses `bytes` into `message`. On failure, InvalidArgument naming the first problem found with
// its field path and index, e.g. "passage.gnss[3].lat_deg: truncated" or "passage.vehicle_id: not
// valid UTF-8"; `prefix` (may be empty) starts every path.
absl::Status ParseWireMessage(std::string_view bytes, std::string_view prefix, google::protobuf::Message* message);

// The bytes of a raw request, flattened.
std::string FlattenByteBuffer(const grpc::ByteBuffer& buffer);

// True when `text` is well-formed UTF-8 (no overlong forms, surrogates or code points above
// U+10FFFF): what protobuf demands of proto3 string fields.
bool IsValidUtf8(std::string_view text);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_WIRE_PARSE_H_
