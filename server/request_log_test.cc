#include "server/request_log.h"

#include <gtest/gtest.h>

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

}  // namespace
}  // namespace crowdmap
