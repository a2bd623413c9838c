#include "core/logging/log_format.h"

#include <memory>

#include <spdlog/pattern_formatter.h>

namespace crowdmap {

void UseTextLogFormat(spdlog::logger& logger) {
  logger.set_formatter(std::make_unique<spdlog::pattern_formatter>(kTextLogPattern, spdlog::pattern_time_type::utc));
}

}  // namespace crowdmap
