#include "core/logging/log_format.h"

#include <cstdlib>
#include <ctime>
#include <regex>
#include <sstream>

#include <spdlog/sinks/ostream_sink.h>

#include "gtest/gtest.h"

namespace crowdmap {
namespace {

TEST(TextLogFormat, LinesCarryTheUtcTimeWithItsZoneTheLevelAndTheMessage) {
  // A zone far from UTC, so that a local time would differ from the UTC one in its hour.
  setenv("TZ", "Asia/Kathmandu", 1);  // UTC+05:45
  tzset();
  std::ostringstream out;
  auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
  spdlog::logger logger("test", sink);
  UseTextLogFormat(logger);
  const std::time_t before = std::time(nullptr);
  logger.warn("passage={} nodes={}", "p7", 412);
  const std::time_t after = std::time(nullptr);
  unsetenv("TZ");
  tzset();

  const std::string line = out.str();
  std::smatch m;
  ASSERT_TRUE(std::regex_match(line, m, std::regex(R"((\d{4})-(\d\d)-(\d\d)T(\d\d):(\d\d):(\d\d)\.\d{3}Z warning passage=p7 nodes=412\n)")))
      << line;
  std::tm utc{};
  gmtime_r(&before, &utc);
  std::tm utc_after{};
  gmtime_r(&after, &utc_after);
  const int minute = std::stoi(m[4]) * 60 + std::stoi(m[5]);
  EXPECT_TRUE(minute == utc.tm_hour * 60 + utc.tm_min || minute == utc_after.tm_hour * 60 + utc_after.tm_min) << line;
}

}  // namespace
}  // namespace crowdmap
