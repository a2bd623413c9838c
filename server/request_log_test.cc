#include "server/request_log.h"

#include <gtest/gtest.h>
#include <spdlog/logger.h>
#include <spdlog/sinks/ostream_sink.h>

#include <regex>
#include <sstream>

namespace crowdmap {
namespace {

TEST(EscapeForLog, KeepsPrintableTextAndEscapesWhatCouldForgeALine) {
  EXPECT_EQ(EscapeForLog("vehicle=v-1 passage=p_2"), "vehicle=v-1 passage=p_2");
  // A newline would start a forged line of its own.
  EXPECT_EQ(EscapeForLog("v\nerror event=disk_full"), "v\\x0aerror event=disk_full");
  EXPECT_EQ(EscapeForLog("a\rb\tc"), "a\\x0db\\x09c");
  EXPECT_EQ(EscapeForLog("back\\slash"), "back\\x5cslash") << "so that an escape cannot be faked either";
  EXPECT_EQ(EscapeForLog("\xc3\xa9"), "\\xc3\\xa9");
  EXPECT_EQ(EscapeForLog(std::string("nul\0byte", 8)), "nul\\x00byte");
}

TEST(JsonText, EscapesQuotesBackslashesControlAndNonAsciiAndReplacesBytesThatAreNotUtf8) {
  EXPECT_EQ(JsonText({{"msg", "rpc=GetTile code=OK"}}), R"({"msg":"rpc=GetTile code=OK"})");
  EXPECT_EQ(JsonText({{"msg", "error=\"a\\b\""}}), R"({"msg":"error=\"a\\b\""})");
  EXPECT_EQ(JsonText({{"msg", "a\nb\tc\x01"}}), R"({"msg":"a\nb\tc\u0001"})");
  EXPECT_EQ(JsonText({{"msg", "\xc3\xa9\x7f"}}), R"({"msg":"\u00e9\u007f"})");
  EXPECT_EQ(JsonText({{"msg", "v\xff"}}), R"({"msg":"v\ufffd"})");
}

TEST(JsonLogFormat, WritesOneObjectPerLineWithTimeLevelAndMessage) {
  std::ostringstream out;
  auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
  spdlog::logger logger("test", sink);
  logger.set_formatter(MakeJsonLogFormatter());
  // A message that tries to end the object and start a line of its own.
  logger.warn("rpc=UploadPassage vehicle={}", "v\"}\n{\"level\":\"error\"");
  const std::string line = out.str();
  EXPECT_TRUE(std::regex_match(
      line, std::regex(R"re(\{"time":"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z","level":"warning","msg":"(.*)"\}\n)re")))
      << line;
  EXPECT_NE(line.find(R"js("msg":"rpc=UploadPassage vehicle=v\"}\n{\"level\":\"error\""})js"), std::string::npos)
      << line;
  EXPECT_EQ(std::count(line.begin(), line.end(), '\n'), 1);
}

TEST(RequestIds, AreSixteenHexDigitsAndDistinct) {
  const std::string a = NewRequestId(), b = NewRequestId();
  EXPECT_TRUE(std::regex_match(a, std::regex("[0-9a-f]{16}"))) << a;
  EXPECT_NE(a, b);
}

}  // namespace
}  // namespace crowdmap
