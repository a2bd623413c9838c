#ifndef CROWDMAP_SERVER_LOG_FORMAT_H_
#define CROWDMAP_SERVER_LOG_FORMAT_H_

#include <memory>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>
#include <spdlog/formatter.h>

namespace crowdmap {

// `value` as one line of JSON text (no newline) that is valid whatever bytes its strings carry:
// characters outside ASCII escaped (\u00e9), bytes that are not UTF-8 replaced by U+FFFD.
std::string JsonText(const nlohmann::ordered_json& value);

// One JSON object per line: {"time":"2026-11-24T10:00:00.123Z","level":"info","msg":"..."}; the
// message is the key=value line the text format prints.
std::unique_ptr<spdlog::formatter> MakeJsonLogFormatter();

// A new id for one RPC: 16 hex digits, unique within the process (a random start, then a counter).
std::string NewRequestId();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_LOG_FORMAT_H_
