#ifndef CROWDMAP_CLIENT_API_PASSAGE_FILES_H_
#define CROWDMAP_CLIENT_API_PASSAGE_FILES_H_

#include <string>

#include "absl/status/statusor.h"
#include "mapservice/v1/passage.pb.h"

namespace crowdmap {

enum class PassageFileFormat { kJson, kBinary };

// "json" | "binary".
absl::StatusOr<PassageFileFormat> ParsePassageFileFormat(const std::string& name);

// Reads one mapservice.v1.Passage: protobuf JSON when the file starts with '{' (after
// whitespace), the binary encoding otherwise. InvalidArgument naming the file when malformed.
absl::StatusOr<::mapservice::v1::Passage> ReadPassageFile(const std::string& path);

absl::Status WritePassageFile(const ::mapservice::v1::Passage& passage, PassageFileFormat format,
                              const std::string& path);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_API_PASSAGE_FILES_H_
