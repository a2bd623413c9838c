#ifndef CROWDMAP_SERVER_LOG_FORMAT_H_
#define CROWDMAP_SERVER_LOG_FORMAT_H_

#include <memory>
#include <string>
#include <string_view>

#include <spdlog/formatter.h>

namespace crowdmap {

// `text` as the body of a JSON string (without the quotes): quote, backslash and control
// characters escaped, and every byte outside ASCII written as \u00XX, so the line is valid JSON
// whatever bytes it carries.
std::string JsonEscape(std::string_view text);

// One JSON object per line: {"time":"2026-11-24T10:00:00.123Z","level":"info","msg":"..."}; the
// message is the key=value line the text format prints.
std::unique_ptr<spdlog::formatter> MakeJsonLogFormatter();

// A new id for one RPC: 16 hex digits, unique within the process (a random start, then a counter).
std::string NewRequestId();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_LOG_FORMAT_H_
