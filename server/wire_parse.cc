#include "server/wire_parse.h"

#include <map>
#include <string>
#include <vector>

#include <google/protobuf/descriptor.h>
#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/wire_format_lite.h>

#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::internal::WireFormatLite;

// Deeper than any message of the API, and below protobuf's own recursion limit (100).
constexpr int kMaxDepth = 32;

std::string Join(std::string_view path, std::string_view name) {
  return path.empty() ? std::string(name) : absl::StrCat(std::string(path), ".", std::string(name));
}

// Walks the wire format of one message of type `type` and returns the first reason protobuf would
// refuse it, or "" when it finds none. Unknown fields, and known fields sent with another wire
// type (which protobuf keeps as unknown), are only checked to be well-formed.
std::string FindProblem(const Descriptor* type, std::string_view bytes, const std::string& path, int depth) {
  if (depth > kMaxDepth) return absl::StrCat(path.empty() ? "request" : path, ": nested too deeply");
  google::protobuf::io::CodedInputStream in(reinterpret_cast<const uint8_t*>(bytes.data()),
                                            static_cast<int>(bytes.size()));
  std::map<int, int> seen;  // occurrences of each field number, for the index in the path
  while (true) {
    const int start = in.CurrentPosition();
    const uint32_t tag = in.ReadTag();
    if (tag == 0) return start == static_cast<int>(bytes.size()) ? std::string()
                                                                : absl::StrCat(path.empty() ? "request" : path,
                                                                               ": malformed field tag at byte ", start);
    const int number = static_cast<int>(WireFormatLite::GetTagFieldNumber(tag));
    const WireFormatLite::WireType wire_type = WireFormatLite::GetTagWireType(tag);
    const FieldDescriptor* field = type != nullptr ? type->FindFieldByNumber(number) : nullptr;
    std::string name = field != nullptr ? Join(path, field->name()) : Join(path, absl::StrCat("<field ", number, ">"));
    if (field != nullptr && field->is_repeated()) absl::StrAppend(&name, "[", seen[number]++, "]");
    switch (wire_type) {
      case WireFormatLite::WIRETYPE_VARINT: {
        uint64_t value;
        if (!in.ReadVarint64(&value)) return absl::StrCat(name, ": truncated or malformed varint");
        break;
      }
      case WireFormatLite::WIRETYPE_FIXED64: {
        uint64_t value;
        if (!in.ReadLittleEndian64(&value)) return absl::StrCat(name, ": truncated 64-bit value");
        break;
      }
      case WireFormatLite::WIRETYPE_FIXED32: {
        uint32_t value;
        if (!in.ReadLittleEndian32(&value)) return absl::StrCat(name, ": truncated 32-bit value");
        break;
      }
      case WireFormatLite::WIRETYPE_LENGTH_DELIMITED: {
        uint32_t length;
        if (!in.ReadVarint32(&length)) return absl::StrCat(name, ": malformed length");
        const int offset = in.CurrentPosition();
        if (length > bytes.size() - static_cast<size_t>(offset)) {
          return absl::StrCat(name, ": length ", length, " runs past the end of the message (", bytes.size() - offset,
                              " bytes left)");
        }
        const std::string_view content = bytes.substr(offset, length);
        in.Skip(static_cast<int>(length));
        if (field == nullptr) break;
        if (field->type() == FieldDescriptor::TYPE_STRING && !IsValidUtf8(content)) {
          return absl::StrCat(name, ": not valid UTF-8");
        }
        if (field->type() == FieldDescriptor::TYPE_MESSAGE) {
          std::string problem = FindProblem(field->message_type(), content, name, depth + 1);
          if (!problem.empty()) return problem;
        }
        break;
      }
      case WireFormatLite::WIRETYPE_START_GROUP:
      case WireFormatLite::WIRETYPE_END_GROUP:
        return absl::StrCat(name, ": groups are not used by this API");
      default:
        return absl::StrCat(name, ": invalid wire type ", static_cast<int>(wire_type));
    }
  }
}

}  // namespace

bool IsValidUtf8(std::string_view text) {
  size_t i = 0;
  const auto byte = [&](size_t k) { return static_cast<unsigned char>(text[k]); };
  while (i < text.size()) {
    const unsigned char c = byte(i);
    if (c < 0x80) {
      ++i;
      continue;
    }
    int extra = 0;
    uint32_t code = 0, min = 0;
    if ((c & 0xE0) == 0xC0) {
      extra = 1, code = c & 0x1F, min = 0x80;
    } else if ((c & 0xF0) == 0xE0) {
      extra = 2, code = c & 0x0F, min = 0x800;
    } else if ((c & 0xF8) == 0xF0) {
      extra = 3, code = c & 0x07, min = 0x10000;
    } else {
      return false;
    }
    if (i + extra >= text.size()) return false;
    for (int k = 1; k <= extra; ++k) {
      if ((byte(i + k) & 0xC0) != 0x80) return false;
      code = (code << 6) | (byte(i + k) & 0x3F);
    }
    if (code < min || code > 0x10FFFF || (code >= 0xD800 && code <= 0xDFFF)) return false;
    i += extra + 1;
  }
  return true;
}

std::string FlattenByteBuffer(const grpc::ByteBuffer& buffer) {
  std::vector<grpc::Slice> slices;
  std::string bytes;
  if (!buffer.Dump(&slices).ok()) return bytes;
  bytes.reserve(buffer.Length());
  for (const grpc::Slice& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
  return bytes;
}

absl::Status ParseWireMessage(std::string_view bytes, std::string_view prefix, google::protobuf::Message* message) {
  if (message->ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) return absl::OkStatus();
  std::string problem = FindProblem(message->GetDescriptor(), bytes, std::string(prefix), 0);
  if (problem.empty()) {
    problem = absl::StrCat(prefix.empty() ? std::string("request") : std::string(prefix), ": not a serialized ",
                           message->GetDescriptor()->full_name());
  }
  return absl::InvalidArgumentError(problem);
}

}  // namespace crowdmap
