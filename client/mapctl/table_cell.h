#ifndef CROWDMAP_CLIENT_MAPCTL_TABLE_CELL_H_
#define CROWDMAP_CLIENT_MAPCTL_TABLE_CELL_H_

#include <cstddef>
#include <string>

#include "absl/strings/string_view.h"

namespace crowdmap {

// `text` safe to print on one terminal line: control characters as \n, \r, \t or \xNN, bytes that
// are not UTF-8 as \xNN, a backslash as \\ (so that an escape cannot be faked).
std::string EscapeForTerminal(absl::string_view text);

// `text` escaped as above and fitted to exactly `width` columns: cut with "…" when longer,
// padded with spaces on the right when shorter. A column is one UTF-8 code point (wide CJK
// characters take two on most terminals and will still shift a row). width >= 1.
std::string TableCell(absl::string_view text, size_t width);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPCTL_TABLE_CELL_H_
