#ifndef CROWDMAP_CORE_LOGGING_LOG_FORMAT_H_
#define CROWDMAP_CORE_LOGGING_LOG_FORMAT_H_

#include <spdlog/logger.h>

namespace crowdmap {

// The text log line of every crowdmap tool (mapd, mapsim): the time in UTC with its zone, the
// level, the message, e.g. "2026-11-24T10:00:00.123Z info passage=p7 nodes=412". mapd's
// --log-format=json carries the same time in its "time" field.
constexpr char kTextLogPattern[] = "%Y-%m-%dT%H:%M:%S.%eZ %l %v";

// Sets the text format on `logger`; times are UTC whatever the TZ of the process.
void UseTextLogFormat(spdlog::logger& logger);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_LOGGING_LOG_FORMAT_H_
