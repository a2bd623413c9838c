#ifndef CROWDMAP_CLIENT_COMMON_EXIT_CODES_H_
#define CROWDMAP_CLIENT_COMMON_EXIT_CODES_H_

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace crowdmap {

// Exit codes of the command-line tools (mapctl, mapsim), as their --help documents.
constexpr int kExitOk = 0;
constexpr int kExitFailure = 1;  // a failed call, file or computation
constexpr int kExitUsage = 2;    // unknown command or flag, missing argument, bad value

// A usage error: INVALID_ARGUMENT marked so that the tools exit with kExitUsage for it, while an
// INVALID_ARGUMENT from the server (a failed call) still exits with kExitFailure.
absl::Status UsageError(absl::string_view message);
// `status` marked as a usage error (OK stays OK).
absl::Status AsUsageError(absl::Status status);
bool IsUsageError(const absl::Status& status);
// kExitOk, kExitUsage for a usage error, else kExitFailure.
int ExitCodeFor(const absl::Status& status);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_COMMON_EXIT_CODES_H_
