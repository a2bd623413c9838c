#include "client/mapctl/table_cell.h"

#include <vector>

#include "absl/strings/str_format.h"

namespace crowdmap {
namespace {

// Length of the valid UTF-8 sequence at text[i], or 0 when it is not one.
size_t Utf8Length(absl::string_view text, size_t i) {
  const unsigned char c = static_cast<unsigned char>(text[i]);
  size_t n = 0;
  if (c >= 0xc2 && c <= 0xdf) n = 2;
  else if (c >= 0xe0 && c <= 0xef) n = 3;
  else if (c >= 0xf0 && c <= 0xf4) n = 4;
  if (n == 0 || i + n > text.size()) return 0;
  for (size_t k = 1; k < n; ++k) {
    if ((static_cast<unsigned char>(text[i + k]) & 0xc0) != 0x80) return 0;
  }
  return n;
}

// The escaped text as a list of columns, each one printable unit (a character or an escape).
std::vector<std::string> Columns(absl::string_view text) {
  std::vector<std::string> columns;
  for (size_t i = 0; i < text.size();) {
    const unsigned char c = static_cast<unsigned char>(text[i]);
    if (c == '\n') {
      columns.push_back("\\n");
    } else if (c == '\r') {
      columns.push_back("\\r");
    } else if (c == '\t') {
      columns.push_back("\\t");
    } else if (c == '\\') {
      columns.push_back("\\\\");
    } else if (c < 0x20 || c == 0x7f) {
      columns.push_back(absl::StrFormat("\\x%02x", c));
    } else if (c < 0x80) {
      columns.push_back(std::string(1, static_cast<char>(c)));
    } else if (size_t n = Utf8Length(text, i); n > 0) {
      // C1 controls (U+0080..U+009F) act on terminals too.
      const bool c1 = n == 2 && c == 0xc2 && static_cast<unsigned char>(text[i + 1]) < 0xa0;
      columns.push_back(c1 ? absl::StrFormat("\\u%04x", static_cast<unsigned char>(text[i + 1]))
                           : std::string(text.substr(i, n)));
      i += n;
      continue;
    } else {
      columns.push_back(absl::StrFormat("\\x%02x", c));
    }
    ++i;
  }
  return columns;
}

}  // namespace

std::string EscapeForTerminal(absl::string_view text) {
  std::string out;
  for (const std::string& column : Columns(text)) out += column;
  return out;
}

std::string TableCell(absl::string_view text, size_t width) {
  if (width == 0) width = 1;
  std::vector<std::string> columns = Columns(text);
  // An escape like \x1b is several columns wide on screen.
  size_t shown = 0, k = 0;
  for (; k < columns.size(); ++k) {
    const size_t w = columns[k].size() > 1 && columns[k][0] == '\\' ? columns[k].size() : 1;
    if (shown + w > width) break;
    shown += w;
  }
  std::string out;
  if (k == columns.size()) {
    for (const std::string& column : columns) out += column;
    return out + std::string(width - shown, ' ');
  }
  // Too long: keep what fits in width - 1 columns, then the ellipsis.
  shown = 0;
  for (size_t j = 0; j < columns.size(); ++j) {
    const size_t w = columns[j].size() > 1 && columns[j][0] == '\\' ? columns[j].size() : 1;
    if (shown + w > width - 1) break;
    out += columns[j];
    shown += w;
  }
  return out + "\u2026" + std::string(width - 1 - shown, ' ');
}

}  // namespace crowdmap
