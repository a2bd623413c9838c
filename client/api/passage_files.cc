#include "client/api/passage_files.h"

#include <fstream>
#include <sstream>

#include <google/protobuf/util/json_util.h>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"

namespace crowdmap {

absl::StatusOr<PassageFileFormat> ParsePassageFileFormat(const std::string& name) {
  if (name == "json") return PassageFileFormat::kJson;
  if (name == "binary") return PassageFileFormat::kBinary;
  return absl::InvalidArgumentError(absl::StrCat("format: '", name, "' is not json or binary"));
}

absl::StatusOr<::mapservice::v1::Passage> ReadPassageFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open"));
  std::stringstream buffer;
  buffer << in.rdbuf();
  const std::string bytes = buffer.str();
  ::mapservice::v1::Passage passage;
  const absl::string_view text = absl::StripLeadingAsciiWhitespace(bytes);
  if (!text.empty() && text.front() == '{') {
    google::protobuf::util::JsonParseOptions options;
    options.ignore_unknown_fields = false;
    const auto status = google::protobuf::util::JsonStringToMessage(std::string(text), &passage, options);
    if (!status.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": not a mapservice.v1.Passage in protobuf JSON: ", std::string(status.message())));
    }
  } else if (bytes.empty() || !passage.ParseFromString(bytes)) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": neither protobuf JSON nor a binary mapservice.v1.Passage"));
  }
  if (passage.vehicle_id().empty() && passage.passage_id().empty() && passage.odometry_size() == 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a passage (no vehicle_id, passage_id or odometry)"));
  }
  return passage;
}

absl::Status WritePassageFile(const ::mapservice::v1::Passage& passage, PassageFileFormat format,
                              const std::string& path) {
  std::string bytes;
  if (format == PassageFileFormat::kJson) {
    google::protobuf::util::JsonPrintOptions options;
    options.add_whitespace = true;
    options.preserve_proto_field_names = true;
    const auto status = google::protobuf::util::MessageToJsonString(passage, &bytes, options);
    if (!status.ok()) return absl::InternalError(absl::StrCat(path, ": ", std::string(status.message())));
  } else if (!passage.SerializeToString(&bytes)) {
    return absl::InternalError(absl::StrCat(path, ": serialization failed"));
  }
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << bytes;
  out.close();
  if (!out) return absl::UnavailableError(absl::StrCat(path, ": write failed"));
  return absl::OkStatus();
}

}  // namespace crowdmap
