#include "client/mapctl/table_cell.h"

#include "gtest/gtest.h"

namespace crowdmap {
namespace {

TEST(TableCell, PadsShortTextToTheWidth) {
  EXPECT_EQ(TableCell("car-7", 8), "car-7   ");
  EXPECT_EQ(TableCell("", 3), "   ");
  EXPECT_EQ(TableCell("exactly8", 8), "exactly8");
}

TEST(TableCell, CutsLongTextWithAnEllipsis) {
  EXPECT_EQ(TableCell("vehicle-with-a-very-long-name", 10), "vehicle-w\u2026");
  EXPECT_EQ(TableCell("ninechars", 8), "ninecha\u2026");
  EXPECT_EQ(TableCell("ab", 1), "\u2026");
}

TEST(TableCell, EscapesControlCharactersAndKeepsTheWidth) {
  EXPECT_EQ(TableCell("a\nb", 6), "a\\nb  ");
  EXPECT_EQ(TableCell("a\tb\r", 8), "a\\tb\\r  ");
  EXPECT_EQ(TableCell("\x1b[31mred", 12), "\\x1b[31mred ");
  // An escape is never cut in the middle.
  EXPECT_EQ(TableCell("ab\x1b", 5), "ab\u2026  ");
}

TEST(TableCell, CountsUtf8CodePointsAsOneColumnAndEscapesInvalidBytes) {
  EXPECT_EQ(TableCell("Zürich", 7), "Zürich ");
  EXPECT_EQ(TableCell("Zürich-Oerlikon", 7), "Zürich\u2026");
  EXPECT_EQ(TableCell("a\xff", 6), "a\\xff ");
  EXPECT_EQ(TableCell("\xc3", 4), "\\xc3");  // a truncated sequence
  EXPECT_EQ(EscapeForTerminal("x\xc2\x9by"), "x\\u009by");  // C1 control (CSI)
}

TEST(EscapeForTerminal, EscapesBackslashesSoThatEscapesCannotBeFaked) {
  EXPECT_EQ(EscapeForTerminal("a\\nb"), "a\\\\nb");
  EXPECT_EQ(EscapeForTerminal("plain/ID-1"), "plain/ID-1");
}

}  // namespace
}  // namespace crowdmap
