#include "client/common/exit_codes.h"

#include "absl/strings/cord.h"

namespace crowdmap {
namespace {
constexpr char kUsagePayload[] = "type.crowdmap/cli.usage_error";
}  // namespace

absl::Status UsageError(absl::string_view message) { return AsUsageError(absl::InvalidArgumentError(message)); }

absl::Status AsUsageError(absl::Status status) {
  if (!status.ok()) status.SetPayload(kUsagePayload, absl::Cord("1"));
  return status;
}

bool IsUsageError(const absl::Status& status) { return status.GetPayload(kUsagePayload).has_value(); }

int ExitCodeFor(const absl::Status& status) {
  if (status.ok()) return kExitOk;
  return IsUsageError(status) ? kExitUsage : kExitFailure;
}

}  // namespace crowdmap
